"""Arm models: one equinox Module for every serial arm (thesis 3.1, App. A; SPEC section 1).

Conventions (SPEC section 0):

* twists are ordered ``(omega, v)`` (Modern Robotics);
* ``screw_axes[i]`` is the unit screw of joint ``i`` in the world (space) frame at ``q = 0``;
* ``home_frames[i]`` is the pose of link frame ``i`` in the world at ``q = 0``;
  forward kinematics is the product of exponentials
  ``T_i(q) = exp([S_1] q_1) ... exp([S_i] q_i) home_frames[i]`` (A.3-A.6);
* link inertial data (``masses``, ``coms``, ``inertias``) and the points of interest are given in
  the link frame; inertias are about the centre of mass.

Structure (number of joints, which joints are prismatic, points per segment) is static; every number
is an array, so a batch of arms with the same structure can be stacked and vmapped.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._host import put
from ._math import concrete

__all__ = ["Arm", "thesis_arm", "JOINT_SEQUENCES"]

# Joint sequences proposed by SPEC section 1 (base -> tip).
JOINT_SEQUENCES: dict[int, tuple[str, ...]] = {
    7: ("Rz", "Pz", "Ry", "Rx", "Ry", "Rx", "Rz"),
    8: ("Rz", "Pz", "Ry", "Rx", "Ry", "Rx", "Ry", "Rz"),
    9: ("Rz", "Pz", "Ry", "Rx", "Ry", "Rx", "Ry", "Rx", "Rz"),
}

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


class Arm(eqx.Module):
    """A serial arm of ``n`` one-degree-of-freedom joints (revolute or prismatic).

    Fields (``n`` joints, ``P = points_per_link``):

    * ``screw_axes``: ``(n, 6)`` unit screws ``(omega, v)`` in the world frame at ``q = 0``.
      Revolute: ``|omega| = 1``, ``v = -omega x r``. Prismatic: ``omega = 0``, ``|v| = 1``.
    * ``home_frames``: ``(n, 4, 4)`` link frames in the world at ``q = 0``.
    * ``ee_home``: ``(4, 4)`` end-effector frame in the world at ``q = 0``; it moves with the
      last link.
    * ``masses`` ``(n,)`` [kg], ``coms`` ``(n, 3)`` [m, link frame], ``inertias`` ``(n, 3, 3)``
      [kg m^2, about the CoM, link-frame axes].
    * ``q_min``, ``q_max`` ``(n,)`` joint limits; ``limited`` ``(n,)`` bool: which joints have
      limits (the contact model and the joint-limit policy act on those only).
    * ``widths`` ``(n,)`` [m] link widths: a point of interest closer than its link's width to an
      obstacle is in collision (thesis: 0.10 m).
    * ``seg_ends`` ``(n, 3)`` [m]: the far end of each segment in its link frame. The points of
      interest lie on the segment from the joint to this end, at fractions ``k / P``,
      ``k = 1..P``. For a prismatic joint the segment telescopes: it starts at the joint's
      fixed side, ``-q_i * axis`` in the link frame (SPEC U11).
    * ``q0`` ``(n,)``: the initial configuration.
    * ``gravity`` ``(3,)`` [m/s^2].
    * ``prismatic``: static tuple of bools; ``joint_names``: static tuple of labels.
    """

    screw_axes: Float[Array, "n 6"]
    home_frames: Float[Array, "n 4 4"]
    ee_home: Float[Array, "4 4"]
    masses: Float[Array, " n"]
    coms: Float[Array, "n 3"]
    inertias: Float[Array, "n 3 3"]
    q_min: Float[Array, " n"]
    q_max: Float[Array, " n"]
    limited: Bool[Array, " n"]
    widths: Float[Array, " n"]
    seg_ends: Float[Array, "n 3"]
    q0: Float[Array, " n"]
    gravity: Float[Array, "3"]
    prismatic: tuple[bool, ...] = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    points_per_link: int = eqx.field(static=True, default=4)
    name: str = eqx.field(static=True, default="arm")

    def __check_init__(self):
        _validate_arm(self)

    @property
    def n_dof(self) -> int:
        return len(self.prismatic)

    @property
    def n_points(self) -> int:
        """Number of points of interest, ``n * points_per_link``."""
        return self.n_dof * self.points_per_link

    @property
    def prismatic_mask(self) -> np.ndarray:
        return np.asarray(self.prismatic, dtype=bool)


def _validate_arm(arm: Arm) -> None:
    """Host-side validation with errors that name the offending field (never a NaN later)."""
    n = len(arm.prismatic)
    if n < 1:
        raise ValueError("Arm.prismatic: an arm needs at least one joint")
    if len(arm.joint_names) != n:
        raise ValueError(f"Arm.joint_names: expected {n} names, got {len(arm.joint_names)}")
    if not isinstance(arm.points_per_link, int) or arm.points_per_link < 1:
        raise ValueError(f"Arm.points_per_link: must be a positive int, got {arm.points_per_link!r}")
    shapes = {
        "screw_axes": (n, 6),
        "home_frames": (n, 4, 4),
        "ee_home": (4, 4),
        "masses": (n,),
        "coms": (n, 3),
        "inertias": (n, 3, 3),
        "q_min": (n,),
        "q_max": (n,),
        "limited": (n,),
        "widths": (n,),
        "seg_ends": (n, 3),
        "q0": (n,),
        "gravity": (3,),
    }
    for field, shape in shapes.items():
        value = getattr(arm, field)
        got = tuple(jnp.shape(value))
        if got != shape:
            raise ValueError(f"Arm.{field}: expected shape {shape}, got {got}")
    vals = {f: concrete(getattr(arm, f)) for f in shapes}
    if any(v is None for v in vals.values()):
        return  # built under a transformation: shapes checked, values cannot be
    for field, v in vals.items():
        if field != "limited" and not np.all(np.isfinite(v)):
            raise ValueError(f"Arm.{field}: contains non-finite values")
    s = vals["screw_axes"]
    for i, pri in enumerate(arm.prismatic):
        w, v = s[i, :3], s[i, 3:]
        if pri:
            if np.linalg.norm(w) > 1e-9 or abs(np.linalg.norm(v) - 1.0) > 1e-6:
                raise ValueError(
                    f"Arm.screw_axes[{i}]: a prismatic joint needs omega = 0 and a unit v, got {s[i]}"
                )
        elif abs(np.linalg.norm(w) - 1.0) > 1e-6:
            raise ValueError(f"Arm.screw_axes[{i}]: a revolute joint needs a unit omega, got {w}")
        elif abs(float(w @ v)) > 1e-6:  # v = -omega x r is orthogonal to omega; else a helical joint
            raise ValueError(f"Arm.screw_axes[{i}]: a revolute joint needs v orthogonal to omega "
                             f"(v = -omega x r, zero pitch), got omega . v = {float(w @ v):.3g}")
    for field in ("home_frames", "ee_home"):
        frames = vals[field].reshape(-1, 4, 4)
        for k, T in enumerate(frames):
            R = T[:3, :3]
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ValueError(f"Arm.{field}[{k}]: rotation part is not a proper rotation")
            if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-12):
                raise ValueError(f"Arm.{field}[{k}]: last row must be (0, 0, 0, 1)")
    if np.any(vals["masses"] <= 0):
        raise ValueError(f"Arm.masses: every mass must be > 0, got {vals['masses']}")
    for i, inertia in enumerate(vals["inertias"]):
        if not np.allclose(inertia, inertia.T, atol=1e-12, rtol=1e-9):
            raise ValueError(f"Arm.inertias[{i}]: not symmetric")
        if np.linalg.eigvalsh(inertia).min() <= 0:
            raise ValueError(f"Arm.inertias[{i}]: not positive definite")
    lim = vals["limited"].astype(bool)
    if np.any(lim & (vals["q_min"] > vals["q_max"])):
        bad = np.nonzero(lim & (vals["q_min"] > vals["q_max"]))[0].tolist()
        raise ValueError(f"Arm.q_min/q_max: q_min > q_max for joints {bad}")
    if np.any(vals["widths"] < 0):
        raise ValueError("Arm.widths: must be >= 0")


def _joint_screw(kind: str, r: np.ndarray) -> np.ndarray:
    """Unit screw (omega, v) of a joint of kind 'Rx' | 'Ry' | 'Rz' | 'Pz' ... at point r (world-aligned)."""
    axis = np.array(_AXES[kind[1].lower()])
    if kind[0].upper() == "R":
        return np.concatenate([axis, -np.cross(axis, r)])
    if kind[0].upper() == "P":
        return np.concatenate([np.zeros(3), axis])
    raise ValueError(f"joint type {kind!r}: expected R or P followed by x, y or z")


def thesis_inertia(length: float = 0.15, cyl_mass: float = 1.5, point_mass: float = 1.0,
                   radius: float = 0.05) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, CoM and inertia of a thesis segment: a solid cylinder plus a point mass at its bottom.

    Returns ``(mass, com (3,), inertia about the CoM (3, 3))`` in the link frame (z along the
    segment). Defaults give SPEC U10: 2.5 kg, ``z_c = 0.045``, ``I_xx = I_yy = 7.125e-3``,
    ``I_zz = 1.875e-3``.
    """
    m = cyl_mass + point_mass
    zc = cyl_mass * (length / 2) / m
    ixx_cyl = cyl_mass * (3 * radius**2 + length**2) / 12 + cyl_mass * (length / 2 - zc) ** 2
    ixx = ixx_cyl + point_mass * zc**2
    izz = 0.5 * cyl_mass * radius**2
    return m, np.array([0.0, 0.0, zc]), np.diag([ixx, ixx, izz])


