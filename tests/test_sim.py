"""Closed-loop simulator: zero-order hold, tracking, collision flags, batching, failure isolation,
determinism and gradients (SPEC sections 5, 9, 10).

The toy controllers below are independent of ``_controllers.py`` (exact computed torque in joint and
operational space), so every test has an analytic or brute-force reference. Problem sizes are
small (7-DOF arm, <= 0.8 s horizons) to keep the file well under a minute.
"""

import dataclasses
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax  # x64, and cast_floating
from redman_jax._control_types import AbstractController, ControlOutput
from redman_jax._dynamics import dynamics_terms
from redman_jax._kinematics import jacobian, jacobian_from, jdot_qdot, kinematics, end_effector_pose
from redman_jax._obstacles import make_obstacles
from redman_jax._robot import thesis_arm
from redman_jax._scenario import Reference, Scenario, stack_scenarios
from redman_jax._sim import SimParams, simulate, simulate_batch, simulate_dense

TS = 0.01


# ----------------------------------------------------------------------------------------------
# toy controller (public so that test_metrics can reuse it)
#
# One controller class holds four independent control laws selected by an array of weights, so
# that the whole file compiles the simulator only once per entry point (compile time dominates).


class ToyGains(eqx.Module):
    w: jax.Array  # (4,) weights of the laws [osc, joint, velocity, held-acceleration]
    kp: jax.Array  # (3,) position gains of [osc, joint, velocity]
    kd: jax.Array  # (3,) damping gains of [osc, joint, velocity (K_dq)]
    kn: jax.Array  # null-space damping (osc) / K_pq (velocity)


def toy_gains(law, kp=None, kd=None, kn=None):
    """Gains selecting one law: "osc", "joint", "velocity" or "held"."""
    i = ["osc", "joint", "velocity", "held"].index(law)
    w = jnp.zeros(4).at[i].set(1.0)
    kp = jnp.asarray([250.0, 1000.0, 10.0]) if kp is None else jnp.asarray(kp)
    kd = jnp.asarray([31.0, 100.0, 100.0]) if kd is None else jnp.asarray(kd)
    kn = jnp.asarray(10.0) if kn is None else jnp.asarray(kn)
    return ToyGains(w=w, kp=kp, kd=kd, kn=kn)


class Toy(AbstractController):
    """Four exact computed-torque laws, ``tau = M qdd + c + g``:

    * osc: ``qdd = J#(a_d + K_d(v_d - v) + K_p(p_d - p) - Jdot qd) + N(-k_n qd)`` (position rows);
    * joint: ``qdd = qdd_d + K_d(qd_d - qd) + K_p(q_d - q)`` (2.5 on the held IK reference);
    * velocity: ``qd_r = J#(v_d + K_p(p_d - p))``, ``z = q_r``, ``qdd = K_pq(q_r - q) + K_dq(qd_r - qd)``
      (structure of 3.10-3.11, with an integrated state);
    * held: open loop, ``qdd = e_0 a_d[0]`` (joint 0 follows the held acceleration exactly).
    """

    def default_gains(self):
        return toy_gains("osc")

    def init_state(self, arm, q0, qd0):
        return q0

    def __call__(self, gains, arm, state, ref, env):
        q, qd = state.q, state.qd
        kin = kinematics(arm, q)
        M, h = dynamics_terms(arm, q, qd, kin)
        J = jacobian_from(kin)[:3]
        eye3 = jnp.eye(3, dtype=J.dtype)
        Jp = J.T @ jnp.linalg.solve(J @ J.T + 1e-4 * eye3, eye3)
        p = kin.ee[:3, 3]
        xdd = ref.a + gains.kd[0] * (ref.v - J @ qd) + gains.kp[0] * (ref.p - p)
        N = jnp.eye(arm.n_dof, dtype=J.dtype) - Jp @ J
        osc = Jp @ (xdd - jdot_qdot(arm, q, qd)[:3]) + N @ (-gains.kn * qd)
        joint = ref.qdd + gains.kd[1] * (ref.qd - qd) + gains.kp[1] * (ref.q - q)
        qdr = Jp @ (ref.v + gains.kp[2] * (ref.p - p))
        vel = gains.kn * (state.z - q) + gains.kd[2] * (qdr - qd)
        held = jnp.zeros_like(q).at[0].set(ref.a[0])
        qdd = gains.w[0] * osc + gains.w[1] * joint + gains.w[2] * vel + gains.w[3] * held
        return ControlOutput(tau=M @ qdd + h, dz=gains.w[2] * qdr, diag={})


# ----------------------------------------------------------------------------------------------
# scenarios


def _quintic(T, t):
    T = max(T, TS)
    s = np.clip(t / T, 0.0, 1.0)
    inside = t <= T
    return (10 * s**3 - 15 * s**4 + 6 * s**5, np.where(inside, (30 * s**2 - 60 * s**3 + 30 * s**4) / T, 0.0),
            np.where(inside, (60 * s - 180 * s**2 + 120 * s**3) / T**2, 0.0))


def joint_motion_scenario(arm, dq, T, capacity, spheres=(), seed=0):
    """A rest-to-rest quintic joint motion ``q0 -> q0 + dq`` over ``T`` s, its exact operational
    reference (FK, ``J qd``, ``J qdd + Jdot qd``) and joint reference ``(q, qd, qdd)``."""
    t = np.arange(capacity) * TS
    s, sd, sdd = _quintic(T, t)
    dq = np.asarray(dq, float)
    q = np.asarray(arm.q0) + s[:, None] * dq
    qd, qdd = sd[:, None] * dq, sdd[:, None] * dq
    p, quat = jax.vmap(lambda x: end_effector_pose(arm, x))(jnp.asarray(q))
    J = jax.vmap(lambda x: jacobian(arm, x))(jnp.asarray(q))
    v = jnp.einsum("kij,kj->ki", J, qd)
    w = jnp.einsum("kij,kj->ki", J[:, 3:], qd)
    acc = jnp.einsum("kij,kj->ki", J, qdd) + jax.vmap(lambda a, b: jdot_qdot(arm, a, b))(jnp.asarray(q), jnp.asarray(qd))
    n = int(round(T / TS)) + 1
    ref = Reference(p=p, v=v[:, :3], a=acc[:, :3], quat=quat, omega=w, omega_dot=acc[:, 3:],
                    rot=jnp.zeros(capacity), mask=jnp.arange(capacity) < n, n_samples=jnp.asarray(n),
                    ts=jnp.asarray(TS))
    obs = make_obstacles(spheres=[(np.eye(3), c, (r,)) for c, r in spheres], capacities=(2, 1, 1))
    sc = Scenario(obstacles=obs, goal_p=p[n - 1], goal_quat=quat[n - 1], reference=ref, seed=jnp.asarray(seed),
                  seed_used=jnp.asarray(seed), valid=jnp.asarray(True), case="custom")
    return sc, (jnp.asarray(q), jnp.asarray(qd), jnp.asarray(qdd))


