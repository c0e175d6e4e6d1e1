"""Geometric reference trajectories (thesis 3.2.3; SPEC section 5 "Lines", U17).

Everything here runs on the host in NumPy float64: the geometry is cheap and rule-heavy, and the
result is one padded :class:`~redman_jax.Reference` of JAX arrays per scenario.

Building blocks (each returns a :class:`Segment`, whose first sample is its start at ``t = 0`` and
whose last sample is its end point at ``t = T``):

* :func:`trapezoid_profile`: rest-to-rest arc length ``s(t)`` on ``[0, T]`` with speed ``<= v`` and
  acceleration ``<= a`` (SPEC: ``T = l/v + v/a`` if ``l >= v^2/a``, else the triangular profile
  ``T = 2 sqrt(l/a)``), sampled at ``k ts`` for ``k ts < T`` with the end point ``t = T``
  appended.
* :func:`line_segment`: ``p(t) = p_a + s(t) u`` with the orientation slerped by the same profile,
  ``R(t) = R_a exp(sigma(t) phi [k]_x)`` with ``sigma = s / l``, so that
  ``omega_d = sigma_dot phi R_a k`` and ``omega_dot_d = sigma_ddot phi R_a k`` (world frame).
* :func:`arc_segment`: the welding circle ``p = c + r (cos th e1 + sin th e2)`` with a trapezoidal
  arc-length profile, ``R(th) = Rot(n, th - th0) R0``, ``omega_d = th_dot n``,
  ``omega_dot_d = th_ddot n`` (SPEC section 4, welding).
* :func:`polyline`: consecutive rest-to-rest lines (the inspection zig-zag: every leg is its own
  rest-to-rest segment).

:func:`assemble_reference` joins segments without duplicating the shared samples (the joint
keeps the next segment's start, whose acceleration is the feed-forward of the interval that
follows it under the zero-order hold), latches the orientation flag (once on, it stays on), sets
the final sample at rest (``v = a = omega = omega_dot = 0``) and pads to the case capacity by
repeating it.

Quaternions are scalar-first ``(w, x, y, z)`` and kept continuous along a reference (consecutive
samples have a non-negative dot product), so a full turn ends at ``-q`` of its start; every
consumer compares them hemisphere-checked (SPEC E1).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ._scenario import Reference

__all__ = [
    "Segment",
    "trapezoid_profile",
    "line_segment",
    "constant_segment",
    "arc_segment",
    "polyline",
    "zigzag_points",
    "concat_segments",
    "latch",
    "rot_within",
    "assemble_reference",
    "min_rotation",
    "quat_from_rot",
    "rot_from_quat",
    "quat_mul",
    "axis_angle_quat",
]

_EPS_T = 1e-9  # [s] two sample times closer than this are the same instant


# ----------------------------------------------------------------------------------------------
# Small host-side rotation helpers (NumPy, float64)
# ----------------------------------------------------------------------------------------------


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a (x) b`` of scalar-first quaternions; broadcasts over leading axes."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, float), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, float), -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def axis_angle_quat(axis: np.ndarray, angle) -> np.ndarray:
    """Quaternion of a rotation by ``angle`` (array, broadcast) about the unit ``axis``."""
    angle = np.asarray(angle, float)[..., None]
    return np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * np.asarray(axis, float)], axis=-1)


def rot_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)``."""
    q = np.asarray(q, float)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=-2)


