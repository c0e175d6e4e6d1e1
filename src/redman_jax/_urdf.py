"""URDF import and export of serial arms (the issue's ``from_urdf``; SPEC section 1 for the Arm).

:func:`from_urdf` turns the serial chain from a root (or ``base_link``) to ``tip_link`` of any URDF
file into an :class:`~redman_jax.Arm`, so the whole study can run on a real arm:

* joints ``revolute``, ``continuous`` (unlimited) and ``prismatic`` become the Arm's joints;
  ``fixed`` joints merge their child link into the body of the last movable joint before them.
* **Bodies.** Body ``k`` is the child link of movable joint ``k`` together with every link rigidly
  attached to it through fixed joints only (on the chain or hanging off it). Their inertials are
  lumped as rigid-body libraries do (Pinocchio's URDF parser appends fixed children to their
  parent body): total mass ``m = sum m_j``, CoM ``c = sum m_j c_j / m``, and inertia about ``c``
  by the parallel-axis theorem ``I = sum R_j I_j R_j^T + m_j (|d_j|^2 1 - d_j d_j^T)``,
  ``d_j = c_j - c``.
* **Branches** (subtrees that leave the chain through a movable joint, e.g. gripper fingers) are
  ignored together with everything below them; meshes, collision and visual data are ignored.
* **Frames.** Link frame ``k`` is the URDF frame of the child link of movable joint ``k`` (its
  origin lies on the joint axis). ``home_frames[k]`` is its world pose at ``q = 0`` (the product
  of the joint ``<origin>`` transforms, ``R = Rz(yaw) Ry(pitch) Rx(roll)``); the world is the
  frame of the root link. The space-frame screw at ``q = 0`` (A.4) is, with ``a`` the unit
  ``<axis>`` in the link frame and ``(R_k, p_k) = home_frames[k]``: revolute
  ``(R_k a, -(R_k a) x p_k)``, prismatic ``(0, R_k a)``.
* **End effector:** the origin (and axes) of ``tip_link``.
* ``seg_ends[k]``: the origin of the next movable joint in link frame ``k`` (the end effector for
  the last), so the points of interest run along the segment between consecutive joints.
* **Limits:** ``<limit lower upper>`` for revolute and prismatic joints (``limited = True``);
  continuous joints are unlimited (``q_min, q_max = -pi, pi``, ``limited = False``).
* ``q0``: zeros clipped into the limits, kept 5 % of each range away from them, unless given.

:func:`to_urdf` writes an Arm back as URDF text (used to hand the thesis arms to Pinocchio in the
benchmark and tested by the round trip ``from_urdf(to_urdf(arm)) == arm``).

Parsing uses :mod:`xml.etree` only. Every malformed input raises a ``ValueError`` naming the
element and attribute at fault.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ._robot import Arm

__all__ = ["from_urdf", "from_urdf_string", "to_urdf", "rpy_to_matrix", "matrix_to_rpy", "example_robot_data_file"]

_MOVABLE = ("revolute", "continuous", "prismatic")
_KNOWN = _MOVABLE + ("fixed", "floating", "planar")


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------


def rpy_to_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw to a rotation matrix: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_matrix` (pitch in ``[-pi/2, pi/2]``; yaw = 0 at gimbal lock)."""
    R = np.asarray(R, dtype=float)
    cp = math.hypot(R[2, 1], R[2, 2])
    pitch = math.atan2(-R[2, 0], cp)  # asin(-R20) loses digits near +-pi/2 (error ~ 1e-16 / cos)
    if cp < 1e-12:  # cos(pitch) = 0: roll and yaw are coupled
        return np.array([math.atan2(-R[1, 2], R[1, 1]), pitch, 0.0])
    return np.array([math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])])