ARM = thesis_arm(7)
CAP = 50  # every scenario of this file has 50 samples, so the simulator compiles once
DQ_FREE = [0.6, 0.15, 0.35, -0.3, 0.25, 0.2, 0.4]  # stays inside the limits, away from obstacles
CTRL = Toy()


def run(sc, jref, law="osc", params=None, **kw):
    return simulate(ARM, sc, CTRL, toy_gains(law), ik=jref, params=params, **kw)


@pytest.fixture(scope="module")
def free():
    return joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP)


# ----------------------------------------------------------------------------------------------
# tests


def test_zero_order_hold_is_exact_and_left_closed():
    """Joint 0 integrates a held, random acceleration: with steps that never straddle a sample
    boundary the piecewise-polynomial solution is reproduced to round-off, and the hold is the
    left-closed interval ``[k t_s, (k+1) t_s)`` (an off-by-one would be O(a t_s^2) = 1e-3)."""
    N = CAP
    a = np.random.default_rng(0).uniform(-20, 20, N)
    sc, jref = joint_motion_scenario(ARM, np.zeros(7), 0.0, N)
    ref = eqx.tree_at(lambda r: (r.a, r.n_samples, r.mask), sc.reference,
                      (jnp.zeros((N, 3)).at[:, 0].set(a), jnp.asarray(N), jnp.ones(N, bool)))
    sc = eqx.tree_at(lambda s: s.reference, sc, ref)
    res = run(sc, jref, "held")
    qd_exact = TS * np.cumsum(a)
    q_exact = np.cumsum(TS * (np.concatenate([[0.0], qd_exact[:-1]])) + 0.5 * a * TS**2)
    np.testing.assert_allclose(res.qd[:, 0], qd_exact, rtol=0, atol=1e-11)
    np.testing.assert_allclose(res.q[:, 0] - ARM.q0[0], q_exact, rtol=0, atol=1e-11)
    np.testing.assert_allclose(res.qd[:, 1:], 0.0, atol=1e-12)
    assert int(res.status) == 0 and not bool(res.diverged)


@pytest.mark.parametrize("law", ["osc", "velocity", "joint"])
def test_free_space_tracking_no_flags(free, law):
    sc, jref = free
    res = run(sc, jref, law)
    m = res.metrics
    # The held reference moves at most v t_s per sample (< 1.5 cm here); every loop keeps the
    # sample-end error at that scale, and the rest-to-rest motion converges at the end.
    step = np.linalg.norm(np.diff(np.asarray(sc.reference.p), axis=0), axis=1).max()
    assert float(jnp.max(jnp.where(res.mask, res.pos_err, 0))) < 2 * step
    # (the velocity loop, K_p = 10 1/s, has 0.1 s after the motion to converge: e^-1 of ~1.5 cm)
    assert float(m.final_pos_err) < 0.01
    assert not bool(m.collided) and not bool(m.joint_limit) and bool(m.success)
    assert float(res.f_obs[-1]) == 0.0 and float(res.f_jl[-1]) == 0.0
    assert float(jnp.min(res.min_dist)) > 0.10
    assert int(res.status) == 0 and not bool(res.diverged)


def test_obstacle_flag_fires_on_collision():
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP)
    mid = np.asarray(sc.reference.p[20])
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP, spheres=[(mid, 0.05)])
    res = run(sc, jref, "osc")
    assert float(res.f_obs[-1]) > 0 and bool(res.metrics.collided)
    assert not bool(res.metrics.success) and int(res.metrics.cause) == 1
    assert float(jnp.min(res.min_dist)) < 0.10
    assert float(res.f_obs[5]) == 0.0  # not before the arm got there