def quat_from_rot(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)``, ``w >= 0``, of one rotation matrix (Shepperd's method)."""
    R = np.asarray(R, float)
    t = np.trace(R)
    d = np.diagonal(R)
    k = int(np.argmax([t, d[0], d[1], d[2]]))
    if k == 0:
        r = math.sqrt(1 + t)
        q = [0.5 * r, (R[2, 1] - R[1, 2]) / (2 * r), (R[0, 2] - R[2, 0]) / (2 * r), (R[1, 0] - R[0, 1]) / (2 * r)]
    elif k == 1:
        r = math.sqrt(1 + d[0] - d[1] - d[2])
        q = [(R[2, 1] - R[1, 2]) / (2 * r), 0.5 * r, (R[0, 1] + R[1, 0]) / (2 * r), (R[0, 2] + R[2, 0]) / (2 * r)]
    elif k == 2:
        r = math.sqrt(1 - d[0] + d[1] - d[2])
        q = [(R[0, 2] - R[2, 0]) / (2 * r), (R[0, 1] + R[1, 0]) / (2 * r), 0.5 * r, (R[1, 2] + R[2, 1]) / (2 * r)]
    else:
        r = math.sqrt(1 - d[0] - d[1] + d[2])
        q = [(R[1, 0] - R[0, 1]) / (2 * r), (R[0, 2] + R[2, 0]) / (2 * r), (R[1, 2] + R[2, 1]) / (2 * r), 0.5 * r]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _point(x, name: str) -> np.ndarray:
    """``x`` as a finite 3-vector; ``ValueError`` naming ``name`` otherwise."""
    x = np.asarray(x, float)
    if x.shape != (3,) or not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: expected a finite 3-vector, got {x}")
    return x


def _unit(x, name: str, size: int = 3) -> np.ndarray:
    """``x / |x|`` for a finite, non-zero ``size``-vector; ``ValueError`` naming ``name`` otherwise
    (a zero or NaN direction would give NaN samples)."""
    x = np.asarray(x, float)
    n = float(np.linalg.norm(x)) if x.shape == (size,) else float("nan")
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"{name}: expected a finite, non-zero {size}-vector, got {x}")
    return x / n


def _flag(rot) -> float:
    """The orientation flag ``rot`` as 0.0 or 1.0; ``ValueError`` naming it otherwise (the
    controllers switch at 0.5, a NaN flag would switch orientation control off unnoticed)."""
    v = float(rot)
    if v not in (0.0, 1.0):
        raise ValueError(f"rot: expected 0 or 1 (orientation control off / on), got {rot!r}")
    return v


def min_rotation(a: np.ndarray) -> np.ndarray:
    """The minimal rotation taking ``e_z`` to the unit vector ``a`` (SPEC section 4, ``R_goal``).

    Rodrigues about ``e_z x a``; for ``a = -e_z`` (no unique axis) a half turn about ``e_x``.
    """
    a = _unit(a, "a")
    ez = np.array([0.0, 0.0, 1.0])
    c = float(ez @ a)
    w = np.cross(ez, a)
    s = np.linalg.norm(w)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = w / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _quat_log_rel(qa: np.ndarray, qb: np.ndarray) -> tuple[float, np.ndarray]:
    """Angle ``phi`` in ``[0, pi]`` and body-frame unit axis ``k`` with ``qb = qa (x) exp(phi k)``."""
    qa_conj = qa * np.array([1.0, -1.0, -1.0, -1.0])
    r = quat_mul(qa_conj, qb)
    if r[0] < 0:
        r = -r  # shortest way round
    vn = np.linalg.norm(r[1:])
    if vn < 1e-15:
        return 0.0, np.array([0.0, 0.0, 1.0])
    return 2.0 * math.atan2(vn, r[0]), r[1:] / vn


# ----------------------------------------------------------------------------------------------
# Segments
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Segment:
    """Samples of one piece of reference (host NumPy arrays, ``n`` samples including both ends).

    ``p, v, a`` ``(n, 3)`` [m, m/s, m/s^2]; ``quat`` ``(n, 4)``; ``omega, omega_dot`` ``(n, 3)``
    [rad/s, rad/s^2] in the world frame; ``rot`` ``(n,)`` in {0, 1}; ``t`` ``(n,)`` [s] the exact
    times from the segment start (the last one is ``T``, not necessarily a multiple of ``ts``).
    """

    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    quat: np.ndarray
    omega: np.ndarray
    omega_dot: np.ndarray
    rot: np.ndarray
    t: np.ndarray

    def __len__(self) -> int:
        return self.p.shape[0]

    @property
    def duration(self) -> float:
        return float(self.t[-1])