def _homogeneous(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    R, p = T[:3, :3], T[:3, 3]
    return _homogeneous(R.T, -R.T @ p)


def _floats(elem: ET.Element, attr: str, count: int, default, where: str) -> np.ndarray:
    """Parse ``count`` whitespace-separated floats of ``elem.attr`` (``default`` when absent)."""
    text = elem.get(attr)
    if text is None:
        if default is None:
            raise ValueError(f"URDF {where}: missing attribute '{attr}'")
        return np.asarray(default, dtype=float)
    parts = text.split()
    if len(parts) != count:
        raise ValueError(f"URDF {where}: attribute '{attr}' needs {count} numbers, got {text!r}")
    try:
        vals = np.array([float(v) for v in parts])
    except ValueError:
        raise ValueError(f"URDF {where}: attribute '{attr}' is not numeric: {text!r}") from None
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"URDF {where}: attribute '{attr}' is not finite: {text!r}")
    return vals


def _origin(parent: ET.Element, where: str) -> np.ndarray:
    """The ``<origin xyz rpy>`` child of ``parent`` as a 4x4 transform (identity when absent)."""
    o = parent.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(o, "xyz", 3, (0.0, 0.0, 0.0), f"{where}/origin")
    rpy = _floats(o, "rpy", 3, (0.0, 0.0, 0.0), f"{where}/origin")
    return _homogeneous(rpy_to_matrix(rpy), xyz)


# ---------------------------------------------------------------------------------------------
# parsing
# ---------------------------------------------------------------------------------------------


class _Joint:
    __slots__ = ("name", "type", "parent", "child", "origin", "axis", "lower", "upper", "mimic")


def _parse_inertial(link: ET.Element, name: str):
    """``(mass, com (3,), inertia about the CoM in link axes (3, 3))``; zeros when absent."""
    where = f"link '{name}'/inertial"
    inertial = link.find("inertial")
    if inertial is None:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    T = _origin(inertial, where)
    mass_el = inertial.find("mass")
    if mass_el is None:
        raise ValueError(f"URDF {where}: missing <mass>")
    mass = float(_floats(mass_el, "value", 1, None, f"{where}/mass")[0])
    if mass < 0:
        raise ValueError(f"URDF {where}/mass: value must be >= 0, got {mass}")
    in_el = inertial.find("inertia")
    if in_el is None:
        if mass > 0:
            raise ValueError(f"URDF {where}: missing <inertia>")
        inertia = np.zeros((3, 3))
    else:
        c = {k: float(_floats(in_el, k, 1, (0.0,), f"{where}/inertia")[0])
             for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
        inertia = np.array(
            [[c["ixx"], c["ixy"], c["ixz"]], [c["ixy"], c["iyy"], c["iyz"]], [c["ixz"], c["iyz"], c["izz"]]]
        )
        scale = max(1.0, float(np.abs(inertia).max()))
        if np.linalg.eigvalsh(inertia).min() < -1e-12 * scale:
            raise ValueError(
                f"URDF {where}/inertia: the inertia matrix must be positive semi-definite, got "
                f"eigenvalues {np.linalg.eigvalsh(inertia)}"
            )
    R = T[:3, :3]
    return mass, T[:3, 3].copy(), R @ inertia @ R.T


def _parse_joint(el: ET.Element, links: dict) -> _Joint:
    name = el.get("name")
    if not name:
        raise ValueError("URDF <joint>: missing attribute 'name'")
    where = f"joint '{name}'"
    j = _Joint()
    j.name = name
    j.type = el.get("type")
    if j.type is None:
        raise ValueError(f"URDF {where}: missing attribute 'type'")
    if j.type not in _KNOWN:
        raise ValueError(f"URDF {where}: unknown joint type {j.type!r} (expected one of {_KNOWN})")
    for role in ("parent", "child"):
        sub = el.find(role)
        if sub is None or not sub.get("link"):
            raise ValueError(f"URDF {where}: missing <{role} link=...>")
        if sub.get("link") not in links:
            raise ValueError(f"URDF {where}/{role}: link {sub.get('link')!r} is not defined")
        setattr(j, role, sub.get("link"))
    j.origin = _origin(el, where)
    mimic = el.find("mimic")
    j.mimic = None if mimic is None else (mimic.get("joint") or "?")
    j.axis = np.array([1.0, 0.0, 0.0])
    j.lower, j.upper = -math.pi, math.pi
    if j.type in _MOVABLE:
        ax = el.find("axis")
        if ax is not None:
            a = _floats(ax, "xyz", 3, (1.0, 0.0, 0.0), f"{where}/axis")
            norm = float(np.linalg.norm(a))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"URDF {where}/axis: xyz must be a unit vector, got {a} (norm {norm:.6g})")
            j.axis = a / norm
    if j.type in ("revolute", "prismatic"):
        lim = el.find("limit")
        if lim is None:
            raise ValueError(f"URDF {where}: a {j.type} joint needs a <limit lower=... upper=...>")
        j.lower = float(_floats(lim, "lower", 1, (0.0,), f"{where}/limit")[0])
        j.upper = float(_floats(lim, "upper", 1, (0.0,), f"{where}/limit")[0])
        if j.lower > j.upper:
            raise ValueError(f"URDF {where}/limit: lower ({j.lower}) > upper ({j.upper})")
    return j