def test_obstacle_slot_layouts_give_the_same_run():
    """A scene of 40 sphere slots (the colliding sphere and 39 padded ones) run with one slot per
    scan step and with the automatic grouping (all 40 slots in one step at batch 2): the same
    trajectory (bit for bit, except for the joint components that are numerically zero at the
    first sample end, about 1e-36 rad: the two layouts are two compiled programs, and under Dopri5
    that noise rounds about 10 ulp apart), distances to rounding and the same collision flag."""
    from redman_jax._obstacles import pad_obstacles

    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP)
    mid = np.asarray(sc.reference.p[20])
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP, spheres=[(mid, 0.05)])
    sc = eqx.tree_at(lambda s: s.obstacles, sc, pad_obstacles(sc.obstacles, (40, 1, 1)))
    scs = stack_scenarios([sc, sc])
    jrefs = jax.tree.map(lambda *x: jnp.stack(x), jref, jref)
    g = toy_gains("osc")
    one = simulate_batch(ARM, scs, CTRL, g, ik=jrefs, params=SimParams(slots_per_step=1))
    auto = simulate_batch(ARM, scs, CTRL, g, ik=jrefs)
    assert bool(one.metrics.collided[0]) and bool(auto.metrics.collided[0])
    q_auto, q_one = np.asarray(auto.q), np.asarray(one.q)
    zero = np.abs(q_one) < 1e-30  # rounding noise of components that are exactly 0 in exact arithmetic
    np.testing.assert_array_equal(q_auto[~zero], q_one[~zero])
    assert np.all(np.abs(q_auto[zero]) < 1e-30)
    np.testing.assert_allclose(np.asarray(auto.min_dist), np.asarray(one.min_dist), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(np.asarray(auto.f_obs), np.asarray(one.f_obs), rtol=1e-12, atol=1e-12)


def test_cases_padded_to_common_shapes_share_one_compilation():
    """Two "cases" with different reference and obstacle capacities, padded to common shapes
    (``_pipeline.pad_case``, what the study does): the second one reuses the first one's compiled
    simulation, and both give the runs of their unpadded versions (valid samples)."""
    from conftest import backend_compiles

    from redman_jax._pipeline import pad_case

    a, ja = joint_motion_scenario(ARM, DQ_FREE, 0.3, 40)
    mid = np.asarray(a.reference.p[15])
    b, jb = joint_motion_scenario(ARM, np.asarray(DQ_FREE) * 0.7, 0.4, CAP, spheres=[(mid, 0.05)])
    b = eqx.tree_at(lambda s: s.obstacles, b, rj_pad(b.obstacles, (3, 2, 1)))
    batch = lambda sc, j: (stack_scenarios([sc, sc]), tuple(jnp.stack([x, x]) for x in j))
    shapes = (CAP, (3, 2, 1))
    g = toy_gains("osc")
    results = []
    for sc, j in ((a, ja), (b, jb)):
        scp, jp = pad_case(*batch(sc, j), shapes)
        assert scp.reference.capacity == CAP and scp.obstacles.capacities == (3, 2, 1)
        with backend_compiles() as compiles:
            padded = simulate_batch(ARM, scp, CTRL, g, ik=jp)
            jax.block_until_ready(padded.q)
        results.append((len(compiles), padded, simulate_batch(ARM, *batch(sc, j)[:1], CTRL, g, ik=batch(sc, j)[1])))
    assert results[1][0] == 0  # no new compilation for the second case
    for _, padded, plain in results:
        n = int(plain.n_samples[0])
        np.testing.assert_allclose(np.asarray(padded.q)[:, :n], np.asarray(plain.q)[:, :n], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(padded.metrics.mean_pos_err), np.asarray(plain.metrics.mean_pos_err),
                                   rtol=1e-10)
        assert np.array_equal(np.asarray(padded.metrics.collided), np.asarray(plain.metrics.collided))
    assert bool(results[1][1].metrics.collided[0])


def rj_pad(obs, caps):
    from redman_jax._obstacles import pad_obstacles

    return pad_obstacles(obs, caps)


def test_joint_limit_flag_fires_past_a_limit():
    """Drive the lift (Pz, limits [0, 1.2]) to -0.05 m: the contact (3.6) stops it near 0 and the
    joint-limit flag integrates the time spent outside; an obstacle-free run stays a success."""
    dq = np.zeros(7)
    dq[1] = -0.25
    sc, jref = joint_motion_scenario(ARM, dq, 0.3, CAP)
    res = run(sc, jref, "joint")
    assert float(res.f_jl[-1]) > 0 and bool(res.metrics.joint_limit)
    assert float(res.f_jl[10]) == 0.0
    assert not bool(res.metrics.collided)
    assert float(jnp.min(res.q[:, 1])) < 0.0


def test_modes_agree(free):
    """The whole-horizon solve and the per-sample scan integrate the same hybrid system."""
    sc, jref = free
    a = run(sc, jref, "velocity")
    b = run(sc, jref, "velocity", params=SimParams(mode="per_sample"))
    # both at rtol 1e-5 / atol 1e-7 on a 0.4 s motion: agreement well below 1e-4 m
    np.testing.assert_allclose(a.p, b.p, atol=2e-5)
    np.testing.assert_allclose(a.f_obs, b.f_obs, atol=0)


def test_padding_past_the_last_sample_is_nearly_free(free):
    """A run whose scenario ends after 5 of its 50 samples of capacity: the first 5 samples equal
    the full run's (the same steps; the fifth sample end is read from a different interpolant, to
    rounding), the state is frozen afterwards, and the padded 45 samples cost
    a few growing steps instead of at least one step each (no jump times there)."""
    sc, jref = free
    full = run(sc, jref, "osc")
    short = eqx.tree_at(lambda s: s.reference.n_samples, sc, jnp.asarray(5))
    res = run(short, jref, "osc")
    np.testing.assert_array_equal(np.asarray(res.q[:4]), np.asarray(full.q[:4]))
    np.testing.assert_allclose(np.asarray(res.q[4]), np.asarray(full.q[4]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(res.q[5:]), np.broadcast_to(np.asarray(res.q[4]), res.q[5:].shape))
    assert int(res.n_steps) < 5 + 45 // 2, int(res.n_steps)
    assert int(res.status) == 0 and not bool(res.diverged)


def test_determinism(free):
    sc, jref = free
    a = run(sc, jref, "osc")
    b = run(sc, jref, "osc")
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def free_batch(seed, count):
    """``count`` free joint motions (random fractions of ``DQ_FREE``): the (scenario, joint
    reference) pairs, the scenarios and the stacked joint references."""
    rng = np.random.default_rng(seed)
    pairs = [joint_motion_scenario(ARM, np.asarray(DQ_FREE) * rng.uniform(0.5, 1.0, 7), 0.4, CAP, seed=i)
             for i in range(count)]
    return pairs, [p[0] for p in pairs], jax.tree.map(lambda *x: jnp.stack(x), *[p[1] for p in pairs])


def with_nan_reference(scs, i):
    """The scenarios with a NaN in member ``i``'s reference (sample 10)."""
    bad = list(scs)
    bad[i] = eqx.tree_at(lambda s: s.reference.p, bad[i], bad[i].reference.p.at[10, 0].set(jnp.nan))
    return stack_scenarios(bad)


def test_a_nan_member_leaves_the_batchs_gradient_finite():
    """Reverse mode through a batch with shared gains: a member poisoned by a NaN reference is
    gated off in the vector field, but its zero cotangent met the control law's NaN partials
    (0 * NaN = NaN) and the gains' gradient, summed over the batch, was NaN for every member. The
    closed loop now reads a NaN state or reference as 0 (the member stays flagged), so the batch's
    gradient of a loss of the healthy members is the clean batch's.

    The same through the run's metrics: the poisoned member's NaN errors (NaN - p_d) had a NaN
    partial in the norm behind their where, and its zero cotangent times NaN was NaN for all. Both
    losses are rows of one reverse-mode Jacobian (one program, two cotangents)."""
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.1, 15)
    batch = stack_scenarios([sc, sc])
    J = jax.tree.map(lambda x: jnp.stack([x, x]), jref)
    bad = eqx.tree_at(lambda s: s.reference.p, batch, batch.reference.p.at[1, 5, 0].set(jnp.nan))

    def losses(kp, scen):
        r = simulate_batch(ARM, scen, CTRL, toy_gains("osc", kp=jnp.stack([kp, 1000.0, 10.0])), ik=J)
        final = jnp.sum(jnp.where(r.diverged, 0.0, jnp.sum(r.q[:, -1] ** 2, axis=-1)))
        metric = r.metrics.mean_pos_err[0] + r.metrics.final_pos_err[0]
        return jnp.stack([final, metric]), (final, r.diverged)

    jac = jax.jit(jax.jacrev(losses, has_aux=True))
    (g0, gm0), (v0, d0) = jac(250.0, batch)
    (g1, gm1), (v1, d1) = jac(250.0, bad)
    assert np.asarray(d0).tolist() == [False, False] and np.asarray(d1).tolist() == [False, True]
    assert np.isfinite(float(g1)) and float(g0) != 0.0
    np.testing.assert_allclose(float(v1), float(v0) / 2, rtol=1e-12)
    np.testing.assert_allclose(float(g1), float(g0) / 2, rtol=1e-9)
    assert np.isfinite(float(gm0)) and float(gm0) != 0.0
    np.testing.assert_allclose(float(gm1), float(gm0), rtol=1e-9)


def test_batch_equals_single_runs_and_nan_is_isolated():
    pairs, scs, jrefs = free_batch(3, 4)
    g = toy_gains("osc")
    batch = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs)
    for i, (sc, jref) in enumerate(pairs):
        single = run(sc, jref, "osc")
        np.testing.assert_allclose(batch.q[i], single.q, rtol=0, atol=1e-12)
        assert int(batch.n_steps[i]) == int(single.n_steps)
    assert not np.any(np.asarray(batch.diverged))
    # inject a NaN into member 2's reference: it is flagged, the others are bit-identical
    poisoned = simulate_batch(ARM, with_nan_reference(scs, 2), CTRL, g, ik=jrefs)
    assert bool(poisoned.diverged[2]) and not bool(poisoned.metrics.success[2])
    assert not np.any(np.asarray(poisoned.out_of_steps))  # flagged, not out of its step budget
    assert int(poisoned.metrics.cause[2]) == 3
    assert np.all(np.isfinite(np.asarray(poisoned.q[2])))  # frozen, not NaN
    for i in (0, 1, 3):
        for x, y in zip(jax.tree.leaves(batch), jax.tree.leaves(poisoned)):
            np.testing.assert_array_equal(np.asarray(x)[i], np.asarray(y)[i])