def _check_limits(v_max, a_max, ts):
    if not (np.isfinite(v_max) and v_max > 0):
        raise ValueError(f"v_max: must be a positive finite speed, got {v_max!r}")
    if not (np.isfinite(a_max) and a_max > 0):
        raise ValueError(f"a_max: must be a positive finite acceleration, got {a_max!r}")
    if not (np.isfinite(ts) and ts > 0):
        raise ValueError(f"ts: must be a positive finite sample time, got {ts!r}")


def trapezoid_profile(length: float, v_max: float = 1.0, a_max: float = 2.0, ts: float = 0.01):
    """Rest-to-rest trapezoidal arc-length profile (SPEC section 5 "Lines", PROPOSAL).

    With ``t_a = v/a``: if ``l >= v^2/a`` the profile cruises at ``v`` and ``T = l/v + v/a``;
    otherwise it is triangular with peak ``sqrt(a l)`` and ``T = 2 sqrt(l/a)``.

    Returns ``(t, s, s_dot, s_ddot)`` at ``t = k ts`` for every ``k ts < T`` plus ``t = T``
    (``n = ceil(T/ts) + 1`` samples; a zero length gives the single sample ``t = 0``).
    The acceleration is the one acting right after each instant (``+a`` at ``t = 0``, ``-a`` at ``T``).
    """
    _check_limits(v_max, a_max, ts)
    length = float(length)
    if not (np.isfinite(length) and length >= 0):
        raise ValueError(f"length: must be finite and >= 0, got {length!r}")
    if length == 0.0:
        z = np.zeros(1)
        return z, z.copy(), z.copy(), z.copy()
    if length >= v_max**2 / a_max:
        ta, vp = v_max / a_max, v_max
        T = length / v_max + ta
    else:
        ta = math.sqrt(length / a_max)
        vp, T = a_max * ta, 2 * ta
    n = max(1, int(math.ceil((T - _EPS_T) / ts)))  # samples k ts < T - _EPS_T, and t = 0
    t = np.append(np.arange(n) * ts, T)
    s = np.empty_like(t)
    sd = np.empty_like(t)
    sdd = np.empty_like(t)
    # the phase acting right after each instant: a sample at the start of the braking (the peak
    # of a triangle, or l/v a multiple of ts) brakes, one at the end of the ramp-up cruises
    up = t < ta - _EPS_T
    down = t >= T - ta - _EPS_T
    cruise = ~up & ~down
    s[up] = 0.5 * a_max * t[up] ** 2
    sd[up] = a_max * t[up]
    sdd[up] = a_max
    s[cruise] = 0.5 * a_max * ta**2 + vp * (t[cruise] - ta)
    sd[cruise] = vp
    sdd[cruise] = 0.0
    tr = T - t[down]
    s[down] = length - 0.5 * a_max * tr**2
    sd[down] = a_max * tr
    sdd[down] = -a_max
    s[-1], sd[-1] = length, 0.0
    return t, s, sd, sdd