def _parse(root: ET.Element):
    if root.tag != "robot":
        raise ValueError(f"URDF: the root element must be <robot>, got <{root.tag}>")
    links: dict[str, ET.Element] = {}
    for el in root.findall("link"):
        name = el.get("name")
        if not name:
            raise ValueError("URDF <link>: missing attribute 'name'")
        if name in links:
            raise ValueError(f"URDF link '{name}': defined twice")
        links[name] = el
    if not links:
        raise ValueError("URDF: no <link> elements")
    joints: list[_Joint] = []
    parent_of: dict[str, _Joint] = {}
    names = set()
    for el in root.findall("joint"):
        j = _parse_joint(el, links)
        if j.name in names:
            raise ValueError(f"URDF joint '{j.name}': defined twice")
        names.add(j.name)
        if j.child in parent_of:
            raise ValueError(
                f"URDF joint '{j.name}': link '{j.child}' already has parent joint '{parent_of[j.child].name}'"
            )
        parent_of[j.child] = j
        joints.append(j)
    return links, joints, parent_of


# ---------------------------------------------------------------------------------------------
# from_urdf
# ---------------------------------------------------------------------------------------------


def from_urdf(path: str | os.PathLike, tip_link: str, base_link: str | None = None, *,
              points_per_link: int = 4, link_width=0.1, q0=None,
              gravity: Sequence[float] = (0.0, 0.0, -9.81), name: str | None = None) -> Arm:
    """Build an :class:`~redman_jax.Arm` from the serial chain ``base_link -> tip_link`` of a URDF file.

    **Arguments:**

    - ``path``: the URDF file.
    - ``tip_link``: the link whose origin is the end effector.
    - ``base_link``: the fixed link whose frame is the world (default: the root of the tree).
    - ``points_per_link``: points of interest per segment (thesis: 4).
    - ``link_width``: link width(s) [m], a scalar or one per movable joint (thesis: 0.10).
    - ``q0``: initial configuration ``(n,)``; default zeros clipped into the joint limits with a
      margin of 5 % of each range (a start on a limit would start in contact).
    - ``gravity``: ``(3,)`` [m/s^2] in the base frame.
    - ``name``: the arm's name (default: the ``<robot name>``).

    **Returns:** an ``Arm`` with one joint per revolute / continuous / prismatic joint on the chain
    (see the module docstring for frames, lumping and limits).

    **Raises:** ``ValueError`` naming the element or field at fault: unreadable file, malformed
    XML, unknown joint type, missing or non-numeric attributes, negative masses, inertias that are
    not positive semi-definite, ``lower > upper``, a ``tip_link`` or ``base_link`` not in the file
    (or not connected), floating / planar joints on the chain, a body with zero total mass, and
    anything :class:`~redman_jax.Arm` rejects.
    """
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as e:
        raise ValueError(f"URDF path {os.fspath(path)!r}: cannot be read ({e})") from None
    return from_urdf_string(text, tip_link, base_link, points_per_link=points_per_link,
                            link_width=link_width, q0=q0, gravity=gravity, name=name,
                            _source=os.fspath(path))