def test_threads_split_the_batch_and_change_nothing_but_rounding():
    """``simulate_batch(threads=2)`` on 5 members (chunks of 3, the second padded with a copy of
    member 4): every member takes the same steps and gets the same flags as in one call, its
    trajectory agrees to rounding (two compiled programs, batch 3 and 5), and a NaN injected into
    one member is flagged there and leaves the others as they were in the threaded clean batch."""
    _, scs, jrefs = free_batch(5, 5)
    g = toy_gains("osc")
    one = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs, threads=1)
    two = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs, threads=2)
    assert jax.tree.structure(one) == jax.tree.structure(two)
    for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(two)):
        assert np.shape(x) == np.shape(y)
    np.testing.assert_array_equal(np.asarray(two.n_steps), np.asarray(one.n_steps))
    np.testing.assert_array_equal(np.asarray(two.metrics.success), np.asarray(one.metrics.success))
    np.testing.assert_allclose(np.asarray(two.q), np.asarray(one.q), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(two.metrics.mean_pos_err), np.asarray(one.metrics.mean_pos_err),
                               rtol=1e-9)
    # per-member initial states are split with their members
    q0 = jnp.asarray(ARM.q0) + 0.01 * jnp.arange(5.0)[:, None]
    one0 = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs, q0=q0, threads=1)
    two0 = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs, q0=q0, threads=2)
    np.testing.assert_allclose(np.asarray(two0.q), np.asarray(one0.q), rtol=0, atol=1e-12)
    assert np.abs(np.asarray(two0.q[:, 0] - two.q[:, 0])).max() > 1e-3  # q0 did change the runs
    poisoned = simulate_batch(ARM, with_nan_reference(scs, 3), CTRL, g, ik=jrefs, threads=2)
    assert bool(poisoned.diverged[3]) and not np.any(np.asarray(poisoned.diverged)[[0, 1, 2, 4]])
    for i in (0, 1, 2, 4):
        for x, y in zip(jax.tree.leaves(two), jax.tree.leaves(poisoned)):
            np.testing.assert_array_equal(np.asarray(x)[i], np.asarray(y)[i])