def thesis_arm(dof: int = 9, *, uniform_inertia: bool = True) -> Arm:
    """The thesis arm with ``dof`` in {7, 8, 9} joints (SPEC section 1, joint sequences proposed there).

    Rotational segments are 0.15 m long, prismatic ones 0.10 m; all 0.10 m wide, 2.5 kg. Limits:
    +-0.75 pi for x/y rotations, none for z rotations, [0, 1.2] m for the lift. ``q0`` is the
    straight vertical column with the lift at 0.2 m. Body frame ``i`` sits at joint ``i`` (the
    bottom of segment ``i``) and is world-aligned at ``q = 0``; the end effector is the tip of the
    last segment with its tool axis along +z.

    With ``uniform_inertia=True`` (the thesis: "every link uses the same inertia") every link gets
    the 0.15 m segment's inertia; with False the prismatic segment gets its own (0.10 m) inertia.
    """
    if dof not in JOINT_SEQUENCES:
        raise ValueError(f"thesis_arm: dof must be one of {sorted(JOINT_SEQUENCES)}, got {dof!r}")
    kinds = JOINT_SEQUENCES[dof]
    lengths = np.array([0.10 if k[0] == "P" else 0.15 for k in kinds])
    heights = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    screws, frames, masses, coms, inertias = [], [], [], [], []
    q_min, q_max, limited, q0 = [], [], [], []
    for kind, L, h in zip(kinds, lengths, heights):
        r = np.array([0.0, 0.0, h])
        screws.append(_joint_screw(kind, r))
        T = np.eye(4)
        T[:3, 3] = r
        frames.append(T)
        m, c, inertia = thesis_inertia(0.15 if uniform_inertia else L)
        masses.append(m)
        coms.append(c)
        inertias.append(inertia)
        if kind == "Pz":
            q_min.append(0.0), q_max.append(1.2), limited.append(True), q0.append(0.2)
        elif kind == "Rz":
            q_min.append(-math.pi), q_max.append(math.pi), limited.append(False), q0.append(0.0)
        else:
            q_min.append(-0.75 * math.pi), q_max.append(0.75 * math.pi)
            limited.append(True), q0.append(0.0)
    ee = np.eye(4)
    ee[2, 3] = lengths.sum()
    return Arm(
        screw_axes=put(np.array(screws)),
        home_frames=put(np.array(frames)),
        ee_home=put(ee),
        masses=put(np.array(masses)),
        coms=put(np.array(coms)),
        inertias=put(np.array(inertias)),
        q_min=put(np.array(q_min)),
        q_max=put(np.array(q_max)),
        limited=put(np.array(limited)),
        widths=put(np.full(dof, 0.10)),
        seg_ends=put(np.stack([np.array([0.0, 0.0, L]) for L in lengths])),
        q0=put(np.array(q0)),
        gravity=put(np.array([0.0, 0.0, -9.81])),
        prismatic=tuple(k[0] == "P" for k in kinds),
        joint_names=tuple(kinds),
        points_per_link=4,
        name=f"thesis{dof}",
    )
