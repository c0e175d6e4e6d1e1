"""Small Lie-group and quaternion helpers (SE(3), so(3), unit quaternions ``(w, x, y, z)``).

Every function is pure, works on a single element and vmaps; none of them has a NaN gradient at
the identity (the double-``where`` trick guards the square roots).

The module also holds the checks the public modules (gains, parameters, arms) run at
construction: :func:`check_finite_fields`, :func:`check_positive`, :func:`check_tolerances` and
:func:`check_count`. They read concrete values only (:func:`concrete`); a module built under a
trace is its caller's to check.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = [
    "skew",
    "exp_revolute",
    "exp_prismatic",
    "adjoint",
    "ad",
    "rot_to_quat",
    "quat_to_rot",
    "quat_mul",
    "quat_conj",
    "quat_error",
    "clip_norm",
    "safe_norm",
    "as_float",
    "as_float_or_none",
    "is_floating_array",
    "floating_dtype",
    "cast_floating",
]


def skew(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """``[w]_x`` such that ``skew(w) @ v = w x v``."""
    z = jnp.zeros_like(w[0])
    return jnp.array([[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]])


def exp_revolute(screw: Float[Array, "6"], theta) -> Float[Array, "4 4"]:
    """Closed-form ``exp([S] theta)`` of a unit revolute screw ``(omega, v)``, ``|omega| = 1``."""
    w, v = screw[:3], screw[3:]
    W = skew(w)
    W2 = W @ W
    s, c = jnp.sin(theta), jnp.cos(theta)
    eye = jnp.eye(3, dtype=W.dtype)
    R = eye + s * W + (1 - c) * W2
    p = (theta * eye + (1 - c) * W + (theta - s) * W2) @ v
    return _homogeneous(R, p)


def exp_prismatic(screw: Float[Array, "6"], theta) -> Float[Array, "4 4"]:
    """``exp([S] theta)`` of a unit prismatic screw ``(0, v)``: a translation by ``v theta``."""
    return _homogeneous(jnp.eye(3, dtype=screw.dtype), screw[3:] * theta)


def _homogeneous(R, p):
    top = jnp.concatenate([R, p[:, None]], axis=1)
    bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=R.dtype)
    return jnp.concatenate([top, bottom], axis=0)


def adjoint(T: Float[Array, "4 4"]) -> Float[Array, "6 6"]:
    """``Ad_T = [[R, 0], [[p]_x R, R]]`` for twists ordered ``(omega, v)``."""
    R, p = T[:3, :3], T[:3, 3]
    z = jnp.zeros_like(R)
    return jnp.block([[R, z], [skew(p) @ R, R]])


def ad(V: Float[Array, "6"]) -> Float[Array, "6 6"]:
    """Lie bracket matrix ``ad_V = [[[w], 0], [[v], [w]]]`` for ``V = (w, v)``."""
    W, Vv = skew(V[:3]), skew(V[3:])
    z = jnp.zeros_like(W)
    return jnp.block([[W, z], [Vv, W]])


def safe_norm(x, axis=-1, keepdims=False, eps=0.0):
    """Euclidean norm whose gradient is 0 (not NaN) at ``x = 0`` (double-``where`` trick)."""
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0) + eps


def rot_to_quat(R: Float[Array, "3 3"]) -> Float[Array, "4"]:
    """Rotation matrix to unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (Shepperd's method).

    The branch is chosen by the largest of ``(trace, R_xx, R_yy, R_zz)``; every branch's square
    root is guarded so that the untaken ones give neither NaN values nor NaN gradients.
    """
    t = jnp.trace(R)
    d = jnp.diagonal(R)
    cands = jnp.stack([t, d[0], d[1], d[2]])
    k = jnp.argmax(cands)

    def root(x):
        x = jnp.maximum(x, 1e-12)
        return jnp.sqrt(x)

    r0 = root(1 + t)
    q0 = jnp.stack([0.5 * r0, (R[2, 1] - R[1, 2]) / (2 * r0), (R[0, 2] - R[2, 0]) / (2 * r0),
                    (R[1, 0] - R[0, 1]) / (2 * r0)])
    r1 = root(1 + d[0] - d[1] - d[2])
    q1 = jnp.stack([(R[2, 1] - R[1, 2]) / (2 * r1), 0.5 * r1, (R[0, 1] + R[1, 0]) / (2 * r1),
                    (R[0, 2] + R[2, 0]) / (2 * r1)])
    r2 = root(1 - d[0] + d[1] - d[2])
    q2 = jnp.stack([(R[0, 2] - R[2, 0]) / (2 * r2), (R[0, 1] + R[1, 0]) / (2 * r2), 0.5 * r2,
                    (R[1, 2] + R[2, 1]) / (2 * r2)])
    r3 = root(1 - d[0] - d[1] + d[2])
    q3 = jnp.stack([(R[1, 0] - R[0, 1]) / (2 * r3), (R[0, 2] + R[2, 0]) / (2 * r3),
                    (R[1, 2] + R[2, 1]) / (2 * r3), 0.5 * r3])
    q = jnp.stack([q0, q1, q2, q3])[k]
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[0] < 0, -q, q)


def quat_to_rot(q: Float[Array, "4"]) -> Float[Array, "3 3"]:
    """Unit quaternion ``(w, x, y, z)`` to rotation matrix."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_mul(a: Float[Array, "4"], b: Float[Array, "4"]) -> Float[Array, "4"]:
    """Hamilton product ``a (x) b`` of scalar-first quaternions."""
    w1, v1 = a[0], a[1:]
    w2, v2 = b[0], b[1:]
    return jnp.concatenate([(w1 * w2 - v1 @ v2)[None], w1 * v2 + w2 * v1 + jnp.cross(v1, v2)])


def quat_conj(q: Float[Array, "4"]) -> Float[Array, "4"]:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_error(q_d: Float[Array, "4"], q: Float[Array, "4"]) -> Float[Array, "3"]:
    """Orientation error ``e_o = vec(Q_d (x) Q^-1) = eta eps_d - eta_d eps - eps_d x eps`` (SPEC E1).

    ``q`` is first flipped into the hemisphere of ``q_d`` (``q_d . q >= 0``), so the error is
    invariant to the sign of either quaternion. Used with positive gains it drives ``q`` to ``q_d``.
    ``|e_o| = sin(phi / 2)`` for a rotation error of angle ``phi``.
    """
    q = jnp.where(q_d @ q < 0, -q, q)
    eta, eps = q[0], q[1:]
    eta_d, eps_d = q_d[0], q_d[1:]
    return eta * eps_d - eta_d * eps - jnp.cross(eps_d, eps)


def clip_norm(e: Float[Array, " k"], limit) -> Float[Array, " k"]:
    """Scale ``e`` so that ``|e| <= limit`` (thesis eq. 3.15); NaN-free gradient at ``e = 0``."""
    n = safe_norm(e)
    scale = jnp.where(n > limit, limit / jnp.where(n > limit, n, 1.0), 1.0)
    return e * scale


def as_float(x):
    """A gain or tolerance as a strongly typed array of the default float dtype.

    ``jnp.asarray(1.0)`` is *weakly* typed, so a gains pytree built from Python floats and one
    built from arrays (a user's, or a tuner's) would compile separately; converting every number
    with this keeps one compilation. Arrays that already have a floating dtype keep it.

    A host value (a Python number or a NumPy array or scalar) is converted in NumPy and placed with
    ``jax.device_put``, the same result without compiling (outside ``jit`` ``jnp.asarray`` and
    ``astype`` each compile a small program per shape, see :mod:`redman_jax._host`).
    """
    if isinstance(x, (bool, int, float, complex, np.ndarray, np.generic)):
        weak = type(x) in (bool, int, float, complex)  # Python scalars: weakly typed in JAX
        a = np.asarray(x)
        if a.dtype.kind == "b" or (a.dtype.kind == "f" and not weak):
            return jax.device_put(a)
        return jax.device_put(a.astype(jnp.result_type(float)))
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.floating) and not x.weak_type:
        return x
    if jnp.issubdtype(x.dtype, jnp.bool_):
        return x
    return x.astype(jnp.result_type(float))


