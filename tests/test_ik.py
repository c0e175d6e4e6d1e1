"""Trajectory IK (redman_jax._ik): tracking, constraints, obstacle avoidance, failure flags, vmap,
validation and the reseeding pipeline.

All IK runs share one reference capacity and one obstacle capacity so that they share compilations
(the IK scan is the expensive thing to compile). References are built here by hand (independent of
the case generators): a circle with a cosine angle profile in front of the 9-DOF thesis arm,
starting and ending at rest, at a constant orientation with orientation control on.
"""

import collections
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax
from redman_jax._ik import IKParams, ik_reference, validate_ik, validated_scenarios
from redman_jax._kinematics import end_effector_pose, poi_positions
from redman_jax._nullspace import ik_policy_gains
from redman_jax._obstacles import make_obstacles, obstacle_distances
from redman_jax._scenario import Reference, Scenario

TS = 0.01
T_MOVE = 3.0
N_MOVE = int(round(T_MOVE / TS)) + 1
CAP = N_MOVE + 20  # padded capacity shared by every run
OBS_CAP = (2, 1, 1)
Q0 = jnp.array([0.0, 0.5, 0.35, -0.3, 0.6, 0.25, 0.5, -0.2, 0.0])  # bent, away from limits
# the 9-DOF thesis arm started at Q0 (every run uses arm.q0, so all runs share one compilation)
ARM = eqx.tree_at(lambda a: a.q0, redman_jax.thesis_arm(9), Q0)
# The designed obstacle: a sphere of radius 0.04 whose surface is 0.01 m from point of interest 20
# (link 5) at mid-trajectory of the obstacle-free IK, at least 0.47 m from the end-effector path and
# 0.155 m from the start configuration (found once by a search over directions around that point).
SPHERE_C = np.array([0.28156667, -0.04584368, 0.95849583])
SPHERE_R = 0.04


def _pad(x, cap):
    return np.vstack([x, np.repeat(x[-1:], cap - len(x), 0)])


def circle_reference(q0=Q0, radius=0.12, cap=CAP, offset=None) -> Reference:
    """Circle through the start end-effector position, ``theta = pi (1 - cos(pi t / T))`` (rest to
    rest), plane spanned by e1, e2; constant start orientation, rot = 1."""
    p0, quat0 = (np.asarray(v) for v in end_effector_pose(ARM, q0))
    t = np.arange(N_MOVE) * TS
    th = np.pi * (1 - np.cos(np.pi * t / T_MOVE))
    thd = np.pi**2 / T_MOVE * np.sin(np.pi * t / T_MOVE)
    thdd = np.pi**3 / T_MOVE**2 * np.cos(np.pi * t / T_MOVE)
    e1, e2 = np.array([0.0, 0.6, 0.8]), np.array([0.0, 0.8, -0.6])
    p = p0 + radius * ((np.cos(th) - 1)[:, None] * e1 + np.sin(th)[:, None] * e2)
    v = radius * ((-np.sin(th) * thd)[:, None] * e1 + (np.cos(th) * thd)[:, None] * e2)
    a = radius * ((-np.cos(th) * thd**2 - np.sin(th) * thdd)[:, None] * e1
                  + (-np.sin(th) * thd**2 + np.cos(th) * thdd)[:, None] * e2)
    if offset is not None:  # a far target: the final samples jump away (unreachable)
        p[-50:] += offset
    P, V, A = _pad(p, cap), _pad(v, cap), _pad(a, cap)
    V[N_MOVE - 1:] = 0
    A[N_MOVE - 1:] = 0
    return Reference(p=jnp.asarray(P), v=jnp.asarray(V), a=jnp.asarray(A), quat=jnp.tile(jnp.asarray(quat0), (cap, 1)),
                     omega=jnp.zeros((cap, 3)), omega_dot=jnp.zeros((cap, 3)), rot=jnp.ones(cap),
                     mask=jnp.arange(cap) < N_MOVE, n_samples=jnp.asarray(N_MOVE), ts=jnp.asarray(TS))


def free_obstacles():
    return make_obstacles(capacities=OBS_CAP)


def sphere_obstacles():
    return make_obstacles(spheres=[(np.eye(3), SPHERE_C, [SPHERE_R])], capacities=OBS_CAP)


def scenario(ref, obs) -> Scenario:
    return Scenario(obstacles=obs, goal_p=ref.p[-1], goal_quat=ref.quat[-1], reference=ref,
                    seed=jnp.asarray(0), seed_used=jnp.asarray(0), valid=jnp.asarray(True), case="custom")