def line_segment(p_a, p_b, quat_a=None, quat_b=None, *, rot: float = 0.0, v_max: float = 1.0,
                 a_max: float = 2.0, ts: float = 0.01) -> Segment:
    """Straight rest-to-rest segment from ``p_a`` to ``p_b`` (thesis 3.2.3, SPEC section 5).

    Position ``p = p_a + s(t) u`` with the :func:`trapezoid_profile` ``s``; the orientation is
    slerped with the same profile, ``R = R_a exp(sigma phi [k]_x)``, ``sigma = s/l``, giving
    ``omega_d = sigma_dot phi R_a k`` and ``omega_dot_d = sigma_ddot phi R_a k`` (world frame).
    ``quat_b=None`` keeps ``quat_a`` (``quat_a=None``: identity). ``rot`` is the orientation
    flag of every sample of the segment.

    Raises ``ValueError`` for non-finite points or a zero-length segment that must rotate.
    """
    p_a, p_b = _point(p_a, "p_a"), _point(p_b, "p_b")
    qa = np.array([1.0, 0, 0, 0]) if quat_a is None else _unit(quat_a, "quat_a", 4)
    qb = qa if quat_b is None else _unit(quat_b, "quat_b", 4)
    d = p_b - p_a
    length = float(np.linalg.norm(d))
    phi, k = _quat_log_rel(qa, qb)
    if length == 0.0 and phi > 1e-12:
        raise ValueError("line_segment: a zero-length segment cannot change the orientation")
    t, s, sd, sdd = trapezoid_profile(length, v_max, a_max, ts)
    u = d / length if length > 0 else np.zeros(3)
    p = p_a + s[:, None] * u
    p[-1] = p_b  # exact end point
    sig = s / length if length > 0 else np.zeros_like(s)
    sigd = sd / length if length > 0 else np.zeros_like(s)
    sigdd = sdd / length if length > 0 else np.zeros_like(s)
    quat = quat_mul(qa, axis_angle_quat(k, sig * phi))
    w_axis = rot_from_quat(qa) @ k  # world axis, constant along the slerp
    return Segment(
        p=p, v=sd[:, None] * u, a=sdd[:, None] * u, quat=quat,
        omega=(sigd * phi)[:, None] * w_axis, omega_dot=(sigdd * phi)[:, None] * w_axis,
        rot=np.full(len(t), _flag(rot)), t=t,
    )


def constant_segment(p, quat, n: int = 1, *, rot: float = 0.0, ts: float = 0.01) -> Segment:
    """``n >= 1`` samples at rest at the pose ``(p, quat)`` (a hold).

    Raises ``ValueError`` naming the argument for a non-finite ``p``, a zero or non-finite
    ``quat``, ``n < 1``, a ``rot`` other than 0 or 1, or a non-positive ``ts``."""
    p, quat = _point(p, "p"), _unit(quat, "quat", 4)
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected an integer number of samples >= 1, got {n!r}")
    if not (np.isfinite(ts) and ts > 0):
        raise ValueError(f"ts: must be a positive finite sample time, got {ts!r}")
    n = int(n)
    z = np.zeros((n, 3))
    return Segment(p=np.tile(p, (n, 1)), v=z, a=z.copy(), quat=np.tile(quat, (n, 1)), omega=z.copy(),
                   omega_dot=z.copy(), rot=np.full(n, _flag(rot)), t=np.arange(n) * ts)


def arc_segment(center, normal, e1, radius: float, theta0: float, quat0, *, angle: float = 2 * math.pi,
                direction: int = 1, rot: float = 1.0, speed: float = 0.10, a_max: float = 2.0,
                ts: float = 0.01) -> Segment:
    """Circular arc at constant speed with short trapezoidal ramps (the welding seam; SPEC U17).

    ``e2 = n x e1``; ``theta(t) = theta0 + direction * s(t)/r`` with the trapezoidal arc-length
    profile ``s`` (speed ``speed``, ramps ``a_max``) over the arc length ``r * angle``;
    ``p = c + r (cos th e1 + sin th e2)``, ``v = s_dot t_hat``, ``a = s_ddot t_hat - s_dot^2/r r_hat``.
    Orientation ``R(th) = Rot(n, th - th0) R0`` (``R0`` from ``quat0``), so ``omega = th_dot n``
    and ``omega_dot = th_ddot n``.
    """
    c = _point(center, "center")
    n = _unit(normal, "normal")
    e1 = _unit(e1, "e1")
    e1 = e1 - (e1 @ n) * n
    if np.linalg.norm(e1) < 1e-9:
        raise ValueError("e1: must not be parallel to the normal (no in-plane direction left)")
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    if not np.isfinite(theta0):
        raise ValueError(f"theta0: must be finite, got {theta0!r}")
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius: must be positive, got {radius!r}")
    if direction not in (1, -1):
        raise ValueError(f"direction: must be +1 or -1, got {direction!r}")
    if not (np.isfinite(angle) and angle > 0):
        raise ValueError(f"angle: must be a positive finite arc angle [rad], got {angle!r}")
    if not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"speed: must be a positive finite speed, got {speed!r}")
    t, s, sd, sdd = trapezoid_profile(radius * angle, speed, a_max, ts)
    th = theta0 + direction * s / radius
    thd = direction * sd / radius
    thdd = direction * sdd / radius
    r_hat = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
    t_hat = -np.sin(th)[:, None] * e1 + np.cos(th)[:, None] * e2
    p = c + radius * r_hat
    v = thd[:, None] * radius * t_hat
    a = (thdd * radius)[:, None] * t_hat - (thd**2 * radius)[:, None] * r_hat
    q0 = _unit(quat0, "quat0", 4)
    quat = quat_mul(axis_angle_quat(n, th - theta0), q0)
    return Segment(p=p, v=v, a=a, quat=quat, omega=thd[:, None] * n, omega_dot=thdd[:, None] * n,
                   rot=np.full(len(t), _flag(rot)), t=t)