def test_threads_is_checked_and_follows_the_cores():
    from redman_jax._sim import _MIN_CHUNK, _chunks

    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.4, CAP)
    scs = stack_scenarios([sc, sc])
    jrefs = jax.tree.map(lambda *x: jnp.stack(x), jref, jref)
    for bad in (0, -1, True, 1.5, "2"):
        with pytest.raises(ValueError, match="threads"):
            simulate_batch(ARM, scs, CTRL, toy_gains("osc"), ik=jrefs, threads=bad)
    with pytest.raises(ValueError, match="threads=2 needs concrete inputs"):
        jax.jit(lambda s: simulate_batch(ARM, s, CTRL, toy_gains("osc"), ik=jrefs, threads=2))(scs)
    assert _chunks(2, 5, ()) == 2 and _chunks(8, 3, ()) == 3 and _chunks(1, 40, ()) == 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    expected = 1 if jax.default_backend() != "cpu" else max(1, min(cores, 40 // _MIN_CHUNK))
    assert _chunks(None, 40, ()) == expected
    assert _chunks(None, _MIN_CHUNK - 1, ()) == 1
    assert _chunks(None, 40, (jnp.ones(2),)) == expected  # concrete arrays are no trace


def test_a_solve_out_of_steps_is_flagged_diverged_and_nothing_else(free):
    """A budget of one step per sample stops the solve early (``throw=False``): diffrax fills the
    rows it did not reach with ``inf``. The run is reported as diverged (cause 3) and nothing else:
    the flags are read from the rows it reached (an ``inf`` flag row read as a collision and a
    joint-limit hit before), and its errors on unreached samples are NaN, not 0 (the NaN pose went
    through a norm that returned 0)."""
    sc, jref = free
    res = run(sc, jref, "osc", params=SimParams(max_steps_per_sample=1, rtol=1e-10))
    m = res.metrics
    assert int(res.status) != 0 and bool(res.diverged) and int(m.cause) == 3 and not bool(m.success)
    assert bool(res.out_of_steps)
    f_obs = np.asarray(res.f_obs)
    assert not np.all(np.isfinite(f_obs)), "the solve was meant to stop early"
    assert not bool(m.collided) and not bool(m.joint_limit)
    pos_err = np.asarray(res.pos_err)
    assert np.all(np.isnan(pos_err[~np.isfinite(np.asarray(res.q)).all(axis=1)]))
    assert np.isnan(float(m.mean_pos_err)) and float(m.final_pos_err) == np.inf


def test_a_contact_or_divergence_seen_only_at_a_negative_stage_weight_still_counts():
    """The flags are integrated like the state: one Dopri5 step sums its stages with the weights
    b = (35/384, 0, 500/1113, 125/192, -2187/6784, 11/84, 0). A contact indicator that is 1 only
    around the fifth stage's time (c = 8/9) leaves the flag at -2187/6784 after the step; the run's
    flags are read by absolute value (``_final_flags``), so it still counts as a contact, while no
    contact at all leaves exactly 0."""
    import diffrax

    from redman_jax._sim import _Y, _diverged, _final_flags

    def flag_after_one_step(window):
        def vf(t, y, args):
            inside = (t > window[0]) & (t < window[1])
            return jnp.stack([inside, jnp.zeros_like(inside)]).astype(y.dtype)

        sol = diffrax.diffeqsolve(diffrax.ODETerm(vf), diffrax.Dopri5(), 0.0, 1.0, 1.0, jnp.zeros(2),
                                  saveat=diffrax.SaveAt(ts=jnp.array([0.0, 1.0])))
        return sol.ys  # rows (t = 0, t = 1), columns (obstacle, joint limit)

    ys = flag_after_one_step((8 / 9 - 0.01, 8 / 9 + 0.01))
    assert float(ys[1, 0]) == pytest.approx(-2187 / 6784, rel=1e-12)
    f = jnp.concatenate([ys, jnp.zeros((2, 1))], axis=1)
    rows = jnp.array([True, True])
    flags = _final_flags(f, rows)
    assert float(flags[0]) > 0 and float(flags[1]) == 0.0
    assert float(jnp.max(f[:, 0])) == 0.0  # what the largest value alone reported
    quiet = jnp.concatenate([flag_after_one_step((2.0, 3.0)), jnp.zeros((2, 1))], axis=1)
    assert float(_final_flags(quiet, rows)[0]) == 0.0
    # the divergence flag (column 2) is read the same way: a stage out of bounds seen only at the
    # negative weight is a divergence; no such stage is none
    q = jnp.zeros((2, 3))
    seen = _Y(q=q, qd=q, z=jnp.zeros((2, 0)), f=jnp.concatenate([jnp.zeros((2, 2)), ys[:, :1]], axis=1))
    assert bool(_diverged(seen, jnp.int32(0), rows))
    none = _Y(q=q, qd=q, z=jnp.zeros((2, 0)), f=jnp.zeros((2, 3)))
    assert not bool(_diverged(none, jnp.int32(0), rows))


def test_gradients_match_finite_differences(free):
    """d(tracking loss)/d(gains, q0) by the RecursiveCheckpointAdjoint against central finite
    differences of the same simulator. Tight tolerances (1e-10) make the discrete solution a smooth
    function of the parameters at the FD scale (relative eps 1e-4); agreement to 1e-4."""
    sc, jref = free
    params = SimParams(rtol=1e-10, atol=1e-12)

    def loss(theta):
        g = toy_gains("osc", kp=jnp.stack([theta[0], 1000.0, 10.0]), kd=jnp.stack([theta[1], 100.0, 100.0]),
                      kn=theta[2])
        r = simulate(ARM, sc, CTRL, g, ik=jref, params=params, q0=ARM.q0.at[2].add(theta[3]))
        return jnp.sum(jnp.where(r.mask, r.pos_err**2, 0.0))

    # one compiled program gives the gradient and the finite differences' values (a separate
    # forward program would compile again: ~20 s)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    value = lambda th: float(value_and_grad(th)[0])
    theta = jnp.asarray([250.0, 31.0, 10.0, 0.05])
    grad = np.asarray(value_and_grad(theta)[1])
    eps = np.asarray(theta) * 1e-4
    fd = np.array([(value(theta.at[i].add(eps[i])) - value(theta.at[i].add(-eps[i]))) / (2 * eps[i])
                   for i in range(4)])
    assert np.all(np.isfinite(grad)) and np.all(np.abs(fd) > 0)
    np.testing.assert_allclose(grad, fd, rtol=1e-4)


def test_dense_resimulation_matches_sample_ends(free):
    sc, jref = free
    res = run(sc, jref, "velocity")
    t, k, q, p, quat, e, eo = simulate_dense(ARM, sc, CTRL, toy_gains("velocity"), ik=jref, points_per_sample=5)
    np.testing.assert_allclose(np.asarray(e)[4::5], np.asarray(res.pos_err), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(t)[4::5], np.asarray(res.t))


class _NeedsJoints(Toy):
    @property
    def needs_joint_reference(self):
        return True


def test_bad_input_raises():
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.2, 30)
    with pytest.raises(ValueError, match="ik"):
        simulate(ARM, sc, _NeedsJoints(), toy_gains("joint"))
    with pytest.raises(ValueError, match="SimParams.mode"):
        SimParams(mode="bogus")
    with pytest.raises(ValueError, match="SimParams.solver"):
        SimParams(solver="rk4")
    # the numbers, where concrete: a negative or NaN tolerance, both tolerances zero, a bound that is
    # not positive (inf: none), a PID coefficient that is not finite
    for kw, match in [(dict(rtol=-1e-5), "SimParams.rtol"), (dict(atol=float("nan")), "SimParams.atol"),
                      (dict(rtol=0.0, atol=0.0), "both zero"), (dict(q_bound=0.0), "SimParams.q_bound"),
                      (dict(qd_bound=float("nan")), "SimParams.qd_bound"),
                      (dict(q_bound=-float("inf")), "SimParams.q_bound"),
                      (dict(goal_radius=-0.1), "SimParams.goal_radius"),
                      (dict(pcoeff=float("inf")), "SimParams.pcoeff"),
                      (dict(max_steps_per_sample=0), "SimParams.max_steps_per_sample"),
                      (dict(hold_samples=0), "SimParams.hold_samples"),
                      (dict(guidance_samples=60.0), "SimParams.guidance_samples"),
                      (dict(buffer_size=0), "SimParams.buffer_size")]:
        with pytest.raises(ValueError, match=match):
            SimParams(**kw)
    SimParams(atol=0.0, q_bound=float("inf"), icoeff=0.0, pcoeff=0.4)  # valid: relative only, no bound
    jax.jit(lambda r: SimParams(rtol=r).rtol)(jnp.asarray(1e-4))  # traced numbers are the caller's
    with pytest.raises(ValueError, match="scenario.reference.p"):
        simulate_batch(ARM, sc, CTRL, toy_gains("osc"))
    with pytest.raises(ValueError, match="ik.q"):
        simulate(ARM, sc, CTRL, toy_gains("osc"), ik=(jref[0][:10], jref[1], jref[2]))


def test_bad_initial_state_and_gains_raise_by_name():
    """``q0`` / ``qd0`` of the wrong shape, or holding a NaN or an infinity, are refused at the call,
    by name: before, a NaN ``q0`` ran the whole run in NaN (flagged as diverged) and a wrong shape
    failed inside ``kinematics``. Traced ones (a caller's ``vmap``) pass to the caller's checks.
    So are the gains of another controller (an ``AttributeError`` inside the law) and batched gains
    without the runs' leading axis (a ``vmap`` size error)."""
    sc, _ = joint_motion_scenario(ARM, DQ_FREE, 0.2, 30)
    n, q = ARM.n_dof, np.asarray(ARM.q0)
    g = toy_gains("osc")
    bad = [(dict(q0=q[:-1]), rf"^q0: expected shape \({n},\)"),
           (dict(q0=np.where(np.arange(n) == 1, np.nan, q)), "^q0: expected finite values"),
           (dict(q0=q, qd0=np.full(n, np.inf)), "^qd0: expected finite values"),
           (dict(qd0=np.zeros((1, n))), rf"^qd0: expected shape \({n},\)")]
    for kw, match in bad:
        with pytest.raises(ValueError, match=match):
            simulate(ARM, sc, CTRL, g, **kw)
        with pytest.raises(ValueError, match=match):
            simulate_dense(ARM, sc, CTRL, g, **kw)
    batch = stack_scenarios([sc, sc])
    with pytest.raises(ValueError, match=rf"^q0: expected shape \(2, {n}\)"):
        simulate_batch(ARM, batch, CTRL, g, q0=q)
    with pytest.raises(ValueError, match="^q0: expected finite values"):
        simulate_batch(ARM, batch, CTRL, g, q0=np.stack([q, q * np.nan]))
    # gains of another controller's class; batch_gains without the runs' leading axis
    with pytest.raises(ValueError, match="^gains: Toy takes ToyGains, got VelocityGains"):
        simulate(ARM, sc, CTRL, redman_jax.VelocityOSC().default_gains())
    three = jax.tree.map(lambda x: jnp.stack([x, x, x]), g)
    with pytest.raises(ValueError, match=r"^gains\.w: batch_gains=True needs a leading axis of 2 runs, got shape \(3, 4\)"):
        simulate_batch(ARM, batch, CTRL, three, batch_gains=True)
    with pytest.raises(ValueError, match=r"^gains\.w: batch_gains=True needs a leading axis of 2 runs, got shape \(4,\)"):
        simulate_batch(ARM, batch, CTRL, g, batch_gains=True)
    # traced: the shape is checked, the values are the caller's
    out = jax.vmap(lambda qq: simulate(ARM, sc, CTRL, g, q0=qq).metrics.final_pos_err)(jnp.stack([q, q]))
    assert np.all(np.isfinite(np.asarray(out)))
    # no gains (or a dict) for a controller whose gains are a Module: an AttributeError inside
    for gains in (None, {"kp": 1.0}):
        with pytest.raises(ValueError, match="^gains: Toy takes ToyGains"):
            simulate(ARM, sc, CTRL, gains)
    # a reference that cannot be run: no samples, more samples than rows, a sample time <= 0
    # (before: NaN errors, rows that do not exist, or nothing integrated, all with status 0)
    ref = sc.reference
    for field, value, match in [("n_samples", 0, "n_samples: expected 1 to 30"),
                                ("n_samples", 31, "n_samples: expected 1 to 30"),
                                ("ts", 0.0, "ts: expected a finite sample time > 0"),
                                ("ts", -0.01, "ts: expected a finite sample time > 0")]:
        broken = eqx.tree_at(lambda s: getattr(s.reference, field), sc, jnp.asarray(value, getattr(ref, field).dtype))
        with pytest.raises(ValueError, match=f"^scenario.reference.{match}"):
            simulate(ARM, broken, CTRL, g)
    # a zero goal quaternion on a sample with rot = 1 made the orientation error 0 there
    broken = eqx.tree_at(lambda s: s.reference.quat, sc, ref.quat.at[2].set(0.0))
    with pytest.raises(ValueError, match=r"^scenario.reference.quat: expected unit quaternions"):
        simulate(ARM, broken, CTRL, g)
    with pytest.raises(ValueError, match="^points_per_sample: expected an int >= 1"):
        simulate_dense(ARM, sc, CTRL, g, points_per_sample=0)


def test_bad_goal_precision_joint_reference_and_sim_params_raise_by_name():
    """Each was accepted and failed deep inside the run (an AttributeError, a cond's dtype error,
    a broadcasting or vmap size error) or ran silently wrong (a NaN goal read as "goal not
    reached", a NaN joint reference as a divergence)."""
    sc, jref = joint_motion_scenario(ARM, DQ_FREE, 0.2, 30)
    g, jl = toy_gains("osc"), toy_gains("joint")
    for kw, match in [(dict(field="plus"), "^SimParams.field: expected a FieldParams"),
                      (dict(contact=None), "^SimParams.contact: expected a LimitContact")]:
        with pytest.raises(ValueError, match=match):
            SimParams(**kw)
    for broken, match in [(eqx.tree_at(lambda s: s.goal_p, sc, sc.goal_p.at[0].set(jnp.nan)),
                           "^scenario.goal_p: expected finite values"),
                          (eqx.tree_at(lambda s: s.goal_quat, sc, jnp.zeros(4)),
                           "^scenario.goal_quat: expected unit quaternions")]:
        with pytest.raises(ValueError, match=match):
            simulate(ARM, broken, CTRL, g)
    f32 = redman_jax.cast_floating(sc, jnp.float32)
    mixed = eqx.tree_at(lambda s: s.obstacles, f32, sc.obstacles)  # float64 obstacles, float32 run
    with pytest.raises(ValueError, match="^scenario.obstacles: float64 arrays with a float32 scenario"):
        simulate(redman_jax.cast_floating(ARM, jnp.float32), mixed, CTRL, redman_jax.cast_floating(g, jnp.float32))
    q, qd, qdd = jref
    with pytest.raises(ValueError, match=r"^ik.q: expected shape \(30, 7\)"):
        simulate(ARM, sc, _NeedsJoints(), jl, ik=(q[:, :6], qd[:, :6], qdd[:, :6]))
    with pytest.raises(ValueError, match="^ik.qdd: expected finite values"):
        simulate(ARM, sc, _NeedsJoints(), jl, ik=(q, qd, qdd.at[3, 2].set(jnp.nan)))
    with pytest.raises(ValueError, match=r"^ik.q: expected shape \(2, 30, 7\)"):  # not batched
        simulate_batch(ARM, stack_scenarios([sc, sc]), _NeedsJoints(), jl, ik=jref)


def test_batch_with_qd0_alone_starts_every_member_at_the_arms_q0():
    """``simulate_batch(qd0=...)`` without ``q0`` gave every member the whole ``(R, n)`` ``qd0``
    (a shape error in ``rnea``); each member now starts at ``arm.q0`` with its own ``qd0`` row, as
    single runs do, and a ``q0`` given as a list compiles once for all values."""
    pairs, scs, jrefs = free_batch(5, 2)
    g = toy_gains("osc")
    qd0 = np.array([[0.1] * 7, [-0.2] * 7])
    batch = simulate_batch(ARM, stack_scenarios(scs), CTRL, g, ik=jrefs, qd0=qd0)
    for i, (sc, jref) in enumerate(pairs):
        single = simulate(ARM, sc, CTRL, g, ik=jref, qd0=qd0[i])
        np.testing.assert_allclose(np.asarray(batch.q[i]), np.asarray(single.q), rtol=0, atol=1e-12)
    q = [float(v) for v in np.asarray(ARM.q0)]
    from conftest import backend_compiles

    with backend_compiles() as compiles:
        for dq in (0.0, 0.01):
            simulate(ARM, pairs[0][0], CTRL, g, ik=pairs[0][1], q0=[v + dq for v in q])
    assert len(compiles) <= 1, compiles  # a list of floats was static: one compilation per value


def test_auto_solver_is_tsit5_for_the_acceleration_level_oscs_and_dopri5_otherwise():
    """``SimParams(solver="auto")`` (the default) integrates with the controller's ``auto_solver``:
    Tsit5 for the acceleration OSC and the gradient-guided controller, Dopri5 for the others and
    for a controller that does not say (this file's toy); a named solver is used for every controller."""
    import diffrax

    from redman_jax._controllers import CONTROLLERS, AccelerationOSC, GradientGuided
    from redman_jax._sim import _make_solver, solver_name

    auto = SimParams()
    assert auto.solver == "auto"
    assert type(_make_solver(auto, CTRL)) is diffrax.Dopri5 and solver_name(auto, CTRL) == "dopri5"
    tsit = {name for name, cls in CONTROLLERS.items() if solver_name(auto, cls()) == "tsit5"}
    assert tsit == {"acceleration", "gradient"}
    for ctrl in (AccelerationOSC(), GradientGuided()):
        assert type(_make_solver(auto, ctrl)) is diffrax.Tsit5
    for name, cls in (("tsit5", diffrax.Tsit5), ("dopri5", diffrax.Dopri5), ("bosh3", diffrax.Bosh3)):
        for ctrl in (CTRL, AccelerationOSC(), GradientGuided()):
            assert type(_make_solver(SimParams(solver=name), ctrl)) is cls
            assert solver_name(SimParams(solver=name), ctrl) == name


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_even_split_keeps_a_step_the_clip_ends_at_the_sample_end(dtype):
    """The even split (``_EvenSplit``) never splits a step that the jump clip ends one float before
    the sample end: it reaches the end. In float32 the 1e-6 margin of its piece count is smaller
    than that float relative to the step, and the step used to be halved again and again (7-DOF
    simple, velocity OSC, float32: 16,578 steps, 3,568 with the check). A step well short of the
    end is still split evenly."""
    from redman_jax._sim import _pid, _Y, tolerances

    ts = jnp.asarray(0.01, dtype)
    ends = ts * jnp.arange(1, 11, dtype=dtype)
    ctrl = _pid(SimParams(), dtype, jump_ts=ends[:-1], ends=ends)
    rtol, atol = tolerances(SimParams(), dtype)
    y = _Y(q=jnp.ones(3, dtype), qd=jnp.zeros(3, dtype), z=jnp.zeros(0, dtype), f=jnp.zeros(3, dtype))
    b = ends[1]
    t0 = jnp.asarray(0.0186666, dtype)
    t1 = jnp.asarray(0.0193333, dtype)
    _, state = ctrl.init(None, t0, t1, y, t1 - t0, None, None, 5)

    def adapt(err):  # the error of the step [t0, t1], as a fraction of the tolerance
        y_err = jax.tree.map(lambda x: err * (atol + rtol * jnp.abs(x)), y)
        keep, nt0, nt1, _, _, _ = ctrl.adapt_step_size(t0, t1, y, y, None, y_err, 5, state)
        return bool(keep), nt0, nt1

    keep, nt0, nt1 = adapt(0.0)  # tiny error: the PID proposes 10x the step, the clip cuts it at b
    assert keep and nt0 == t1
    assert nt1 == jnp.nextafter(b, jnp.asarray(-jnp.inf, dtype))  # not halved
    keep, nt0, nt1 = adapt(2.0)  # rejected: the retry from t0 covers the rest in equal pieces
    pieces = float(b - nt0) / float(nt1 - nt0)
    assert not keep and nt0 == t0
    assert pieces > 1.5 and pieces == pytest.approx(round(pieces), rel=1e-4)


def test_default_tolerances_follow_the_state_precision():
    """``SimParams()`` leaves the tolerances to the states' precision (``tolerances``); given ones
    are kept in any precision, and checked at construction whichever is given."""
    from redman_jax._sim import DEFAULT_TOLERANCES, tolerances

    assert tolerances(SimParams(), jnp.float64) == DEFAULT_TOLERANCES["float64"] == (1e-5, 1e-7)
    assert tolerances(SimParams(), jnp.float32) == DEFAULT_TOLERANCES["float32"]
    r, a = tolerances(SimParams(rtol=1e-6), jnp.float32)
    assert float(r) == 1e-6 and a == DEFAULT_TOLERANCES["float32"][1]
    with pytest.raises(ValueError, match="SimParams.atol"):
        SimParams(atol=-1.0)


def f32(tree):
    return redman_jax.cast_floating(tree, jnp.float32)


def test_float32_run_matches_float64_in_as_many_steps(free):
    """The same run with every input cast to float32 (default tolerances): its errors agree with
    float64's to float32's level and it takes no more steps. Before the even split kept clipped
    steps and the float32 tolerances, it took 10x the steps (halved toward every sample end)."""
    sc, jref = free
    r64 = run(sc, jref)
    r32 = simulate(f32(ARM), f32(sc), CTRL, f32(toy_gains("osc")), ik=f32(jref))  # params: cast inside
    assert r32.q.dtype == jnp.float32 and not bool(r32.diverged)
    m32, m64 = r32.metrics, r64.metrics
    assert float(m32.mean_pos_err) == pytest.approx(float(m64.mean_pos_err), rel=1e-3, abs=1e-6)
    np.testing.assert_allclose(np.asarray(r32.q), np.asarray(r64.q), atol=1e-4)
    assert int(r32.n_steps) <= int(r64.n_steps)


def test_mixed_precision_inputs_are_refused_by_name(free):
    """A float32 scenario with a float64 arm, gains or joint reference is refused, naming the
    argument (mixed, the vector field would be promoted and fail inside the solver)."""
    sc, jref = free
    sc32, g32 = f32(sc), f32(toy_gains("osc"))
    for kw, name in [(dict(arm=ARM, gains=g32, ik=f32(jref)), "arm"),
                     (dict(arm=f32(ARM), gains=toy_gains("osc"), ik=f32(jref)), "gains"),
                     (dict(arm=f32(ARM), gains=g32, ik=jref), "ik")]:
        with pytest.raises(ValueError, match=f"^{name}: float64 arrays with a float32 scenario"):
            simulate(kw["arm"], sc32, CTRL, kw["gains"], ik=kw["ik"])
        with pytest.raises(ValueError, match=f"^{name}: float64"):
            simulate_batch(kw["arm"], stack_scenarios([sc32, sc32]), CTRL, kw["gains"],
                           ik=None if kw["ik"] is None else tuple(jnp.stack([x, x]) for x in kw["ik"]))


def test_stack_scenarios_refuses_mixed_shapes_and_pads_on_request():
    """Scenes of different reference capacities, obstacle capacities and cases: refused by name
    (before: a pytree-structure error from ``jax.tree.map``); with ``pad=True`` stacked at the largest
    shapes, case ``"custom"``, and each member of the batch runs as its unpadded scene did."""
    a, ja = joint_motion_scenario(ARM, DQ_FREE, 0.2, CAP)
    b, jb = joint_motion_scenario(ARM, [0.3, -0.2, 0.1, 0.2, -0.1, 0.3, -0.2], 0.15, CAP - 10, seed=1)
    b = eqx.tree_at(lambda s: s.obstacles, b, make_obstacles(
        spheres=[(np.eye(3), c, (0.05,)) for c in ((0.6, 0.6, 0.2), (-0.6, 0.5, 0.3), (0.5, -0.6, 0.4))],
        capacities=(3, 1, 1)))
    b = dataclasses.replace(b, case="simple")
    with pytest.raises(ValueError, match=r"^scenarios: need at least one"):
        stack_scenarios([])
    with pytest.raises(ValueError, match=r"^scenarios\[1\]: reference capacity 40, obstacle capacities \(3, 1, 1\)"):
        stack_scenarios([a, b])
    with pytest.raises(ValueError, match=r"^scenarios\[0\]: already batched"):
        stack_scenarios([stack_scenarios([a, a])])
    both = stack_scenarios([a, b], pad=True)
    assert both.reference.p.shape == (2, CAP, 3) and both.obstacles.capacities == (3, 1, 1)
    assert both.case == "custom"
    pad_rows = lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], CAP - x.shape[0], axis=0)])
    jref = tuple(jnp.stack([x, pad_rows(y)]) for x, y in zip(ja, jb))
    batch = simulate_batch(ARM, both, CTRL, toy_gains("osc"), ik=jref)
    for i, (sc, j) in enumerate(((a, ja), (b, jb))):
        one = run(sc, j)
        n = int(sc.reference.n_samples)
        np.testing.assert_allclose(np.asarray(batch.q[i, :n]), np.asarray(one.q[:n]), rtol=0, atol=1e-9)
        assert bool(batch.metrics.success[i]) == bool(one.metrics.success)
        np.testing.assert_allclose(float(batch.metrics.mean_pos_err[i]), float(one.metrics.mean_pos_err),
                                   rtol=1e-9)