def with_gamma(gamma, **kw):
    return IKParams(policy=eqx.tree_at(lambda p: p.gamma, ik_policy_gains(), jnp.asarray(gamma)), **kw)


@pytest.fixture(scope="module")
def free_run():
    ref = circle_reference()
    return ref, ik_reference(ARM, ref, free_obstacles(), IKParams())


@pytest.fixture(scope="module")
def sphere_runs():
    """The designed case: QP obstacle constraint only (gamma = 0), constraint + policy (default),
    and neither (activation < 0 switches the constraint rows off)."""
    ref, obs = circle_reference(), sphere_obstacles()
    bind = ik_reference(ARM, ref, obs, with_gamma(0.0))
    default = ik_reference(ARM, ref, obs, IKParams())
    none = ik_reference(ARM, ref, obs, with_gamma(0.0, activation=-1.0))
    return ref, obs, bind, default, none


def test_tracks_reachable_path(free_run):
    """Obstacle-free circle: the joint path reproduces the end-effector path within 1 mm and the
    orientation within 1e-3 at every sample (errors measured at q_k by forward kinematics)."""
    ref, res = free_run
    q = np.asarray(res.q[:N_MOVE])
    fk = jax.vmap(lambda qq: end_effector_pose(ARM, qq))(jnp.asarray(q))
    e_p = np.linalg.norm(np.asarray(fk[0]) - np.asarray(ref.p[:N_MOVE]), axis=1)
    quat_d = np.asarray(ref.quat[0])
    ori = np.abs(np.asarray(fk[1]) @ quat_d)  # |cos(phi / 2)|
    e_o = np.sqrt(np.maximum(1 - ori**2, 0))  # |e_o| = sin(phi / 2)
    assert e_p.max() < 1e-3
    assert e_o.max() < 1e-3
    np.testing.assert_allclose(np.asarray(res.ee_error[:N_MOVE]), e_p, atol=1e-12)
    assert bool(res.valid) and bool(jnp.all(res.qp_converged))
    # the path moves the arm (not a trivial pass): the end effector crosses the 0.24 m circle
    p_fk = np.asarray(fk[0])
    assert np.linalg.norm(p_fk - p_fk[0], axis=1).max() > 0.2
    # padding: q frozen at the final sample, zero velocity and acceleration
    assert np.allclose(res.q[N_MOVE:], res.q[N_MOVE - 1]) and not np.any(res.qd[N_MOVE - 1:])
    # qdd is the backward difference of qd (3.41's last step)
    np.testing.assert_allclose(res.qdd[1:N_MOVE - 1], np.diff(res.qd[:N_MOVE - 1], axis=0) / TS, atol=1e-9)
    np.testing.assert_allclose(res.q[1:N_MOVE], res.q[:N_MOVE - 1] + TS * res.qd[:N_MOVE - 1], atol=1e-12)


def _check_constraints(ref, obs, res, params):
    """Every bound at every sample: acceleration |qd_k - qd_{k-1}| <= 40 ts, joint limits, and the
    linearised obstacle constraint on the 16 closest active pairs, recomputed here by autodiff of
    the distance along the joint path (not the IK's point Jacobians)."""
    n = N_MOVE - 1
    q, qd = np.asarray(res.q), np.asarray(res.qd)
    tol = 1e-8  # QP residuals are <= 1e-9 (checked below) on velocities of order 1
    dqd = np.diff(np.vstack([np.zeros(ARM.n_dof), qd[:n]]), axis=0)
    assert np.abs(dqd).max() <= float(params.acc_limit) * TS + tol
    lim = np.asarray(ARM.limited)
    assert np.all(q[:, lim] >= np.asarray(ARM.q_min)[lim] - tol)
    assert np.all(q[:, lim] <= np.asarray(ARM.q_max)[lim] + tol)
    assert float(res.qp_primal.max()) <= 1e-9

    def pair_dist(qq, i, o):
        return obstacle_distances(obs, poi_positions(ARM, qq)[i])[o]

    grad = jax.jit(jax.vmap(jax.grad(pair_dist), in_axes=(None, 0, 0)))
    dist = jax.jit(lambda qq: jax.vmap(lambda x: obstacle_distances(obs, x))(poi_positions(ARM, qq)))
    worst, n_active = np.inf, 0
    for k in range(n):
        D = np.asarray(dist(q[k]))
        flat = np.argsort(D.ravel())[:16]
        i, o = np.unravel_index(flat, D.shape)
        act = D[i, o] < float(params.activation)
        if not act.any():
            continue
        g = np.asarray(grad(q[k], jnp.asarray(i[act]), jnp.asarray(o[act])))
        lhs = D[i, o][act] + TS * g @ qd[k]
        worst = min(worst, (lhs - float(params.margin)).min())
        n_active += int(act.sum())
    return worst, n_active