def from_urdf_string(text: str, tip_link: str, base_link: str | None = None, *,
                     points_per_link: int = 4, link_width=0.1, q0=None,
                     gravity: Sequence[float] = (0.0, 0.0, -9.81), name: str | None = None,
                     _source: str = "<string>") -> Arm:
    """:func:`from_urdf` on URDF text instead of a file (same arguments after ``text``)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise ValueError(f"URDF {_source}: malformed XML ({e})") from None
    links, joints, parent_of = _parse(root)
    if tip_link not in links:
        raise ValueError(f"from_urdf tip_link: link {tip_link!r} is not in {_source}")
    if base_link is not None and base_link not in links:
        raise ValueError(f"from_urdf base_link: link {base_link!r} is not in {_source}")

    # The chain: walk up from the tip to the base (or the root).
    path: list[_Joint] = []
    link = tip_link
    seen = {link}
    while link != base_link and link in parent_of:
        j = parent_of[link]
        path.append(j)
        link = j.parent
        if link in seen:
            raise ValueError(f"URDF joint '{j.name}': the kinematic tree has a cycle through link '{link}'")
        seen.add(link)
    if base_link is not None and link != base_link:
        raise ValueError(f"from_urdf base_link: link {base_link!r} is not an ancestor of tip_link {tip_link!r}")
    path.reverse()
    for j in path:
        if j.type in ("floating", "planar"):
            raise ValueError(f"URDF joint '{j.name}': type {j.type!r} is not supported on the chain")
        if j.mimic is not None and j.type in _MOVABLE:  # it would become an independent joint
            raise ValueError(f"URDF joint '{j.name}': mimics joint '{j.mimic}'; mimic joints are not "
                             "supported on the chain (choose a tip_link before it)")
    movable = [j for j in path if j.type in _MOVABLE]
    if not movable:
        raise ValueError(f"from_urdf: no movable joint between {link!r} and tip_link {tip_link!r}")

    # World poses at q = 0 of every link on the chain.
    pose = {link: np.eye(4)}
    for j in path:
        pose[j.child] = pose[j.parent] @ j.origin

    children: dict[str, list[_Joint]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)

    def rigid_links(start: str):
        """Links rigidly attached to ``start`` by fixed joints, with their pose in ``start``'s frame."""
        out, stack = [], [(start, np.eye(4))]
        while stack:
            lk, T = stack.pop()
            out.append((lk, T))
            for cj in children.get(lk, []):
                if cj.type == "fixed":
                    stack.append((cj.child, T @ cj.origin))
        return out

    n = len(movable)
    home = np.stack([pose[j.child] for j in movable])
    ee_home = pose[tip_link]
    screws, masses, coms, inertias = [], [], [], []
    for k, j in enumerate(movable):
        R, p = home[k][:3, :3], home[k][:3, 3]
        a = R @ j.axis
        screws.append(np.concatenate([np.zeros(3), a]) if j.type == "prismatic"
                      else np.concatenate([a, -np.cross(a, p)]))
        parts = []
        for lk, T in rigid_links(j.child):
            m, c, inertia = _parse_inertial(links[lk], lk)
            if m > 0:
                parts.append((m, T[:3, :3] @ c + T[:3, 3], T[:3, :3] @ inertia @ T[:3, :3].T))
        where = f"link '{j.child}' (the body moved by joint '{j.name}', fixed-joint children merged)"
        m_tot = sum(pt[0] for pt in parts)
        if m_tot <= 0:
            raise ValueError(f"URDF {where}: total mass must be > 0 for the dynamics")
        com = sum(pt[0] * pt[1] for pt in parts) / m_tot
        inertia = np.zeros((3, 3))
        for m, c, Ic in parts:
            d = c - com
            inertia += Ic + m * (d @ d * np.eye(3) - np.outer(d, d))
        inertia = 0.5 * (inertia + inertia.T)
        if np.linalg.eigvalsh(inertia).min() <= 0:
            raise ValueError(f"URDF {where}: lumped inertia is not positive definite "
                             f"(eigenvalues {np.linalg.eigvalsh(inertia)})")
        masses.append(m_tot)
        coms.append(com)
        inertias.append(inertia)

    nxt = [home[k + 1] for k in range(n - 1)] + [ee_home]
    seg_ends = np.stack([(_inv(home[k]) @ nxt[k])[:3, 3] for k in range(n)])
    limited = np.array([j.type != "continuous" for j in movable])
    q_min = np.array([j.lower for j in movable])
    q_max = np.array([j.upper for j in movable])
    if q0 is None:
        margin = 0.05 * (np.asarray(q_max) - np.asarray(q_min))
        q0_arr = np.where(limited, np.clip(0.0, q_min + margin, q_max - margin), 0.0)
    else:
        q0_arr = np.asarray(q0, dtype=float)
        if q0_arr.shape != (n,):
            raise ValueError(f"from_urdf q0: expected shape ({n},), got {q0_arr.shape}")
    widths = np.asarray(link_width, dtype=float)
    if widths.ndim == 0:
        widths = np.full(n, float(widths))
    if widths.shape != (n,):
        raise ValueError(f"from_urdf link_width: expected a scalar or shape ({n},), got {widths.shape}")
    if not isinstance(points_per_link, int) or isinstance(points_per_link, bool) or points_per_link < 1:
        raise ValueError(f"from_urdf points_per_link: must be a positive int, got {points_per_link!r}")
    grav = np.asarray(gravity, dtype=float)
    if grav.shape != (3,):
        raise ValueError(f"from_urdf gravity: expected shape (3,), got {grav.shape}")

    return Arm(
        screw_axes=jnp.asarray(np.stack(screws)),
        home_frames=jnp.asarray(home),
        ee_home=jnp.asarray(ee_home),
        masses=jnp.asarray(np.array(masses)),
        coms=jnp.asarray(np.stack(coms)),
        inertias=jnp.asarray(np.stack(inertias)),
        q_min=jnp.asarray(q_min),
        q_max=jnp.asarray(q_max),
        limited=jnp.asarray(limited),
        widths=jnp.asarray(widths),
        seg_ends=jnp.asarray(seg_ends),
        q0=jnp.asarray(q0_arr),
        gravity=jnp.asarray(grav),
        prismatic=tuple(j.type == "prismatic" for j in movable),
        joint_names=tuple(j.name for j in movable),
        points_per_link=points_per_link,
        name=name if name is not None else (root.get("name") or "urdf_arm"),
    )


