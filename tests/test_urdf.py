"""URDF import/export: the Panda against Pinocchio, lumping, round trips, validation errors."""

import dataclasses
import math
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from redman_jax._dynamics import bias_forces, forward_dynamics, mass_matrix
from redman_jax._kinematics import end_effector_frame, jacobian
from redman_jax._robot import thesis_arm
from redman_jax._urdf import example_robot_data_file, from_urdf, from_urdf_string, matrix_to_rpy, rpy_to_matrix, to_urdf

pin = pytest.importorskip("pinocchio")


@pytest.fixture(scope="module")
def panda_path():
    try:
        return example_robot_data_file("panda_description/urdf/panda.urdf")
    except FileNotFoundError:
        pytest.skip("example-robot-data not installed")


def _no_fingers(path):
    root = ET.parse(path).getroot()
    for el in list(root):
        if el.tag in ("link", "joint") and "finger" in el.get("name", ""):
            root.remove(el)
    return ET.tostring(root, encoding="unicode")


def _pin_q(model, q):
    parts = [np.array([np.cos(x), np.sin(x)]) if model.joints[j + 1].nq == 2 else np.array([x])
             for j, x in enumerate(q)]
    return np.concatenate(parts)


def _compare_with_pinocchio(arm, xml, tip, seeds=range(4)):
    """M, c + g, forward dynamics, EE pose and Jacobian against Pinocchio on random states."""
    model = pin.buildModelFromXML(xml)
    data = model.createData()
    assert model.nv == arm.n_dof
    fid = model.getFrameId(tip)
    ours = jax.jit(lambda q, qd, tau: (mass_matrix(arm, q), bias_forces(arm, q, qd), jacobian(arm, q),
                                       end_effector_frame(arm, q), forward_dynamics(arm, q, qd, tau, limits=False)))
    for seed in seeds:
        rng = np.random.default_rng(seed)
        lo = np.where(np.asarray(arm.limited), np.asarray(arm.q_min), -np.pi)
        hi = np.where(np.asarray(arm.limited), np.asarray(arm.q_max), np.pi)
        q, qd, tau = rng.uniform(lo, hi), rng.normal(size=arm.n_dof), rng.normal(size=arm.n_dof)
        qp = _pin_q(model, q)
        M = pin.crba(model, data, qp)
        M = np.triu(M) + np.triu(M, 1).T  # crba fills the upper triangle
        h = pin.nonLinearEffects(model, data, qp, qd)
        J = pin.computeFrameJacobian(model, data, qp, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        pin.framesForwardKinematics(model, data, qp)
        T = data.oMf[fid].homogeneous
        ddq = pin.aba(model, data, qp, qd, tau)
        Mo, ho, Jo, To, ddqo = map(np.asarray, ours(q, qd, tau))
        rel = lambda a, b: np.max(np.abs(a - b)) / np.max(np.abs(b))  # noqa: E731
        # an independent library in float64: agreement to rounding (~1e-15); 1e-9 as the issue asks
        assert rel(Mo, M) < 1e-9 and rel(ho, h) < 1e-9 and rel(Jo, J) < 1e-9 and rel(ddqo, ddq) < 1e-9
        np.testing.assert_allclose(To, T, atol=1e-12)


def test_panda_loads(panda_path):
    arm = from_urdf(panda_path, tip_link="panda_hand")
    assert arm.n_dof == 7 and arm.name == "panda"
    assert arm.joint_names == tuple(f"panda_joint{k}" for k in range(1, 8))
    assert not any(arm.prismatic) and bool(np.all(np.asarray(arm.limited)))
    np.testing.assert_allclose(np.asarray(arm.q_min)[3:4], [-3.0718])
    # zeros clipped into the limits with a 5 % margin: joint 4 in [-3.0718, -0.0698], joint 6 in [-0.0175, 3.7525]
    np.testing.assert_allclose(np.asarray(arm.q0), [0, 0, 0, -0.0698 - 0.05 * 3.002, 0, -0.0175 + 0.05 * 3.77, 0], atol=1e-12)
    # link7 + link8 (massless) + hand (0.73 kg) lumped; the fingers (a movable branch) ignored
    assert float(arm.masses[-1]) == pytest.approx(0.735522 + 0.73)
    M = np.asarray(mass_matrix(arm, arm.q0))
    assert M.shape == (7, 7) and np.allclose(M, M.T) and np.linalg.eigvalsh(M).min() > 0
    # the end effector is the hand frame: 0.107 m beyond the flange, yawed by -45 degrees
    T = np.asarray(end_effector_frame(arm, jnp.zeros(7)))
    np.testing.assert_allclose(T[:3, 3], [0.088, 0, 0.333 + 0.316 + 0.384 - 0.107], atol=1e-12)


def test_panda_against_pinocchio(panda_path):
    arm = from_urdf(panda_path, tip_link="panda_hand")
    _compare_with_pinocchio(arm, _no_fingers(panda_path), "panda_hand")


def test_thesis_arm_against_pinocchio():
    # the prismatic lift and the continuous joints, through to_urdf; Pinocchio parses the text
    arm = thesis_arm(9)
    _compare_with_pinocchio(arm, to_urdf(arm), "ee", seeds=range(2))


@pytest.mark.parametrize("dof", [7, 9])
def test_round_trip_thesis(dof):
    arm = thesis_arm(dof)
    back = from_urdf_string(to_urdf(arm), "ee", q0=arm.q0)
    assert back.prismatic == arm.prismatic and back.n_dof == arm.n_dof
    for a, b in zip(jax.tree.leaves(arm), jax.tree.leaves(back)):
        np.testing.assert_allclose(np.asarray(b, float), np.asarray(a, float), atol=1e-12)


def test_round_trip_panda(panda_path):
    arm = from_urdf(panda_path, tip_link="panda_hand")
    back = from_urdf_string(to_urdf(arm, tip_link="panda_hand"), "panda_hand")
    assert back.joint_names == arm.joint_names
    for a, b in zip(jax.tree.leaves(arm), jax.tree.leaves(back)):
        np.testing.assert_allclose(np.asarray(b, float), np.asarray(a, float), atol=1e-12)


def test_rpy_round_trip():
    rng = np.random.default_rng(0)
    for rpy in list(rng.uniform(-3, 3, (20, 3))) + [np.array([0.3, np.pi / 2, 0.0]), np.array([0.3, -np.pi / 2, 0.0])]:
        R = rpy_to_matrix(rpy)
        np.testing.assert_allclose(rpy_to_matrix(matrix_to_rpy(R)), R, atol=1e-12)
    # near gimbal lock asin(-R20) lost digits (9.6e-9 at pi/2 - 1e-8); atan2 keeps them
    for d in (1e-4, 1e-6, 1e-8, 1e-10):
        for sgn in (1.0, -1.0):
            R = rpy_to_matrix([0.3, sgn * (np.pi / 2 - d), -0.7])
            np.testing.assert_allclose(rpy_to_matrix(matrix_to_rpy(R)), R, atol=1e-14)
    # URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)
    np.testing.assert_allclose(rpy_to_matrix([0, 0, np.pi / 2]) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rpy_to_matrix([np.pi / 2, 0, 0]) @ [0, 1, 0], [0, 0, 1], atol=1e-15)


# ---- a small hand-written URDF ---------------------------------------------------------------

SMALL = """<?xml version="1.0"?>
<robot name="small">
  <link name="base"/>
  <link name="a"><inertial><origin xyz="0 0 0.1" rpy="0 0 0"/><mass value="2.0"/>
    <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.01"/></inertial></link>
  <link name="a_tool"><inertial><origin xyz="0.1 0 0" rpy="0 0 0.5"/><mass value="1.0"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.003" iyz="0" izz="0.002"/></inertial></link>
  <link name="b"><inertial><origin xyz="0 0 0.05"/><mass value="1.5"/>
    <inertia ixx="0.01" ixy="0.001" ixz="0" iyy="0.01" iyz="0" izz="0.005"/></inertial></link>
  <link name="c"><inertial><mass value="0.5"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
  <link name="finger"><inertial><mass value="3.0"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
  <link name="tip"/>
  <joint name="j1" type="continuous"><parent link="base"/><child link="a"/>
    <origin xyz="0 0 0.2" rpy="0 0 0.3"/><axis xyz="0 0 1"/></joint>
  <joint name="fix" type="fixed"><parent link="a"/><child link="a_tool"/><origin xyz="0 0.05 0.2" rpy="0.2 0 0"/></joint>
  <joint name="j2" type="revolute"><parent link="a_tool"/><child link="b"/>
    <origin xyz="0 0 0.1" rpy="0.5 -0.2 0.1"/><axis xyz="0 1 0"/><limit lower="-1" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j3" type="prismatic"><parent link="b"/><child link="c"/>
    <origin xyz="0.1 0 0.3"/><axis xyz="0.6 0 0.8"/><limit lower="0.1" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="grip" type="revolute"><parent link="b"/><child link="finger"/>
    <origin xyz="0 0.1 0"/><axis xyz="1 0 0"/><limit lower="0" upper="1" effort="1" velocity="1"/></joint>
  <joint name="tipj" type="fixed"><parent link="c"/><child link="tip"/><origin xyz="0 0 0.07" rpy="0 0.4 0"/></joint>
</robot>
"""


def test_small_urdf_lumping_and_limits():
    arm = from_urdf_string(SMALL, "tip")
    assert arm.joint_names == ("j1", "j2", "j3") and arm.prismatic == (False, False, True)
    assert [bool(x) for x in arm.limited] == [False, True, True]
    np.testing.assert_allclose(np.asarray(arm.q0), [0, 0, 0.12])  # zero clipped into [0.1, 0.5], 5 % margin
    np.testing.assert_allclose(np.asarray(arm.q_min)[1:], [-1, 0.1])
    # body of j1 = a + a_tool (fixed): lumped mass and CoM by hand, in a's frame
    assert float(arm.masses[0]) == pytest.approx(3.0)
    c_tool = np.array([0, 0.05, 0.2]) + rpy_to_matrix([0.2, 0, 0]) @ np.array([0.1, 0, 0])
    np.testing.assert_allclose(np.asarray(arm.coms[0]), (2.0 * np.array([0, 0, 0.1]) + c_tool) / 3.0, atol=1e-15)
    # the branch "finger" (a movable joint off the chain) is ignored: b keeps its own mass
    assert float(arm.masses[1]) == pytest.approx(1.5)
    # seg_ends: next joint origin in the link frame; the tip for the last
    np.testing.assert_allclose(np.asarray(arm.seg_ends[1]), [0.1, 0, 0.3], atol=1e-15)
    np.testing.assert_allclose(np.asarray(arm.seg_ends[2]), [0, 0, 0.07], atol=1e-15)


def test_small_urdf_against_pinocchio():
    arm = from_urdf_string(SMALL, "tip")
    root = ET.fromstring(SMALL)
    for el in list(root):  # Pinocchio keeps branches: drop it for the same chain
        if el.get("name") in ("finger", "grip"):
            root.remove(el)
    _compare_with_pinocchio(arm, ET.tostring(root, encoding="unicode"), "tip", seeds=range(2))


def test_base_link_and_options():
    arm = from_urdf_string(SMALL, "tip", base_link="a_tool", link_width=[0.1, 0.2], q0=[0.3, 0.2],
                           points_per_link=3, name="sub")
    assert arm.joint_names == ("j2", "j3") and arm.points_per_link == 3 and arm.name == "sub"
    np.testing.assert_allclose(np.asarray(arm.widths), [0.1, 0.2])
    # the base frame is a_tool's: joint j2 sits at its origin offset
    np.testing.assert_allclose(np.asarray(arm.home_frames[0])[:3, 3], [0, 0, 0.1], atol=1e-15)


# ---- validation ------------------------------------------------------------------------------


def _edit(old, new):
    assert old in SMALL
    return SMALL.replace(old, new, 1)


@pytest.mark.parametrize(
    "text, tip, match",
    [
        (SMALL[:-30], "tip", "malformed XML"),
        (SMALL, "nowhere", "tip_link"),
        (_edit('type="continuous"', 'type="hinge"'), "tip", "unknown joint type"),
        (_edit('type="continuous"', 'type="floating"'), "tip", "floating"),
        (_edit('<mass value="2.0"/>', '<mass value="-2.0"/>'), "tip", "link 'a'/inertial/mass"),
        (_edit('<mass value="2.0"/>', '<mass value="two"/>'), "tip", "not numeric"),
        (_edit('ixx="0.02"', 'ixx="-0.02"'), "tip", "link 'a'/inertial/inertia"),
        (_edit('<limit lower="-1" upper="2"', '<limit lower="3" upper="2"'), "tip", "joint 'j2'/limit"),
        (_edit('<limit lower="-1" upper="2" effort="1" velocity="1"/>', ''), "tip", "joint 'j2'.*limit"),
        (_edit('<axis xyz="0 1 0"/>', '<axis xyz="0 2 0"/>'), "tip", "joint 'j2'/axis"),
        (_edit('<origin xyz="0.1 0 0.3"/>', '<origin xyz="0.1 0"/>'), "tip", "joint 'j3'/origin"),
        (_edit('<child link="b"/>', '<child link="zz"/>'), "tip", "joint 'j2'/child"),
        (_edit('<mass value="1.5"/>', '<mass value="0.0"/>'), "tip", "link 'b'.*total mass"),
        (SMALL.replace("<robot", "<robbot").replace("</robot>", "</robbot>"), "tip", "<robot>"),
        # a mimic joint would silently become an independent degree of freedom
        (_edit('<axis xyz="0 1 0"/>', '<axis xyz="0 1 0"/><mimic joint="j1" multiplier="1"/>'), "tip",
         "joint 'j2': mimics joint 'j1'"),
    ],
)
def test_invalid_urdf(text, tip, match):
    with pytest.raises(ValueError, match=match):
        from_urdf_string(text, tip)


def test_invalid_arguments(tmp_path):
    with pytest.raises(ValueError, match="base_link"):
        from_urdf_string(SMALL, "tip", base_link="nowhere")
    with pytest.raises(ValueError, match="base_link"):
        from_urdf_string(SMALL, "a", base_link="b")  # not an ancestor
    with pytest.raises(ValueError, match="q0"):
        from_urdf_string(SMALL, "tip", q0=[0.0, 0.0])
    with pytest.raises(ValueError, match="link_width"):
        from_urdf_string(SMALL, "tip", link_width=[0.1, 0.1])
    with pytest.raises(ValueError, match="path"):
        from_urdf(tmp_path / "missing.urdf", "tip")
    p = tmp_path / "small.urdf"
    p.write_text(SMALL)
    assert from_urdf(p, "tip").n_dof == 3
    with pytest.raises(ValueError, match="no movable joint"):
        from_urdf_string(SMALL, "a_tool", base_link="a")


def test_to_urdf_rejects_what_urdf_cannot_express():
    arm = thesis_arm(7)
    S = np.asarray(arm.screw_axes).copy()
    S[2, 3:] += np.array([0.0, 0.0, 0.0]) + np.cross(S[2, :3], [0.1, 0, 0])  # axis moved off the origin
    import equinox as eqx

    moved = eqx.tree_at(lambda a: a.screw_axes, arm, jnp.asarray(S))
    with pytest.raises(ValueError, match="screw_axes"):
        to_urdf(moved)
    unlimited = eqx.tree_at(lambda a: a.limited, arm, jnp.zeros(7, bool))
    with pytest.raises(ValueError, match="prismatic"):
        to_urdf(unlimited)
    assert math.isfinite(float(from_urdf_string(to_urdf(arm), "ee").masses.sum()))


def test_to_urdf_refuses_a_tip_link_whose_names_are_taken():
    """A ``tip_link`` named ``base`` or ``link3``, or whose fixed joint ``{tip_link}_joint`` is a
    joint of the arm, wrote a URDF with a name defined twice (an error only when read back)."""
    arm = thesis_arm(7)
    for tip in ("base", "link3", "link7", ""):
        with pytest.raises(ValueError, match="tip_link"):
            to_urdf(arm, tip_link=tip)
    named = dataclasses.replace(arm, joint_names=("ee_joint", "b", "c", "d", "e", "f", "g"))
    with pytest.raises(ValueError, match="tip_link 'ee' names its fixed joint ee_joint"):
        to_urdf(named)  # the default tip_link "ee"
    back = from_urdf_string(to_urdf(arm, tip_link="link8"), "link8")  # not a link of a 7-DOF arm
    assert back.n_dof == 7
