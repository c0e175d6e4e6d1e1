"""Potential fields: obstacle repulsion, goal attractor, virtual obstacles and their sum.

Thesis 2.6.1, 3.2.4 and 3.3.3; SPEC section 3 (and 9 for the guidance velocity).

**Obstacle potential** (2.38 form, eq. 3.8 corrected; E4/E5). With ``r`` the signed distance to
the obstacle surface, ``a`` the amplitude and ``D`` the range::

    "minus" (default):  V_o(r) = a (1/r - 1/D) / r^2,   dV_o/dr = -a (3D - 2r) / (D r^4)
    "plus"  (3.8/3.9):  V_o(r) = a (1/r + 1/D) / r^2,   dV_o/dr = -a (3D + 2r) / (D r^4)

for ``r <= D`` and 0 beyond. The "minus" form is continuous, >= 0 and monotone on (0, D]; the
"plus" form is the thesis's literal pair (V jumps by 2a/D^3 at D). The gradient in space is
``grad V_o = dV_o/dr * grad sdf`` (3.9 corrected; the sdf gradient is rotated back with ``R_o``
only, E10). Obstacles add up (3.22-3.23).

**Clamp** (SPEC U3). Inside or on an obstacle ``r <= 0`` and the potential is infinite, so only the
*magnitude* is clamped: ``grad V_o(x) = V_o'(max(sdf, eps)) * grad sdf(x)`` with ``eps = 1e-3`` and
the direction from the *unclamped* sdf. The clamp is a ``jax.custom_jvp`` on the radial function,
so ``jax.grad`` of :func:`total_potential` equals :func:`total_gradient` everywhere (a non-zero,
finite force inside obstacles) and the Hessian (:func:`total_hessian`, the forward Jacobian of the
gradient) is the derivative of that gradient: ``V_o''(r) [r > eps] n n^T + V_o'(max(r, eps))
grad^2 sdf``. Differentiating through a plain ``max`` would give zero force inside an obstacle.

**Goal attractor** (3.20-3.21, quadratic, E13): ``V_g = |x - x_g|^2``, ``g_g = 2 (x - x_g)``,
``H_g = 2 I``.

**Virtual obstacles** (3.25-3.27, E14/E15), with ``rho = |x - x_v|`` (floored at 1e-6 where it
divides) and range ``d_v = 0.25``::

    V_v = A (1/(rho + 1) - 1/(d_v + 1))  (rho <= d_v), else 0
    grad V_v = -A (x - x_v) / (rho (rho + 1)^2)

``A = amp |x - x_g|^2`` with ``amp = 0.1`` held constant in derivatives (U4,
``stop_gradient``); ``amp_exact=True`` differentiates it, and ``vo_amp="site"`` uses the
per-obstacle ``A_j = amp |x_v,j - x_g|^2`` instead (the second reading of 3.27).

**Total field** (3.22-3.24): ``V = V_g + sum V_o(a=0.0005, D=0.5) + sum_buffer V_v``; masked
buffer slots and masked obstacle slots contribute 0.

**Guidance velocity** (3.18-3.19 corrected, E13; SPEC section 9):
``xdot_g = -a tanh(|x - x_g| / b) g / (|g| + 1e-9)`` with ``a = 0.5`` m/s, ``b = 0.1`` m.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._math import as_float, check_positive, safe_norm
from ._obstacles import BIG_DISTANCE, ObstacleSet, Shapes, box_sdf, cylinder_sdf, sphere_sdf

__all__ = [
    "FORMS",
    "FieldParams",
    "obstacle_potential",
    "obstacle_potential_dr",
    "obstacle_potential_d2r",
    "obstacle_sdf_and_normals",
    "points_sdf_and_normals",
    "obstacle_field_potential",
    "obstacle_field_gradient",
    "obstacle_field_gradients",
    "goal_potential",
    "goal_gradient",
    "virtual_potential",
    "virtual_gradient",
    "total_potential",
    "total_gradient",
    "total_hessian",
    "guidance_velocity",
    "total_potential_points",
    "total_gradient_points",
    "total_hessian_points",
    "guidance_velocity_points",
    "total_potential_batch",
    "total_gradient_batch",
    "DISTANCE_CLAMP",
    "RHO_FLOOR",
]

FORMS = ("minus", "plus")
DISTANCE_CLAMP = 1e-3  # SPEC U3: magnitude clamp of the obstacle distance [m]
RHO_FLOOR = 1e-6  # SPEC section 3: floor of the virtual-obstacle distance where it divides [m]
_VO_AMPS = ("ee", "site")


def _check_form(form: str) -> None:
    if form not in FORMS:
        raise ValueError(f"form: expected one of {FORMS}, got {form!r}")


# ----------------------------------------------------------------------------------------------
# Radial obstacle potential (3.8/3.9 corrected)
# ----------------------------------------------------------------------------------------------


def obstacle_potential(r, a, D, form: str = "minus"):
    """Obstacle potential ``V_o(r)`` of the distance ``r > 0`` (3.8 / 2.38, E4), 0 for ``r > D``.

    ``"minus"``: ``a (1/r - 1/D) / r^2``; ``"plus"``: ``a (1/r + 1/D) / r^2`` (thesis literal).
    No clamp here: ``r`` must be positive (see :func:`obstacle_field_potential` for the clamped
    field of an obstacle set).
    """
    _check_form(form)
    sgn = -1.0 if form == "minus" else 1.0
    r_safe = jnp.where(r > 0, r, 1.0)
    v = a * (1.0 / r_safe + sgn / D) / r_safe**2
    return jnp.where((r <= D) & (r > 0), v, jnp.where(r > D, 0.0, jnp.inf))


def obstacle_potential_dr(r, a, D, form: str = "minus"):
    """``dV_o/dr`` (3.9 corrected, E5): ``-a (3D -/+ 2r) / (D r^4)`` for ``0 < r <= D``, 0 for
    ``r > D`` and ``-inf`` for ``r <= 0`` (unclamped; the field functions clamp ``r`` first).

    ``"minus"`` gives ``-a (3D - 2r)/(D r^4)``, ``"plus"`` gives ``-a (3D + 2r)/(D r^4)``.
    """
    _check_form(form)
    sgn = -1.0 if form == "minus" else 1.0
    r_safe = jnp.where(r > 0, r, 1.0)
    dv = -a * (3.0 * D + sgn * 2.0 * r_safe) / (D * r_safe**4)
    return jnp.where((r <= D) & (r > 0), dv, jnp.where(r > D, 0.0, -jnp.inf))


def obstacle_potential_d2r(r, a, D, form: str = "minus"):
    """``d^2V_o/dr^2 = a (12 D -/+ 6 r) / (D r^5)`` for ``0 < r <= D``, 0 for ``r > D`` and ``+inf``
    for ``r <= 0`` (unclamped)."""
    _check_form(form)
    sgn = -1.0 if form == "minus" else 1.0
    r_safe = jnp.where(r > 0, r, 1.0)
    d2 = a * (12.0 * D + sgn * 6.0 * r_safe) / (D * r_safe**5)
    return jnp.where((r <= D) & (r > 0), d2, jnp.where(r > D, 0.0, jnp.inf))


def _radial_value(s, a, D, eps, form):
    r = jnp.maximum(s, eps)
    return jnp.where(s <= D, obstacle_potential(r, a, D, form), 0.0)


def _radial_slope(s, a, D, eps, form):
    """``V_o'(max(s, eps))`` for ``s <= D`` else 0: the clamped-magnitude slope (SPEC U3)."""
    r = jnp.maximum(s, eps)
    return jnp.where(s <= D, obstacle_potential_dr(r, a, D, form), 0.0)