# ---------------------------------------------------------------------------------------------
# to_urdf
# ---------------------------------------------------------------------------------------------


def _fmt(vals) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(vals))


def to_urdf(arm: Arm, *, robot_name: str | None = None, tip_link: str = "ee") -> str:
    """Write ``arm`` as URDF text: links ``base``, ``link1`` ... ``linkn`` and ``tip_link``.

    Joint ``k`` (named after ``arm.joint_names[k]`` when those are unique, else
    ``joint{k+1}_{name}``) places link ``k`` at ``home_frames[k]`` relative to link ``k - 1``; a
    fixed joint places the massless ``tip_link`` at ``ee_home``. Limited revolute joints become
    ``revolute``, unlimited ones ``continuous``. Widths, ``seg_ends``, ``q0`` and gravity have no
    URDF field (``from_urdf`` recomputes ``seg_ends`` from the joint origins).

    **Raises:** ``ValueError`` for an arm URDF cannot express: a revolute axis that misses its link
    frame origin, or an unlimited prismatic joint; and for a ``tip_link`` whose link or joint name
    is taken (``base``, ``link1`` ...; ``{tip_link}_joint`` among the joint names).
    """
    n = arm.n_dof
    S = np.asarray(arm.screw_axes, dtype=float)
    home = np.asarray(arm.home_frames, dtype=float)
    ee = np.asarray(arm.ee_home, dtype=float)
    limited = np.asarray(arm.limited, dtype=bool)
    q_min, q_max = np.asarray(arm.q_min, dtype=float), np.asarray(arm.q_max, dtype=float)
    masses, coms = np.asarray(arm.masses, dtype=float), np.asarray(arm.coms, dtype=float)
    inertias = np.asarray(arm.inertias, dtype=float)
    names = list(arm.joint_names)
    if len(set(names)) != n:
        names = [f"joint{k + 1}_{nm}" for k, nm in enumerate(names)]
    links = ["base"] + [f"link{k + 1}" for k in range(n)]
    if not isinstance(tip_link, str) or not tip_link or tip_link in links:
        raise ValueError(f"to_urdf: tip_link must be a link name other than base, link1 ... link{n}, "
                         f"got {tip_link!r}")
    if f"{tip_link}_joint" in names:
        raise ValueError(f"to_urdf: tip_link {tip_link!r} names its fixed joint {tip_link}_joint, "
                         f"which is already a joint of the arm; choose another tip_link")
    robot = ET.Element("robot", name=robot_name or arm.name)
    ET.SubElement(robot, "link", name="base")
    parent, T_parent = "base", np.eye(4)
    for k in range(n):
        R, p = home[k][:3, :3], home[k][:3, 3]
        if arm.prismatic[k]:
            if not limited[k]:
                raise ValueError(f"to_urdf Arm.limited[{k}]: URDF has no unlimited prismatic joint")
            jtype, axis = "prismatic", R.T @ S[k, 3:]
        else:
            w, v = S[k, :3], S[k, 3:]
            if np.linalg.norm(v + np.cross(w, p)) > 1e-9 * max(1.0, np.linalg.norm(p)):
                raise ValueError(
                    f"to_urdf Arm.screw_axes[{k}]: the revolute axis does not pass through the origin "
                    f"of home_frames[{k}], which URDF requires"
                )
            jtype, axis = ("revolute" if limited[k] else "continuous"), R.T @ w
        child = f"link{k + 1}"
        link = ET.SubElement(robot, "link", name=child)
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", xyz=_fmt(coms[k]), rpy="0.0 0.0 0.0")
        ET.SubElement(inertial, "mass", value=repr(float(masses[k])))
        Ik = inertias[k]
        ET.SubElement(inertial, "inertia", **{
            f"i{'xyz'[a]}{'xyz'[b]}": repr(float(Ik[a, b])) for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        })
        rel = _inv(T_parent) @ home[k]
        joint = ET.SubElement(robot, "joint", name=names[k], type=jtype)
        ET.SubElement(joint, "origin", xyz=_fmt(rel[:3, 3]), rpy=_fmt(matrix_to_rpy(rel[:3, :3])))
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=child)
        ET.SubElement(joint, "axis", xyz=_fmt(axis))
        if jtype != "continuous":
            ET.SubElement(joint, "limit", lower=repr(float(q_min[k])), upper=repr(float(q_max[k])),
                          effort="1000000.0", velocity="1000000.0")
        parent, T_parent = child, home[k]
    ET.SubElement(robot, "link", name=tip_link)
    rel = _inv(T_parent) @ ee
    joint = ET.SubElement(robot, "joint", name=f"{tip_link}_joint", type="fixed")
    ET.SubElement(joint, "origin", xyz=_fmt(rel[:3, 3]), rpy=_fmt(matrix_to_rpy(rel[:3, :3])))
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=tip_link)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def example_robot_data_file(relative: str) -> str:
    """Path of a file shipped by the PyPI package ``example-robot-data`` (a test / bench extra).

    ``relative`` is the path below its ``robots`` folder, e.g.
    ``"panda_description/urdf/panda.urdf"``. Works for the versions that ship a Python module
    (``example_robot_data.getModelPath``) and for the data-only wheels (6.x, files under
    ``cmeel.prefix/share/example-robot-data``).

    **Raises:** ``FileNotFoundError`` when the package or the file is missing.
    """
    import importlib.metadata as md

    candidates = []
    try:  # older wheels: a Python module that knows its model path
        import example_robot_data  # type: ignore[import-not-found]

        candidates.append(os.path.join(example_robot_data.getModelPath(relative), relative))
    except Exception:
        pass
    try:
        dist = md.distribution("example-robot-data")
        for f in dist.files or ():
            if str(f).replace("\\", "/").endswith("robots/" + relative):
                candidates.append(str(dist.locate_file(f)))
    except md.PackageNotFoundError:
        pass
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise FileNotFoundError(f"example-robot-data file {relative!r} not found (pip install example-robot-data)")
