"""Geometric trajectories (SPEC section 5 "Lines", U17): limits, rest-to-rest, orientation, assembly.

References are independent of the implementation: finite differences of the sampled positions and
quaternions, the closed-form durations of SPEC section 5, and plain geometry (radius, plane).
"""

import math

import numpy as np
import pytest

from redman_jax._trajectories import (
    arc_segment,
    assemble_reference,
    concat_segments,
    constant_segment,
    line_segment,
    min_rotation,
    polyline,
    quat_from_rot,
    quat_mul,
    rot_from_quat,
    rot_within,
    trapezoid_profile,
    zigzag_points,
)

TS = 0.01
V, A = 1.0, 2.0
ROUND = 1e-9  # float64 round-off on O(1) quantities


def _fd_omega(quat, ts):
    """World angular velocity from a central difference: omega = 2 vec(q_dot (x) q^-1)."""
    qd = (quat[2:] - quat[:-2]) / (2 * ts)
    conj = quat[1:-1] * np.array([1, -1, -1, -1])
    return 2 * quat_mul(qd, conj)[:, 1:]


@pytest.mark.parametrize("length", [1e-4, 0.05, 0.3, 0.5, 0.8, 2.0])
def test_trapezoid_profile_limits_duration_and_rest(length):
    t, s, sd, sdd = trapezoid_profile(length, V, A, TS)
    T_expected = length / V + V / A if length >= V**2 / A else 2 * math.sqrt(length / A)
    assert t[-1] == pytest.approx(T_expected, rel=1e-12)
    assert np.all(np.diff(t) > 0) and np.all(np.diff(t) <= TS + ROUND)
    np.testing.assert_allclose(t[:-1], np.arange(len(t) - 1) * TS, atol=1e-12)  # k ts, then T
    assert s[0] == 0 and s[-1] == pytest.approx(length, abs=1e-15)
    assert sd[0] == 0 and sd[-1] == 0
    assert np.all(sd <= V + ROUND) and np.all(np.abs(sdd) <= A + ROUND)
    assert np.all(np.diff(s) >= 0)
    # Independent check of s(t): integrate the acceleration on a fine grid (midpoint rule).
    fine = np.linspace(0.0, t[-1], 200_001)
    ta = min(V / A, t[-1] / 2)
    acc = np.where(fine < ta, A, np.where(fine > t[-1] - ta, -A, 0.0))
    vel = np.concatenate([[0.0], np.cumsum(0.5 * (acc[1:] + acc[:-1]) * np.diff(fine))])
    pos = np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * np.diff(fine))])
    # fine-grid error: a switch inside a cell costs <= A * h per switch in velocity (h = T/2e5)
    h = fine[1]
    np.testing.assert_allclose(np.interp(t, fine, vel), sd, atol=4 * A * h)
    np.testing.assert_allclose(np.interp(t, fine, pos), s, atol=4 * A * h * t[-1] + 1e-12)


def test_trapezoid_zero_length_and_bad_input():
    t, s, sd, sdd = trapezoid_profile(0.0)
    assert len(t) == 1 and s[0] == 0 and sd[0] == 0
    with pytest.raises(ValueError, match="length"):
        trapezoid_profile(-0.1)
    with pytest.raises(ValueError, match="v_max"):
        trapezoid_profile(0.3, v_max=0.0)
    with pytest.raises(ValueError, match="ts"):
        trapezoid_profile(0.3, ts=float("nan"))


@pytest.mark.parametrize("length", [0.5, 0.7, 1.0, 1.23, 2 * 0.1**2, 2 * 0.37**2])
def test_trapezoid_acceleration_is_the_one_acting_after_each_sample(length):
    """Lengths whose phase switches fall on samples (cruise: ``l/v`` a multiple of ts; triangle:
    ``sqrt(l/a)`` one): the acceleration held over each interval takes the velocity to the next
    sample's exactly. The sample where the braking starts had ``0`` (1.0 and the triangle peak of
    0.02: the velocity off by ``a ts``), now ``-a``."""
    t, s, sd, sdd = trapezoid_profile(length, V, A, TS)
    np.testing.assert_allclose(sd[1:], sd[:-1] + sdd[:-1] * np.diff(t), atol=ROUND)
    np.testing.assert_allclose(s[1:], s[:-1] + sd[:-1] * np.diff(t) + 0.5 * sdd[:-1] * np.diff(t) ** 2,
                               atol=ROUND)