@partial(jax.custom_jvp, nondiff_argnums=(4,))
def _clamped_radial(s, a, D, eps, form):
    """``V_o(max(s, eps))`` whose derivative in ``s`` is ``V_o'(max(s, eps))`` (not zero inside)."""
    return _radial_value(s, a, D, eps, form)


def _clamped_radial_jvp(form, primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    s, a, D, eps = primals
    ds, da, dD, deps = tangents
    # the clamp's term only where its tangent is not a symbolic zero (it is one unless the clamp
    # itself is differentiated): the others are instantiated as before the term existed, so the
    # programs that do not differentiate the clamp (the simulator's) are unchanged, bit for bit
    zero = lambda t, x: jnp.zeros(jnp.shape(x), jnp.result_type(x)) if isinstance(t, SymbolicZero) else t  # noqa: E731
    ds, da, dD = zero(ds, s), zero(da, a), zero(dD, D)
    r = jnp.maximum(s, eps)
    sgn = -1.0 if form == "minus" else 1.0
    inside = s <= D
    v = _radial_value(s, a, D, eps, form)
    # dV/da = V/a ; dV/dD = -sgn a / (D^2 r^2) (the range only enters through the 1/D term)
    dv_da = jnp.where(inside, (1.0 / r + sgn / D) / r**2, 0.0)
    dv_dD = jnp.where(inside, -sgn * a / (D**2 * r**2), 0.0)
    slope = _radial_slope(s, a, D, eps, form)  # V_o'(max(s, eps)) within D
    tangent = slope * ds + dv_da * da + dv_dD * dD
    if not isinstance(deps, SymbolicZero):
        # where the clamp holds (s < eps) the value is V_o(eps): dV/deps = V_o'(eps) (it was left 0)
        tangent = tangent + jnp.where(s < eps, slope, 0.0) * deps
    return v, tangent


_clamped_radial.defjvp(_clamped_radial_jvp, symbolic_zeros=True)


# ----------------------------------------------------------------------------------------------
# Obstacle sets
# ----------------------------------------------------------------------------------------------


def _family_sdf_normals(s: Shapes, x, fn):
    """Signed distances ``(K,)`` and world-frame unit normals ``grad sdf`` ``(K, 3)``.

    The sdf is evaluated in the obstacle frame ``x_l = R^T (x - p)``; its gradient is rotated back
    with ``R`` only (E10). Masked slots give ``BIG_DISTANCE`` and a zero normal.
    """
    xl = jnp.einsum("kji,kj->ki", s.R, x[None, :] - s.p)
    d, nl = jax.vmap(jax.value_and_grad(fn))(xl, s.dims)
    n = jnp.einsum("kij,kj->ki", s.R, nl)
    d = jnp.where(s.mask, d, BIG_DISTANCE)
    n = jnp.where(s.mask[:, None], n, 0.0)
    return d, n


def obstacle_sdf_and_normals(obs: ObstacleSet, x: Float[Array, "3"]):
    """Signed distances ``(K,)`` and unit normals ``(K, 3)`` (gradients of the *unclamped* sdf)
    from ``x`` to every obstacle slot (order: spheres, boxes, cylinders, as
    :func:`~redman_jax.obstacle_distances`)."""
    parts = [
        _family_sdf_normals(obs.spheres, x, sphere_sdf),
        _family_sdf_normals(obs.boxes, x, box_sdf),
        _family_sdf_normals(obs.cylinders, x, cylinder_sdf),
    ]
    return jnp.concatenate([p[0] for p in parts]), jnp.concatenate([p[1] for p in parts])


def _pos_sqrt(x2):
    """``(sqrt(x2), 1/sqrt(x2))`` for ``x2 >= 0``, ``(0, 0)`` at 0, NaN-free gradients (double where)."""
    pos = x2 > 0
    r = jnp.sqrt(jnp.where(pos, x2, 1.0))
    return jnp.where(pos, r, 0.0), jnp.where(pos, 1.0 / r, 0.0)


def _family_sdf_normals_planes(kind: str, s: Shapes, X):
    """Signed distances ``(m, K)`` and world unit normals (three ``(m, K)`` planes) of one family
    at all points ``X`` (three ``(m, 1)`` planes): the analytic gradient of the unclamped sdf."""
    R = s.R[None]  # (1, K, 3, 3)
    d = [X[j] - s.p[None, :, j] for j in range(3)]
    if kind == "spheres":
        r, inv = _pos_sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        return r - s.dims[None, :, 0], [d[j] * inv for j in range(3)]
    xl = [R[..., 0, i] * d[0] + R[..., 1, i] * d[1] + R[..., 2, i] * d[2] for i in range(3)]
    one = jnp.ones((), X[0].dtype)
    sg = [jnp.where(v < 0, -one, one) for v in xl]
    if kind == "boxes":
        u = [jnp.abs(xl[i]) - s.dims[None, :, i] for i in range(3)]
        o = [jnp.maximum(v, 0.0) for v in u]
        on, inv_on = _pos_sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2])
        out = on > 0
        sdf = on + jnp.minimum(jnp.maximum(jnp.maximum(u[0], u[1]), u[2]), 0.0)
        pick0 = (u[0] >= u[1]) & (u[0] >= u[2])
        pick1 = ~pick0 & (u[1] >= u[2])
        picks = (pick0, pick1, ~pick0 & ~pick1)
        gl = [sg[i] * jnp.where(out, o[i] * inv_on, picks[i].astype(on.dtype)) for i in range(3)]
    else:
        rho, inv_rho = _pos_sqrt(xl[0] * xl[0] + xl[1] * xl[1])
        d1 = rho - s.dims[None, :, 0]
        d2 = jnp.abs(xl[2]) - s.dims[None, :, 1]
        o1, o2 = jnp.maximum(d1, 0.0), jnp.maximum(d2, 0.0)
        on, inv_on = _pos_sqrt(o1 * o1 + o2 * o2)
        out = on > 0
        sdf = on + jnp.minimum(jnp.maximum(d1, d2), 0.0)
        w_rad = jnp.where(out, o1 * inv_on, (d1 >= d2).astype(on.dtype))
        w_ax = jnp.where(out, o2 * inv_on, (d1 < d2).astype(on.dtype))
        gl = [w_rad * xl[0] * inv_rho, w_rad * xl[1] * inv_rho, w_ax * sg[2]]
    n = [R[..., j, 0] * gl[0] + R[..., j, 1] * gl[1] + R[..., j, 2] * gl[2] for j in range(3)]
    return sdf, n