def test_constraint_binds_and_arm_goes_around(sphere_runs):
    ref, obs, bind, default, none = sphere_runs
    # without any obstacle handling the link passes through the sphere
    assert float(none.min_distance.min()) < 0.0
    assert not bool(none.collision_free) and not bool(validate_ik(ARM, scenario(ref, obs), none))
    # with the QP constraint alone it binds (distance held at the 0.11 margin) and the arm goes
    # around: collision free, valid, still tracking (1 cm; the constraint competes with the task)
    assert 0.105 < float(bind.min_distance.min()) < 0.1105
    assert bool(bind.valid) and bool(validate_ik(ARM, scenario(ref, obs), bind))
    assert float(bind.ee_error.max()) < 1e-2
    assert np.abs(np.asarray(bind.q) - np.asarray(none.q)).max() > 0.05
    # with the null-space policy too (default), the arm keeps clear earlier and tracks within 1 mm
    assert float(default.min_distance.min()) > 0.11
    assert bool(default.valid) and float(default.ee_error.max()) < 1e-3


def test_every_constraint_holds_when_active(sphere_runs):
    ref, obs, bind, _, _ = sphere_runs
    worst, n_active = _check_constraints(ref, obs, bind, with_gamma(0.0))
    assert n_active > 50  # the obstacle rows were active for many samples
    assert worst >= -1e-8


def test_unreachable_target_gives_failure_flag():
    ref = circle_reference(offset=np.array([2.5, 0.0, 0.0]))
    res = ik_reference(ARM, ref, free_obstacles(), IKParams())
    assert not bool(res.valid) and not bool(res.reached)
    assert float(res.final_error) > 1.0
    for leaf in (res.q, res.qd, res.qdd, res.ee_error, res.qp_primal):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert bool(res.finite)


def test_vmap_over_seeds_equals_single_runs(free_run, sphere_runs):
    ref, single_free = free_run
    _, obs, _, single_sphere, _ = sphere_runs
    refs = jax.tree.map(lambda *x: jnp.stack(x), ref, ref)
    obss = jax.tree.map(lambda *x: jnp.stack(x), free_obstacles(), obs)
    batch = ik_reference(ARM, refs, obss, IKParams())
    for b, single in enumerate((single_free, single_sphere)):
        np.testing.assert_allclose(batch.q[b], single.q, atol=1e-9)
        np.testing.assert_allclose(batch.qd[b], single.qd, atol=1e-7)
        assert bool(batch.valid[b]) == bool(single.valid)
    scen = jax.tree.map(lambda *x: jnp.stack(x), scenario(ref, free_obstacles()), scenario(ref, obs))
    np.testing.assert_array_equal(np.asarray(validate_ik(ARM, scen, batch)), np.asarray(batch.valid))


def test_stop_on_invalid_stops_a_colliding_run_and_changes_nothing_else(free_run, sphere_runs):
    """Screening (the retry rounds of validated_scenarios): in a batch of the free circle and the
    circle through the sphere with the obstacle handling off (a collision), the colliding run takes
    no QP iteration after its first collision and holds its configuration; the free run and every
    flag are the same to the bit, and both settings run one compiled program."""
    from conftest import backend_compiles

    ref, _ = free_run
    _, obs, _, _, _ = sphere_runs
    params = with_gamma(0.0, activation=-1.0)
    refs = jax.tree.map(lambda *x: jnp.stack(x), ref, ref)
    obss = jax.tree.map(lambda *x: jnp.stack(x), free_obstacles(), obs)
    full = jax.tree.map(np.asarray, ik_reference(ARM, refs, obss, params))
    with backend_compiles() as seen:
        screened = jax.tree.map(np.asarray, ik_reference(ARM, refs, obss, params, stop_on_invalid=True))
    assert seen == []
    assert full.valid.tolist() == [True, False] and not full.collision_free[1]
    for name in ("valid", "collision_free", "within_limits", "finite"):
        np.testing.assert_array_equal(getattr(screened, name), getattr(full, name), err_msg=name)
    for name in ("q", "qd", "qdd", "qp_iterations", "clearance"):
        np.testing.assert_array_equal(getattr(screened, name)[0], getattr(full, name)[0], err_msg=name)
    k = int(np.argmax(full.clearance[1] < 0))  # the first collision
    assert 0 < k < N_MOVE - 2
    for name in ("q", "qd", "qp_iterations", "clearance"):  # the same up to it
        np.testing.assert_array_equal(getattr(screened, name)[1, :k + 1], getattr(full, name)[1, :k + 1],
                                      err_msg=name)
    assert np.all(screened.qp_iterations[1, k + 1:] == 0) and np.all(full.qp_iterations[1, k + 1:N_MOVE - 1] > 0)
    assert np.all(screened.qd[1, k + 1:] == 0)
    np.testing.assert_array_equal(screened.q[1, k + 2:], np.broadcast_to(screened.q[1, k + 1], screened.q[1, k + 2:].shape))


