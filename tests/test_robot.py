"""Arm model: thesis arm numbers (SPEC section 1, U10) and construction-time validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from redman_jax._kinematics import end_effector_pose, jacobian, poi_positions
from redman_jax._robot import JOINT_SEQUENCES, Arm, thesis_arm, thesis_inertia

# ---- thesis arms ----------------------------------------------------------------------------


@pytest.mark.parametrize("dof, length, sigma", [(7, 1.20, 0.18), (8, 1.35, 0.18), (9, 1.50, 0.34)])
def test_thesis_arm_geometry(dof, length, sigma):
    arm = thesis_arm(dof)
    assert arm.n_dof == dof and arm.n_points == 4 * dof
    assert arm.joint_names == JOINT_SEQUENCES[dof]
    p, quat = end_effector_pose(arm, arm.q0)
    # straight vertical column at q0 (lift at 0.2 m): SPEC section 1 table
    np.testing.assert_allclose(np.asarray(p), [0, 0, length], atol=1e-12)
    np.testing.assert_allclose(np.asarray(quat), [1, 0, 0, 0], atol=1e-12)
    # SPEC: smallest singular value of the 6xn Jacobian at q0 is 0.18 / 0.18 / 0.34 (2 digits)
    s = np.linalg.svd(np.asarray(jacobian(arm, arm.q0)), compute_uv=False)
    assert s.size == 6 and abs(s.min() - sigma) < 0.005
    # horizontal chain after pivot J3 at height 0.25 + q2: L_h = length - 0.45
    assert np.asarray(arm.home_frames)[2, 2, 3] == pytest.approx(0.25)
    # POIs: 4 per segment on the axis, the last one is the end effector
    pois = np.asarray(poi_positions(arm, arm.q0))
    np.testing.assert_allclose(pois[:, :2], 0, atol=1e-12)
    assert pois[-1, 2] == pytest.approx(length)
    assert np.all(np.diff(pois[:, 2]) > 0)


def test_thesis_arm_limits_and_q0():
    arm = thesis_arm(9)
    for k, name in enumerate(arm.joint_names):
        lim, lo, hi, q0 = bool(arm.limited[k]), float(arm.q_min[k]), float(arm.q_max[k]), float(arm.q0[k])
        if name == "Rz":
            assert not lim and q0 == 0
        elif name == "Pz":
            assert lim and (lo, hi, q0) == (0.0, 1.2, 0.2) and arm.prismatic[k]
        else:
            assert lim and lo == pytest.approx(-0.75 * math.pi) and hi == pytest.approx(0.75 * math.pi)
    np.testing.assert_allclose(np.asarray(arm.widths), 0.10)
    np.testing.assert_allclose(np.asarray(arm.gravity), [0, 0, -9.81])


def test_thesis_inertia_u10():
    # SPEC U10: 1.5 kg solid cylinder (r 0.05, L 0.15) + 1.0 kg point mass at the bottom
    m, c, inertia = thesis_inertia()
    assert m == 2.5 and c[2] == pytest.approx(0.045)
    np.testing.assert_allclose(np.diag(inertia), [7.125e-3, 7.125e-3, 1.875e-3], rtol=1e-12)
    # independent check by the parallel-axis theorem from the origin (the point mass)
    m_c, L, r = 1.5, 0.15, 0.05
    ixx_origin = m_c * (3 * r**2 + L**2) / 12 + m_c * (L / 2) ** 2  # point mass at origin adds 0
    assert inertia[0, 0] == pytest.approx(ixx_origin - m * c[2] ** 2, rel=1e-12)
    arm = thesis_arm(9)
    np.testing.assert_allclose(np.asarray(arm.masses), 2.5)
    np.testing.assert_allclose(np.asarray(arm.inertias), np.broadcast_to(inertia, (9, 3, 3)))


def test_thesis_arm_bad_dof():
    with pytest.raises(ValueError, match="dof"):
        thesis_arm(6)


# ---- validation ------------------------------------------------------------------------------


def _fields(arm):
    names = ["screw_axes", "home_frames", "ee_home", "masses", "coms", "inertias", "q_min", "q_max",
             "limited", "widths", "seg_ends", "q0", "gravity", "prismatic", "joint_names",
             "points_per_link", "name"]
    return {k: getattr(arm, k) for k in names}


def _with(**changes):
    f = _fields(thesis_arm(7))
    for k, fn in changes.items():
        f[k] = fn(f[k])
    return Arm(**f)



def _np_set(x, index, value):
    y = np.array(x, copy=True)
    y[index] = value
    return jnp.asarray(y)


@pytest.mark.parametrize(
    "field, change",
    [
        ("screw_axes", lambda x: x[:, :5]),  # wrong shape
        ("masses", lambda x: x[:3]),
        ("screw_axes", lambda x: _np_set(x, (0, 2), 2.0)),  # non-unit revolute axis
        ("screw_axes", lambda x: _np_set(x, (1, 0), 1.0)),  # prismatic with omega != 0
        ("screw_axes", lambda x: _np_set(x, (0, 5), 0.5)),  # revolute Rz with pitch (helical)
        ("masses", lambda x: _np_set(x, 3, 0.0)),
        ("masses", lambda x: _np_set(x, 3, -1.0)),
        ("inertias", lambda x: _np_set(x, (2, 0, 1), 1e-3)),  # not symmetric
        ("inertias", lambda x: _np_set(x, (2, 2, 2), -1e-3)),  # not positive definite
        ("q_min", lambda x: _np_set(x, 2, 3.0)),  # q_min > q_max on a limited joint
        ("home_frames", lambda x: _np_set(x, (1, 0, 0), 2.0)),  # not a rotation
        ("coms", lambda x: _np_set(x, (0, 0), np.nan)),  # non-finite
        ("widths", lambda x: _np_set(x, 0, -0.1)),
    ],
)
def test_arm_validation_names_field(field, change):
    with pytest.raises(ValueError, match=f"Arm.{field}"):
        _with(**{field: change})


def test_arm_validation_structure():
    with pytest.raises(ValueError, match="joint_names"):
        _with(joint_names=lambda x: x[:-1])
    with pytest.raises(ValueError, match="points_per_link"):
        _with(points_per_link=lambda x: 0)


def test_arm_is_a_pytree_for_jit_and_vmap():
    arm = thesis_arm(7)
    stacked = jax.tree.map(lambda a, b: jnp.stack([a, b]), arm, _with(masses=lambda m: 2 * m))
    f = jax.jit(jax.vmap(lambda a: jnp.sum(a.masses)))
    np.testing.assert_allclose(np.asarray(f(stacked)), [17.5, 35.0])