def points_sdf_and_normals(obs: ObstacleSet, points: Float[Array, "m 3"]):
    """Signed distances ``(m, K)`` and unit normals ``(m, K, 3)`` from ``m`` points to every slot:
    :func:`obstacle_sdf_and_normals` for all points at once (equal to its ``vmap``, tested).

    Structure-of-arrays: every quantity is an ``(m, K)`` plane and the normal is the analytic
    gradient of the sdf (no autodiff pass, no ``(..., 3)`` minor axes), so under ``vmap`` the whole
    evaluation is a few fused element-wise loops; the IK needs every pair (its linearised
    constraints take the closest ones), the warehouse's 146 boxes included. Masked slots give
    :data:`~redman_jax.BIG_DISTANCE` and a zero normal.
    """
    points = jnp.asarray(points)
    X = [points[:, j, None] for j in range(3)]
    ds, ns = [], []
    for kind in ("spheres", "boxes", "cylinders"):
        fam = getattr(obs, kind)
        if fam.capacity == 0:
            continue
        sdf, n = _family_sdf_normals_planes(kind, fam, X)
        m = fam.mask[None, :]
        ds.append(jnp.where(m, sdf, BIG_DISTANCE))
        ns.append(jnp.stack([jnp.where(m, v, 0.0) for v in n], axis=-1))
    if not ds:  # a set without any slot: no columns
        return jnp.zeros((points.shape[0], 0), points.dtype), jnp.zeros((points.shape[0], 0, 3), points.dtype)
    return jnp.concatenate(ds, axis=1), jnp.concatenate(ns, axis=1)


