"""RRT planning and the smoothing / quartic / time-scaling pipeline (SPEC section 5; thesis 3.2.3).

The scenes are built by hand (a simple-obstacle-like triangle of spheres, an agriculture-like set
of tilted cylinders). Checks are independent of the implementation: dense clearance sampling of
the path, NumPy moving averages, Taylor bounds for the sampled derivatives, bit-for-bit
determinism, and the structural invariants of the tree.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from redman_jax._math import cast_floating
from redman_jax._obstacles import make_obstacles, obstacle_distances, stack_obstacles
from redman_jax._planning import (
    RRTParams,
    evaluate_trajectory,
    plan_reference,
    plan_reference_batch,
    plan_rrt,
    plan_rrt_batch,
    quartic_trajectory,
    reference_from_path,
    rrt_reference,
    smooth_path,
    subsample_path,
    time_scale,
    trajectory_extrema,
)

CAPS = (4, 1, 8)  # one obstacle structure for every scene here, so each function compiles once
TS = 0.01
CAPACITY = 2000
ROT_RADIUS = 0.2
QUAT = np.array([0.9238795, 0.0, 0.3826834, 0.0])


def _simple_scene(seed):
    """SPEC section 4 "Simple obstacle": 3 spheres (r 0.07) on a triangle of circumradius 0.16
    midway between start and goal, perpendicular to the start-goal line, plus a 4th sphere."""
    rng = np.random.default_rng(seed)
    start = np.array([0.0, 0.0, 1.2])
    while True:
        r, th, z = rng.uniform(0.45, 0.7), rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.0)
        goal = np.array([r * np.cos(th), r * np.sin(th), z])
        if 0.7 <= np.linalg.norm(goal - start) <= 1.2:
            break
    u = (goal - start) / np.linalg.norm(goal - start)
    e1 = np.cross(u, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    mid, roll = (start + goal) / 2, rng.uniform(0, 2 * np.pi)
    spheres = [(np.eye(3), mid + 0.16 * (np.cos(roll + k * 2 * np.pi / 3) * e1
                                        + np.sin(roll + k * 2 * np.pi / 3) * e2), [0.07])
               for k in range(3)]
    spheres.append((np.eye(3), start + rng.uniform(0.3, 0.7) * (goal - start)
                    + rng.uniform(0.25, 0.35) * e1, [0.07]))
    return make_obstacles(spheres=spheres, capacities=CAPS), start, goal


def _tilted(axis_dir, base, length, radius):
    a = np.asarray(axis_dir, float)
    a /= np.linalg.norm(a)
    z = np.array([0, 0, 1.0])
    v = np.cross(z, a)
    s, c = np.linalg.norm(v), z @ a
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    R = np.eye(3) + K + K @ K * ((1 - c) / s**2) if s > 1e-12 else np.eye(3)
    return (R, np.asarray(base) + 0.5 * length * a, [radius, 0.5 * length])


def _agri_scene():
    """Agriculture-like: two tilted trunks with branches around the arm; goal among them."""
    cyl = [
        _tilted([0.1, 0.05, 1], [0.45, 0.1, 0.0], 0.8, 0.025),
        _tilted([0.6, 0.2, 1], [0.5, 0.13, 0.78], 0.45, 0.018),
        _tilted([-0.3, 0.5, 1], [0.5, 0.13, 0.78], 0.45, 0.018),
        _tilted([-0.1, 0.1, 1], [-0.3, 0.4, 0.0], 0.7, 0.025),
        _tilted([-0.5, 0.3, 1], [-0.33, 0.43, 0.68], 0.4, 0.018),
    ]
    start = np.array([0.0, 0.0, 1.2])
    goal = np.array([0.55, -0.25, 0.85])
    return make_obstacles(cylinders=cyl, capacities=CAPS), start, goal


def _blocked_scene():
    """The goal lies inside a sphere: no plan can succeed."""
    obs = make_obstacles(spheres=[(np.eye(3), [0.5, 0.0, 0.8], [0.1])], capacities=CAPS)
    return obs, np.array([0.0, 0.0, 1.2]), np.array([0.52, 0.0, 0.8])


N_OK = 5  # scenes 0..4 are plannable, scene 5 has its goal inside an obstacle


def _batch():
    scenes = [_simple_scene(s) for s in range(4)] + [_agri_scene(), _blocked_scene()]
    obs = stack_obstacles([s[0] for s in scenes])
    start = jnp.asarray(np.stack([s[1] for s in scenes]))
    goal = jnp.asarray(np.stack([s[2] for s in scenes]))
    keys = jax.random.split(jax.random.PRNGKey(7), len(scenes))
    quat = jnp.broadcast_to(jnp.asarray(QUAT), (len(scenes), 4))
    return scenes, obs, start, goal, keys, quat


PARAMS = RRTParams(max_nodes=2048, path_capacity=256)


@pytest.fixture(scope="module")
def planned():
    scenes, obs, start, goal, keys, quat = _batch()
    out = plan_reference_batch(keys, obs, start, goal, quat, ROT_RADIUS, TS, CAPACITY, PARAMS)
    return scenes, obs, start, goal, keys, quat, jax.device_get(out)


_clearance_jit = jax.jit(jax.vmap(lambda o, x: jnp.min(obstacle_distances(o, x)), in_axes=(None, 0)))
_CHUNK = 8192


def _clearance(obs, pts):
    """Minimum signed distance of every point, in fixed-size chunks (one compilation)."""
    pts = np.asarray(pts)
    out = []
    for k in range(0, len(pts), _CHUNK):
        chunk = pts[k:k + _CHUNK]
        pad = np.concatenate([chunk, np.repeat(chunk[-1:], _CHUNK - len(chunk), 0)])
        out.append(np.asarray(_clearance_jit(obs, jnp.asarray(pad)))[: len(chunk)])
    return np.concatenate(out)


def test_rrt_paths_connect_and_keep_safety_radius(planned):
    scenes, *_, out = planned
    res = out.rrt
    assert np.all(res.success[:N_OK]), res.success
    step, tol, safety, res_edge = 0.05, 0.05, 0.15, 0.01
    for i in range(N_OK):
        obs, start, goal = scenes[i]
        n = int(res.n_path[i])
        path = res.path[i, :n]
        np.testing.assert_array_equal(path[0], start)
        np.testing.assert_array_equal(path[-1], goal)
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        assert np.all(seg <= max(step, tol) + 1e-12) and np.all(seg > 0)
        np.testing.assert_allclose(res.cost[i], seg.sum(), rtol=1e-12)
        # dense check, 1 mm: edges are checked every <= edge_res, and the sdf is 1-Lipschitz, so
        # between two checked points the clearance can dip by at most edge_res / 2
        t = np.linspace(0, 1, 51)[:, None]
        dense = (path[:-1, None, :] + t[None] * (path[1:] - path[:-1])[:, None, :]).reshape(-1, 3)
        clear = _clearance(obs, dense)
        assert clear.min() >= safety - res_edge / 2, clear.min()
        # every tree node keeps the full safety radius
        nodes = res.nodes[i, : int(res.n_nodes[i])]
        assert _clearance(obs, nodes).min() >= safety


def test_planner_failure_is_a_value_not_an_exception(planned):
    *_, out = planned
    k = N_OK  # goal inside an obstacle
    assert not out.rrt.success[k] and not out.success[k]
    ref = out.reference
    assert int(ref.n_samples[k]) == 1
    for leaf in jax.tree.leaves(ref):
        assert np.all(np.isfinite(np.asarray(leaf, float)))
    np.testing.assert_array_equal(ref.p[k], np.broadcast_to(np.asarray(_batch()[2][k]), ref.p[k].shape))
    assert np.all(ref.v[k] == 0) and np.all(ref.a[k] == 0)


def test_budget_too_small_fails_cleanly():
    scenes, obs, start, goal, keys, _ = _batch()
    # iteration budget (an array: no recompilation) and node budget (static)
    traces = []

    def counted(keys, obs, start, goal, params):
        traces.append(1)
        return jax.vmap(plan_rrt, in_axes=(0, 0, 0, 0, None))(keys, obs, start, goal, params)

    f = eqx.filter_jit(counted)
    tiny_iter = RRTParams(max_iter=5, max_nodes=2048, path_capacity=256)
    r = f(keys, obs, start, goal, tiny_iter)
    assert not np.any(r.success) and np.all(r.n_iter <= 5)
    # new numbers (budget, step, tolerance, safety, bias) never recompile: they are arrays
    other = RRTParams(max_iter=7, step=0.04, goal_tol=0.03, safety=0.12, goal_bias=0.2,
                      edge_points=PARAMS.edge_points, max_nodes=2048, path_capacity=256)
    r = f(keys, obs, start, goal, other)
    assert len(traces) == 1 and not np.any(r.success) and np.all(r.n_iter <= 7)
    tiny_nodes = RRTParams(max_nodes=8, path_capacity=256)
    r = plan_rrt_batch(keys, obs, start, goal, tiny_nodes)
    assert not np.any(r.success) and np.all(r.n_nodes <= 8)
    for leaf in jax.tree.leaves(r):
        assert np.all(np.isfinite(np.asarray(leaf, float)))


def test_reference_respects_limits_and_rests_at_both_ends(planned):
    scenes, *_, out = planned
    ref, traj = out.reference, out.trajectory
    assert np.all(out.success[:N_OK])
    for i in range(N_OK):
        n = int(ref.n_samples[i])
        p, v, a = ref.p[i], ref.v[i], ref.a[i]
        speed, acc = np.linalg.norm(v, axis=1), np.linalg.norm(a, axis=1)
        # The scale factor comes from 64 samples per segment; between samples the norms can
        # exceed the sampled maximum by h^2/8 * max|f''| (h = T_k/63 ~ 5 ms, |f''| of the speed
        # <= a few m/s^3 and of the acceleration norm <= ~1e2 m/s^4): < 1e-3. Tolerance 1e-2.
        assert speed.max() <= 1.0 + 1e-2 and acc.max() <= 2.0 + 1e-2, (speed.max(), acc.max())
        # at rest at both ends; padding repeats the final sample at rest
        assert np.all(v[0] == 0) and np.all(a[0] == 0)
        assert np.all(v[n - 1:] == 0) and np.all(a[n - 1:] == 0)
        np.testing.assert_array_equal(p[0], scenes[i][1])
        np.testing.assert_allclose(p[n - 1], scenes[i][2], atol=1e-12)
        np.testing.assert_array_equal(p[n:], np.broadcast_to(p[n - 1], p[n:].shape))
        assert np.all(ref.mask[i, :n]) and not np.any(ref.mask[i, n:])
        # sampled velocity is the derivative of the sampled position: central differences agree
        # within ts^2/6 * max|jerk| (Taylor remainder); the jerk is bounded from the coefficients
        c = traj.coeffs[i, : int(traj.n_seg[i])]
        T = traj.durations[i, : int(traj.n_seg[i])]
        jerk = np.abs(6 * c[:, :, 3]).max() + np.abs(24 * c[:, :, 4] * T[:, None]).max()
        fd_v = (p[2:n - 2] - p[: n - 4]) / (2 * TS)
        assert np.abs(fd_v - v[1:n - 3]).max() <= TS**2 / 6 * jerk * np.sqrt(3) + 1e-12
        # orientation: constant goal quaternion, no angular velocity; rot latched near the goal
        np.testing.assert_array_equal(ref.quat[i], np.broadcast_to(QUAT, ref.quat[i].shape))
        assert np.all(ref.omega[i] == 0) and np.all(ref.omega_dot[i] == 0)
        rot = ref.rot[i]
        assert np.all(np.diff(rot) >= 0) and rot[0] == 0 and rot[n - 1] == 1
        first = int(np.argmax(rot))
        d = np.linalg.norm(p - scenes[i][2], axis=1)
        assert d[first] <= ROT_RADIUS and np.all(d[:first] > ROT_RADIUS)


def test_trajectory_continuity_and_time_scaling(planned):
    *_, out = planned
    for i in range(N_OK):
        traj = jax.tree.map(lambda x: x[i], out.trajectory)
        S = int(traj.n_seg)
        c, T = np.asarray(traj.coeffs), np.asarray(traj.durations)
        for k in range(S - 1):
            tau = T[k]
            left = [sum(c[k, :, j] * tau**j for j in range(5)),
                    sum(j * c[k, :, j] * tau ** (j - 1) for j in range(1, 5)),
                    sum(j * (j - 1) * c[k, :, j] * tau ** (j - 2) for j in range(2, 5))]
            right = [c[k + 1, :, 0], c[k + 1, :, 1], 2 * c[k + 1, :, 2]]
            for lft, rgt, scale in zip(left, right, (1.0, 1.0, 2.0)):
                np.testing.assert_allclose(lft, rgt, atol=1e-9 * scale)
        # the down-sampled waypoints are hit at the segment boundaries
        wp = out.waypoints[i, : int(out.n_waypoints[i])]
        np.testing.assert_allclose(c[:S, :, 0], wp[:-1], atol=1e-12)
        # the scale factor is the one of SPEC step 5 and the result meets it
        vmax, amax = trajectory_extrema(traj)
        assert max(vmax, np.sqrt(amax / 2.0)) <= 1.0 + 1e-9
        assert np.isclose(vmax, 1.0) or np.isclose(amax, 2.0)


def test_smoothing_and_subsampling_against_numpy(rng):
    P, n = 40, 23
    path = np.zeros((P, 3))
    path[:n] = np.cumsum(rng.normal(size=(n, 3)) * 0.05, axis=0)
    path[n:] = path[n - 1]
    sm = np.asarray(smooth_path(jnp.asarray(path), n, 5))
    padded = np.concatenate([np.repeat(path[:1], 2, 0), path[:n], np.repeat(path[n - 1:n], 2, 0)])
    ref = np.stack([np.convolve(padded[:, d], np.ones(5) / 5, mode="valid") for d in range(3)], 1)
    np.testing.assert_allclose(sm[1:n - 1], ref[1:n - 1], atol=1e-15)
    np.testing.assert_array_equal(sm[0], path[0])
    np.testing.assert_array_equal(sm[n - 1:], np.broadcast_to(path[n - 1], (P - n + 1, 3)))
    wp, m = subsample_path(jnp.asarray(sm), n, 4)
    keep = list(range(0, n - 1, 4)) + [n - 1]
    assert int(m) == len(keep)
    np.testing.assert_array_equal(np.asarray(wp)[: len(keep)], sm[keep])
    with pytest.raises(ValueError, match="window"):
        smooth_path(jnp.asarray(path), n, 4)


def test_quartic_segments_and_exact_retiming():
    wp = jnp.array([[0.0, 0, 0], [0.2, 0.0, 0.0], [0.3, 0.2, 0.0], [0.3, 0.4, 0.1], [0.0, 0, 0]])
    traj = jax.jit(quartic_trajectory)(wp, 4, 0.5)  # last row is padding
    T = np.linalg.norm(np.diff(np.asarray(wp[:4]), axis=0), axis=1) / 0.5
    np.testing.assert_allclose(traj.durations[:3], T, rtol=1e-14)
    assert float(traj.durations[3]) == 0.0 and int(traj.n_seg) == 3
    # interior velocities (P_{k+1} - P_{k-1}) / (T_{k-1} + T_k); zero at the ends
    c = np.asarray(traj.coeffs)
    np.testing.assert_allclose(c[1, :, 1], (wp[2] - wp[0]) / (T[0] + T[1]), rtol=1e-13)
    np.testing.assert_allclose(c[2, :, 1], (wp[3] - wp[1]) / (T[1] + T[2]), rtol=1e-13)
    p_end, v_end, _ = jax.jit(evaluate_trajectory)(traj, traj.total_time)
    np.testing.assert_allclose(p_end, wp[3], atol=1e-13)
    np.testing.assert_allclose(v_end, 0.0, atol=1e-12)
    np.testing.assert_array_equal(c[0, :, 1:3], 0.0)  # starts at rest, zero acceleration
    # uniform re-timing is exact: p_c(c t) = p(t), v_c = v / c, a_c = a / c^2
    scaled, k = jax.jit(time_scale)(traj, 0.2, 0.3)
    assert float(k) > 1
    ev = jax.jit(jax.vmap(evaluate_trajectory, in_axes=(None, 0)))
    t = jnp.linspace(0, float(traj.total_time), 7)
    p0, v0, a0 = ev(traj, t)
    p1, v1, a1 = ev(scaled, k * t)
    np.testing.assert_allclose(p1, p0, atol=1e-13)
    np.testing.assert_allclose(v1 * k, v0, atol=1e-12)
    np.testing.assert_allclose(a1 * k**2, a0, atol=1e-10)


def test_determinism_and_batching_modes(planned):
    scenes, obs, start, goal, keys, quat, out = planned
    again = plan_reference_batch(keys, obs, start, goal, quat, ROT_RADIUS, TS, CAPACITY, PARAMS)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    # vmap and map give the same trees; a single jitted run gives the same tree as the batch
    rv = plan_rrt_batch(keys, obs, start, goal, PARAMS, batch="vmap")
    for a, b in zip(jax.tree.leaves(out.rrt), jax.tree.leaves(rv)):
        np.testing.assert_array_equal(a, b)
    single = jax.jit(plan_rrt)(keys[1], scenes[1][0], start[1], goal[1], PARAMS)
    for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[1], out.rrt)), jax.tree.leaves(single)):
        np.testing.assert_array_equal(a, b)
    # another key gives another tree
    other = jax.jit(plan_rrt)(jax.random.PRNGKey(99), scenes[1][0], start[1], goal[1], PARAMS)
    assert not np.array_equal(other.path, single.path)


def test_reference_capacity_overflow_fails(planned):
    scenes, obs, start, goal, keys, quat, out = planned
    res0 = jax.tree.map(lambda x: jnp.asarray(x[0]), out.rrt)
    small = jax.jit(reference_from_path, static_argnums=6)(res0, start[0], goal[0], quat[0],
                                                           ROT_RADIUS, TS, 16, PARAMS)
    assert bool(res0.success) and not bool(small.success)
    assert int(small.reference.n_samples) == 1 and small.reference.p.shape == (16, 3)


def test_rrt_star_rewiring_keeps_an_exact_cost_tree(planned):
    scenes, obs, start, goal, keys, quat, out = planned
    star = RRTParams(rrt_star=True, max_nodes=2048, path_capacity=256)
    r = jax.device_get(plan_rrt_batch(keys, obs, start, goal, star))
    assert np.all(r.success[:N_OK]) and not r.success[N_OK]
    for i in range(N_OK):
        n = int(r.n_nodes[i])
        nodes, parent, cost = r.nodes[i, :n], r.parent[i, :n], r.node_cost[i, :n]
        assert parent[0] == 0 and np.all(parent[1:] < n)
        # acyclic: every node reaches the root within n parent steps
        cur = np.arange(n)
        for _ in range(n):
            cur = parent[cur]
        assert np.all(cur == 0)
        # costs are exact after rewiring: cost = parent cost + edge length
        edge = np.linalg.norm(nodes - nodes[parent], axis=1)
        np.testing.assert_allclose(cost, cost[parent] + edge, atol=1e-12)
        np.testing.assert_allclose(r.cost[i], np.linalg.norm(np.diff(
            r.path[i, : int(r.n_path[i])], axis=0), axis=1).sum(), rtol=1e-12)
        # rewired edges (up to near_radius long) keep the clearance as well (1 mm dense check)
        t = np.linspace(0, 1, 151)[:, None]
        a, b = nodes[parent[1:]], nodes[1:]
        dense = (a[:, None, :] + t[None] * (b - a)[:, None, :]).reshape(-1, 3)
        assert _clearance(scenes[i][0], dense).min() >= 0.15 - 0.005
    # rewiring shortens the paths on average (deterministic given the keys)
    assert r.cost[:N_OK].mean() < out.rrt.cost[:N_OK].mean()


def test_float32_runs():
    obs, start, goal = _simple_scene(1)
    f32 = lambda t: cast_floating(t, jnp.float32)
    ref, ok = jax.jit(rrt_reference, static_argnums=7)(
        jax.random.PRNGKey(0), f32(obs), jnp.asarray(start, jnp.float32),
        jnp.asarray(goal, jnp.float32), jnp.asarray(QUAT, jnp.float32), ROT_RADIUS, TS, CAPACITY,
        PARAMS)
    assert bool(ok) and ref.p.dtype == jnp.float32
    n = int(ref.n_samples)
    assert np.all(np.isfinite(ref.p)) and np.all(np.isfinite(ref.a))
    assert np.linalg.norm(ref.v, axis=1).max() <= 1.0 + 1e-2
    assert np.linalg.norm(ref.a, axis=1).max() <= 2.0 + 1e-2
    np.testing.assert_allclose(ref.p[n - 1], goal, atol=1e-5)


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="step"):
        RRTParams(step=-0.05)
    with pytest.raises(ValueError, match="goal_bias"):
        RRTParams(goal_bias=1.5)
    with pytest.raises(ValueError, match="goal_tol"):
        RRTParams(goal_tol=0.1)
    with pytest.raises(ValueError, match="edge_points"):
        RRTParams(step=0.08, edge_points=4)
    with pytest.raises(ValueError, match="window"):
        RRTParams(window=4)
    with pytest.raises(ValueError, match="max_nodes"):
        RRTParams(max_nodes=1)
    with pytest.raises(ValueError, match="near_radius"):
        RRTParams(rrt_star=True, near_radius=0.02)
    # counts were truncated without a word (2.5 iterations -> 2)
    for kw in (dict(max_iter=2.5), dict(refine_iters=True), dict(max_nodes=4096.5), dict(dense=float("nan"))):
        with pytest.raises(ValueError, match=f"RRTParams.{next(iter(kw))}: expected a whole number"):
            RRTParams(**kw)
    assert int(RRTParams(max_iter=2e4).max_iter) == 20000
    obs, start, goal = _simple_scene(0)
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match="start"):
        plan_rrt(key, obs, np.zeros(2), goal, PARAMS)
    with pytest.raises(ValueError, match="goal"):
        plan_rrt(key, obs, start, np.array([np.nan, 0, 0]), PARAMS)
    with pytest.raises(ValueError, match="ts"):
        rrt_reference(key, obs, start, goal, QUAT, 0.2, 0.0, 100, PARAMS)
    with pytest.raises(ValueError, match="capacity"):
        rrt_reference(key, obs, start, goal, QUAT, 0.2, 0.01, 0, PARAMS)
    with pytest.raises(ValueError, match="capacity: expected a positive int"):
        rrt_reference(key, obs, start, goal, QUAT, 0.2, 0.01, 100.5, PARAMS)  # was 100 samples
    for bad in (np.array([np.nan, 0.0, 0.0, 0.0]), np.zeros(4)):  # went into every sample
        with pytest.raises(ValueError, match="goal_quat: expected a unit quaternion"):
            rrt_reference(key, obs, start, goal, bad, 0.2, 0.01, 100, PARAMS)
    with pytest.raises(ValueError, match=r"start: expected a 3-vector, got shape \(2, 3\)"):
        plan_rrt(key, obs, np.zeros((2, 3)), goal, PARAMS)  # was a broadcasting error inside
    with pytest.raises(ValueError, match="goal_quat"):
        rrt_reference(key, obs, start, goal, QUAT[:3], 0.2, 0.01, 100, PARAMS)
    with pytest.raises(ValueError, match="batch"):
        plan_rrt_batch(key[None], obs, start[None], goal[None], PARAMS, batch="pmap")


def test_rrt_star_costs_exact_whatever_the_path_buffer():
    """The rewired tree's costs come from pointer jumping, whose rounds must cover the tree's depth
    (bounded by max_nodes, not by path_capacity): with path_capacity 2 or 4 the costs were wrong
    and rewiring closed cycles (373 of 510 nodes never reached the root)."""
    obs = make_obstacles(spheres=[(np.eye(3), [0.5, 0.1, 1.05], [0.1])], capacities=(1, 1, 1))
    start, goal = np.array([0.0, 0.0, 1.2]), np.array([1.0, 0.2, 0.9])
    P = RRTParams(rrt_star=True, max_nodes=1024, path_capacity=2, max_iter=1500, goal_bias=0.0)
    r = jax.device_get(jax.jit(plan_rrt)(jax.random.PRNGKey(1), obs, start, goal, P))
    n = int(r.n_nodes)
    nodes, parent, cost = r.nodes[:n], r.parent[:n], r.node_cost[:n]
    true, depth = np.zeros(n), np.zeros(n, int)
    for i in range(1, n):  # walk to the root on the host (a cycle never gets there)
        k = i
        while k != 0 and depth[i] <= n:
            true[i] += np.linalg.norm(nodes[k] - nodes[parent[k]])
            depth[i] += 1
            k = parent[k]
        assert k == 0, f"node {i} is on a cycle"
    assert depth.max() > 4  # deeper than the path buffer's pointer-jumping rounds covered
    np.testing.assert_allclose(cost, true, atol=1e-12)


def test_mixed_dtypes_integer_points_and_empty_obstacle_sets():
    """float32 points with float64 obstacles plan a float32 tree (the while loop's carry changed
    dtype); integer points are promoted; a set without any slot plans like an empty scene."""
    obs, start, goal = _simple_scene(1)
    r = plan_rrt(jax.random.PRNGKey(0), obs, jnp.asarray(start, jnp.float32), jnp.asarray(goal, jnp.float32), PARAMS)
    assert bool(r.success) and r.path.dtype == jnp.float32
    r = plan_rrt(jax.random.PRNGKey(0), make_obstacles(), [0, 0, 1], [1, 0, 1], PARAMS)
    assert bool(r.success) and jnp.issubdtype(r.path.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(r.path)[int(r.n_path) - 1], [1, 0, 1], atol=1e-12)


def test_safety_must_cover_the_edge_check_spacing():
    """Check points edge_res apart leave safety - edge_res / 2 between them: a 2 mm wall passed
    between two points with safety 2 mm; such a setting is refused, naming the field."""
    with pytest.raises(ValueError, match="RRTParams.safety"):
        RRTParams(safety=0.002)
    RRTParams(safety=0.006)  # just above edge_res / 2 = 0.005


@pytest.mark.parametrize("star", [False, True])
def test_start_at_the_goal_is_the_start_alone(star):
    """A free start at the goal is a plan of the start alone (cost 0, no tree), and its reference
    holds it at rest as a success; the planner used to make a 0.1 m out-and-back detour. A start
    at a blocked goal still fails."""
    obs, _, goal = _simple_scene(1)
    params = RRTParams(rrt_star=star, max_nodes=PARAMS.max_nodes, path_capacity=PARAMS.path_capacity)
    r = plan_rrt(jax.random.PRNGKey(0), obs, goal, goal, params)
    assert bool(r.success) and int(r.n_path) == 1 and float(r.cost) == 0.0 and int(r.n_iter) == 0
    np.testing.assert_array_equal(np.asarray(r.path), np.broadcast_to(np.asarray(goal), r.path.shape))
    quat = jnp.array([1.0, 0.0, 0.0, 0.0])
    out = plan_reference(jax.random.PRNGKey(0), obs, goal, goal, quat, 0.5, 0.01, 64, params)
    ref = out.reference
    assert bool(out.success) and int(ref.n_samples) == 1 and float(ref.rot[0]) == 1.0
    np.testing.assert_array_equal(np.asarray(ref.p[0]), np.asarray(goal))
    assert np.all(np.asarray(ref.v) == 0) and np.all(np.asarray(ref.a) == 0)
    inside = jnp.asarray(obs.spheres.p[0])  # the centre of a sphere: blocked
    r = plan_rrt(jax.random.PRNGKey(0), obs, inside, inside, params)
    assert not bool(r.success)
    out = plan_reference(jax.random.PRNGKey(0), obs, inside, inside, quat, 0.5, 0.01, 64, params)
    assert not bool(out.success)


def test_quartic_trajectory_refuses_bad_input_naming_it():
    """Waypoints that are not ``(W, 3)`` and a speed or end factor that is not finite and positive
    (a negative speed gives negative segment durations) are errors at the call; traced values (a
    caller's jit) are the caller's."""
    wp = jnp.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.3, 0.3, 0.0]])
    for args, kw, match in [((jnp.zeros(3), 2), {}, "waypoints must have shape"),
                            ((wp, 3), dict(v_init=-0.5), "v_init"), ((wp, 3), dict(v_init=0.0), "v_init"),
                            ((wp, 3), dict(end_factor=float("nan")), "end_factor")]:
        with pytest.raises(ValueError, match=match):
            quartic_trajectory(*args, **kw)
    ref = quartic_trajectory(wp, 3, v_init=0.4)
    traced = jax.jit(lambda v: quartic_trajectory(wp, 3, v_init=v))(jnp.asarray(0.4))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.allclose(a, b)), ref, traced))
