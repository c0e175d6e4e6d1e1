"""Dynamics: invariants, two formulations, finite differences, energy conservation, limits, float32."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from redman_jax._dynamics import (
    LimitContact,
    _mass_matrix_com,
    _rnea_spatial6,
    bias_forces,
    bias_forces_lagrange,
    cholesky_solve,
    coriolis_matrix,
    dynamics_terms,
    forward_dynamics,
    gravity_forces,
    joint_limit_torque,
    kinetic_energy,
    mass_matrix,
    mass_matrix_lagrange,
    potential_energy,
    rnea,
    state_derivative,
)
from redman_jax._kinematics import kinematics
from redman_jax._robot import thesis_arm
from redman_jax._urdf import example_robot_data_file, from_urdf

from conftest import fd_jacobian


def _arms():
    arms = [thesis_arm(7), thesis_arm(8), thesis_arm(9)]
    try:
        arms.append(from_urdf(example_robot_data_file("panda_description/urdf/panda.urdf"), "panda_hand"))
    except FileNotFoundError:
        pass
    return arms


ARMS = _arms()


def _state(arm, seed):
    rng = np.random.default_rng(seed)
    q = np.where(np.asarray(arm.prismatic), rng.uniform(0.1, 0.8, arm.n_dof), rng.uniform(-2, 2, arm.n_dof))
    return q, rng.normal(size=arm.n_dof), rng.normal(size=arm.n_dof)


def _terms(arm, christoffel):
    """All dynamics quantities of a batch of states in one compiled call (fast tests)."""

    def one(q, qd, qdd):
        kin = kinematics(arm, q)
        M, h = dynamics_terms(arm, q, qd)
        out = dict(
            M=M, h=h, M_call=mass_matrix(arm, q), h_call=bias_forces(arm, q, qd),
            M_lag=mass_matrix_lagrange(arm, q), h_lag=bias_forces_lagrange(arm, q, qd),
            M_com=_mass_matrix_com(arm, kin), h_rnea6=_rnea_spatial6(arm, q, qd, jnp.zeros_like(qd)),
            g=gravity_forces(arm, q), tau=rnea(arm, q, qd, qdd), tau6=_rnea_spatial6(arm, q, qd, qdd),
            tau_nog=rnea(arm, q, qd, qdd, gravity=False),
        )
        if christoffel:
            out["Mdot"] = jax.jvp(lambda x: mass_matrix(arm, x), (q,), (qd,))[1]
            out["C"] = coriolis_matrix(arm, q, qd)
        return out

    return jax.jit(jax.vmap(one))


# Two float64 formulations of the same quantity: they differ by rounding only, ~1e-15 relative
# to the largest entry; the issue asks for 1e-10.
REL = 1e-10


def _rel(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


@pytest.mark.parametrize("arm", ARMS, ids=lambda a: a.name)
def test_formulations_and_invariants(arm):
    christoffel = arm.name in ("thesis9", "panda")  # the costly jacfwd of M: two arms suffice
    states = [_state(arm, seed) for seed in range(3)]
    batch = _terms(arm, christoffel)(*(np.stack(x) for x in zip(*states)))
    for b, (q, qd, qdd) in enumerate(states):
        t = {k: np.asarray(v[b]) for k, v in batch.items()}
        M = t["M"]
        # symmetric positive definite
        np.testing.assert_array_equal(M, M.T)
        assert np.linalg.eigvalsh(M).min() > 0
        # Lagrangian twist form (thesis 3.1-3.4) vs CRBA / RNEA vs the CoM form
        assert _rel(M, t["M_lag"]) < REL and _rel(M, t["M_com"]) < REL
        assert _rel(t["h"], t["h_lag"]) < REL and _rel(t["h"], t["h_rnea6"]) < REL
        np.testing.assert_array_equal(M, t["M_call"])
        np.testing.assert_array_equal(t["h"], t["h_call"])
        # inverse dynamics = M qdd + c + g, both RNEA forms
        assert _rel(t["tau"], M @ qdd + t["h"]) < REL and _rel(t["tau6"], t["tau"]) < REL
        assert _rel(t["tau_nog"], t["tau"] - t["g"]) < REL
        if not christoffel:
            continue
        # Christoffel C: C qd = c and Mdot - 2C skew-symmetric
        assert _rel(t["C"] @ qd, t["h"] - t["g"]) < 1e-9
        N = t["Mdot"] - 2 * t["C"]
        assert np.max(np.abs(N + N.T)) < 1e-12 * np.max(np.abs(t["Mdot"]))
        # qd^T (Mdot - 2C) qd = 0 (power balance)
        assert abs(qd @ N @ qd) < 1e-12 * np.max(np.abs(t["Mdot"])) * (qd @ qd)


@pytest.mark.parametrize("arm", [ARMS[0], ARMS[-1]], ids=lambda a: a.name)
def test_gravity_is_gradient_of_potential(arm):
    q, _, _ = _state(arm, 7)
    V = jax.jit(lambda x: potential_energy(arm, x))
    g_fd = fd_jacobian(lambda x: np.asarray(V(x)), q, eps=1e-5)
    # V ~ 1e2 J: rounding 1e-16 * 1e2 / 1e-5 = 1e-9, truncation ~eps^2 * 1e2 = 1e-8
    np.testing.assert_allclose(np.asarray(jax.jit(lambda x: gravity_forces(arm, x))(q)), g_fd, atol=1e-7)
    # and g is independent of the velocity: bias at qd = 0
    np.testing.assert_allclose(np.asarray(bias_forces(arm, q, np.zeros(arm.n_dof))),
                               np.asarray(gravity_forces(arm, q)), rtol=1e-14, atol=1e-12)


def test_forward_dynamics_matches_numpy_solve_and_limits():
    arm = thesis_arm(9)
    q, qd, tau = _state(arm, 8)
    q[2], qd[2] = 0.8 * np.pi, 0.3  # Ry beyond +0.75 pi, moving outwards
    q[4], qd[4] = -0.8 * np.pi, 0.3  # Ry below -0.75 pi, moving inwards (no damping)
    c = LimitContact()
    x = jnp.concatenate([jnp.asarray(q), jnp.asarray(qd)])
    fd, M, h, tl, sd, fd_free = jax.jit(lambda q, qd, tau, x: (
        forward_dynamics(arm, q, qd, tau, c), mass_matrix(arm, q), bias_forces(arm, q, qd),
        joint_limit_torque(arm, q, qd, c), state_derivative(arm, x, tau),
        forward_dynamics(arm, q, qd, tau, limits=False)))(q, qd, tau, x)
    M, h, tl = map(np.asarray, (M, h, tl))
    np.testing.assert_allclose(np.asarray(fd), np.linalg.solve(M, tau - h - tl), rtol=1e-10, atol=1e-10)
    # eq. 3.6 by hand: s(qd) = cos(arctan(50 qd) + pi) + 1
    s = np.cos(np.arctan(50 * 0.3) + np.pi) + 1
    assert tl[2] == pytest.approx(1000 * (0.8 * np.pi - 0.75 * np.pi) + 100 * 0.3 * s, rel=1e-12)
    assert tl[4] == pytest.approx(1000 * (-0.8 * np.pi + 0.75 * np.pi), rel=1e-12)
    assert np.all(tl[[0, 1, 3, 5, 6, 7, 8]] == 0)  # inside the limits or unlimited (Rz)
    # an unlimited Rz far outside [-pi, pi] gets no contact torque
    q2 = q.copy()
    q2[0] = 10.0
    assert float(joint_limit_torque(arm, q2, qd)[0]) == 0.0
    # the lift below 0 moving down: restoring (negative tau_lim means q_dd > 0 after subtraction)
    q3, qd3 = np.asarray(arm.q0).copy(), np.zeros(9)
    q3[1], qd3[1] = -0.01, -0.2
    t3 = float(np.asarray(joint_limit_torque(arm, q3, qd3))[1])
    assert t3 == pytest.approx(1000 * -0.01 + 100 * -0.2 * (1 - 1 / np.sqrt(1 + 2500 * 0.04)), rel=1e-12)
    np.testing.assert_allclose(np.asarray(sd), np.concatenate([qd, np.asarray(fd)]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(fd_free), np.linalg.solve(M, tau - h), rtol=1e-10, atol=1e-10)


def test_cholesky_solve():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(9, 9))
    M = A @ A.T + 0.1 * np.eye(9)
    b = rng.normal(size=9)
    x = np.asarray(jax.jit(cholesky_solve)(M, b))
    assert np.linalg.norm(M @ x - b) < 1e-10 * np.linalg.norm(b) * np.linalg.cond(M) ** 0.5 + 1e-12
    np.testing.assert_allclose(x, np.linalg.solve(M, b), rtol=1e-9)


def test_grad_through_forward_dynamics():
    arm = thesis_arm(7)
    q, qd, tau = _state(arm, 9)
    w = np.random.default_rng(1).normal(size=7)

    def loss(q, qd, tau):
        return jnp.dot(w, forward_dynamics(arm, q, qd, tau, limits=False))

    d = tuple(np.random.default_rng(k).normal(size=7) for k in (2, 3, 4))

    @jax.jit
    def both(q, qd, tau):  # reverse mode, and forward mode along a direction d, in one compile
        return jax.grad(loss, argnums=(0, 1, 2))(q, qd, tau), jax.jvp(loss, (q, qd, tau), d)[1], loss(q, qd, tau)

    grads, jvp, _ = both(q, qd, tau)
    L = lambda *a: both(*a)[2]  # noqa: E731
    for k, x in enumerate((q, qd, tau)):
        def f(z, k=k):
            args = [q, qd, tau]
            args[k] = z
            return np.asarray(L(*args))
        # The loss (~3e2) carries rounding noise ~1e-10: cond(M) ~ 8e3 amplifies the rounding of M.
        # A two-point stencil at eps 1e-5 turns that into ~1e-5 of error (it once passed by luck);
        # the five-point one at eps 1e-3 gives ~1e-7 (rounding) + ~1e-9 (truncation, O(eps^4)).
        np.testing.assert_allclose(np.asarray(grads[k]), fd_jacobian(f, x, eps=1e-3, order=4), rtol=1e-6, atol=1e-6)
    # forward mode agrees with reverse mode (rounding only)
    rev = sum(float(np.dot(np.asarray(g), dk)) for g, dk in zip(grads, d))
    assert abs(float(jvp) - rev) < 1e-11 * sum(np.abs(np.asarray(g)).sum() for g in grads)


def test_energy_conservation():
    """tau = 0, no limits: E = T + V is constant. Tsit5 at rtol = atol = 1e-12 over 2 s."""
    arm = thesis_arm(7)
    q0, qd0, _ = _state(arm, 10)
    n = arm.n_dof

    def vf(t, x, args):
        return jnp.concatenate([x[n:], forward_dynamics(arm, x[:n], x[n:], jnp.zeros(n), limits=False)])

    def energy(x):
        return kinetic_energy(arm, x[:n], x[n:]) + potential_energy(arm, x[:n])

    @jax.jit
    def run(x0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vf), diffrax.Tsit5(), 0.0, 2.0, 1e-3, x0,
            saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 2.0, 21)),
            stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12), max_steps=200_000)
        return jax.vmap(energy)(sol.ys), sol.ys

    E, ys = run(jnp.concatenate([jnp.asarray(q0), jnp.asarray(qd0)]))
    E = np.asarray(E)
    T0 = float(kinetic_energy(arm, q0, qd0))
    assert T0 > 1.0  # the arm really moves
    assert np.max(np.abs(np.asarray(ys)[-1, :n] - q0)) > 0.1
    drift = np.max(np.abs(E - E[0])) / abs(E[0])
    assert drift < 1e-8, drift
    assert np.max(np.abs(E - E[0])) / T0 < 1e-8


def test_float32_smoke():
    with jax.enable_x64(False):
        arm = thesis_arm(7)
        q, qd, tau = (jnp.asarray(x, jnp.float32) for x in _state(arm, 11))
        qd = 0.1 * qd

        def everything(q, qd, tau):
            return [mass_matrix(arm, q), mass_matrix_lagrange(arm, q), bias_forces(arm, q, qd),
                    bias_forces_lagrange(arm, q, qd), gravity_forces(arm, q), coriolis_matrix(arm, q, qd),
                    rnea(arm, q, qd, tau), dynamics_terms(arm, q, qd), forward_dynamics(arm, q, qd, tau),
                    kinetic_energy(arm, q, qd), potential_energy(arm, q), joint_limit_torque(arm, q, qd),
                    state_derivative(arm, jnp.concatenate([q, qd]), tau), cholesky_solve(mass_matrix(arm, q), tau),
                    jax.grad(lambda t: jnp.sum(forward_dynamics(arm, q, qd, t)))(tau),
                    jax.vmap(forward_dynamics, in_axes=(None, 0, 0, 0))(arm, q[None], qd[None], tau[None])]

        outs = jax.jit(everything)(q, qd, tau)
        for leaf in jax.tree.leaves(outs):
            assert leaf.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(leaf)))
        fd32 = np.asarray(outs[8])
    arm64 = thesis_arm(7)
    fd64 = np.asarray(forward_dynamics(arm64, *(np.asarray(x, np.float64) for x in (q, qd, tau))))
    # float32: M's condition number ~1e3 times eps 1e-7
    np.testing.assert_allclose(fd32, fd64, rtol=1e-3, atol=1e-3 * np.abs(fd64).max())


def test_float32_state_stays_float32_with_x64_on():
    """The default ``LimitContact`` is float64; with float64 enabled it promoted a float32 arm's
    and state's contact torque, forward dynamics and state derivative to float64. It takes the
    state's dtype."""
    from redman_jax._math import cast_floating

    arm = cast_floating(thesis_arm(7), jnp.float32)
    q, qd, tau = (jnp.asarray(x, jnp.float32) for x in _state(arm, 12))
    q = q.at[2].set(arm.q_max[2] + 0.05)  # in contact, so the contact torque is not all zeros
    outs = [joint_limit_torque(arm, q, qd), forward_dynamics(arm, q, qd, tau),
            state_derivative(arm, jnp.concatenate([q, qd]), tau)]
    assert [o.dtype for o in outs] == [jnp.float32] * 3
    tau_lim = outs[0]
    assert float(tau_lim[2]) > 0
    ref = joint_limit_torque(thesis_arm(7), *(np.asarray(x, np.float64) for x in (q, qd)))
    np.testing.assert_allclose(np.asarray(tau_lim), np.asarray(ref), rtol=1e-5, atol=1e-4)