def _family_sdf(s: Shapes, x, fn):
    xl = jnp.einsum("kji,kj->ki", s.R, x[None, :] - s.p)
    d = jax.vmap(fn)(xl, s.dims)
    return jnp.where(s.mask, d, BIG_DISTANCE)


def _all_sdf(obs: ObstacleSet, x):
    return jnp.concatenate([
        _family_sdf(obs.spheres, x, sphere_sdf),
        _family_sdf(obs.boxes, x, box_sdf),
        _family_sdf(obs.cylinders, x, cylinder_sdf),
    ])


def obstacle_field_potential(obs: ObstacleSet, x: Float[Array, "3"], a, D, form: str = "minus",
                             clamp=DISTANCE_CLAMP) -> Float[Array, ""]:
    """``sum_o V_o(max(sdf_o(x), clamp))`` over the active obstacles (3.8 corrected, 3.22).

    Differentiable: ``jax.grad`` of it equals :func:`obstacle_field_gradient` (custom JVP of the
    clamp, SPEC U3), also inside obstacles.
    """
    _check_form(form)
    s = _all_sdf(obs, x)
    a, D, clamp = (jnp.asarray(v, s.dtype) for v in (a, D, clamp))
    return jnp.sum(_clamped_radial(s, a, D, clamp, form))