def test_policy_from_shared_distances_matches_nullspace_module():
    """The IK evaluates 3.34 from its one distance pass; it must equal _nullspace.obstacle_policy."""
    from redman_jax._ik import _geometry, _policy
    from redman_jax._kinematics import kinematics
    from redman_jax._nullspace import joint_limit_policy, obstacle_policy

    @jax.jit
    def both(q, obs, pol):
        kin = kinematics(ARM, q)
        _, poi_jac, D, normals = _geometry(ARM, kin, q, obs)
        ours = _policy(ARM, q, D, normals, poi_jac, pol)
        ref = (obstacle_policy(ARM, kin, q, obs, pol.gamma, pol.obs_a, pol.obs_D)
               + joint_limit_policy(ARM, q, pol.jl_a, pol.jl_outside))
        return ours, ref

    ours, ref = both(Q0 + 0.1, sphere_obstacles(), ik_policy_gains())
    np.testing.assert_allclose(ours, ref, rtol=1e-10, atol=1e-10)
    assert float(jnp.abs(ref).max()) > 1e-3


def test_k_smallest_equals_top_k():
    """The IK's pair selection equals ``lax.top_k(-x, k)``: values ascending, the same indices,
    ties broken by the lowest index, also when ``k`` equals the size."""
    from redman_jax._ik import _k_smallest

    rng = np.random.default_rng(3)
    for x in (rng.uniform(0, 2, 5328), np.round(rng.uniform(0, 1, 300), 1), rng.normal(size=16)):
        for k in (1, 5, 16):
            v, i = jax.jit(_k_smallest, static_argnums=1)(jnp.asarray(x), k)
            neg, j = jax.lax.top_k(-jnp.asarray(x), k)
            np.testing.assert_array_equal(np.asarray(v), -np.asarray(neg))
            np.testing.assert_array_equal(np.asarray(i), np.asarray(j))


