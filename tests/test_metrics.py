"""Evaluation measures (thesis 3.5 and 4; SPEC section 10)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax  # noqa: F401  (x64)
from redman_jax._math import quat_mul
from redman_jax._metrics import (aggregate_errors, failure_rate, guidance_termination, masked_mean,
                                 orientation_errors, path_length, per_run_mean, pooled_mean,
                                 position_errors, run_metrics, time_per_call,
                                 wall_time_per_sample)


def _axis_angle(axis, phi):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(phi / 2)], np.sin(phi / 2) * axis])


def test_orientation_error_is_sin_half_angle():
    """E19: 45 deg gives 0.383, 90 deg gives 0.707; independent of the reference attitude and of
    the quaternion sign."""
    rng = np.random.default_rng(0)
    qd = _axis_angle(rng.normal(size=3), 0.7)
    phis = np.array([0.0, np.pi / 4, np.pi / 2, 2.0])
    qs = np.stack([np.asarray(quat_mul(jnp.asarray(_axis_angle(rng.normal(size=3), -p)), jnp.asarray(qd)))
                   for p in phis])
    qs[1] *= -1.0  # sign flip must not matter
    e = orientation_errors(jnp.asarray(qs), jnp.asarray(np.tile(qd, (4, 1))))
    np.testing.assert_allclose(e, np.sin(phis / 2), atol=1e-12)
    np.testing.assert_allclose(float(e[1]), 0.38268343236, atol=1e-10)


def test_position_errors_and_path_length():
    p = jnp.asarray([[0.0, 0, 0], [3.0, 4.0, 0], [3.0, 4.0, 1.0]])
    pd = jnp.zeros((3, 3))
    np.testing.assert_allclose(position_errors(p, pd), [0.0, 5.0, np.sqrt(26.0)])
    assert float(path_length(jnp.zeros(3), p, jnp.asarray([True, True, False]))) == pytest.approx(5.0)
    assert np.isnan(float(masked_mean(jnp.ones(3), jnp.zeros(3, bool))))


def test_non_finite_poses_give_nan_errors_and_zero_gradients_stay():
    """A NaN pose (a run whose solve stopped) is a NaN error, never 0; an inf one is inf. A zero
    difference still has a zero, not NaN, gradient (the tuning losses differentiate these)."""
    p = jnp.asarray([[jnp.nan, 0.0, 0.0], [1.0, 0.0, 0.0], [jnp.inf, 0.0, 0.0]])
    e = np.asarray(position_errors(p, jnp.zeros((3, 3))))
    assert np.isnan(e[0]) and e[1] == 1.0 and e[2] == np.inf
    assert np.isnan(float(path_length(jnp.zeros(3), p, jnp.ones(3, bool))))
    assert float(path_length(jnp.zeros(3), p, jnp.asarray([False, False, False]))) == 0.0
    qn = jnp.asarray([[jnp.nan, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    eo = np.asarray(orientation_errors(qn, jnp.asarray([[1.0, 0, 0, 0]] * 2)))
    assert np.isnan(eo[0]) and eo[1] == 0.0
    g = jax.grad(lambda x: jnp.sum(position_errors(x, jnp.zeros((2, 3)))))(jnp.zeros((2, 3)))
    assert np.all(np.asarray(g) == 0.0)
    g = jax.grad(lambda x: jnp.sum(position_errors(x, jnp.zeros((1, 3)))))(jnp.asarray([[3.0, 4.0, 0.0]]))
    np.testing.assert_allclose(g, [[0.6, 0.8, 0.0]])


def test_run_metrics_failure_rules():
    e = jnp.asarray([0.01, 0.02, 0.03, 0.5])
    rot = jnp.asarray([0.0, 0.0, 1.0, 1.0])
    mask = jnp.asarray([True, True, True, False])
    m = run_metrics(e, e, rot, mask, jnp.asarray(0.05), jnp.asarray(0.0), jnp.asarray(0.2), False)
    assert float(m.mean_pos_err) == pytest.approx(0.02) and float(m.mean_ori_err) == pytest.approx(0.03)
    assert bool(m.success) and bool(m.joint_limit) and int(m.cause) == 0  # contact is not a failure
    m = run_metrics(e, e, rot, mask, jnp.asarray(0.05), jnp.asarray(1e-3), jnp.asarray(0.0), False)
    assert not bool(m.success) and int(m.cause) == 1
    m = run_metrics(e, e, rot, mask, jnp.asarray(0.11), jnp.asarray(0.0), jnp.asarray(0.0), False)
    assert not bool(m.success) and int(m.cause) == 2


def test_guidance_termination():
    N, ts = 600, 0.01
    err = np.full(N, 0.5)
    err[50:60] = 0.05  # a short visit: not held
    err[200:] = 0.05  # enters for good at sample 200
    t = guidance_termination(jnp.asarray(err), ts, hold_samples=100)
    assert bool(t.held) and bool(t.success)
    assert int(t.n_samples) == 300  # samples 200..299 are the 100 held sample ends
    assert float(t.time_to_goal) == pytest.approx(2.01)
    assert int(t.mask.sum()) == 300
    never = guidance_termination(jnp.full(N, 0.3), ts)
    assert not bool(never.success) and int(never.n_samples) == N and np.isinf(float(never.time_to_goal))
    late = np.full(N, 0.3)
    late[-30:] = 0.05  # reached at the end without the hold: the final error decides (U26)
    t = guidance_termination(jnp.asarray(late), ts)
    assert not bool(t.held) and bool(t.success) and int(t.n_samples) == N
    assert not bool(guidance_termination(jnp.asarray(err), ts, collided=True).success)


def test_pooled_vs_per_run():
    err = jnp.asarray([[1.0, 1.0, 1.0, 1.0], [3.0, 0.0, 0.0, 0.0], [100.0, 100.0, 100.0, 100.0]])
    mask = jnp.asarray([[True, True, True, True], [True, False, False, False], [True] * 4])
    ok = jnp.asarray([True, True, False])  # the failed run is excluded
    assert float(pooled_mean(err, mask, ok)) == pytest.approx(7.0 / 5.0)
    assert float(per_run_mean(err, mask, ok)) == pytest.approx(2.0)
    assert float(aggregate_errors(err, mask, ok, "per_run")) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="pooling"):
        aggregate_errors(err, mask, ok, "median")
    assert float(failure_rate(ok)) == pytest.approx(1 / 3)
    assert float(failure_rate(ok, valid=jnp.asarray([False, True, True]))) == pytest.approx(1 / 2)
    assert np.isnan(float(failure_rate(ok, valid=jnp.zeros(3, bool))))  # no valid run: was 0 %


def test_time_per_call_positive():
    t = time_per_call(lambda x: jnp.sin(x) @ x, jnp.ones(8), n_calls=20)
    assert 0.0 < t < 1.0
    # 0 calls divided by zero, a negative count returned a negative time
    for kw, match in [(dict(n_calls=0), "^n_calls: expected an int >= 1"),
                      (dict(n_calls=-5), "^n_calls: expected an int >= 1"),
                      (dict(n_calls=2.5), "^n_calls: expected an int >= 1"),
                      (dict(warmup=-1), "^warmup: expected an int >= 0")]:
        with pytest.raises(ValueError, match=match):
            time_per_call(lambda x: x, jnp.ones(2), **kw)


def test_wall_time_per_sample_divides_by_all_samples_of_a_batch(monkeypatch):
    """A batch's call is divided by the samples of all its runs, a single run's by its own (a fake
    clock that advances 1 s per reading, so the call takes exactly 1 s)."""
    import itertools

    import redman_jax._metrics as metrics

    x, f = np.ones(2), (lambda x: x)  # no JAX work inside the timed call
    clock = itertools.count()
    monkeypatch.setattr(metrics.time, "perf_counter", lambda: float(next(clock)))
    one = wall_time_per_sample(f, x, n_samples=10, warmup=0)
    batch = wall_time_per_sample(f, x, n_samples=np.array([10, 10, 10, 10]), warmup=0)
    monkeypatch.undo()
    assert one == 1.0 / 10 and batch == 1.0 / 40


def _timing_scene():
    """A 7-DOF arm, the velocity OSC, an environment with a sphere and a box in reach, and K = 6
    samples of distinct states and reference samples."""
    import redman_jax as rj
    from redman_jax._control_types import ControlState, RefSample, make_environment
    from redman_jax._controllers import CONTROLLERS

    arm = rj.thesis_arm(7)
    n, K = arm.n_dof, 6
    rng = np.random.default_rng(3)
    ctrl = CONTROLLERS["velocity"]()
    obs = rj.make_obstacles(spheres=[(np.eye(3), [0.35, 0.0, 0.9], [0.08])],
                            boxes=[(np.eye(3), [-0.3, 0.3, 1.0], [0.1, 0.05, 0.2])], capacities=(1, 1, 1))
    env = make_environment(obs, jnp.asarray([0.3, 0.2, 0.8]), jnp.asarray([1.0, 0.0, 0.0, 0.0]))
    q = jnp.asarray(np.asarray(arm.q0) + rng.uniform(-0.4, 0.4, (K, n)))
    qd = jnp.asarray(rng.normal(0.0, 0.3, (K, n)))
    z = jax.vmap(lambda a, b: ctrl.init_state(arm, a, b))(q, qd)
    states = ControlState(t=jnp.arange(K) * 0.01, q=q, qd=qd, z=z)
    quat = rng.normal(size=(K, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    z3, zn = jnp.zeros((K, 3)), jnp.zeros((K, n))
    refs = RefSample(p=jnp.asarray(rng.uniform(-0.3, 0.3, (K, 3)) + [0, 0, 0.9]), v=jnp.asarray(rng.normal(size=(K, 3))),
                     a=z3, quat=jnp.asarray(quat), omega=z3, omega_dot=z3, rot=jnp.asarray([1.0, 0.0] * (K // 2)),
                     q=zn, qd=zn, qdd=zn)
    return arm, ctrl, ctrl.default_gains(), states, refs, env


def test_the_timed_loop_is_the_control_law_at_every_sample():
    """What ``controller_time_per_sample`` times (``control_torques``) returns, sample by sample,
    the torques of single calls of the controller."""
    from redman_jax._metrics import control_torques

    arm, ctrl, gains, states, refs, env = _timing_scene()
    taus = jax.jit(control_torques, static_argnums=0)(ctrl, gains, arm, states, refs, env)
    for k in range(states.q.shape[0]):
        one = ctrl(gains, arm, jax.tree.map(lambda x: x[k], states), jax.tree.map(lambda x: x[k], refs), env).tau
        np.testing.assert_allclose(np.asarray(taus[k]), np.asarray(one), rtol=1e-9, atol=1e-9)
    assert float(jnp.std(taus[:, 0])) > 0  # distinct samples, distinct torques


def test_controller_time_per_sample_divides_one_loop_call_by_its_samples(monkeypatch):
    """One call over the K samples, timed (a fake clock: every call takes 1 s), divided by K; the
    least of ``repeats`` calls. Bad shapes are refused naming the field."""
    import itertools

    import redman_jax._metrics as metrics
    from redman_jax._metrics import controller_call_time, controller_time_per_sample

    arm, ctrl, gains, states, refs, env = _timing_scene()
    real = controller_time_per_sample(ctrl, gains, arm, states, refs, env, repeats=2)
    assert 0.0 < real < 0.01
    assert 0.0 < controller_call_time(ctrl, gains, arm, jax.tree.map(lambda x: x[0], states),
                                      jax.tree.map(lambda x: x[0], refs), env, n_calls=3) < 0.1
    clock = itertools.count()
    monkeypatch.setattr(metrics.time, "perf_counter", lambda: float(next(clock)))
    assert controller_time_per_sample(ctrl, gains, arm, states, refs, env, repeats=3) == 1.0 / 6
    monkeypatch.undo()
    one = jax.tree.map(lambda x: x[0], states)
    with pytest.raises(ValueError, match=r"states.q must have shape \(K, 7\)"):
        controller_time_per_sample(ctrl, gains, arm, one, refs, env)
    with pytest.raises(ValueError, match="leading sample axis of states.q"):
        controller_time_per_sample(ctrl, gains, arm, states, jax.tree.map(lambda x: x[:4], refs), env)
    with pytest.raises(ValueError, match="^repeats: expected an int >= 1"):
        controller_time_per_sample(ctrl, gains, arm, states, refs, env, repeats=0)