def obstacle_field_gradient(obs: ObstacleSet, x: Float[Array, "3"], a, D, form: str = "minus",
                            clamp=DISTANCE_CLAMP) -> Float[Array, "3"]:
    """``sum_o grad V_o(x) = sum_o V_o'(max(sdf_o, clamp)) grad sdf_o(x)`` (3.9 corrected, E5, U3).

    Arguments:
        obs: padded :class:`~redman_jax.ObstacleSet` (masked slots contribute 0).
        x: point ``(3,)`` [m].
        a, D: amplitude and range (arrays; 0.05 / 0.75 for the null-space policies, 0.0005 / 0.5
            for the guidance field).
        form: ``"minus"`` (default, E4) or ``"plus"`` (3.8/3.9 literally).
        clamp: distance floor of the magnitude (1e-3 m).

    Returns:
        ``(3,)``, the gradient (the repulsive force is its negative). Inside an obstacle it is the
        clamped magnitude along the unclamped sdf gradient: finite and non-zero.
    """
    _check_form(form)
    # the structure-of-arrays pass of points_sdf_and_normals at one point: the same values as
    # obstacle_sdf_and_normals (tested), about 4x cheaper under vmap (8-DOF warehouse, 97 boxes,
    # batch 20: 17 against 69-90 us; it runs at every evaluation of the gradient-guided controller)
    s, n = points_sdf_and_normals(obs, x[None, :])
    a, D, clamp = (jnp.asarray(v, s.dtype) for v in (a, D, clamp))
    slope = _clamped_slope(s[0], a, D, clamp, form)
    return slope @ n[0]


def _clamped_slope(s, a, D, clamp, form):
    # V_o'(max(s, eps)) as a plain function of s: its forward derivative (the Hessian's radial
    # term) is V_o''(s) [s > eps], exactly the derivative of the custom JVP of the potential.
    return _radial_slope(s, a, D, clamp, form)


def obstacle_field_gradients(obs: ObstacleSet, xs: Float[Array, "N 3"], a, D, form: str = "minus",
                             clamp=DISTANCE_CLAMP) -> Float[Array, "N 3"]:
    """:func:`obstacle_field_gradient` at many points (e.g. the arm's POIs), ``(N, 3)``."""
    return jax.vmap(obstacle_field_gradient, in_axes=(None, 0, None, None, None, None))(
        obs, xs, a, D, form, clamp)


# ----------------------------------------------------------------------------------------------
# Goal attractor and virtual obstacles
# ----------------------------------------------------------------------------------------------


def goal_potential(x, goal_p):
    """``V_g = |x - x_g|^2`` (3.20; quadratic, E13)."""
    e = x - goal_p
    return e @ e


def goal_gradient(x, goal_p):
    """``g_g = 2 (x - x_g)`` (3.21)."""
    return 2.0 * (x - goal_p)


class FieldParams(eqx.Module):
    """Parameters of the end-effector guidance field (thesis 3.3.3; SPEC section 3).

    Arrays (so changing them never recompiles):

    * ``a`` = 0.0005, ``D`` = 0.5 m: obstacle amplitude and range;
    * ``d_v`` = 0.25 m: virtual-obstacle range (3.25);
    * ``amp`` = 0.1: virtual-obstacle amplitude factor of 3.27;
    * ``clamp`` = 1e-3 m: obstacle distance clamp (U3).

    Static: ``form`` (``"minus"``/``"plus"``, E4), ``vo_amp`` (``"ee"``: A from the evaluation point,
    ``"site"``: per-obstacle A, E15) and ``amp_exact`` (differentiate A, U4).
    """

    a: Float[Array, ""] = eqx.field(default=0.0005, converter=as_float)
    D: Float[Array, ""] = eqx.field(default=0.5, converter=as_float)
    d_v: Float[Array, ""] = eqx.field(default=0.25, converter=as_float)
    amp: Float[Array, ""] = eqx.field(default=0.1, converter=as_float)
    clamp: Float[Array, ""] = eqx.field(default=DISTANCE_CLAMP, converter=as_float)
    form: str = eqx.field(static=True, default="minus")
    vo_amp: str = eqx.field(static=True, default="ee")
    amp_exact: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        _check_form(self.form)
        if self.vo_amp not in _VO_AMPS:
            raise ValueError(f"FieldParams.vo_amp: expected one of {_VO_AMPS}, got {self.vo_amp!r}")
        check_positive("FieldParams.a", self.a)
        check_positive("FieldParams.D", self.D)
        check_positive("FieldParams.d_v", self.d_v)
        check_positive("FieldParams.amp", self.amp, allow_zero=True)
        check_positive("FieldParams.clamp", self.clamp)