def test_trapezoid_no_sample_just_before_the_end():
    """A duration a hair (5e-10 s) past a multiple of ts left a sample 5e-10 s before ``T`` that
    held ``-a`` for a whole ts from rest (the tolerance was applied in samples, not seconds)."""
    t, s, sd, sdd = trapezoid_profile(0.5 + 5e-10, V, A, TS)
    assert np.min(np.diff(t)) > TS / 2
    np.testing.assert_allclose(sd[1:], sd[:-1] + sdd[:-1] * np.diff(t), atol=1e-8)


def _rand_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_line_segment_position_orientation_and_finite_differences(seed):
    rng = np.random.default_rng(seed)
    pa, pb = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3)
    qa, qb = _rand_quat(rng), _rand_quat(rng)
    seg = line_segment(pa, pb, qa, qb, rot=1.0)
    np.testing.assert_allclose(seg.p[0], pa, atol=1e-15)
    np.testing.assert_allclose(seg.p[-1], pb, atol=1e-15)
    assert abs(seg.quat[0] @ qa) == pytest.approx(1, abs=1e-12)
    assert abs(seg.quat[-1] @ qb) == pytest.approx(1, abs=1e-12)
    # straight: every sample on the segment, velocity along it
    u = (pb - pa) / np.linalg.norm(pb - pa)
    rel = seg.p - pa
    np.testing.assert_allclose(rel - (rel @ u)[:, None] * u, 0, atol=1e-12)
    np.testing.assert_allclose(np.cross(seg.v, u), 0, atol=1e-12)
    assert np.all(np.linalg.norm(seg.v, axis=1) <= V + ROUND)
    assert np.all(np.linalg.norm(seg.a, axis=1) <= A + ROUND)
    np.testing.assert_allclose(seg.v[[0, -1]], 0, atol=0)
    # uniform interior: the central difference of a piecewise quadratic is exact except across
    # a switch of acceleration, where it is off by at most A ts / 2
    n = len(seg) - 1  # the last interval is shorter than ts
    fd_v = (seg.p[2:n] - seg.p[: n - 2]) / (2 * TS)
    assert np.max(np.linalg.norm(fd_v - seg.v[1 : n - 1], axis=1)) <= A * TS / 2 + 1e-9
    # second differences are averages of the acceleration: bounded by A
    dd = (seg.p[2:n] - 2 * seg.p[1 : n - 1] + seg.p[: n - 2]) / TS**2
    assert np.max(np.linalg.norm(dd, axis=1)) <= A * (1 + 1e-6)
    # angular velocity against a finite difference of the quaternions (slerp: omega proportional
    # to s_dot; away from switches the O(ts^2) error is tiny, across one it is <= phi A ts / l)
    phi = 2 * math.acos(min(1.0, abs(float(qa @ qb))))
    w_fd = _fd_omega(seg.quat[:n], TS)
    err = np.linalg.norm(w_fd - seg.omega[1 : n - 1], axis=1)
    assert np.max(err) <= phi * A * TS / np.linalg.norm(pb - pa) + 1e-3
    # the rotation axis is constant (a geodesic)
    wn = np.linalg.norm(seg.omega, axis=1)
    axes = seg.omega[wn > 1e-9] / wn[wn > 1e-9, None]
    np.testing.assert_allclose(axes, np.broadcast_to(axes[0], axes.shape), atol=1e-12)


def test_line_segment_zero_length_cannot_rotate():
    with pytest.raises(ValueError, match="zero-length"):
        line_segment([0, 0, 1], [0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0])
    seg = line_segment([0, 0, 1], [0, 0, 1])
    assert len(seg) == 1


def test_min_rotation_maps_ez():
    rng = np.random.default_rng(3)
    for a in list(rng.normal(size=(20, 3))) + [np.array([0, 0, 1.0]), np.array([0, 0, -1.0])]:
        a = a / np.linalg.norm(a)
        R = min_rotation(a)
        np.testing.assert_allclose(R @ np.array([0, 0, 1.0]), a, atol=1e-12)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(rot_from_quat(quat_from_rot(R)), R, atol=1e-12)