def test_bad_input_raises():
    ref = circle_reference()
    with pytest.raises(ValueError, match="q0"):
        ik_reference(ARM, ref, free_obstacles(), IKParams(), jnp.zeros(3))
    # a NaN start made every sample NaN and the trajectory silently invalid
    with pytest.raises(ValueError, match="^q0: expected finite values"):
        ik_reference(ARM, ref, free_obstacles(), IKParams(), jnp.asarray(Q0).at[2].set(jnp.nan))
    with pytest.raises(ValueError, match="method"):
        IKParams(method="newton")
    # a reference that cannot be run: ts = 0 made the whole trajectory NaN (read as an invalid
    # scene, so silently reseeded), a zero quaternion with rot = 1 and 0 samples gave valid=True
    quat_off = ref.quat.at[3].set(0.0)
    for field, value, match in [("ts", jnp.asarray(0.0), "ts: expected a finite sample time > 0"),
                                ("ts", jnp.asarray(jnp.nan), "ts: expected a finite sample time > 0"),
                                ("n_samples", jnp.asarray(0), "n_samples: expected 1 to"),
                                ("quat", quat_off, "quat: expected unit quaternions"),
                                ("p", ref.p.at[2, 1].set(jnp.inf), "p: expected finite values"),
                                ("rot", ref.rot.at[4].set(0.5), "rot: expected flags 0 or 1")]:
        broken = eqx.tree_at(lambda r: getattr(r, field), ref, value)
        with pytest.raises(ValueError, match=f"^Reference.{match}"):
            ik_reference(ARM, broken, free_obstacles(), IKParams())
    with pytest.raises(ValueError, match=r"^seed: must be a non-negative int, got .*2\.5"):
        validated_scenarios("warehouse", [2.5, 7.9], ARM, max_retries=0)  # was truncated to 2, 7
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), ref)  # a batch is checked whole
    with pytest.raises(ValueError, match="^Reference.quat: expected unit quaternions"):
        ik_reference(ARM, eqx.tree_at(lambda r: r.quat, batch, batch.quat.at[1, 3].set(0.0)),
                     jax.tree.map(lambda x: jnp.stack([x, x]), free_obstacles()), IKParams())
    # a zero or NaN acceleration bound made every bound NaN and every candidate silently invalid
    for kw, field in [({"acc_limit": 0.0}, "acc_limit"), ({"acc_limit": float("nan")}, "acc_limit"),
                      ({"goal_tolerance": -0.1}, "goal_tolerance"), ({"w": -1e-4}, "w"),
                      ({"ns_speed_limit": 0.0}, "ns_speed_limit"), ({"K_r": -40.0}, "K_r"),
                      ({"obstacle_rate": -1.0}, "obstacle_rate"), ({"margin": float("nan")}, "margin"),
                      ({"activation": float("nan")}, "activation")]:
        with pytest.raises(ValueError, match=f"IKParams.{field}"):
            IKParams(**kw)
    IKParams(ns_speed_limit=float("inf"), activation=-1.0, K_r=0.0, obstacle_rate=0.0)  # documented settings stay valid


def test_padded_samples_carry_no_qp_diagnostics(free_run):
    """Past ``n_samples`` the QP iteration and constraint counts are 0, like the other fields."""
    ref, res = free_run
    n = int(res.n_samples)
    assert n < res.q.shape[0], "the circle reference must be padded for this test"
    assert np.all(np.asarray(res.qp_iterations)[n:] == 0) and np.all(np.asarray(res.n_constrained)[n:] == 0)
    assert np.any(np.asarray(res.qp_iterations)[:n] > 0)


def test_validated_scenarios_reseeds(monkeypatch):
    """The pipeline keeps the first valid candidate per seed and records seed_used. A fake
    generator: seed 1's first candidate has the sphere but no obstacle handling possible (its
    reference is unreachable), seed + 1000 is the free circle."""
    import redman_jax._cases as cases

    calls = []

    def fake_make_scenarios(case, seeds, arm, params=None, validate=None, max_retries=20, stats=None):
        # mimic the generator's loop: move a seed on by 1000 when validate rejects it
        seeds = list(seeds)
        attempt = [0] * len(seeds)
        out = [None] * len(seeds)
        pending = list(range(len(seeds)))
        while pending:
            cands = []
            for i in pending:
                su = seeds[i] + 1000 * attempt[i]
                bad = seeds[i] == 1 and attempt[i] == 0
                ref = circle_reference(offset=np.array([2.5, 0, 0])) if bad else circle_reference()
                s = scenario(ref, sphere_obstacles())
                cands.append(eqx.tree_at(lambda s: (s.seed, s.seed_used), s, (jnp.asarray(seeds[i]), jnp.asarray(su))))
            batch = jax.tree.map(lambda *x: jnp.stack(x), *cands)
            calls.append(len(cands))
            ok = validate(batch)
            for j, i in enumerate(pending):
                if ok[j]:
                    out[i] = cands[j]
                else:
                    attempt[i] += 1
            pending = [i for i in pending if out[i] is None and attempt[i] <= max_retries]
        return jax.tree.map(lambda *x: jnp.stack(x), *out)

    monkeypatch.setattr(cases, "make_scenarios", fake_make_scenarios)
    # q0 of the fake scenes is arm.q0 (straight column): use an arm whose q0 is Q0
    arm = ARM
    stats = collections.Counter()
    scen, res = validated_scenarios("custom", [1, 2], arm, max_retries=2, stats=stats)
    assert calls == [2, 1]
    assert stats["ik_rounds"] == 2 and stats["ik_batch_qp_iterations"] > 0
    np.testing.assert_array_equal(np.asarray(scen.seed_used), [1001, 2])
    np.testing.assert_array_equal(np.asarray(scen.seed), [1, 2])
    assert np.all(np.asarray(res.valid)) and res.q.shape == (2, CAP, ARM.n_dof)