def polyline(points, quat, *, rot: float = 0.0, v_max: float = 1.0, a_max: float = 2.0,
             ts: float = 0.01) -> list[Segment]:
    """Rest-to-rest straight legs through ``points`` ``(m, 3)`` at a constant orientation."""
    pts = np.asarray(points, float)
    return [line_segment(pts[i], pts[i + 1], quat, rot=rot, v_max=v_max, a_max=a_max, ts=ts)
            for i in range(len(pts) - 1)]


def zigzag_points(origin, row_dir, step_dir, width: float, rows) -> np.ndarray:
    """Vertices of a zig-zag scan (SPEC U15): rows of ``width`` along ``row_dir`` centred on
    ``origin + h step_dir`` for each offset ``h`` in ``rows``, alternating direction; the legs
    are the rows and the steps between their ends. Returns ``(2 len(rows), 3)``."""
    o, r, st = _point(origin, "origin"), _unit(row_dir, "row_dir"), _point(step_dir, "step_dir")
    if not (np.isfinite(width) and width > 0):
        raise ValueError(f"width: must be a positive finite length, got {width!r}")
    rows = np.asarray(rows, float)
    if rows.ndim != 1 or not np.all(np.isfinite(rows)):
        raise ValueError(f"rows: expected a 1-D sequence of finite offsets, got {rows}")
    pts = []
    for i, h in enumerate(rows):
        sgn = 1.0 if i % 2 == 0 else -1.0
        c = o + h * st
        pts += [c - sgn * 0.5 * width * r, c + sgn * 0.5 * width * r]
    return np.array(pts)


# ----------------------------------------------------------------------------------------------
# Assembly
# ----------------------------------------------------------------------------------------------


def concat_segments(segments) -> Segment:
    """Join segments in order. Consecutive segments share a sample (the end of one is the start of
    the next, both at rest): it is kept once, as the next segment's start, whose acceleration is
    the feed-forward for the interval that follows it. Quaternion signs are made continuous.

    Raises ``ValueError`` if a segment does not start where the previous one ended.
    """
    segs = [s for s in segments]
    if not segs:
        raise ValueError("segments: need at least one segment")
    parts = {f: [] for f in ("p", "v", "a", "quat", "omega", "omega_dot", "rot", "t")}
    t_off = 0.0
    q_prev = None
    for i, s in enumerate(segs):
        last = i == len(segs) - 1
        if i > 0:
            gap = np.linalg.norm(s.p[0] - segs[i - 1].p[-1])
            if gap > 1e-9:
                raise ValueError(f"segments[{i}]: starts {gap:.3g} m away from the end of segments[{i - 1}]")
            if abs(abs(float(s.quat[0] @ segs[i - 1].quat[-1])) - 1.0) > 1e-9:
                raise ValueError(f"segments[{i}]: starts at another orientation than segments[{i - 1}] ends")
        quat = s.quat
        if q_prev is not None and float(quat[0] @ q_prev) < 0:
            quat = -quat
        q_prev = quat[-1]
        keep = slice(None) if last else slice(0, len(s) - 1)  # drop the shared end sample
        for f in parts:
            arr = quat if f == "quat" else getattr(s, f)
            if f == "t":
                arr = arr + t_off
            parts[f].append(arr[keep])
        t_off += s.duration
    out = {f: np.concatenate(v) for f, v in parts.items()}
    return Segment(**out)