def as_float_or_none(x):
    """:func:`as_float`, keeping ``None`` (a field whose default is resolved later, e.g. tolerances
    by the run's precision, :func:`resolve_tolerances`)."""
    return None if x is None else as_float(x)


def floating_dtype(*arrays):
    """The dtype ``arrays`` promote to if it is floating, else the default float dtype (integer
    points or goals are computed in floats)."""
    dtype = jnp.result_type(*arrays)
    return dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.result_type(float)


def is_floating_array(x) -> bool:
    """Whether ``x`` is an array (JAX, traced or NumPy) of a floating-point dtype."""
    return isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating)


def cast_floating(tree, dtype):
    """``tree`` with every floating-point array cast to ``dtype`` (integer and boolean arrays and
    non-array leaves kept): an arm, scenario, gains or IK result in one precision, for example
    ``cast_floating(arm, jnp.float32)`` to run in float32 with float64 enabled."""
    dtype = jnp.dtype(dtype)
    return jax.tree.map(lambda x: x.astype(dtype) if is_floating_array(x) and x.dtype != dtype else x,
                        tree)


def check_finite_fields(module) -> None:
    """Raise ``ValueError`` naming the field if a concrete floating-point array field of ``module``
    (gains, contact parameters) holds a NaN or an infinity: every run with it would be NaN.
    Traced fields (a module built inside ``jit`` / ``vmap`` / ``grad``), sub-modules (they check
    themselves) and arrays this process cannot read whole are skipped."""
    for f in dataclasses.fields(module):
        v = getattr(module, f.name)
        if isinstance(v, jax.core.Tracer) or not isinstance(v, (jax.Array, np.ndarray)):
            continue
        if not getattr(v, "is_fully_addressable", True):
            continue
        a = np.asarray(v)
        if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
            raise ValueError(f"{type(module).__name__}.{f.name}: expected finite values, got {a}")


