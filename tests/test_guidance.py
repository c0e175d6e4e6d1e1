"""Local-minima estimator, virtual-obstacle buffer and perfect-controller ODE (thesis 3.3.3, 3.4;
SPEC section 9)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax  # noqa: F401  (x64)
from redman_jax._fields import FieldParams, total_potential
from redman_jax._guidance import (PerfectParams, VirtualBuffer, estimate_local_minimum, goal_field_minimum,
                                  perfect_controller,
                                  perfect_controller_batch)
from redman_jax._obstacles import make_obstacles, stack_obstacles


def simple_scene(seed, x_start=(0.0, 0.0, 1.5)):
    """Simple-obstacle scene built by hand per SPEC section 4 (U18): a goal at radius 0.45-0.70 m,
    an impassable triangle of three r = 0.07 spheres (circumradius 0.16) midway and perpendicular
    to the start-goal line, and a fourth sphere beside the line."""
    rng = np.random.default_rng(seed)
    xs = np.asarray(x_start, float)
    while True:
        r, th, z = rng.uniform(0.45, 0.70), rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.0)
        xg = np.array([r * np.cos(th), r * np.sin(th), z])
        if 0.7 <= np.linalg.norm(xg - xs) <= 1.2:
            break
    u = (xg - xs) / np.linalg.norm(xg - xs)
    a = np.cross(u, [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    mid, roll = 0.5 * (xs + xg), rng.uniform(0, 2 * np.pi)
    tri = [mid + 0.16 * (np.cos(roll + k * 2 * np.pi / 3) * a + np.sin(roll + k * 2 * np.pi / 3) * b)
           for k in range(3)]
    for _ in range(100):
        s, phi = rng.uniform(0.25, 0.75), rng.uniform(0, 2 * np.pi)
        c4 = xs + s * (xg - xs) + rng.uniform(0.25, 0.35) * (np.cos(phi) * a + np.sin(phi) * b)
        if (min(np.linalg.norm(c4 - xs), np.linalg.norm(c4 - xg)) >= 0.3
                and min(np.linalg.norm(c4 - t) for t in tri) - 0.14 >= 0.2):
            break
    spheres = [(np.eye(3), c, (0.07,)) for c in tri + [c4]]
    return make_obstacles(spheres=spheres, capacities=(4, 1, 1)), xs, xg, mid


def test_buffer_is_fifo_of_last_20():
    buf = VirtualBuffer.empty(20)
    for i in range(25):
        buf = buf.push(jnp.asarray([float(i), 0.0, 0.0]), jnp.asarray(True))
    assert bool(jnp.all(buf.mask))
    assert sorted(np.asarray(buf.p[:, 0]).tolist()) == list(range(5, 25))
    same = buf.push(jnp.asarray([99.0, 0, 0]), jnp.asarray(False))
    np.testing.assert_array_equal(np.asarray(same.p), np.asarray(buf.p))
    assert int(same.head) == int(buf.head) == 5
    part = VirtualBuffer.empty(20).push(jnp.ones(3), jnp.asarray(True))
    assert int(part.mask.sum()) == 1


def test_estimate_far_from_obstacles_is_the_goal():
    """Without obstacles in range H = 2I and one Newton step lands on the goal (E13)."""
    obs = make_obstacles(spheres=[(np.eye(3), [5.0, 5.0, 5.0], (0.1,))], capacities=(1, 1, 1))
    goal = jnp.asarray([0.5, 0.2, 0.8])
    buf = VirtualBuffer.empty(20)
    x_min, ok = estimate_local_minimum(jnp.asarray([0.0, 0.0, 1.5]), goal, obs, buf.p, buf.mask, FieldParams())
    assert bool(ok)
    np.testing.assert_allclose(x_min, goal, atol=1e-6)  # mu = 1e-6 biases the step by 5e-7 relative
    far, ok2 = estimate_local_minimum(jnp.asarray([0.0, 0.0, 1.5]), goal, obs, buf.p, buf.mask, FieldParams(),
                                      max_jump=0.5)
    assert not bool(ok2)  # |x_min - x| = 0.98 m > 0.5 m: skipped


def test_estimate_is_a_newton_step_on_the_potential():
    """Near the triangle: the step equals -(H + mu I)^-1 g with g, H of the total potential by
    central finite differences (an independent route through total_potential)."""
    obs, xs, xg, mid = simple_scene(1)
    x = jnp.asarray(mid + 0.25 * (xs - mid) / np.linalg.norm(xs - mid) + np.array([0.01, -0.02, 0.015]))
    buf = VirtualBuffer.empty(20)
    fp = FieldParams()
    f = lambda y: float(total_potential(jnp.asarray(y), jnp.asarray(xg), obs, buf.p, buf.mask, fp))
    h = 1e-4
    E = np.eye(3) * h
    g = np.array([(f(x + E[i]) - f(x - E[i])) / (2 * h) for i in range(3)])
    H = np.array([[(f(x + E[i] + E[j]) - f(x + E[i] - E[j]) - f(x - E[i] + E[j]) + f(x - E[i] - E[j])) / (4 * h * h)
                   for j in range(3)] for i in range(3)])
    expect = np.asarray(x) - np.linalg.solve(H + 1e-6 * np.eye(3), g)
    x_min, ok = estimate_local_minimum(x, jnp.asarray(xg), obs, buf.p, buf.mask, fp)
    assert bool(ok)
    np.testing.assert_allclose(x_min, expect, atol=1e-4 * max(1.0, np.abs(expect - np.asarray(x)).max()))


@pytest.mark.parametrize("seed", [2, 3])
def test_perfect_controller_needs_the_estimator(seed):
    """Plain gradient descent sticks in front of the triangle; with the estimator the point reaches
    the goal and holds it, and the virtual obstacles sit around the trap (Figure 3.7)."""
    obs, xs, xg, mid = simple_scene(seed)
    plain = perfect_controller(xs, xg, obs, PerfectParams(estimator=False))
    guided = perfect_controller(xs, xg, obs, PerfectParams())
    assert not bool(plain.success) and float(plain.termination.final_err) > 0.3
    assert bool(guided.success) and bool(guided.termination.held) and not bool(guided.failed)
    n = int(guided.termination.n_samples)
    assert n < 600 and float(guided.goal_err[n - 1]) < 0.10
    assert float(jnp.min(guided.min_dist[:n])) > 0.0  # never inside an obstacle
    # estimates were placed near the trap (within 0.3 m of the triangle centre) while passing it
    est = np.asarray(guided.estimates)[np.asarray(guided.estimate_valid)]
    assert np.min(np.linalg.norm(est - mid, axis=1)) < 0.3
    assert float(guided.path_length) > np.linalg.norm(xg - xs)
    assert np.isfinite(float(guided.termination.time_to_goal))


def test_perfect_controller_batch_equals_singles():
    scenes = [simple_scene(s) for s in (2, 4)]
    obs = stack_obstacles([s[0] for s in scenes])
    x0 = jnp.asarray(np.stack([s[1] for s in scenes]))
    xg = jnp.asarray(np.stack([s[2] for s in scenes]))
    pp = PerfectParams(n_samples=200, hold_samples=20)
    batch = perfect_controller_batch(x0, xg, obs, pp)
    for i, s in enumerate(scenes):
        single = perfect_controller(s[1], s[2], s[0], pp)
        # vmapped and unbatched XLA kernels round differently (~1e-16); near the trap the guided
        # descent amplifies that (measured: 2.5e-4 m after 30 samples in front of the triangle),
        # so compare the approach before the trap tightly and the outcome exactly.
        np.testing.assert_allclose(batch.x[i, :10], single.x[:10], rtol=0, atol=1e-9)
        assert bool(batch.success[i]) == bool(single.success)
    # a float32 start with a float64 goal is promoted, as perfect_controller does (it failed in
    # the estimator's buffer update), and integer points run in the default float type (they
    # failed in jacfwd); both give the float64 batch's results
    x32 = x0.astype(jnp.float32)
    mixed, ref = (perfect_controller_batch(x, xg, obs, pp) for x in (x32, x32.astype(jnp.float64)))
    assert mixed.x.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(mixed.x), np.asarray(ref.x))
    ints = perfect_controller_batch(np.ones((2, 3), int), np.array([[1, 0, 0], [0, 1, 1]]), obs, pp)
    floats = perfect_controller_batch(np.ones((2, 3)), np.array([[1.0, 0, 0], [0, 1, 1]]), obs, pp)
    np.testing.assert_array_equal(np.asarray(ints.x), np.asarray(floats.x))


def test_perfect_controller_reports_failed_solves_and_collisions():
    """A step budget too small for the samples (3 steps per 10 ms sample at rtol 1e-5) stops the
    solves short: the run is ``failed`` and not a success (it carried on from wherever the solver
    stopped). A point started inside an obstacle has collided (``min_dist < 0``) and fails even if
    the field pushes it to the goal. A float32 start runs (the field parameters are float64)."""
    obs, xs, xg, _ = simple_scene(2)
    pp = PerfectParams(n_samples=120, hold_samples=20)
    ok = perfect_controller(xs, xg, obs, pp)
    assert not bool(ok.failed) and not bool(ok.collided) and int(ok.n_short) == 0
    short = perfect_controller(xs, xg, obs, PerfectParams(n_samples=120, hold_samples=20,
                                                          max_steps_per_sample=3, rtol=1e-12, atol=1e-14))
    assert bool(short.failed) and not bool(short.success) and int(short.n_short) > 0
    # start 1 cm from the centre of a lone sphere (radius 5 cm), the goal 0.3 m away
    c = np.asarray(xs) + np.array([0.0, 0.0, -0.5])
    one = make_obstacles(spheres=[(np.eye(3), c, (0.05,))], capacities=(1, 1, 1))
    inside = perfect_controller(c + np.array([0.01, 0.0, 0.0]), c + np.array([0.3, 0.0, 0.0]), one,
                                PerfectParams(n_samples=200, hold_samples=20))
    assert bool(inside.collided) and not bool(inside.success)
    f32 = perfect_controller(np.asarray(xs, np.float32), xg, obs, pp)
    np.testing.assert_allclose(f32.x, ok.x, rtol=0, atol=1e-6)


def test_perfect_controller_in_float32_takes_float32_tolerances():
    """Every input cast to float32: the step-size controller takes float32's default tolerances
    (1e-4 / 1e-5). float64's 1e-5 / 1e-7 sit at float32's rounding, where the error estimate is
    noise: with them (the default before it went by precision) these four runs took 8,137 / 13,284
    / 9,883 / 1,148 steps against 1,536 / 1,405 / 1,590 / 1,122, 12 samples' solves ran out of
    their step budget, and the outcome turned on rounding (with the tolerances as Python floats
    instead of float32 arrays one run failed). Same outcome as float64, no short solve."""
    from redman_jax import cast_floating
    from redman_jax._math import DEFAULT_TOLERANCES, resolve_tolerances

    assert resolve_tolerances(None, None, jnp.float32) == DEFAULT_TOLERANCES["float32"] == (1e-4, 1e-5)
    assert resolve_tolerances(None, 1e-9, jnp.float64) == (1e-5, 1e-9)
    scenes = [simple_scene(s) for s in (2, 3, 4, 5)]
    obs = stack_obstacles([s[0] for s in scenes])
    x0 = jnp.asarray(np.stack([s[1] for s in scenes]))
    xg = jnp.asarray(np.stack([s[2] for s in scenes]))
    r64 = perfect_controller_batch(x0, xg, obs, PerfectParams())
    r32 = perfect_controller_batch(*cast_floating((x0, xg, obs, PerfectParams()), jnp.float32))
    assert r32.x.dtype == jnp.float32
    assert np.all(np.asarray(r64.success)) and np.all(np.asarray(r32.success))
    assert not np.any(np.asarray(r32.failed)) and int(np.max(np.asarray(r32.n_short))) == 0
    assert np.all(np.asarray(r32.termination.final_err) < 0.10)
    # with our default parameters (float64) the float32 batch failed inside diffrax, and a float32
    # single run was promoted to float64: the parameters take the points' precision
    r32d = perfect_controller_batch(*cast_floating((x0, xg, obs), jnp.float32))
    np.testing.assert_array_equal(np.asarray(r32d.x), np.asarray(r32.x))
    obs0 = jax.tree.map(lambda x: x[0], obs)
    short = PerfectParams(n_samples=30, hold_samples=5)
    one = perfect_controller(*cast_floating((x0[0], xg[0], obs0), jnp.float32), short)
    assert one.x.dtype == jnp.float32
    with pytest.raises(ValueError, match="^obs: float64 arrays with float32 points"):
        perfect_controller(*cast_floating((x0[0], xg[0]), jnp.float32), obs0, short)


def test_bad_input_raises():
    obs, xs, xg, _ = simple_scene(1)
    with pytest.raises(ValueError, match="x0"):
        perfect_controller(np.zeros(2), xg, obs)
    # a NaN or infinite start or goal ran the descent in NaN and reported a plain failure
    with pytest.raises(ValueError, match="^x0: expected finite values"):
        perfect_controller(np.array([np.nan, 0.0, 0.5]), xg, obs)
    with pytest.raises(ValueError, match="^goal_p: expected finite values"):
        perfect_controller(xs, np.asarray(xg) * np.inf, obs)
    two = stack_obstacles([obs, obs])
    with pytest.raises(ValueError, match=r"^x0: expected shape \(S, 3\)"):
        perfect_controller_batch(np.asarray(xs), np.stack([xg, xg]), two)
    with pytest.raises(ValueError, match=r"^goal_p: expected shape \(2, 3\)"):
        perfect_controller_batch(np.stack([xs, xs]), np.asarray(xg), two)
    with pytest.raises(ValueError, match="^goal_p: expected finite values"):
        perfect_controller_batch(np.stack([xs, xs]), np.stack([xg, np.full(3, np.nan)]), two)


@pytest.mark.parametrize("clearance", [0.12, 0.15, 0.2, 0.3])
def test_goal_field_minimum_matches_the_radial_balance(clearance):
    """One sphere: the minimum lies on the ray from the centre through the goal, where the goal's
    pull 2 delta balances the obstacle's push -V_o'(c + delta) (SPEC 3, "minus" form), solved here
    by bisection on the scalar equation."""
    R, a, D = 0.1, 0.0005, 0.5
    centre = np.array([0.4, -0.2, 0.6])
    u = np.array([1.0, 2.0, -2.0]) / 3.0
    goal = centre + (R + clearance) * u
    obs = make_obstacles(spheres=[(np.eye(3), centre, (R,))], capacities=(2, 1, 1))

    def balance(delta):
        r = clearance + delta
        dv = -a * (3 / r**4 - 2 / (D * r**3)) if r < D else 0.0
        return 2 * delta + dv

    lo, hi = 0.0, 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if balance(mid) < 0 else (lo, mid)
    x, shift, gnorm = goal_field_minimum(jnp.asarray(goal), obs)
    assert float(shift) == pytest.approx(lo, abs=1e-9)
    np.testing.assert_allclose(np.asarray(x), goal + lo * u, atol=1e-9)
    assert float(gnorm) < 1e-10


def test_goal_field_minimum_without_obstacles_is_the_goal():
    obs = make_obstacles(capacities=(1, 1, 1))
    goal = jnp.asarray([0.3, 0.1, 0.5])
    x, shift, _ = goal_field_minimum(goal, obs)
    assert float(shift) == 0.0
    assert float(goal_field_minimum([0.3, 0.1, 0.5], obs)[1]) == 0.0  # a list goal (was an AttributeError)


def test_newton_step_3_matches_lapack_and_the_eigenvalue_test():
    """The unrolled L D L^T step of ``goal_field_minimum`` against ``numpy.linalg.solve`` and
    ``numpy.linalg.eigvalsh`` on random symmetric matrices: definite ones (well and badly
    conditioned, up to 1e8), indefinite, semi-definite (singular) and with a zero leading pivot."""
    from redman_jax._guidance import _newton_step_3

    rng = np.random.default_rng(3)
    cases = []
    for cond in (1.0, 1e3, 1e8):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        cases.append(Q @ np.diag([1.0, np.sqrt(cond), cond]) @ Q.T)
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        cases.append(A + A.T)  # mostly indefinite
        cases.append(A @ A.T + 0.1 * np.eye(3))  # definite
    cases.append(np.diag([1.0, 1.0, 0.0]))  # singular
    cases.append(np.array([[0.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]]))  # zero pivot, indefinite
    n_pd = 0
    for H in cases:
        g = rng.normal(size=3)
        dx, convex = _newton_step_3(jnp.asarray(H), jnp.asarray(g))
        pd = bool(np.all(np.linalg.eigvalsh(H) > 0))
        assert bool(convex) == pd, H
        if pd:
            n_pd += 1
            ref = np.linalg.solve(H, g)
            cond = np.linalg.cond(H)
            np.testing.assert_allclose(np.asarray(dx), ref, rtol=0, atol=1e-14 * cond * np.abs(ref).max() * 10)
        else:
            assert np.all(np.isfinite(np.asarray(dx)))
    assert n_pd >= 23
    # gradients through the untaken branch stay finite (double where)
    gr = jax.grad(lambda h: jnp.sum(_newton_step_3(h, jnp.ones(3))[0]))(jnp.asarray(cases[-1]))
    assert np.all(np.isfinite(np.asarray(gr)))


def test_goal_field_minimum_calls_no_lapack_kernel():
    """Vmapped over 20,000 goals, the former ``solve`` + ``eigvalsh`` step hung the process (jaxlib
    0.10's batched CPU LAPACK kernels block XLA's thread pool; README, "Known issues"). The step is
    now plain arithmetic: no LAPACK custom call in the program."""
    obs = make_obstacles(spheres=[(np.eye(3), np.array([0.4, -0.2, 0.6]), (0.1,))], capacities=(2, 1, 1))
    goals = jnp.zeros((4, 3)) + jnp.asarray([0.3, 0.1, 0.5])
    text = jax.jit(jax.vmap(lambda g: goal_field_minimum(g, obs))).lower(goals).as_text()
    assert "lapack" not in text.lower()
    assert "custom_call" not in text


def test_goal_field_minimum_refuses_bad_input_by_name():
    """A NaN goal came back as a converged minimum (shift and gradient 0), a negative max_step
    stepped uphill, a negative n_iter was taken."""
    obs = make_obstacles(capacities=(1, 1, 1))
    goal = jnp.asarray([0.3, 0.1, 0.5])
    for args, kw, match in [((goal.at[0].set(jnp.nan), obs), {}, "^goal_p: expected finite values"),
                            ((goal[:2], obs), {}, r"^goal_p: expected shape \(3,\)"),
                            ((goal, obs), dict(max_step=-0.02), "^max_step: expected a finite positive"),
                            ((goal, obs), dict(n_iter=-1), "^n_iter: expected an int >= 0")]:
        with pytest.raises(ValueError, match=match):
            goal_field_minimum(*args, **kw)


def test_bad_perfect_params_are_errors_naming_the_field():
    """Non-positive speeds, sample time, radius or jump, negative regularisation, bad tolerances
    and counts below one are refused at construction, where concrete."""
    for kw, match in [(dict(a=0.0), "PerfectParams.a"), (dict(b=float("nan")), "PerfectParams.b"),
                      (dict(ts=-0.01), "PerfectParams.ts"), (dict(radius=0.0), "PerfectParams.radius"),
                      (dict(max_jump=float("inf")), "PerfectParams.max_jump"), (dict(mu=-1.0), "PerfectParams.mu"),
                      (dict(rtol=-1e-5), "PerfectParams.rtol"), (dict(rtol=0.0, atol=0.0), "both zero"),
                      (dict(n_samples=0), "PerfectParams.n_samples"), (dict(hold_samples=1.5), "PerfectParams.hold_samples"),
                      (dict(buffer_size=0), "PerfectParams.buffer_size"),
                      (dict(max_steps_per_sample=0), "PerfectParams.max_steps_per_sample")]:
        with pytest.raises(ValueError, match=match):
            PerfectParams(**kw)
    PerfectParams(mu=0.0, atol=0.0, hold_samples=1)
    assert float(jax.jit(lambda r: PerfectParams(radius=r).radius)(jnp.asarray(0.2))) == 0.2