def latch(flags) -> np.ndarray:
    """Orientation flag latched on: ``rot_k = max_{j <= k} flag_j`` (SPEC section 4)."""
    return np.maximum.accumulate(np.asarray(flags, float))


def _point_polyline_distance(x: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance of each point ``x`` ``(m, 3)`` to the polyline through ``pts`` ``(k, 3)``."""
    x = np.asarray(x, float)
    pts = np.asarray(pts, float)
    if len(pts) == 1:
        return np.linalg.norm(x - pts[0], axis=-1)
    a, b = pts[:-1], pts[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, -1), 1e-300)
    lam = np.clip(np.einsum("mkj,kj->mk", x[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    proj = a[None] + lam[..., None] * ab[None]
    return np.min(np.linalg.norm(x[:, None, :] - proj, axis=-1), axis=1)


def rot_within(p, target_points, radius: float) -> np.ndarray:
    """Latched flag: 1 from the first sample within ``radius`` of the polyline ``target_points``
    (a single point: the goal) onwards (SPEC U13, inspection: 0.20 m from the scan pattern)."""
    d = _point_polyline_distance(np.atleast_2d(p), np.atleast_2d(target_points))
    return latch(d <= radius)


def assemble_reference(segments, ts: float = 0.01, capacity: int | None = None, rot=None) -> Reference:
    """Concatenate ``segments`` into a padded :class:`~redman_jax.Reference` (SPEC section 5).

    * Shared samples between segments are kept once (:func:`concat_segments`).
    * ``rot``: optional per-sample flags overriding the segments' own (after concatenation);
      either way the flag is latched (:func:`latch`).
    * The final sample is at rest (``v = a = omega = omega_dot = 0``), and the padding up to
      ``capacity`` repeats it (``mask`` False there). ``capacity=None``: no padding.

    Raises ``ValueError`` when the samples exceed ``capacity``, or ``rot`` has the wrong length or
    a flag other than 0 or 1.
    """
    if not (np.isfinite(ts) and ts > 0):
        raise ValueError(f"ts: must be a positive finite sample time, got {ts!r}")
    seg = segments if isinstance(segments, Segment) else concat_segments(segments)
    n = len(seg)
    flags = seg.rot if rot is None else np.asarray(rot, float)
    if flags.shape != (n,):
        raise ValueError(f"rot: expected {n} per-sample flags, got shape {flags.shape}")
    if not np.all((flags == 0.0) | (flags == 1.0)):  # a NaN was latched into every later sample
        raise ValueError(f"rot: expected flags 0 or 1 (orientation control off / on), got {np.unique(flags)}")
    if capacity is None:
        capacity = n
    if not isinstance(capacity, (int, np.integer)) or capacity < 1:
        raise ValueError(f"capacity: must be a positive int, got {capacity!r}")
    if n > capacity:
        raise ValueError(f"capacity: {n} samples exceed the reference capacity {capacity}")
    pad = capacity - n

    def padded(x, rest=False):
        x = np.array(x, float)
        if rest:
            x[-1] = 0.0
        return np.concatenate([x, np.repeat(x[-1:], pad, axis=0)])

    return Reference(
        p=jnp.asarray(padded(seg.p)),
        v=jnp.asarray(padded(seg.v, rest=True)),
        a=jnp.asarray(padded(seg.a, rest=True)),
        quat=jnp.asarray(padded(seg.quat)),
        omega=jnp.asarray(padded(seg.omega, rest=True)),
        omega_dot=jnp.asarray(padded(seg.omega_dot, rest=True)),
        rot=jnp.asarray(padded(latch(flags))),
        mask=jnp.asarray(np.arange(capacity) < n),
        n_samples=jnp.asarray(n),
        ts=jnp.asarray(float(ts)),
    )
