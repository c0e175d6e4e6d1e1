"""A small dense convex QP solver that jits, vmaps and differentiates (SPEC section 8, U7).

Problem (``n`` variables, ``m`` general rows; ``n <= ~10``, ``m <= ~30``)::

    minimise    1/2 x^T P x + c^T x
    subject to  l <= A x <= h           (general rows; entries of l / h may be -inf / +inf)
                lb <= x <= ub           (box; entries may be infinite)

with ``P`` symmetric positive definite (the IK's ``J_s^T J_s + w I``, ``w = 1e-4``).

Method: a primal-dual interior-point method with Mehrotra's predictor-corrector. Every finite
bound is a one-sided row ``G_i x + s_i = g_i``, ``s_i >= 0``, with dual ``z_i >= 0``; rows with an
infinite bound are masked out (``s = 1``, ``z = 0``, never updated), so shapes are static. One
iteration factorises the reduced KKT matrix ``P + G^T diag(z / s) G`` (``n x n``, Cholesky) once
and solves it twice (predictor and corrector). The box rows enter that matrix on its diagonal and
the general rows as ``A^T diag(.) A``, so the box never costs a matrix product.

Why not OSQP-style ADMM (the SPEC's first proposal): ``P`` has eigenvalues from ``w = 1e-4`` (the
null space of ``J_s``) to ``~4``; with ``rho = 1`` ADMM contracts by about ``1 - w / rho`` per
iteration along the null space (``(1 - 1e-4)^200 = 0.98``), so 200 iterations barely reduce the
error there. The interior-point method reaches ``1e-10`` in 10-20
iterations independently of that conditioning. The loop is a ``lax.while_loop`` that stops when
the residuals meet the tolerances (or at ``max_iter``); under ``vmap`` it runs until every member
of the batch has converged.

Differentiation is implicit, at the returned solution (the iterations are never unrolled):
differentiating ``P x + c + G^T z = 0``, ``G x + s = g`` and ``s_i z_i = mu`` gives::

    [ P      G^T ] [dx]   [ -(dP x + dc + dG^T z) ]
    [ Z G    -S  ] [dz] = [  Z (dg - dG x)         ]

At convergence (``mu -> 0``) an active row (``s -> 0``) gives ``G_i dx = dg_i - dG_i x`` and an
inactive one (``z -> 0``) gives ``dz_i = 0``: the derivative of the equality-constrained QP on
the active set, which is the exact derivative wherever strict complementarity holds. The system is
solved by LU (it is well scaled, unlike the reduced form), inside a ``jax.custom_jvp``, so forward
and reverse mode both work.

Failure is a value: :class:`QPSolution` carries the primal and dual residuals of the original
problem, the complementarity gap, the iteration count and a ``converged`` flag. An infeasible
problem returns finite numbers and ``converged = False``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._math import as_float_or_none, check_count, check_finite, check_positive, concrete

__all__ = ["QPSettings", "QPSolution", "solve_qp", "solve_box_qp", "qp_residuals"]

_BIG = 1e20  # bounds beyond this are treated as infinite


class QPSettings(eqx.Module):
    """Solver settings. ``max_iter`` is static (it sizes nothing, but bounds the loop); the
    tolerances are arrays (``None``: chosen from the dtype, ``1e-9`` in float64, ``1e-6`` in
    float32: at 1e-4 the IK's QPs stopped with the null-space part of ``u`` far from optimal,
    0.38 rad/s on a 7-DOF warehouse sample, and float32 IK drifted 0.88 m off where float64's
    is valid).

    Convergence when, in the infinity norm,

    * primal: ``|G x + s - g| <= eps_abs + eps_rel max(|G x|, |g|)`` (masked rows excluded);
    * dual:   ``|P x + c + G^T z| <= eps_abs + eps_rel max(|P x|, |G^T z|, |c|)``;
    * gap:    ``s^T z / m <= eps_abs + eps_rel |1/2 x^T P x + c^T x|``.
    """

    # arrays (as_float): a Python float was a static leaf, and every new value recompiled the QP
    # and the whole IK around it
    eps_abs: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    eps_rel: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    max_iter: int = eqx.field(static=True, default=40)
    step_fraction: float = eqx.field(static=True, default=0.99)
    polish: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        for name in ("eps_abs", "eps_rel"):  # None: the default
            if getattr(self, name) is not None:
                check_positive(f"QPSettings.{name}", getattr(self, name), allow_zero=True)
        check_count("QPSettings.max_iter", self.max_iter, 1)
        if not 0 < self.step_fraction < 1:
            raise ValueError(f"QPSettings.step_fraction: expected a value in (0, 1), got {self.step_fraction!r}")


class QPSolution(eqx.Module):
    """Result of :func:`solve_qp`.

    * ``x`` ``(n,)``: the minimiser.
    * ``y`` ``(m,)``: duals of the general rows, OSQP convention (``y_i > 0``: upper bound active,
      ``< 0``: lower bound active); ``y_box`` ``(n,)`` likewise for the box, so that
      ``P x + c + A^T y + y_box = 0``.
    * ``primal_residual``: largest violation of ``l <= A x <= h`` and ``lb <= x <= ub``.
    * ``dual_residual``: ``|P x + c + A^T y + y_box|_inf``.
    * ``gap``: mean complementarity ``s^T z / m_active``.
    * ``iterations``: interior-point iterations used; ``converged``: the tolerances were met.
    """

    x: Float[Array, " n"]
    y: Float[Array, " m"]
    y_box: Float[Array, " n"]
    primal_residual: Float[Array, ""]
    dual_residual: Float[Array, ""]
    gap: Float[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


# --------------------------------------------------------------------------------------------
# Stacked one-sided rows: G = [A; -A; I; -I], g = [h; -l; ub; -lb] (4 blocks, m + m + n + n rows).


class _Rows(eqx.Module):
    A: Float[Array, "m n"]
    g: Float[Array, " M"]  # M = 2m + 2n, masked entries replaced by 1
    mask: Bool[Array, " M"]

    def G(self, x):
        Ax = self.A @ x
        return jnp.concatenate([Ax, -Ax, x, -x]) * self.mask

    def GT(self, z):
        m, n = self.A.shape
        z = z * self.mask
        return self.A.T @ (z[:m] - z[m:2 * m]) + z[2 * m:2 * m + n] - z[2 * m + n:]

    def GTDG(self, d):
        """``G^T diag(d) G`` using the structure (box rows on the diagonal)."""
        m, n = self.A.shape
        d = d * self.mask
        dg = d[:m] + d[m:2 * m]
        return (self.A.T * dg) @ self.A + jnp.diag(d[2 * m:2 * m + n] + d[2 * m + n:])

    def dense(self):
        m, n = self.A.shape
        eye = jnp.eye(n, dtype=self.A.dtype)
        return jnp.concatenate([self.A, -self.A, eye, -eye]) * self.mask[:, None]


def _make_rows(A, l, h, lb, ub) -> _Rows:
    raw = jnp.concatenate([h, -l, ub, -lb])
    mask = jnp.isfinite(raw) & (jnp.abs(raw) < _BIG)
    g = jnp.where(mask, raw, 1.0)
    return _Rows(A=A, g=g, mask=mask)


def _default_tols(dtype, settings: QPSettings):
    f64 = jnp.dtype(dtype) == jnp.float64
    eps_abs = settings.eps_abs if settings.eps_abs is not None else (1e-9 if f64 else 1e-6)
    eps_rel = settings.eps_rel if settings.eps_rel is not None else (1e-9 if f64 else 1e-6)
    return jnp.asarray(eps_abs, dtype), jnp.asarray(eps_rel, dtype)


class _State(eqx.Module):
    x: Array
    s: Array
    z: Array
    it: Array
    done: Array


def _max_step(v, dv, mask):
    """Largest ``a in [0, 1]`` with ``v + a dv >= 0`` on the masked rows."""
    neg = (dv < 0) & mask
    ratio = jnp.where(neg, -v / jnp.where(neg, dv, -1.0), jnp.inf)
    return jnp.minimum(1.0, jnp.min(ratio, initial=jnp.inf))


def _criteria(P, c, rows: _Rows, x, s, z, eps_abs, eps_rel):
    Gx = rows.G(x)
    mask = rows.mask
    r_p = jnp.where(mask, Gx + s - rows.g, 0.0)
    Px = P @ x
    GTz = rows.GT(z)
    r_d = Px + c + GTz
    n_act = jnp.maximum(jnp.sum(mask), 1)
    mu = jnp.sum(jnp.where(mask, s * z, 0.0)) / n_act
    inf = lambda v: jnp.max(jnp.abs(v), initial=0.0)
    ok_p = inf(r_p) <= eps_abs + eps_rel * jnp.maximum(inf(jnp.where(mask, Gx, 0.0)),
                                                        inf(jnp.where(mask, rows.g, 0.0)))
    ok_d = inf(r_d) <= eps_abs + eps_rel * jnp.maximum(jnp.maximum(inf(Px), inf(GTz)), inf(c))
    obj = 0.5 * x @ Px + c @ x
    ok_g = mu <= eps_abs + eps_rel * jnp.abs(obj)
    return r_p, r_d, mu, ok_p & ok_d & ok_g


def _ipm(P, c, rows: _Rows, settings: QPSettings, active=None):
    """Mehrotra predictor-corrector; returns the final ``(x, s, z, iterations, converged)``.
    ``active`` False: no iteration (the initial point)."""
    n = P.shape[0]
    dtype = P.dtype
    mask = rows.mask
    eps_abs, eps_rel = _default_tols(dtype, settings)
    tiny = jnp.asarray(jnp.finfo(dtype).tiny ** 0.5, dtype)
    reg = jnp.asarray(jnp.finfo(dtype).eps, dtype) * (1.0 + jnp.max(jnp.abs(jnp.diag(P))))
    eye = jnp.eye(n, dtype=dtype)
    n_act = jnp.maximum(jnp.sum(mask), 1)
    frac = settings.step_fraction

    # Initial point (CVXOPT's): x minimises 1/2 x'Px + c'x + 1/2 |Gx - g|^2, s = g - Gx, z = -s,
    # both shifted to be positive.
    H0 = P + rows.GTDG(jnp.ones_like(rows.g)) + reg * eye
    x0 = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(H0), -c + rows.GT(rows.g))
    s0 = rows.g - rows.G(x0)
    z0 = -s0
    mins = jnp.min(jnp.where(mask, s0, jnp.inf), initial=jnp.inf)
    minz = jnp.min(jnp.where(mask, z0, jnp.inf), initial=jnp.inf)
    s0 = jnp.where(mins < 1.0, s0 + (1.0 - mins), s0)
    z0 = jnp.where(minz < 1.0, z0 + (1.0 - minz), z0)
    s0 = jnp.where(mask, s0, 1.0)
    z0 = jnp.where(mask, z0, 0.0)

    def solve_newton(chol, D, r_d, r_p, r_c, s):
        # dz = D (G dx + r_p) - r_c / s ;  (P + G'DG) dx = -r_d - G'(D r_p - r_c / s)
        w = jnp.where(mask, D * r_p - r_c / s, 0.0)
        dx = jax.scipy.linalg.cho_solve(chol, -r_d - rows.GT(w))
        Gdx = rows.G(dx)
        dz = jnp.where(mask, D * (Gdx + r_p) - r_c / s, 0.0)
        ds = jnp.where(mask, -r_p - Gdx, 0.0)
        return dx, ds, dz

    def body(st: _State) -> _State:
        x, s, z = st.x, st.s, st.z
        r_p, r_d, mu, _ = _criteria(P, c, rows, x, s, z, eps_abs, eps_rel)
        D = jnp.where(mask, z / s, 0.0)
        H = P + rows.GTDG(D) + reg * eye
        chol = jax.scipy.linalg.cho_factor(H)
        # predictor (affine scaling)
        r_c = jnp.where(mask, s * z, 0.0)
        dx_a, ds_a, dz_a = solve_newton(chol, D, r_d, r_p, r_c, s)
        a_aff = jnp.minimum(_max_step(s, ds_a, mask), _max_step(z, dz_a, mask))
        mu_aff = jnp.sum(jnp.where(mask, (s + a_aff * ds_a) * (z + a_aff * dz_a), 0.0)) / n_act
        sigma = jnp.clip(mu_aff / jnp.maximum(mu, tiny), 0.0, 1.0) ** 3
        # corrector (centring + second-order term)
        r_c = jnp.where(mask, s * z + ds_a * dz_a - sigma * mu, 0.0)
        dx, ds, dz = solve_newton(chol, D, r_d, r_p, r_c, s)
        a = frac * jnp.minimum(_max_step(s, ds, mask), _max_step(z, dz, mask))
        a = jnp.minimum(a, 1.0)
        xn = x + a * dx
        sn = jnp.where(mask, jnp.maximum(s + a * ds, tiny), 1.0)
        zn = jnp.where(mask, jnp.maximum(z + a * dz, tiny), 0.0)
        finite = jnp.all(jnp.isfinite(xn)) & jnp.all(jnp.isfinite(sn)) & jnp.all(jnp.isfinite(zn))
        xn = jnp.where(finite, xn, x)
        sn = jnp.where(finite, sn, s)
        zn = jnp.where(finite, zn, z)
        _, _, _, ok = _criteria(P, c, rows, xn, sn, zn, eps_abs, eps_rel)
        return _State(x=xn, s=sn, z=zn, it=st.it + 1, done=ok | ~finite)

    def cond(st: _State):
        return (~st.done) & (st.it < settings.max_iter)

    _, _, _, ok0 = _criteria(P, c, rows, x0, s0, z0, eps_abs, eps_rel)
    done0 = ok0 if active is None else ok0 | ~jnp.asarray(active, bool)
    st = _State(x=x0, s=s0, z=z0, it=jnp.asarray(0, jnp.int32), done=done0)
    st = jax.lax.while_loop(cond, body, st)
    _, _, _, ok = _criteria(P, c, rows, st.x, st.s, st.z, eps_abs, eps_rel)
    return st.x, st.s, st.z, st.it, ok


# --------------------------------------------------------------------------------------------
# Active-set KKT system: polishing and implicit differentiation.
#
# With the active set read off the interior-point iterate (row i active when z_i > s_i), the
# solution solves a square linear system in (x, y), y the signed duals of the general rows:
#   free variable j:    (P x + c + A^T y)_j = 0        fixed variable j (box active): x_j = v_j
#   active row i:       A_i x = b_i                     inactive row i:                y_i = 0
# (v_j, b_i: the active bound). A pair of equal bounds (l_i = h_i, lb_j = ub_j) is one equation.
# Dependent active rows are regularised by -delta on their diagonal.


def _active_set(rows: _Rows, s, z):
    """Row ``i`` is active when ``z_i / z_scale > s_i / max(1, |g_i|)``: ``s > z`` on the central
    path (``s_i z_i = mu``), made scale-aware so that duals of size ``|c|`` do not make nearly
    active rows with small multipliers look active (and the other way round). The slack is scaled
    by its own row's bound, so that one far-off bound does not make a nearly active row look active.

    Of a pair of distinct bounds (``l_i < h_i``, ``lb_j < ub_j``) at most one side is active: where
    both pass the test (a narrow pair), the side with the larger dual. Both sides stay active only
    for equal bounds (an equality)."""
    m = rows.A.shape[0]
    n = rows.A.shape[1]
    z_scale = jnp.maximum(1.0, jnp.max(jnp.where(rows.mask, z, 0.0), initial=0.0))
    s_scale = jnp.maximum(1.0, jnp.abs(rows.g))
    act = rows.mask & (z / z_scale > s / s_scale)

    def one_side(au, al, zu, zl, gu, gl):
        equal = gu + gl == 0.0  # g = [h; -l] or [ub; -lb]: equal bounds
        both = au & al & ~equal
        return au & ~(both & (zl > zu)), al & ~(both & (zu >= zl))

    act_u, act_l = one_side(act[:m], act[m:2 * m], z[:m], z[m:2 * m], rows.g[:m], rows.g[m:2 * m])
    fix_u, fix_l = one_side(act[2 * m:2 * m + n], act[2 * m + n:], z[2 * m:2 * m + n], z[2 * m + n:],
                            rows.g[2 * m:2 * m + n], rows.g[2 * m + n:])
    return act_u, act_l, fix_u, fix_l


def _kkt_matrix(P, A, act_u, act_l, fix_u, fix_l):
    n, m = P.shape[0], A.shape[0]
    dtype = P.dtype
    fixed = fix_u | fix_l
    active = act_u | act_l
    eye_n, eye_m = jnp.eye(n, dtype=dtype), jnp.eye(m, dtype=dtype)
    delta = jnp.asarray(jnp.finfo(dtype).eps, dtype) * (1.0 + jnp.max(jnp.abs(jnp.diag(P))))
    top = jnp.where(fixed[:, None], jnp.concatenate([eye_n, jnp.zeros((n, m), dtype)], 1),
                    jnp.concatenate([P, A.T], 1))
    bottom = jnp.where(active[:, None], jnp.concatenate([A, -delta * eye_m], 1),
                       jnp.concatenate([jnp.zeros((m, n), dtype), eye_m], 1))
    return jnp.concatenate([top, bottom], 0)


def _kkt_rhs(c, l, h, lb, ub, act_u, act_l, fix_u, fix_l):
    v = jnp.where(fix_u, ub, jnp.where(fix_l, lb, 0.0))
    b = jnp.where(act_u, h, jnp.where(act_l, l, 0.0))
    top = jnp.where(fix_u | fix_l, v, -c)
    return jnp.concatenate([top, jnp.where(act_u | act_l, b, 0.0)])


def _box_dual(P, c, A, x, y, fix_u, fix_l):
    return jnp.where(fix_u | fix_l, -(P @ x + c + A.T @ y), 0.0)


@jax.custom_jvp
def _implicit(P, c, A, l, h, lb, ub, x, y, act):
    return x, y


@_implicit.defjvp
def _implicit_jvp(primals, tangents):
    P, c, A, l, h, lb, ub, x, y, act = primals
    dP, dc, dA, dl, dh, dlb, dub = tangents[:7]
    act_u, act_l, fix_u, fix_l = (a > 0.5 for a in act)
    fixed = fix_u | fix_l
    K = _kkt_matrix(P, A, act_u, act_l, fix_u, fix_l)
    dv = jnp.where(fix_u, dub, jnp.where(fix_l, dlb, 0.0))
    db = jnp.where(act_u, dh, jnp.where(act_l, dl, 0.0))
    top = jnp.where(fixed, dv, -(dP @ x + dc + dA.T @ y))
    bottom = jnp.where(act_u | act_l, db - dA @ x, 0.0)
    sol = jnp.linalg.solve(K, jnp.concatenate([top, bottom]))
    n = x.shape[0]
    return (x, y), (sol[:n], sol[n:])


# --------------------------------------------------------------------------------------------
# Public API


def _check_shapes(P, c, A, l, h, lb, ub):
    n = c.shape[-1]
    if P.shape[-2:] != (n, n):
        raise ValueError(f"solve_qp: P must be ({n}, {n}) to match c, got {P.shape}")
    if A.shape[-1] != n:
        raise ValueError(f"solve_qp: A must have {n} columns, got shape {A.shape}")
    m = A.shape[-2]
    for name, v, k in (("l", l, m), ("h", h, m), ("lb", lb, n), ("ub", ub, n)):
        if v.shape[-1] != k:
            raise ValueError(f"solve_qp: {name} must have length {k}, got shape {v.shape}")


def qp_residuals(P, c, A, l, h, lb, ub, x, y, y_box):
    """Primal and dual residuals (infinity norms) of a candidate ``(x, y, y_box)``."""
    Ax = A @ x
    viol = jnp.concatenate([
        jnp.maximum(Ax - h, 0.0), jnp.maximum(l - Ax, 0.0),
        jnp.maximum(x - ub, 0.0), jnp.maximum(lb - x, 0.0),
    ])
    primal = jnp.max(viol, initial=0.0)
    dual = jnp.max(jnp.abs(P @ x + c + A.T @ y + y_box), initial=0.0)
    return primal, dual


def _check_values(P, c, A, l, h, lb, ub):
    """Where concrete (an eager call): ``P``, ``c``, ``A`` finite, no bound NaN (infinite bounds
    are allowed: no bound)."""
    for name, v in (("P", P), ("c", c), ("A", A)):
        if v is not None:
            check_finite(f"solve_qp: {name}", v)
    for name, v in (("l", l), ("h", h), ("lb", lb), ("ub", ub)):
        a = None if v is None else concrete(v)
        if a is not None and a.dtype.kind in "fc" and np.any(np.isnan(a)):
            raise ValueError(f"solve_qp: {name}: NaN bound (use -inf / inf for no bound), got {a}")


def solve_qp(P, c, A=None, l=None, h=None, lb=None, ub=None,
             settings: QPSettings = QPSettings(), *, active=None) -> QPSolution:
    """Solve ``min 1/2 x'Px + c'x  s.t.  l <= A x <= h,  lb <= x <= ub`` (see the module docstring).

    **Arguments:** ``P`` ``(n, n)`` symmetric positive definite; ``c`` ``(n,)``; ``A`` ``(m, n)``
    (``None``: no general rows); ``l``, ``h`` ``(m,)`` and ``lb``, ``ub`` ``(n,)``, infinite entries
    allowed (``None``: unbounded). ``settings``: :class:`QPSettings`. ``active`` (a boolean array,
    ``None``: true): where false the interior-point loop takes no iteration and the solution is
    its initial point (``converged`` false unless that is optimal). Under ``vmap`` the loop runs
    until its last member stops, so a caller that no longer needs a member's solution (the IK of
    a candidate already known invalid) takes it out of the count.

    **Returns:** a :class:`QPSolution`. Differentiable in every array argument (implicit
    differentiation at the solution; see the module docstring), jit- and vmap-able.

    **Raises:** ``ValueError`` for inconsistent shapes (at trace time) and, for concrete
    arguments (an eager call), for a NaN or infinity in ``P``, ``c`` or ``A`` or a NaN bound, naming
    the argument. Traced (inside the caller's ``jit`` / ``vmap``), a NaN bound is never read as "no
    bound": the solution has ``converged = False``.

    Jitted (``equinox.filter_jit``): called eagerly in a Python loop it compiles once per shape
    and ``settings.max_iter`` (its ``lax.while_loop`` body is a new closure at every trace, which
    compiled anew on every call and exhausted LLVM's memory after some hundred calls).
    """
    _check_values(P, c, A, l, h, lb, ub)
    return _solve_qp(P, c, A, l, h, lb, ub, settings, active)


@eqx.filter_jit
def _solve_qp(P, c, A, l, h, lb, ub, settings: QPSettings, active=None) -> QPSolution:
    P = jnp.asarray(P)
    c = jnp.asarray(c)
    dtype = jnp.result_type(P.dtype, c.dtype, jnp.float32)
    P, c = P.astype(dtype), c.astype(dtype)
    n = c.shape[-1]
    if A is None:
        A = jnp.zeros((0, n), dtype)
    A = jnp.asarray(A, dtype)
    m = A.shape[-2]
    inf = jnp.asarray(jnp.inf, dtype)
    l = jnp.full((m,), -inf) if l is None else jnp.asarray(l, dtype)
    h = jnp.full((m,), inf) if h is None else jnp.asarray(h, dtype)
    lb = jnp.full((n,), -inf) if lb is None else jnp.asarray(lb, dtype)
    ub = jnp.full((n,), inf) if ub is None else jnp.asarray(ub, dtype)
    _check_shapes(P, c, A, l, h, lb, ub)
    if P.ndim != 2:
        raise ValueError("solve_qp: solves one problem; vmap it for a batch")
    P = 0.5 * (P + P.T)
    rows = _make_rows(A, l, h, lb, ub)
    sg = jax.lax.stop_gradient
    Ps, cs, As, ls, hs, lbs, ubs = (sg(v) for v in (P, c, A, l, h, lb, ub))
    x_ip, s, z, it, ok_ip = _ipm(Ps, cs, _Rows(A=As, g=sg(rows.g), mask=rows.mask), settings, active)
    act_u, act_l, fix_u, fix_l = _active_set(rows, s, z)
    zm = z * rows.mask
    y_ip = zm[:m] - zm[m:2 * m]
    yb_ip = zm[2 * m:2 * m + n] - zm[2 * m + n:]
    res_ip = qp_residuals(Ps, cs, As, ls, hs, lbs, ubs, x_ip, y_ip, yb_ip)
    x, y, yb, (primal, dual) = x_ip, y_ip, yb_ip, res_ip
    if settings.polish:
        # One active-set KKT solve (as OSQP's polish): exact where the active set is right.
        K = _kkt_matrix(Ps, As, act_u, act_l, fix_u, fix_l)
        sol = jnp.linalg.solve(K, _kkt_rhs(cs, ls, hs, lbs, ubs, act_u, act_l, fix_u, fix_l))
        x_po, y_po = sol[:n], sol[n:]
        yb_po = _box_dual(Ps, cs, As, x_po, y_po, fix_u, fix_l)
        res_po = qp_residuals(Ps, cs, As, ls, hs, lbs, ubs, x_po, y_po, yb_po)
        eps_abs, _ = _default_tols(dtype, settings)
        # signs: an upper-active row needs y >= 0, a lower-active one y <= 0 (equal bounds: free)
        sign_ok = (jnp.all(jnp.where(act_u & ~act_l, y_po >= -eps_abs, True))
                   & jnp.all(jnp.where(act_l & ~act_u, y_po <= eps_abs, True))
                   & jnp.all(jnp.where(fix_u & ~fix_l, yb_po >= -eps_abs, True))
                   & jnp.all(jnp.where(fix_l & ~fix_u, yb_po <= eps_abs, True)))
        better = (jnp.maximum(res_po[0], res_po[1]) <= jnp.maximum(jnp.maximum(res_ip[0], res_ip[1]), eps_abs))
        use = sign_ok & better & jnp.all(jnp.isfinite(sol))
        x = jnp.where(use, x_po, x_ip)
        y = jnp.where(use, y_po, y_ip)
        yb = jnp.where(use, yb_po, yb_ip)
        primal = jnp.where(use, res_po[0], res_ip[0])
        dual = jnp.where(use, res_po[1], res_ip[1])
    act = tuple(a.astype(dtype) for a in (act_u, act_l, fix_u, fix_l))
    x, y = _implicit(P, c, A, l, h, lb, ub, x, y, act)
    # the box duals that go with (x, y): the polish's active set where it was taken, else the
    # interior point's own (rebuilt from the polish's guess they broke P x + c + A^T y + y_box = 0
    # by up to 0.56 while dual_residual reported 3.6e-3)
    y_box = jnp.where(use, _box_dual(P, c, A, x, y, fix_u, fix_l), yb) if settings.polish else yb
    gap = jnp.sum(jnp.where(rows.mask, s * z, 0.0)) / jnp.maximum(jnp.sum(rows.mask), 1)
    eps_abs, eps_rel = _default_tols(dtype, settings)
    # An accepted polish is a KKT point (active rows met exactly with duals of the right sign,
    # inactive rows feasible with zero dual), so its residuals alone prove optimality; an
    # interior-point iterate also needs its complementarity gap (ok_ip).
    polished_ok = (use & (primal <= eps_abs) & (dual <= eps_abs)) if settings.polish else False
    # a NaN bound is masked out like an infinite one by _make_rows; it must not pass as "no bound"
    no_nan_bound = ~jnp.any(jnp.isnan(jnp.concatenate([l, h, lb, ub])))
    converged = (ok_ip | polished_ok) & no_nan_bound
    return QPSolution(x=x, y=y, y_box=y_box, primal_residual=primal, dual_residual=dual, gap=gap,
                      iterations=it, converged=converged)


def solve_box_qp(P, c, lb, ub, A=None, l=None, h=None,
                 settings: QPSettings = QPSettings()) -> QPSolution:
    """:func:`solve_qp` with the box first (the name in docs/CONTRACTS.md)."""
    return solve_qp(P, c, A, l, h, lb, ub, settings)