def test_a_seed_without_a_valid_candidate_gets_its_last_candidates_full_ik(monkeypatch, sphere_runs):
    """The retry rounds screen (``stop_on_invalid``), but what comes back for a seed that found no
    valid candidate is its last candidate's whole IK, as without screening (``screen=False``),
    which iterates the rounds' QPs more."""
    import redman_jax._cases as cases

    ref, obs, _, _, _ = sphere_runs
    params = with_gamma(0.0, activation=-1.0)  # the circle through the sphere collides

    def always_colliding(case, seeds, arm, params=None, validate=None, max_retries=20, stats=None):
        s = scenario(ref, obs)
        for attempt in range(max_retries + 1):
            s = eqx.tree_at(lambda s: s.seed_used, s, jnp.asarray(seeds[0] + 1000 * attempt))
            assert not validate(jax.tree.map(lambda x: x[None], s))[0]
        return jax.tree.map(lambda x: x[None], eqx.tree_at(lambda s: s.valid, s, jnp.asarray(False)))

    monkeypatch.setattr(cases, "make_scenarios", always_colliding)
    full = ik_reference(ARM, ref, obs, params)
    k = int(np.argmax(np.asarray(full.clearance) < 0))
    assert k > 0
    stats = {}
    for screen in (True, False):
        stats[screen] = {}
        scen, res = validated_scenarios("custom", [3], ARM, max_retries=3, params=params, screen=screen,
                                        stats=stats[screen])
        assert int(scen.seed_used[0]) == 3003 and not bool(res.valid[0])
        assert int(np.asarray(res.qp_iterations[0, k + 1:]).sum()) > 0  # not stopped
        np.testing.assert_allclose(np.asarray(res.q[0]), np.asarray(full.q), rtol=0, atol=1e-12)
    assert stats[True]["ik_rounds"] == 5 and stats[False]["ik_rounds"] == 4  # + the full IK
    assert stats[True]["ik_batch_qp_iterations"] < stats[False]["ik_batch_qp_iterations"]


def test_importing_redman_jax_starts_no_jax_backend():
    """The IK's default parameters are built at the call, not at import (they were default
    arguments holding arrays): ``import redman_jax`` starts no JAX backend, so that a user can still
    call ``jax.distributed.initialize()``, set XLA options or pin the process after it, as JAX
    requires before its backend starts. Nor does it load matplotlib: the figures' functions are
    imported when first asked for (by attribute, ``from redman_jax import``, or ``dir``)."""
    import os
    import subprocess
    import sys

    script = textwrap.dedent("""
        import sys
        import redman_jax
        from jax._src import xla_bridge
        print(xla_bridge.backends_are_initialized(), "matplotlib" in sys.modules)
        from redman_jax import plot_field_slice
        from redman_jax._plots import plot_field_slice as direct, plot_scenario
        print(plot_field_slice is direct, redman_jax.plot_scenario is plot_scenario,
              {"plot_scenario", "plot_field_slice"} <= set(dir(redman_jax)), "matplotlib" in sys.modules)
        try:
            redman_jax.plot_nothing
        except AttributeError as e:
            print(e)
        """)
    proc = subprocess.run([sys.executable, "-c", script], env=dict(os.environ, JAX_PLATFORMS="cpu"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert lines[0].split() == ["False", "False"]
    assert lines[1].split() == ["True"] * 4
    assert lines[2] == "module 'redman_jax' has no attribute 'plot_nothing'"


def test_float32_ik_runs_with_default_params_and_tracks_float64():
    """A float32 arm and scenario with the default (float64) ``IKParams`` failed in ``lax.scan``
    (its carry promoted to float64); with the parameters cast by hand the QPs stopped at the float32
    tolerance 1e-4 far from optimal in the null space, and on this 7-DOF warehouse scene the IK
    drifted 0.88 m off (joint limits and clearance broken) where float64's is valid."""
    from redman_jax._cases import make_scenario
    from redman_jax._ik import ik_trajectory
    from redman_jax._math import cast_floating

    arm = redman_jax.thesis_arm(7)
    sc = make_scenario("warehouse", 2, arm)
    r64 = ik_trajectory(arm, sc)
    r32 = ik_trajectory(cast_floating(arm, jnp.float32), cast_floating(sc, jnp.float32))
    assert r32.q.dtype == jnp.float32 and bool(r64.valid)
    assert bool(r32.valid) and float(r32.final_error) < 0.01
