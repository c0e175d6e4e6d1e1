"""The NumPy + SciPy baseline of ``benchmarks/bench_sim.py`` computes the same closed loop as the
JAX simulator (what makes the speed comparison honest).

At random states ``(q, qd, q_r)`` of the 9-DOF arm, with the obstacles and reference samples of
real study scenarios (inspection: boxes and a cylinder; simple: spheres), orientation control on
and off, and some joints beyond their limits:

* the NumPy obstacle distances and potential-field gradients equal ``points_min_distance`` and
  ``obstacle_gradients`` (also at points inside obstacles);
* the NumPy torque and ``dz`` of ``joint_space``, ``velocity`` and ``acceleration`` equal
  ``CONTROLLERS[name]()(gains, arm, ControlState, RefSample, env)`` to ~1e-9 relative;
* the NumPy closed-loop state derivative equals ``redman_jax._sim._closed_loop``;
* the gradient-guided controller and closed loop too, with virtual obstacles in and out of range,
  and the NumPy local-minima estimate equals ``estimate_local_minimum``;
* the held reference sample of the NumPy loop equals ``_sim._ref_sample`` (joint-space rows
  included, also past the last sample).
"""

import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import redman_jax as rj
from redman_jax._cases import make_scenarios
from redman_jax._control_types import ControlState, RefSample, make_environment
from redman_jax._controllers import CONTROLLERS
from redman_jax._nullspace import obstacle_gradients
from redman_jax._obstacles import pad_obstacles, points_min_distance
from redman_jax._sim import SimParams, _closed_loop, _ref_sample, _Y, joint_reference

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import bench_sim as B  # noqa: E402

ARM = rj.thesis_arm(9)
NA = B.NumpyArm(ARM)
N = ARM.n_dof
RTOL = 1e-9
N_STATES = 6


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1.0))


@pytest.fixture(scope="module")
def scenes():
    """Two real scenarios (seed 1), their obstacles padded to common capacities."""
    scs = [jax.tree.map(lambda x: x[0], make_scenarios(c, [1], ARM)) for c in ("inspection", "simple")]
    caps = tuple(max(s.obstacles.capacities[i] for s in scs) for i in range(3))
    return [eqx.tree_at(lambda s: s.obstacles, s, pad_obstacles(s.obstacles, caps)) for s in scs]


def _states(scene, seed):
    """``N_STATES`` random states and reference samples (half with orientation control off)."""
    rng = np.random.default_rng(seed)
    ref = scene.reference
    out = []
    for i in range(N_STATES):
        q = np.asarray(ARM.q0) + rng.uniform(-0.7, 0.7, N)
        if i == 1:  # beyond the limits: contact torque and the saturated joint-limit policy
            q[2] = float(ARM.q_max[2]) + 0.05
            q[1] = float(ARM.q_min[1]) - 0.02
        qd = rng.normal(0.0, 0.6, N)
        q_r = q + rng.normal(0.0, 0.05, N)
        k = int(rng.integers(0, int(ref.n_samples)))
        rs = RefSample(p=ref.p[k], v=ref.v[k], a=ref.a[k], quat=ref.quat[k], omega=ref.omega[k],
                       omega_dot=ref.omega_dot[k], rot=jnp.asarray(float(i % 2)),
                       q=jnp.asarray(q + rng.normal(0.0, 0.1, N)), qd=jnp.asarray(rng.normal(0, 0.3, N)),
                       qdd=jnp.asarray(rng.normal(0, 1.0, N)))
        out.append((q, qd, q_r, rs))
    return out


def _np_ref(rs):
    return B.SimpleNamespace(**{k: (float(v) if k == "rot" else np.asarray(v)) for k, v in vars(rs).items()})


@eqx.filter_jit
def _jax_controller(ctrl, gains, q, qd, z, rs, env):
    return ctrl(gains, ARM, ControlState(t=jnp.asarray(0.0), q=q, qd=qd, z=z), rs, env)


@eqx.filter_jit
def _jax_field(ctrl, gains, q, qd, z, rs, env):
    y = _Y(q=q, qd=qd, z=z, f=jnp.zeros(3))
    return _closed_loop(jnp.asarray(0.0), y, rs, env, jnp.asarray(True), ARM, ctrl, gains, SimParams())