def test_limit_contact_refuses_negative_gains():
    """A negative stiffness, damping or steepness turns the restoring torque around (it pushed a
    joint 0.1 rad past its limit further out with -100 N m); each is refused by name."""
    for name in ("k_p", "k_d", "steepness"):
        with pytest.raises(ValueError, match=f"LimitContact.{name}"):
            LimitContact(**{name: -1.0})
    LimitContact(k_p=0.0, k_d=0.0, steepness=0.0)  # zero switches a term off


def test_a_joint_vector_of_the_wrong_length_is_an_error_naming_it():
    """A state or torque of another length than the arm's joints would be read past its end (JAX
    clamps indices) or broadcast, giving numbers for a configuration nobody asked for; every public
    entry point names the argument instead, also under ``vmap`` (per member) and ``jit``."""
    from redman_jax._kinematics import jacobian, jdot_qdot

    arm = thesis_arm(7)
    z7, z6 = jnp.zeros(7), jnp.zeros(6)
    cases = [
        ("kinematics: q", lambda: kinematics(arm, z6)),
        ("kinematics: q", lambda: jax.vmap(lambda q: jacobian(arm, q))(jnp.zeros((3, 6)))),
        ("kinematics: q", lambda: jax.jit(lambda q: mass_matrix(arm, q))(jnp.zeros(8))),
        ("rnea: qd", lambda: rnea(arm, z7, z6, z7)),
        ("rnea: qdd", lambda: rnea(arm, z7, z7, jnp.zeros(9))),
        ("forward_dynamics: tau", lambda: forward_dynamics(arm, z7, z7, z6)),
        ("joint_limit_torque: qd", lambda: joint_limit_torque(arm, z7, z6)),
        ("jdot_qdot: qd", lambda: jdot_qdot(arm, z7, z6)),
        ("state_derivative: x", lambda: state_derivative(arm, jnp.zeros(13), z7)),
    ]
    for match, call in cases:
        with pytest.raises(ValueError, match=match):
            call()
    # the right length passes, batched too
    assert jax.vmap(lambda q: jacobian(arm, q))(jnp.zeros((3, 7))).shape == (3, 6, 7)
    assert forward_dynamics(arm, z7, z7, z7).shape == (7,)