def test_the_controller_is_timed_at_the_states_of_a_run_that_did_not_diverge():
    """``_pipeline._timing_samples``: the states the batch's first undiverged run saved (its valid
    samples repeated up to the capacity, one timing program per shape), the reference samples held
    then with the IK's joint reference as the simulator holds it, and ``init_state`` as ``z``."""
    import types

    from redman_jax._controllers import CONTROLLERS
    from redman_jax._pipeline import _timing_samples

    sc, j = joint_motion_scenario(ARM, DQ_FREE, 0.3, CAP)
    scen = stack_scenarios([sc, sc])
    j = (j[0], j[1] + 1.0, j[2])  # a joint velocity reference nonzero at the last valid sample too
    jref = tuple(jnp.stack([x, x]) for x in j)
    n_valid = int(sc.reference.n_samples)
    rng = np.random.default_rng(1)
    res = types.SimpleNamespace(diverged=np.array([True, False]), mask=np.arange(CAP)[None] < np.array([[CAP], [n_valid]]),
                                q=rng.normal(size=(2, CAP, 7)), qd=rng.normal(size=(2, CAP, 7)))
    idx = np.arange(CAP) % n_valid
    js = CONTROLLERS["joint_space"]()
    states, refs, env = _timing_samples(ARM, scen, jref, js, res)
    np.testing.assert_array_equal(np.asarray(states.q), res.q[1][idx])
    np.testing.assert_array_equal(np.asarray(states.qd), res.qd[1][idx])
    np.testing.assert_allclose(np.asarray(states.t), idx * TS, rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(refs.p), np.asarray(sc.reference.p)[idx])
    jq = np.asarray(j[0])
    jqd = np.concatenate([np.asarray(j[1]), np.zeros((CAP - len(j[1]), 7))])  # qd_d: N or N - 1 rows
    np.testing.assert_array_equal(np.asarray(refs.q), jq[idx])
    moving = idx < n_valid - 1  # the last sample holds q_{N-1} at rest (SPEC 6)
    np.testing.assert_array_equal(np.asarray(refs.qd)[moving], jqd[idx[moving]])
    assert np.any(~moving) and not np.any(np.asarray(refs.qd)[~moving])
    assert env.obstacles.capacities == sc.obstacles.capacities
    vel = CONTROLLERS["velocity"]()
    states, refs, _ = _timing_samples(ARM, scen, None, vel, res)
    np.testing.assert_array_equal(np.asarray(states.z), res.q[1][idx])  # q_r starts at q
    assert not np.any(np.asarray(refs.q))  # no joint reference: zeros, as in the simulator