def test_obstacle_distances_and_gradients(scenes):
    rng = np.random.default_rng(0)
    for sc in scenes:
        obs = sc.obstacles
        nobs = B.NumpyObstacles(obs)
        centres = np.concatenate([p for _, _, p, _ in nobs.families])
        # points around every obstacle, some inside, plus the arm's points of interest
        X = np.concatenate([centres[:, None, :] + rng.normal(0, s, (len(centres), 20, 3))
                            for s in (0.05, 0.3, 0.8)], axis=1).reshape(-1, 3)
        X = np.concatenate([X, NA.pois(NA.fk(NA.q0)[0], NA.q0)])
        d_np = nobs.min_distance(X)
        assert np.any(d_np < 0) and np.any((d_np > 0) & (d_np < 0.75))
        np.testing.assert_allclose(d_np, np.asarray(points_min_distance(obs, jnp.asarray(X))), rtol=1e-12, atol=1e-12)
        g_np = nobs.gradients(X, 0.05, 0.75)
        g_jax = np.asarray(obstacle_gradients(obs, jnp.asarray(X), 0.05, 0.75, "minus", 1e-3))
        assert _rel(g_np, g_jax) < RTOL


def test_reference_hold_matches_simulator(scenes):
    sc = scenes[0]
    Ncap = sc.reference.capacity
    rng = np.random.default_rng(1)
    jr = joint_reference(tuple(jnp.asarray(rng.normal(size=(Ncap, N))) for _ in range(3)))
    loop = B.NumpyLoop(NA, "joint_space", CONTROLLERS["joint_space"]().default_gains(), sc, (jr.q, jr.qd, jr.qdd))
    last = int(sc.reference.n_samples) - 1
    for k in (0, 7, last - 1, last, last + 3):
        a = loop.ref_sample(k)
        b = _ref_sample(sc.reference, jr, jnp.asarray(k), N, jnp.float64)
        for name in ("p", "v", "a", "quat", "omega", "omega_dot", "rot", "q", "qd", "qdd"):
            np.testing.assert_array_equal(getattr(a, name), np.asarray(getattr(b, name)), err_msg=f"{k} {name}")


@pytest.mark.parametrize("name", B.NUMPY_CONTROLLERS)
def test_controller_and_closed_loop_match_jax(scenes, name):
    ctrl = CONTROLLERS[name]()
    gains = ctrl.default_gains()
    g_np = B.numpy_gains(gains)
    worst_tau = worst_dz = worst_f = 0.0
    for si, sc in enumerate(scenes):
        env = make_environment(sc.obstacles, sc.goal_p, sc.goal_quat)
        nobs = B.NumpyObstacles(sc.obstacles)
        loop = B.NumpyLoop(NA, name, gains, sc,
                           (jnp.zeros((sc.reference.capacity, N)),) * 3 if ctrl.needs_joint_reference else None)
        for q, qd, q_r, rs in _states(sc, 10 * si + len(name)):
            z = jnp.asarray(q_r) if name == "velocity" else ()
            out = _jax_controller(ctrl, gains, jnp.asarray(q), jnp.asarray(qd), z, rs, env)
            ps = B.state_pass(NA, q, qd)
            tau, dz = B.NP_CONTROLLERS[name](g_np, NA, ps, q_r if name == "velocity" else None, _np_ref(rs), nobs)
            worst_tau = max(worst_tau, _rel(tau, out.tau))
            if name == "velocity":
                worst_dz = max(worst_dz, _rel(dz, out.dz))
            # closed loop: dy/dt = (qd, qdd, dz)
            zz = jnp.asarray(q_r) if name == "velocity" else jnp.zeros((0,))
            dy = _jax_field(ctrl, gains, jnp.asarray(q), jnp.asarray(qd), zz, rs, env)
            y = np.concatenate([q, qd] + ([q_r] if name == "velocity" else []))
            f_np = loop.field(0.0, y, _np_ref(rs))
            f_jax = np.concatenate([np.asarray(dy.q), np.asarray(dy.qd)] + ([np.asarray(dy.z)] if name == "velocity" else []))
            worst_f = max(worst_f, _rel(f_np, f_jax))
    assert worst_tau < RTOL, worst_tau
    assert worst_dz < RTOL, worst_dz
    assert worst_f < RTOL, worst_f
    assert loop.outside  # the state beyond the limits was seen by the latched flag