def _amplitudes(x, goal_p, virtual_p, params: FieldParams):
    """Virtual-obstacle amplitudes ``A`` ``(B,)`` (3.27 with E15 / U4)."""
    if params.vo_amp == "site":
        e = virtual_p - goal_p
        return params.amp * jnp.sum(e * e, axis=-1)
    A = params.amp * goal_potential(x, goal_p)
    if not params.amp_exact:
        A = jax.lax.stop_gradient(A)
    return jnp.broadcast_to(A, virtual_p.shape[:-1])


def _virtual_shape(rho, d_v):
    """``phi(rho) = 1/(rho + 1) - 1/(d_v + 1)`` for ``rho <= d_v``, else 0 (3.25 without A)."""
    return jnp.where(rho <= d_v, 1.0 / (rho + 1.0) - 1.0 / (d_v + 1.0), 0.0)


def virtual_potential(x, goal_p, virtual_p, virtual_mask, params: FieldParams):
    """``sum_j V_v,j(x)`` over the active buffer slots (3.25, 3.27)."""
    d = x[None, :] - virtual_p
    rho = safe_norm(d)
    A = _amplitudes(x, goal_p, virtual_p, params)
    return jnp.sum(jnp.where(virtual_mask, A * _virtual_shape(rho, params.d_v), 0.0))


def virtual_gradient(x, goal_p, virtual_p, virtual_mask, params: FieldParams):
    """``sum_j grad V_v,j = -A_j (x - x_v,j) / (rho_j (rho_j + 1)^2)`` (3.26 corrected, E14).

    ``rho`` is floored at :data:`RHO_FLOOR` where it divides. With ``amp_exact`` (and
    ``vo_amp="ee"``) the term ``grad A * phi(rho) = 2 amp (x - x_g) phi(rho)`` is added.
    """
    d = x[None, :] - virtual_p
    rho = safe_norm(d)
    A = _amplitudes(x, goal_p, virtual_p, params)
    active = virtual_mask & (rho <= params.d_v)
    coef = -A / (jnp.maximum(rho, RHO_FLOOR) * (rho + 1.0) ** 2)
    g = jnp.sum(jnp.where(active[:, None], coef[:, None] * d, 0.0), axis=0)
    if params.amp_exact and params.vo_amp == "ee":
        phi = jnp.sum(jnp.where(virtual_mask, _virtual_shape(rho, params.d_v), 0.0))
        g = g + 2.0 * params.amp * (x - goal_p) * phi
    return g


# ----------------------------------------------------------------------------------------------
# Total field (3.22-3.24) and guidance (3.18-3.19)
# ----------------------------------------------------------------------------------------------


def total_potential(x: Float[Array, "3"], goal_p: Float[Array, "3"], obs: ObstacleSet,
                    virtual_p: Float[Array, "B 3"], virtual_mask: Bool[Array, " B"],
                    params: FieldParams) -> Float[Array, ""]:
    """``V = V_g + sum V_o + sum V_v`` (3.22). ``jax.grad`` of it equals :func:`total_gradient`
    (with A held constant, U4, unless ``amp_exact``)."""
    return (goal_potential(x, goal_p)
            + obstacle_field_potential(obs, x, params.a, params.D, params.form, params.clamp)
            + virtual_potential(x, goal_p, virtual_p, virtual_mask, params))


def total_gradient(x: Float[Array, "3"], goal_p: Float[Array, "3"], obs: ObstacleSet,
                   virtual_p: Float[Array, "B 3"], virtual_mask: Bool[Array, " B"],
                   params: FieldParams) -> Float[Array, "3"]:
    """``g = g_g + sum g_o + sum g_v`` (3.23), analytic, with the clamp semantics of SPEC U3."""
    return (goal_gradient(x, goal_p)
            + obstacle_field_gradient(obs, x, params.a, params.D, params.form, params.clamp)
            + virtual_gradient(x, goal_p, virtual_p, virtual_mask, params))


