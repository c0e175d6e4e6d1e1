"""Kinematics against independent references: scipy.linalg.expm PoE, finite differences, jacfwd."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from redman_jax._kinematics import (
    end_effector_frame,
    end_effector_pose,
    forward_kinematics,
    jacobian,
    jdot_qdot,
    kinematics,
    link_jacobians,
    point_jacobian,
    poi_jacobians,
    poi_link_index,
    poi_positions,
    space_jacobian,
)
from redman_jax._math import quat_to_rot
from redman_jax._robot import thesis_arm
from redman_jax._urdf import example_robot_data_file, from_urdf

from conftest import fd_jacobian

# Central differences with h = 1e-6 on O(1) trigonometric functions: truncation ~h^2 = 1e-12,
# rounding ~1e-16 / 1e-6 = 1e-10; 1e-8 absolute leaves a margin of 100 over both.
FD_TOL = 1e-8


def _arms():
    arms = [thesis_arm(7), thesis_arm(9)]
    try:
        arms.append(from_urdf(example_robot_data_file("panda_description/urdf/panda.urdf"), "panda_hand"))
    except FileNotFoundError:
        pass
    return arms


ARMS = _arms()


def _rand_q(arm, seed):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1.5, 1.5, arm.n_dof)
    return np.where(np.asarray(arm.prismatic), rng.uniform(0.1, 0.8, arm.n_dof), q)


def _vee_rot(dR, R):
    W = dR @ R.T
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


@pytest.mark.parametrize("arm", ARMS, ids=lambda a: a.name)
def test_fk_against_scipy_expm(arm):
    q = _rand_q(arm, 0)
    S = np.asarray(arm.screw_axes)
    P = np.eye(4)
    frames = np.asarray(forward_kinematics(arm, q))
    for i in range(arm.n_dof):
        w, v = S[i, :3], S[i, 3:]
        X = np.zeros((4, 4))
        X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        X[:3, 3] = v
        P = P @ scipy.linalg.expm(X * q[i])
        np.testing.assert_allclose(frames[i], P @ np.asarray(arm.home_frames[i]), atol=1e-12)
    np.testing.assert_allclose(np.asarray(end_effector_frame(arm, q)), P @ np.asarray(arm.ee_home), atol=1e-12)


@pytest.mark.parametrize("arm", ARMS, ids=lambda a: a.name)
def test_ee_jacobian_finite_differences(arm):
    q = _rand_q(arm, 1)
    J = np.asarray(jacobian(arm, q))
    Tj = jax.jit(lambda x: end_effector_frame(arm, x))
    T = lambda x: np.asarray(Tj(x))  # noqa: E731
    dT = fd_jacobian(T, q)  # (4, 4, n)
    R = T(q)[:3, :3]
    Jv = dT[:3, 3, :]
    Jw = np.stack([_vee_rot(dT[:3, :3, i], R) for i in range(arm.n_dof)], axis=1)
    np.testing.assert_allclose(J, np.concatenate([Jv, Jw]), atol=FD_TOL)
    # the spatial Jacobian is the same twist seen at the world origin
    Js = np.asarray(space_jacobian(arm, q))
    p = T(q)[:3, 3]
    np.testing.assert_allclose(Js[:3], J[3:], atol=1e-12)
    np.testing.assert_allclose(Js[3:] + np.cross(Js[:3].T, p).T, J[:3], atol=1e-12)


@pytest.mark.parametrize("arm", ARMS[1:], ids=lambda a: a.name)
def test_link_and_point_jacobians_finite_differences(arm):
    q = _rand_q(arm, 2)
    Jl = np.asarray(link_jacobians(arm, q))
    Fj = jax.jit(lambda x: forward_kinematics(arm, x))
    F = lambda x: np.asarray(Fj(x))  # noqa: E731
    dF = fd_jacobian(F, q)  # (n, 4, 4, n)
    Fq = F(q)
    for i in range(arm.n_dof):
        Jw = np.stack([_vee_rot(dF[i, :3, :3, j], Fq[i, :3, :3]) for j in range(arm.n_dof)], axis=1)
        np.testing.assert_allclose(Jl[i], np.concatenate([dF[i, :3, 3, :], Jw]), atol=FD_TOL)
    # a point fixed in link 4
    link, local = 4, np.array([0.03, -0.02, 0.05])
    pw = lambda x: F(x)[link, :3, :3] @ local + F(x)[link, :3, 3]  # noqa: E731
    Jp = np.asarray(point_jacobian(arm, q, link, pw(q)))
    np.testing.assert_allclose(Jp, fd_jacobian(pw, q), atol=FD_TOL)


@pytest.mark.parametrize("arm", ARMS, ids=lambda a: a.name)
def test_poi_jacobians(arm):
    q = _rand_q(arm, 3)
    Jp, Jauto = jax.jit(lambda x: (poi_jacobians(arm, x), jax.jacfwd(lambda y: poi_positions(arm, y))(x)))(q)
    Jp = np.asarray(Jp)
    assert Jp.shape == (arm.n_points, 3, arm.n_dof)
    np.testing.assert_allclose(Jp, np.asarray(Jauto), atol=1e-12)
    pj = jax.jit(lambda x: poi_positions(arm, x))
    np.testing.assert_allclose(Jp, fd_jacobian(lambda x: np.asarray(pj(x)), q), atol=FD_TOL)
    assert poi_link_index(arm).shape == (arm.n_points,)


def test_prismatic_pois_span_the_telescope():
    arm = thesis_arm(7)
    q = np.asarray(arm.q0).copy()
    q[1] = 0.6
    pois = np.asarray(poi_positions(arm, q)).reshape(7, 4, 3)
    # segment 2 (Pz) runs from its fixed side (z = 0.15) to its top (0.15 + 0.6 + 0.10)
    np.testing.assert_allclose(pois[1, :, 2], 0.15 + np.arange(1, 5) / 4 * 0.70, atol=1e-12)


@pytest.mark.parametrize("arm", ARMS[1:], ids=lambda a: a.name)
def test_jdot_qdot_finite_differences(arm):
    q = _rand_q(arm, 4)
    qd = np.random.default_rng(4).normal(size=arm.n_dof)
    h = 1e-6
    Jj = jax.jit(lambda x: jacobian(arm, x))
    Jdot = (np.asarray(Jj(q + h * qd)) - np.asarray(Jj(q - h * qd))) / (2 * h)
    np.testing.assert_allclose(np.asarray(jdot_qdot(arm, q, qd)), Jdot @ qd, atol=1e-7)
    # and it is the acceleration of the end effector along q(t) = q + t qd (second derivative of FK)
    Tj = jax.jit(lambda x: end_effector_frame(arm, x))
    pos = lambda t: np.asarray(Tj(q + t * qd))[:3, 3]  # noqa: E731
    h2 = 1e-4
    acc = (pos(h2) - 2 * pos(0.0) + pos(-h2)) / h2**2
    np.testing.assert_allclose(np.asarray(jdot_qdot(arm, q, qd))[:3], acc, atol=1e-5)


@pytest.mark.parametrize("arm", ARMS, ids=lambda a: a.name)
def test_end_effector_quaternion(arm):
    q = _rand_q(arm, 5)
    p, quat = end_effector_pose(arm, q)
    T = np.asarray(end_effector_frame(arm, q))
    assert float(jnp.linalg.norm(quat)) == pytest.approx(1.0, abs=1e-14) and float(quat[0]) >= 0
    np.testing.assert_allclose(np.asarray(quat_to_rot(quat)), T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(np.asarray(p), T[:3, 3], atol=0)


def test_jit_vmap_grad():
    arm = thesis_arm(9)
    qs = jnp.asarray(np.stack([_rand_q(arm, s) for s in range(4)]))
    Jb = jax.jit(jax.vmap(jacobian, in_axes=(None, 0)))(arm, qs)
    np.testing.assert_allclose(np.asarray(Jb[2]), np.asarray(jacobian(arm, qs[2])), atol=1e-14)
    f = jax.jit(jax.grad(lambda x: jnp.sum(end_effector_pose(arm, x)[1] ** 3) + jnp.sum(poi_positions(arm, x))))
    assert np.all(np.isfinite(np.asarray(f(qs[0]))))
    # no NaN gradient at q = 0 (the quaternion square roots are guarded)
    assert np.all(np.isfinite(np.asarray(f(jnp.zeros(9)))))
    # and the gradient is right: against finite differences of the same scalar
    fs = jax.jit(lambda x: jnp.sum(end_effector_pose(arm, x)[1] ** 3) + jnp.sum(poi_positions(arm, x)))
    np.testing.assert_allclose(np.asarray(f(qs[1])), fd_jacobian(lambda x: np.asarray(fs(x)), qs[1]), atol=FD_TOL)


def test_float32_smoke():
    with jax.enable_x64(False):
        arm = thesis_arm(9)
        assert arm.screw_axes.dtype == jnp.float32
        q = jnp.asarray(_rand_q(arm, 6), jnp.float32)
        qd = jnp.ones(9, jnp.float32)
        def everything(arm, q, qd):
            return [kinematics(arm, q), forward_kinematics(arm, q), end_effector_frame(arm, q),
                    end_effector_pose(arm, q), jacobian(arm, q), space_jacobian(arm, q),
                    link_jacobians(arm, q), point_jacobian(arm, q, 3, jnp.zeros(3, jnp.float32)),
                    poi_positions(arm, q), poi_jacobians(arm, q), jdot_qdot(arm, q, qd),
                    jax.vmap(jacobian, in_axes=(None, 0))(arm, q[None]),
                    jax.grad(lambda x: jnp.sum(end_effector_pose(arm, x)[1]))(q)]

        outs = jax.jit(everything)(arm, q, qd)
        for leaf in jax.tree.leaves(outs):
            assert leaf.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(leaf)))
        # float32 agrees with float64 to float32 precision
        J32 = np.asarray(jacobian(arm, q))
    J64 = np.asarray(jacobian(thesis_arm(9), np.asarray(q, np.float64)))
    np.testing.assert_allclose(J32, J64, atol=1e-5)


def test_point_jacobian_refuses_a_link_out_of_range_and_a_point_of_another_shape():
    """``link=-1`` gave an all-zero Jacobian and ``link=n`` the last link's; a 2-vector point was
    crossed as a 2-vector. Each is a ``ValueError`` naming the argument; a traced link still works."""
    arm = thesis_arm(7)
    q, p = arm.q0, jnp.array([0.1, 0.2, 0.3])
    for link in (-1, 7, 2.0):
        with pytest.raises(ValueError, match="link must be an integer in \\[0, 7\\)"):
            point_jacobian(arm, q, link, p)
    with pytest.raises(ValueError, match="p_world must have shape \\(3,\\)"):
        point_jacobian(arm, q, 3, p[:2])
    J = jax.jit(lambda k: point_jacobian(arm, q, k, p))(3)
    np.testing.assert_array_equal(np.asarray(J), np.asarray(point_jacobian(arm, q, np.int64(3), p)))