@pytest.mark.parametrize("direction", [1, -1])
def test_welding_arc_constant_speed_radius_and_rotation(direction):
    rng = np.random.default_rng(7)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    e1 = np.cross(n, [0.3, 0.2, 0.9])
    e1 /= np.linalg.norm(e1)
    c, r, th0 = np.array([0.3, 0.1, 1.0]), 0.17, 0.4
    q0 = quat_from_rot(min_rotation(-n))
    seg = arc_segment(c, n, e1, r, th0, q0, direction=direction, speed=0.10, a_max=A, ts=TS)
    rel = seg.p - c
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), r, atol=1e-12)
    np.testing.assert_allclose(rel @ n, 0, atol=1e-12)
    np.testing.assert_allclose(seg.p[-1], seg.p[0], atol=1e-12)  # a full turn
    speed = np.linalg.norm(seg.v, axis=1)
    ramp = 0.10 / A
    cruise = (seg.t > ramp + 1e-12) & (seg.t < seg.t[-1] - ramp - 1e-12)
    np.testing.assert_allclose(speed[cruise], 0.10, rtol=1e-12)
    assert np.all(speed <= 0.10 + ROUND) and speed[0] == 0 and speed[-1] == 0
    # tangential acceleration <= A; centripetal v^2/r is tiny at 0.1 m/s
    assert np.all(np.linalg.norm(seg.a, axis=1) <= math.hypot(A, 0.10**2 / r) + ROUND)
    assert seg.t[-1] == pytest.approx(2 * math.pi * r / 0.10 + 0.10 / A, rel=1e-12)
    # direction of travel
    tang = np.cross(n, rel[1] / r)
    assert np.sign(seg.v[1] @ tang) == direction
    # orientation: R(th) = Rot(n, th - th0) R0 keeps the tool axis' angle to n; omega parallel to n
    tool = rot_from_quat(seg.quat)[:, :, 2]
    np.testing.assert_allclose(tool @ n, -1.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(seg.omega, n), 0, atol=1e-12)
    m = len(seg) - 1
    w_fd = _fd_omega(seg.quat[:m], TS)
    assert np.max(np.linalg.norm(w_fd - seg.omega[1 : m - 1], axis=1)) <= A * TS / r + 1e-6
    # quaternion continuity
    assert np.min(np.sum(seg.quat[1:] * seg.quat[:-1], axis=1)) > math.cos(0.1 / 2)


def test_degenerate_directions_raise_naming_the_argument():
    """A zero or NaN direction or quaternion, or an arc start direction along the normal, gave NaN
    samples; each is a ``ValueError`` naming the argument."""
    q = np.array([1.0, 0, 0, 0])
    n, e1 = np.array([0.0, 0, 1]), np.array([1.0, 0, 0])
    cases = [
        (lambda: min_rotation([0.0, 0.0, 0.0]), "a:"),
        (lambda: min_rotation([np.nan, 0.0, 1.0]), "a:"),
        (lambda: line_segment(np.zeros(3), np.ones(3), np.zeros(4), q, v_max=V, a_max=A, ts=TS), "quat_a"),
        (lambda: line_segment(np.zeros(3), np.ones(3), q, np.zeros(4), v_max=V, a_max=A, ts=TS), "quat_b"),
        (lambda: arc_segment(np.zeros(3), np.zeros(3), e1, 0.1, 0.0, q), "normal"),
        (lambda: arc_segment(np.zeros(3), n, 2 * n, 0.1, 0.0, q), "e1"),
        (lambda: arc_segment(np.zeros(3), n, e1, 0.1, np.nan, q), "theta0"),
        (lambda: arc_segment(np.full(3, np.nan), n, e1, 0.1, 0.0, q), "center"),
        (lambda: arc_segment(np.zeros(3), n, e1, 0.1, 0.0, np.zeros(4)), "quat0"),
    ]
    for make, name in cases:
        with pytest.raises(ValueError, match=name):
            make()


def test_bad_segment_inputs_raise_naming_the_argument():
    """Inputs that gave NaN samples (a zero quaternion or NaN point for a hold, a zero row
    direction), an empty hold that failed later in ``concat_segments``, an orientation flag other
    than 0 or 1, and arc arguments reported under another name."""
    q, z = np.array([1.0, 0, 0, 0]), np.zeros(3)
    n, e1 = np.array([0.0, 0, 1]), np.array([1.0, 0, 0])
    cases = [
        (lambda: constant_segment(z, np.zeros(4)), "quat:"),
        (lambda: constant_segment([np.nan, 0, 0], q), "p:"),
        (lambda: constant_segment(z, q, 0), "n:"),
        (lambda: constant_segment(z, q, rot=0.5), "rot:"),
        (lambda: line_segment(z, [0.1, 0, 0], rot=np.nan), "rot:"),
        (lambda: arc_segment(z, n, e1, 0.1, 0.0, q, angle=-1.0), "angle:"),
        (lambda: arc_segment(z, n, e1, 0.1, 0.0, q, speed=0.0), "speed:"),
        (lambda: zigzag_points(z, z, n, 0.2, [0.0]), "row_dir:"),
        (lambda: zigzag_points(z, e1, n, -0.2, [0.0]), "width:"),
        (lambda: zigzag_points(z, e1, n, 0.2, [np.nan]), "rows:"),
    ]
    for make, name in cases:
        with pytest.raises(ValueError, match=name):
            make()
    hold = constant_segment([0, 0, 1], [2.0, 0, 0, 0], 3, rot=1)
    np.testing.assert_array_equal(hold.quat, np.tile(q, (3, 1)))
    np.testing.assert_array_equal(hold.rot, np.ones(3))