def total_hessian(x: Float[Array, "3"], goal_p: Float[Array, "3"], obs: ObstacleSet,
                  virtual_p: Float[Array, "B 3"], virtual_mask: Bool[Array, " B"],
                  params: FieldParams) -> Float[Array, "3 3"]:
    """``H = dg/dx`` (used in 3.24), the forward Jacobian of :func:`total_gradient`.

    Taking it from the gradient (not from a clamped potential) keeps the SPEC U3 semantics: inside
    an obstacle the radial term vanishes and the curvature term ``V_o'(eps) grad^2 sdf`` remains.
    With A held constant (U4) this is the Hessian of a constant-A potential (symmetric).
    """
    return jax.jacfwd(total_gradient)(x, goal_p, obs, virtual_p, virtual_mask, params)


def guidance_velocity(x: Float[Array, "3"], goal_p: Float[Array, "3"], obs: ObstacleSet,
                      virtual_p: Float[Array, "B 3"], virtual_mask: Bool[Array, " B"],
                      params: FieldParams, a=0.5, b=0.1) -> Float[Array, "3"]:
    """Guidance velocity ``xdot_g = -a tanh(|x - x_g| / b) g / (|g| + 1e-9)`` (3.18-3.19, E13).

    ``a`` [m/s] is the cruise speed and ``b`` [m] the slow-down distance near the goal; the
    direction is steepest descent of the total field, the magnitude ``a tanh(|x - x_g|/b)``.
    """
    g = total_gradient(x, goal_p, obs, virtual_p, virtual_mask, params)
    mag = a * jnp.tanh(safe_norm(x - goal_p) / b)
    return -mag * g / (safe_norm(g) + 1e-9)


_PT = (0, None, None, None, None, None)


def total_potential_points(xs: Float[Array, "N 3"], goal_p, obs, virtual_p, virtual_mask,
                           params: FieldParams) -> Float[Array, " N"]:
    """:func:`total_potential` at many points (e.g. a slice grid for Figs. 3.4 / 4.9)."""
    return jax.vmap(total_potential, in_axes=_PT)(xs, goal_p, obs, virtual_p, virtual_mask, params)


def total_gradient_points(xs: Float[Array, "N 3"], goal_p, obs, virtual_p, virtual_mask,
                          params: FieldParams) -> Float[Array, "N 3"]:
    """:func:`total_gradient` at many points."""
    return jax.vmap(total_gradient, in_axes=_PT)(xs, goal_p, obs, virtual_p, virtual_mask, params)


def total_hessian_points(xs: Float[Array, "N 3"], goal_p, obs, virtual_p, virtual_mask,
                         params: FieldParams) -> Float[Array, "N 3 3"]:
    """:func:`total_hessian` at many points."""
    return jax.vmap(total_hessian, in_axes=_PT)(xs, goal_p, obs, virtual_p, virtual_mask, params)


def guidance_velocity_points(xs: Float[Array, "N 3"], goal_p, obs, virtual_p, virtual_mask,
                             params: FieldParams, a=0.5, b=0.1) -> Float[Array, "N 3"]:
    """:func:`guidance_velocity` at many points."""
    return jax.vmap(guidance_velocity, in_axes=_PT + (None, None))(
        xs, goal_p, obs, virtual_p, virtual_mask, params, a, b)


@eqx.filter_jit
def total_potential_batch(xs: Float[Array, "S N 3"], goal_p: Float[Array, "S 3"], obs: ObstacleSet,
                          virtual_p: Float[Array, "S B 3"], virtual_mask: Bool[Array, "S B"],
                          params: FieldParams) -> Float[Array, "S N"]:
    """:func:`total_potential_points` batched over ``S`` scenarios (stacked obstacle sets)."""
    return jax.vmap(total_potential_points, in_axes=(0, 0, 0, 0, 0, None))(
        xs, goal_p, obs, virtual_p, virtual_mask, params)


@eqx.filter_jit
def total_gradient_batch(xs: Float[Array, "S N 3"], goal_p: Float[Array, "S 3"], obs: ObstacleSet,
                         virtual_p: Float[Array, "S B 3"], virtual_mask: Bool[Array, "S B"],
                         params: FieldParams) -> Float[Array, "S N 3"]:
    """:func:`total_gradient_points` batched over ``S`` scenarios (stacked obstacle sets)."""
    return jax.vmap(total_gradient_points, in_axes=(0, 0, 0, 0, 0, None))(
        xs, goal_p, obs, virtual_p, virtual_mask, params)