def test_batch_use_counts_the_iterations_of_each_chunk():
    """``bench_sim.batch_use``: steps over the row-iterations the chunks pay (each iterates to its
    slowest member; the last chunk padded with copies of its last member), against a count of
    the loop's iterations row by row."""
    def counted(steps, chunks):
        size = -(-len(steps) // chunks)
        busy = paid = 0
        for i in range(chunks):
            rows = [steps[min(j, len(steps) - 1)] for j in range(i * size, (i + 1) * size)]
            for it in range(max(rows)):
                paid += len(rows)
                busy += sum(it < s for s in rows[: len(steps) - i * size])  # padded copies are not runs
        return busy / paid

    assert B.batch_use([5, 5, 5, 5], 2) == 1.0
    assert B.batch_use([1, 2, 3, 4], 2) == pytest.approx(10 / 12)
    assert B.batch_use([1, 2, 3], 2) == pytest.approx(6 / 10)  # rows (1, 2) and (3, copy of 3)
    rng = np.random.default_rng(0)
    for chunks in (1, 2, 3):
        for R in (3, 7, 20):
            steps = list(rng.integers(1, 40, R))
            assert B.batch_use(steps, chunks) == pytest.approx(counted(steps, chunks))


def test_gradient_guided_controller_field_and_estimator_match_jax(scenes):
    """The NumPy gradient-guided controller (guidance field with virtual obstacles, orientation
    latch on and off) and its closed loop equal ``GradientGuided`` and ``_closed_loop`` to ~1e-9
    relative; the loop's local-minima estimate (Hessian by central differences) equals
    ``estimate_local_minimum`` (Hessian by ``jacfwd``) to 1e-6 m where valid, and both reject the
    same steps."""
    from redman_jax._guidance import estimate_local_minimum
    from redman_jax._sim import _goal_sample

    ctrl = CONTROLLERS["gradient"]()
    gains = ctrl.default_gains()
    params = SimParams()
    worst_tau = worst_f = worst_est = 0.0
    n_virtual = n_valid = 0
    for si, sc in enumerate(scenes):
        loop = B.NumpyGuidedLoop(NA, gains, sc, params)
        rng = np.random.default_rng(40 + si)
        for i, (q, qd, _, _) in enumerate(_states(sc, 20 + si)):
            x = NA.fk(q)[1][:3, 3]
            # virtual obstacles: some within d_v = 0.25 m of the end effector, some beyond, two slots empty
            vp = x + rng.normal(0.0, 0.2, (params.buffer_size - 2, 3))
            mask = np.arange(params.buffer_size) < params.buffer_size - 2
            vp_full = np.concatenate([vp, np.zeros((2, 3))])
            n_virtual += int(np.sum(np.linalg.norm(vp - x, axis=1) <= 0.25))
            env = make_environment(sc.obstacles, sc.goal_p, sc.goal_quat, params.buffer_size)
            env = eqx.tree_at(lambda e: (e.virtual_p, e.virtual_mask), env, (jnp.asarray(vp_full), jnp.asarray(mask)))
            rot = float(i % 2)
            rs = _goal_sample(sc.goal_p, sc.goal_quat, rot, N, jnp.float64)
            out = _jax_controller(ctrl, gains, jnp.asarray(q), jnp.asarray(qd), (), rs, env)
            tau, _ = B.np_gradient(loop.g, NA, B.state_pass(NA, q, qd), None, loop.env(list(vp), rot), loop.obs)
            worst_tau = max(worst_tau, _rel(tau, out.tau))
            dy = _jax_field(ctrl, gains, jnp.asarray(q), jnp.asarray(qd), jnp.zeros((0,)), rs, env)
            f_np = loop.field(0.0, np.concatenate([q, qd]), loop.env(list(vp), rot))
            worst_f = max(worst_f, _rel(f_np, np.concatenate([np.asarray(dy.q), np.asarray(dy.qd)])))
            for xx in (x, np.asarray(sc.goal_p) + rng.normal(0.0, 0.1, 3)):
                x_min, ok = loop.estimate(xx, list(vp))
                j_min, j_ok = estimate_local_minimum(jnp.asarray(xx), sc.goal_p, sc.obstacles, jnp.asarray(vp_full),
                                                     jnp.asarray(mask), gains.field, params.lme_mu, params.lme_max_jump)
                assert ok == bool(j_ok)
                if ok:  # a rejected step (beyond lme_max_jump, near a singular H) is not pushed
                    n_valid += 1
                    worst_est = max(worst_est, float(np.abs(x_min - np.asarray(j_min)).max()))
    assert n_virtual > 0 and n_valid >= 10  # virtual obstacles in range; estimates compared
    assert worst_tau < RTOL, worst_tau
    assert worst_f < RTOL, worst_f
    assert worst_est < 1e-6, worst_est