def test_zigzag_every_leg_rest_to_rest():
    pts = zigzag_points([0.5, 0.0, 1.0], [0, 1, 0], [0, 0, 1], 0.16, (0.1, 0.0, -0.1))
    assert pts.shape == (6, 3)
    np.testing.assert_allclose(np.linalg.norm(pts[1] - pts[0]), 0.16)
    segs = polyline(pts, [1, 0, 0, 0], rot=1.0)
    assert len(segs) == 5
    for s in segs:
        assert np.all(s.v[[0, -1]] == 0)
    seg = concat_segments(segs)
    # every vertex is visited at rest, exactly once
    for p in pts:
        hits = np.nonzero(np.linalg.norm(seg.p - p, axis=1) < 1e-12)[0]
        assert len(hits) == 1 and np.all(seg.v[hits] == 0)


def _two_segments():
    q_end = quat_from_rot(min_rotation([1.0, 0, 0]))
    s1 = line_segment([0, 0, 1.5], [0.3, 0.2, 1.0], [1, 0, 0, 0], q_end, rot=0.0)
    s2 = line_segment([0.3, 0.2, 1.0], [0.55, 0.2, 1.0], q_end, rot=1.0)
    return s1, s2


def test_assemble_reference_joins_pads_and_latches():
    s1, s2 = _two_segments()
    ref = assemble_reference([s1, s2], TS, capacity=300)
    n = int(ref.n_samples)
    assert n == len(s1) + len(s2) - 1  # the shared sample is kept once
    p, v, a = np.asarray(ref.p), np.asarray(ref.v), np.asarray(ref.a)
    assert np.all(np.linalg.norm(np.diff(p[:n], axis=0), axis=1) > 0)  # no duplicated samples
    mask = np.asarray(ref.mask)
    assert mask[:n].all() and not mask[n:].any() and ref.capacity == 300
    # padding repeats the final sample at rest
    np.testing.assert_array_equal(p[n:], np.broadcast_to(p[n - 1], p[n:].shape))
    for f in (v, a, np.asarray(ref.omega), np.asarray(ref.omega_dot)):
        assert np.all(f[n - 1 :] == 0)
    assert np.all(v[0] == 0)
    # speed / acceleration limits over the whole reference; finite differences never exceed them
    assert np.all(np.linalg.norm(v, axis=1) <= V + ROUND)
    assert np.all(np.linalg.norm(a, axis=1) <= A + ROUND)
    assert np.max(np.linalg.norm(np.diff(p[:n], axis=0), axis=1)) <= V * TS + ROUND
    # rot: off on segment 1, on from the joint (the start of segment 2), latched
    rot = np.asarray(ref.rot)
    assert np.all(np.diff(rot) >= 0)
    j = len(s1) - 1
    assert rot[j - 1] == 0 and rot[j] == 1
    # the joint keeps the next segment's start: acceleration pointing along segment 2
    np.testing.assert_allclose(a[j], s2.a[0])
    # quaternion continuity across the joint and along the reference
    qt = np.asarray(ref.quat)
    assert np.min(np.sum(qt[1:n] * qt[: n - 1], axis=1)) > 0.99


def test_assemble_reference_errors():
    s1, s2 = _two_segments()
    with pytest.raises(ValueError, match="capacity"):
        assemble_reference([s1, s2], TS, capacity=10)
    with pytest.raises(ValueError, match=r"segments\[1\]"):
        assemble_reference([s2, s1], TS, capacity=300)
    with pytest.raises(ValueError, match="rot"):
        assemble_reference([s1], TS, capacity=300, rot=np.zeros(3))
    # a NaN flag was latched into every later sample (orientation control silently off), 2 and -1 kept
    for bad in (np.nan, 2.0, -1.0):
        flags = np.zeros(len(s1.p))
        flags[5] = bad
        with pytest.raises(ValueError, match="rot: expected flags 0 or 1"):
            assemble_reference([s1], TS, capacity=300, rot=flags)
    with pytest.raises(ValueError, match="ts"):
        assemble_reference([s1], -1.0, capacity=300)


def test_rot_within_latches():
    p = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], 1)
    flags = rot_within(p, np.array([[0.5, 0.0, 0.0]]), 0.2)
    np.testing.assert_array_equal(flags, (np.arange(11) >= 3).astype(float))  # latched after 0.7