def concrete(x):
    """NumPy value of ``x`` if it is concrete (not traced), else None. The checks below skip a
    traced value: a module built inside ``jit`` / ``vmap`` / ``grad`` is checked by its caller."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # pragma: no cover - exotic array types
        return None


def check_initial_state(name: str, x, n: int, R: int | None = None) -> None:
    """A given initial state (``q0`` or ``qd0``; None: the default): shape ``(n,)``, or ``(R, n)``
    per run of a batch of ``R`` (``R`` None: one run); where concrete, finite (a NaN there makes the
    whole run NaN, flagged as diverged, instead of saying which input was wrong)."""
    if x is not None:
        check_shape_finite(name, x, (n,) if R is None else (R, n),
                           f" ({n}-DOF arm{'' if R is None else f', {R} runs'})")


def check_shape_finite(name: str, x, shape: tuple, about: str = "") -> None:
    """Raise ``ValueError`` naming ``name`` unless ``x`` has ``shape`` (``about``: what the shape
    follows from, in the message) and, where concrete, finite values (:func:`check_finite`)."""
    got = tuple(np.shape(x))
    if got != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}{about}, got {got}")
    check_finite(name, x)


def check_finite(name: str, x) -> None:
    """Raise ``ValueError`` naming ``name`` if concrete floating-point ``x`` holds a NaN or an
    infinity (traced: the caller's to check)."""
    a = concrete(x)
    if a is not None and a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values, got {a}")


QUAT_NORM_TOL = 1e-5  # a zero or scaled quaternion is refused, rounding of a unit one is not


def check_unit_quaternions(name: str, q, mask=None, plural: bool | None = None, allow_nan: bool = True) -> None:
    """Raise ``ValueError`` naming ``name`` if a concrete quaternion ``(w, x, y, z)`` (the last axis;
    any leading axes, only the rows where ``mask`` is True) has a norm off 1 by more than
    :data:`QUAT_NORM_TOL`: a zero one turns orientation control off unnoticed, a longer one scales
    its gain. Rows holding a NaN pass (finiteness is the caller's check: in a batch a NaN member is
    that member's flagged failure) unless ``allow_nan=False``. The message speaks of one quaternion for a single one (of
    several with ``plural=True``: an argument that may be a batch)."""
    v = concrete(q)
    m = None if mask is None else concrete(mask)
    if v is None or (mask is not None and m is None):
        return
    norm = np.linalg.norm(v, axis=-1)
    off = ~(np.abs(norm - 1.0) <= QUAT_NORM_TOL) if not allow_nan else np.abs(norm - 1.0) > QUAT_NORM_TOL
    if m is not None:
        off = off & m
    if not np.any(off):
        return
    idx = tuple(int(i) for i in np.argwhere(off)[0])
    where = f" at {idx}" if idx else ""
    what = "unit quaternions" if (v.ndim > 1 if plural is None else plural) else "a unit quaternion"
    raise ValueError(f"{name}: expected {what} (w, x, y, z), got {v[idx]}{where} (norm {float(norm[idx]):.6g})")


def check_same_precision(name: str, tree, dtype, run: str) -> None:
    """Raise ``ValueError`` naming ``name`` if ``tree`` holds strongly typed floating arrays of
    another dtype than the run's ``dtype`` (mixed, they would promote the computation and fail deep
    inside it); ``run`` says what the run's precision follows, e.g. ``"a float32 scenario"``."""
    other = {jnp.dtype(x.dtype).name for x in jax.tree.leaves(tree)
             if is_floating_array(x) and not getattr(x, "weak_type", False) and x.dtype != dtype}
    if other:
        raise ValueError(f"{name}: {'/'.join(sorted(other))} arrays with {run}; cast them (or the "
                         f"{run.split()[-1]}) to one precision")


def check_positive(name: str, x, allow_zero: bool = False, allow_inf: bool = False) -> None:
    """Raise ``ValueError`` naming ``name`` unless concrete ``x`` is finite and positive
    (non-negative with ``allow_zero``; ``+inf`` also passes with ``allow_inf``)."""
    v = concrete(x)
    if v is None:
        return
    finite = np.isfinite(v) | (allow_inf & (v == np.inf))
    bad = ~finite | ((v < 0) if allow_zero else (v <= 0))
    if np.any(bad):
        kind = "non-negative" if allow_zero else "positive"
        extra = " (inf: no bound)" if allow_inf else ""
        raise ValueError(f"{name}: expected a {'' if allow_inf else 'finite '}{kind} value{extra}, got {v}")


# An adaptive step-size controller's default tolerances by the state's precision. float64: SPEC U9
# (about MATLAB ode113's use; benchmarks/bench_tolerance.py). float32: the float64 values sit at its
# rounding (eps 1.2e-7), so the error estimates are rounding noise and the steps stop growing
# (7-DOF simple, gradient-guided, a float64 scene cast to float32: 25,981 steps at float64's
# values, 1,590 at these, 1,114 in float64); ``bench_tolerance.py --float32`` gives the evidence
# for these. Used by ``SimParams`` and ``PerfectParams`` where their tolerances are None.
DEFAULT_TOLERANCES = {"float64": (1e-5, 1e-7), "float32": (1e-4, 1e-5)}


def resolve_tolerances(rtol, atol, dtype) -> tuple:
    """``(rtol, atol)``: the given ones, or where None the :data:`DEFAULT_TOLERANCES` of ``dtype``'s
    precision (float64's for any other)."""
    r, a = DEFAULT_TOLERANCES.get(np.dtype(dtype).name, DEFAULT_TOLERANCES["float64"])
    return (r if rtol is None else rtol, a if atol is None else atol)


def check_tolerances(owner: str, rtol, atol) -> None:
    """An adaptive solver's ``rtol`` and ``atol``, where concrete: finite, non-negative, not both
    zero (no step would ever be accepted)."""
    check_positive(f"{owner}.rtol", rtol, allow_zero=True)
    check_positive(f"{owner}.atol", atol, allow_zero=True)
    r, a = concrete(rtol), concrete(atol)
    if r is not None and a is not None and np.any((r == 0) & (a == 0)):
        raise ValueError(f"{owner}.rtol, {owner}.atol: both zero, no step would ever be accepted")


def check_count(name: str, value, least: int) -> None:
    """A static count: an ``int`` (not a bool) of at least ``least``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise ValueError(f"{name}: expected an int >= {least}, got {value!r}")
