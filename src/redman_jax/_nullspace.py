"""Null-space projection and null-space policies (thesis 2.5-2.6, 3.3.4-3.3.5; SPEC section 7).

Projection
----------
* **Adaptive damped pseudo-inverse** (3.29, 3.32): ``J# = J^T (J J^T + lam^2 I)^-1`` with
  ``lam = max(ratio * sigma_min(J), floor)``, ``ratio = 0.1``, ``floor = 0.01`` (E31: implemented
  literally). ``sigma_min`` is *not* taken from a full SVD: ``sigma_min^2`` is the smallest eigenvalue
  of the small Gram matrix ``G = J J^T`` (``k x k``, ``k <= 6``), found by Laguerre's iteration on
  ``det(G - mu I)`` from ``mu = 0`` (all roots real: monotone, cubically convergent, linearly near
  a double root; eight steps of a scalar-unrolled ``k x k`` Cholesky inverse). It is about 10x
  cheaper than ``eigvalsh`` under ``vmap`` on CPU (``benchmarks/bench_controllers.py``) and has an
  exact derivative ``d mu = v^T dG v`` (``custom_jvp``).
* **Row masks.** Orientation control switches per sample (3.13-3.14) without changing shapes:
  the inactive rows of the 6-row task are zeroed and excluded from ``sigma_min`` (their Gram block is
  shifted far above the spectrum). ``J^T (J J^T + lam^2 I)^-1`` is block diagonal in active/inactive
  rows, so the zeroed rows contribute exactly nothing: the result equals the explicit 3-row damped
  pseudo-inverse (tested).
* **Orthogonal projector** (2.32, 3.30): ``N = I - J# J``; null-space term ``alpha N h`` (alpha 0.1).
* **Oblique (weighted) projectors** (2.36 corrected, E11): torque level
  ``P_tau = I - J^T (J W^-1 J^T)^-1 J W^-1`` (``P_tau J^T = 0``, ``J W^-1 P_tau = 0``) and
  velocity/acceleration level ``P_v = I - W^-1 J^T (J W^-1 J^T)^-1 J`` (``J P_v = 0``); with
  ``W = M`` the torque form is the dynamically consistent projector. ``P_tau`` is not a valid
  acceleration-level projector (``J P_tau != 0``).
* **Task priority** (2.5.3): ``q_d = J1# x1 + (J2 N1)# (x2 - J2 J1# x1)``.

Leak of the damped projector (tested): with ``J = U S V^T`` (``k`` singular values ``s_i``),
``J N = J - J J# J = U diag(s_i - s_i^3 / (s_i^2 + lam^2)) V^T = U diag(s_i lam^2 / (s_i^2 + lam^2)) V^T``,
so ``|J N h| <= max_i s_i lam^2 / (s_i^2 + lam^2) |h| <= lam / 2 |h|`` (the maximum over ``s`` of
``s lam^2 / (s^2 + lam^2)`` is ``lam / 2`` at ``s = lam``), and ``<= lam^2 / sigma_min |h|`` when
``sigma_min >= lam``.

Policies (acceleration domain, 3.33): ``h = q_dd_obs + q_dd_jl + q_dd_damp`` with

* obstacles (3.34 corrected, E9): ``q_dd_obs = sum_{poi} J_poi^T (-gamma sum_o grad V_o(x_poi))``,
  ``gamma = 1000``, ``a = 0.05``, ``D = 0.75`` (point Jacobians by default; ``mode="link"`` uses one
  rigid link Jacobian per link at the segment midpoint, as the thesis did);
* joint limits (3.35 simplified, E12): ``-a u / (h_j^2 - u^2)^(3/2)`` inside, ``-sign(u) outside``
  beyond the limits, ``u = q - q_mid``, ``h_j`` the half range; zero on unlimited joints;
* damping (3.36): ``-G_d q_d``, ``G_d = 800``.

The velocity-domain variants of the IK (3.3.6, E17, U23) use :func:`ik_policy_gains`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._math import as_float, check_finite_fields, check_positive
from jaxtyping import Array, Float

from ._kinematics import Kinematics, poi_positions_from
from ._robot import Arm

__all__ = [
    "PolicyGains",
    "ik_policy_gains",
    "smallest_eigenvalue",
    "damping_factor",
    "damped_pinv",
    "damped_solve",
    "nullspace_projector",
    "oblique_projector",
    "task_priority",
    "obstacle_gradients",
    "poi_jacobian_transpose",
    "obstacle_policy",
    "joint_limit_policy",
    "damping_policy",
    "nullspace_policy",
    "masked_task_jacobian",
]

_LAGUERRE_ITERS = 8  # 4 left near-double roots (arm poses) at up to 2.6e-3 relative; 8: 8e-14


def _arr(x):
    return as_float(x)


class PolicyGains(eqx.Module):
    """Gains of the null-space projection and policies (acceleration domain defaults, SPEC section 7).

    * ``alpha``: null-space gain of 3.30 (0.1);
    * ``lam_ratio``, ``lam_floor``: adaptive damping of 3.32 (0.1, 0.01);
    * ``gamma``, ``obs_a``, ``obs_D``: obstacle policy multiplier, potential amplitude and range
      (1000, 0.05, 0.75 m; 3.34);
    * ``jl_a``, ``jl_outside``: joint-limit policy gain and out-of-range value (100, 5000; 3.35);
    * ``damping``: null-space damping gain ``G_d`` (800; 3.36).

    All fields are arrays (Python floats are converted), so sweeping or differentiating them never
    recompiles.
    """

    alpha: Float[Array, ""] = eqx.field(default=0.1, converter=_arr)
    lam_ratio: Float[Array, ""] = eqx.field(default=0.1, converter=_arr)
    lam_floor: Float[Array, ""] = eqx.field(default=0.01, converter=_arr)
    gamma: Float[Array, ""] = eqx.field(default=1000.0, converter=_arr)
    obs_a: Float[Array, ""] = eqx.field(default=0.05, converter=_arr)
    obs_D: Float[Array, ""] = eqx.field(default=0.75, converter=_arr)
    jl_a: Float[Array, ""] = eqx.field(default=100.0, converter=_arr)
    jl_outside: Float[Array, ""] = eqx.field(default=5000.0, converter=_arr)
    damping: Float[Array, ""] = eqx.field(default=800.0, converter=_arr)

    def __check_init__(self):
        check_finite_fields(self)
        # where concrete, the potential's parameters as FieldParams takes them (a range <= 0
        # switched the obstacle policy off unnoticed, an amplitude < 0 made it attract) and the
        # damping of 3.32, a length; the gains, like the controllers', may take any sign
        for name in ("obs_a", "obs_D"):
            check_positive(f"PolicyGains.{name}", getattr(self, name))
        for name in ("lam_ratio", "lam_floor"):
            check_positive(f"PolicyGains.{name}", getattr(self, name), allow_zero=True)


def ik_policy_gains() -> PolicyGains:
    """Velocity-domain policy gains of the IK (3.3.6; E17, U23): obstacle ``gamma = 10``,
    joint-limit ``a = 1`` and ``50`` outside the range, no damping policy, ``alpha = 0.1``."""
    return PolicyGains(gamma=10.0, jl_a=1.0, jl_outside=50.0, damping=0.0)


# ----------------------------------------------------------------------------------------------
# Small dense linear algebra, unrolled (k <= 6): vectorises over a vmapped batch on CPU, where
# LAPACK calls on tiny matrices are dominated by per-matrix overhead.
# ----------------------------------------------------------------------------------------------


def _cholesky_rows(A, floor):
    """Lower Cholesky factor of the symmetric ``A`` (k x k) as nested lists of scalars.

    Pivots are clamped at ``floor`` (> 0): a (numerically) singular or slightly indefinite ``A``
    gives a huge but finite factor instead of NaN.
    """
    k = A.shape[-1]
    L = [[None] * k for _ in range(k)]
    inv_diag = [None] * k
    for j in range(k):
        s = A[j, j]
        for p in range(j):
            s = s - L[j][p] * L[j][p]
        d = jnp.sqrt(jnp.maximum(s, floor))
        L[j][j] = d
        inv_diag[j] = 1.0 / d
        for i in range(j + 1, k):
            s = A[i, j]
            for p in range(j):
                s = s - L[i][p] * L[j][p]
            L[i][j] = s * inv_diag[j]
    return L, inv_diag


def _cho_solve_rows(L, inv_diag, B):
    """Solve ``L L^T X = B`` for ``B`` (k, r) with the factor of :func:`_cholesky_rows`."""
    k = len(L)
    y = [None] * k
    for i in range(k):
        s = B[i]
        for p in range(i):
            s = s - L[i][p] * y[p]
        y[i] = s * inv_diag[i]
    x = [None] * k
    for i in reversed(range(k)):
        s = y[i]
        for p in range(i + 1, k):
            s = s - L[p][i] * x[p]
        x[i] = s * inv_diag[i]
    return jnp.stack(x)


def _spd_inverse_scalars(A, floor):
    """Inverse of a symmetric positive definite ``k x k`` matrix given and returned as nested lists
    of scalars (``A[i][j]``, both triangles): Cholesky ``A = L L^T`` (pivots clamped at ``floor`` as
    in :func:`_cholesky_rows`), the triangular inverse ``W = L^-1`` and ``X = W^T W``.

    Every entry is a scalar (a ``(batch,)`` plane under ``vmap``), so XLA fuses the whole inverse
    into a few element-wise loops; ``k^3 / 2`` multiplications instead of the ``7 k^3 / 6`` of a
    Cholesky solve against the identity, and no small batched dots or reductions.
    """
    k = len(A)
    L = [[None] * k for _ in range(k)]
    inv = [None] * k
    for j in range(k):
        s = A[j][j]
        for p in range(j):
            s = s - L[j][p] * L[j][p]
        inv[j] = 1.0 / jnp.sqrt(jnp.maximum(s, floor))
        for i in range(j + 1, k):
            s = A[i][j]
            for p in range(j):
                s = s - L[i][p] * L[j][p]
            L[i][j] = s * inv[j]
    W = [[None] * k for _ in range(k)]  # W = L^-1, lower triangular
    for j in range(k):
        W[j][j] = inv[j]
        for i in range(j + 1, k):
            s = L[i][j] * W[j][j]
            for p in range(j + 1, i):
                s = s + L[i][p] * W[p][j]
            W[i][j] = -s * inv[i]
    X = [[None] * k for _ in range(k)]  # X = W^T W = A^-1
    for i in range(k):
        for j in range(i, k):
            s = W[j][i] * W[j][j]
            for p in range(j + 1, k):
                s = s + W[p][i] * W[p][j]
            X[i][j] = X[j][i] = s
    return X


def _pivot_floor(G):
    eps = jnp.finfo(G.dtype).eps
    return 16 * eps * (jnp.trace(G) + jnp.finfo(G.dtype).tiny / eps)


def _laguerre(G):
    """Smallest eigenvalue of the SPD ``G`` by Laguerre's method on ``det(G - mu I)``, polished by a
    Rayleigh quotient.

    With ``X = (G - mu I)^-1``: ``g = sum 1/(l_i - mu) = tr X``, ``H = sum 1/(l_i - mu)^2 = |X|_F^2``,
    and the step ``k / (g + sqrt((k-1)(k H - g^2)))``. From ``mu = 0 <= l_min`` the iterates increase
    monotonically to ``l_min`` (all roots real), cubically for a simple root but only linearly for a
    (near-)double one, which symmetric arm poses produce. The final value is therefore the Rayleigh
    quotient of the inverse-iteration vector ``v = X X e_j`` (``j`` the largest diagonal of ``X``):
    an upper bound whose error is quadratic in the vector error and which is exact for any vector in
    a degenerate eigenspace. Returns ``(l_min, v)`` (``v`` unnormalised, for the derivative).

    The ``k x k`` inverses are scalar-unrolled (:func:`_spd_inverse_scalars`): under ``vmap`` on CPU
    this is about 3x cheaper than row-vector Cholesky solves against the identity followed by
    ``trace`` / ``sum`` reductions (``benchmarks/bench_controllers.py``).
    """
    k = G.shape[-1]
    if k == 1:
        return G[0, 0], jnp.ones((1,), G.dtype)
    floor = _pivot_floor(G)
    Gs = [[G[i, j] for j in range(k)] for i in range(k)]

    def inverse_at(mu):
        return _spd_inverse_scalars([[Gs[i][j] - mu if i == j else Gs[i][j] for j in range(k)]
                                     for i in range(k)], floor)

    def step(_, mu):
        X = inverse_at(mu)
        g = X[0][0]
        H = X[0][0] * X[0][0]
        for i in range(1, k):
            g = g + X[i][i]
            H = H + X[i][i] * X[i][i]
        off = X[0][1] * X[0][1]
        for i in range(k):
            for j in range(i + 1, k):
                if (i, j) != (0, 1):
                    off = off + X[i][j] * X[i][j]
        H = H + 2.0 * off
        disc = jnp.sqrt(jnp.maximum((k - 1) * (k * H - g * g), 0.0))
        return mu + k / (g + disc)

    # a rolled loop: the unrolled k x k inverse is compiled once (compile time ~4x lower); the
    # last iteration's inverse is only needed for the polish vector
    mu = jax.lax.fori_loop(0, _LAGUERRE_ITERS - 1, step, jnp.zeros_like(G[0, 0]))  # (varies as G does, shard_map)
    X = jnp.stack([jnp.stack(row) for row in inverse_at(mu)])
    X = X / jnp.max(jnp.abs(X))
    d = jnp.diagonal(X)
    e = (jnp.arange(k) == jnp.argmax(d)).astype(G.dtype)
    v = X @ (X @ e)
    v = v / jnp.max(jnp.abs(v))
    rq = (v @ G @ v) / (v @ v)
    return rq, v


@jax.custom_jvp
def smallest_eigenvalue(G: Float[Array, "k k"]) -> Float[Array, ""]:
    """Smallest eigenvalue of a small symmetric positive semi-definite matrix (no SVD / eigh).

    Laguerre's iteration plus a Rayleigh-quotient polish (see :func:`_laguerre`), 8 scalar-unrolled
    ``k x k`` Cholesky inverses: relative error below 1e-13 on 20000 poses of the 9-DOF arm, about
    a tenth of which have a near-double smallest eigenvalue (relative gap ~1e-3, where 4 steps were
    off by up to 2.6e-3); for relative gaps below ~1e-3 the error stays within the gap, and an exactly
    double one is exact (tested against ``numpy.linalg.eigvalsh``). Derivative:
    ``v^T dG v / v^T v`` with the same vector.
    """
    return _laguerre(G)[0]


@smallest_eigenvalue.defjvp
def _smallest_eigenvalue_jvp(primals, tangents):
    (G,), (dG,) = primals, tangents
    mu, v = _laguerre(jax.lax.stop_gradient(G))
    dmu = (v @ dG @ v) / (v @ v)
    return mu, dmu


def _row_mask(k, row_mask, dtype):
    if row_mask is None:
        return jnp.ones((k,), bool)
    return jnp.asarray(row_mask).astype(bool)


def masked_task_jacobian(J: Float[Array, "k n"], row_mask) -> Float[Array, "k n"]:
    """``J`` with the inactive rows (``row_mask`` False) zeroed."""
    return jnp.where(_row_mask(J.shape[0], row_mask, J.dtype)[:, None], J, 0.0)


def damping_factor(J: Float[Array, "k n"], ratio=0.1, floor=0.01, *, row_mask=None,
                   method: str = "laguerre") -> Float[Array, ""]:
    """Adaptive damping ``lam = max(ratio * sigma_min(J_active), floor)`` (3.31-3.32).

    ``sigma_min`` is over the active rows only (``row_mask``; all rows if None). ``method``:
    ``"laguerre"`` (default, see :func:`smallest_eigenvalue`), ``"eigvalsh"`` or ``"svd"`` (references).
    """
    k = J.shape[0]
    m = _row_mask(k, row_mask, J.dtype)
    Jm = jnp.where(m[:, None], J, 0.0)
    if method == "svd":
        # Reference only: push inactive rows' singular values above the spectrum.
        G = Jm @ Jm.T
        shift = jnp.trace(G) + 1.0
        Gs = G + jnp.diag(jnp.where(m, 0.0, shift))
        s = jnp.linalg.svd(Gs, compute_uv=False)
        mu = s[-1]
    else:
        G = Jm @ Jm.T
        shift = jnp.trace(G) + 1.0
        Gs = G + jnp.diag(jnp.where(m, 0.0, shift))
        if method == "laguerre":
            mu = smallest_eigenvalue(Gs)
        elif method == "eigvalsh":
            mu = jnp.linalg.eigvalsh(Gs)[0]
        else:
            raise ValueError(f"damping_factor: method must be 'laguerre', 'eigvalsh' or 'svd', got {method!r}")
    pos = mu > 0
    sigma = jnp.where(pos, jnp.sqrt(jnp.where(pos, mu, 1.0)), 0.0)
    return jnp.maximum(ratio * sigma, floor)


def damped_solve(J: Float[Array, "k n"], B: Float[Array, "k r"], lam) -> Float[Array, "n r"]:
    """``J^T (J J^T + lam^2 I)^-1 B`` by an unrolled ``k x k`` Cholesky (3.29 applied to ``B``)."""
    k = J.shape[0]
    Y = J @ J.T + (lam * lam) * jnp.eye(k, dtype=J.dtype)
    L, inv_diag = _cholesky_rows(Y, _pivot_floor(Y))
    return J.T @ _cho_solve_rows(L, inv_diag, B)


def damped_pinv(J: Float[Array, "k n"], ratio=0.1, floor=0.01, *, row_mask=None,
                method: str = "laguerre") -> tuple[Float[Array, "n k"], Float[Array, ""]]:
    """Adaptive damped pseudo-inverse ``J# = J^T (J J^T + lam^2 I)^-1`` (3.29, 3.32) and ``lam``.

    Arguments:
        J: task Jacobian ``(k, n)``.
        ratio, floor: ``lam = max(ratio sigma_min, floor)`` (0.1, 0.01 [T]); ``floor = ratio = 0``
            gives the undamped Moore-Penrose inverse of a full-row-rank ``J``.
        row_mask: ``(k,)`` bool, active task rows (inactive rows are zeroed; their columns of ``J#``
            are zero). None: all rows.
        method: how ``sigma_min`` is found (see :func:`damping_factor`).

    Returns:
        ``(J#, lam)`` with ``J#`` of shape ``(n, k)``.
    """
    if J.ndim != 2:
        raise ValueError(f"damped_pinv: J must be 2-D (k, n), got shape {J.shape}")
    m = _row_mask(J.shape[0], row_mask, J.dtype)
    Jm = jnp.where(m[:, None], J, 0.0)
    lam = damping_factor(Jm, ratio, floor, row_mask=m, method=method)
    Jp = damped_solve(Jm, jnp.eye(J.shape[0], dtype=J.dtype), lam)
    return Jp, lam


def nullspace_projector(J: Float[Array, "k n"], J_pinv: Float[Array, "n k"]) -> Float[Array, "n n"]:
    """Orthogonal null-space projector ``N = I - J# J`` (2.32 / 3.30)."""
    n = J.shape[1]
    return jnp.eye(n, dtype=J.dtype) - J_pinv @ J


def oblique_projector(J: Float[Array, "k n"], W: Float[Array, "n n"], level: str = "torque"
                      ) -> Float[Array, "n n"]:
    """Weighted (oblique) null-space projector (2.36 corrected, E11).

    * ``level="torque"``: ``P_tau = I - J^T (J W^-1 J^T)^-1 J W^-1``; ``P_tau J^T = 0`` and
      ``J W^-1 P_tau = 0`` (with ``W = M``: projected torques cause no end-effector acceleration).
    * ``level="velocity"`` (or ``"acceleration"``): ``P_v = I - W^-1 J^T (J W^-1 J^T)^-1 J``,
      ``J P_v = 0`` (the ``W``-weighted minimum-norm projector; ``P_v = P_tau^T``).

    ``W`` must be symmetric positive definite (a Cholesky factorisation is used).
    """
    n = J.shape[1]
    cf = jax.scipy.linalg.cho_factor(W, lower=True)
    WiJt = jax.scipy.linalg.cho_solve(cf, J.T)  # W^-1 J^T (n, k)
    A = J @ WiJt  # J W^-1 J^T (k, k)
    ca = jax.scipy.linalg.cho_factor(A, lower=True)
    eye = jnp.eye(n, dtype=J.dtype)
    if level == "torque":
        # J^T A^-1 J W^-1 = J^T A^-1 (W^-1 J^T)^T
        return eye - J.T @ jax.scipy.linalg.cho_solve(ca, WiJt.T)
    if level in ("velocity", "acceleration"):
        return eye - WiJt @ jax.scipy.linalg.cho_solve(ca, J)
    raise ValueError(f"oblique_projector: level must be 'torque', 'velocity' or 'acceleration', got {level!r}")


def task_priority(J1: Float[Array, "k1 n"], x1: Float[Array, " k1"], J2: Float[Array, "k2 n"],
                  x2: Float[Array, " k2"], ratio=0.0, floor=0.0, *, method: str = "laguerre"
                  ) -> Float[Array, " n"]:
    """Two-level task-priority resolution (2.5.3, SPEC section 7):
    ``q_d = J1# x1 + (J2 N1)# (x2 - J2 J1# x1)`` with ``N1 = I - J1# J1``.

    The secondary task acts only in the null space of the first: ``J1 q_d = x1`` exactly for
    undamped inverses (``ratio = floor = 0``) whatever ``x2``. Pseudo-inverses are the damped
    ones of :func:`damped_pinv` with the given ``ratio``/``floor``. (Not used by the thesis's
    controllers, which sum the policies, 3.33.)
    """
    J1p, _ = damped_pinv(J1, ratio, floor, method=method)
    q1 = J1p @ x1
    N1 = nullspace_projector(J1, J1p)
    J2N1 = J2 @ N1
    # (J2 N1)# may be rank deficient in general; a tiny floor keeps it finite.
    tiny = jnp.maximum(floor, 1e-9)
    J2p, _ = damped_pinv(J2N1, ratio, tiny, method=method)
    return q1 + J2p @ (x2 - J2 @ q1)


# ----------------------------------------------------------------------------------------------
# Policies
# ----------------------------------------------------------------------------------------------


def _select_max(x, y):
    """``max(x, y)`` as a compare and a select: ``jnp.maximum`` lowers to a NaN-propagating
    ``llvm.maximum`` that costs several instructions per lane on x86; equal for non-NaN operands."""
    return jnp.where(x > y, x, y)


def _clamped_numerator(sdf, mask, a, D, form: str, clamp):
    """``(r, num, dnum)`` with ``r = max(sdf, clamp)``, ``V_o'(r) = num / r^4 = -a (3D -/+ 2r) /
    (D r^4)`` and ``dnum = d num / dr`` (both zero beyond ``D`` and on masked slots), as
    compare-and-selects: the one formula of the magnitude that :func:`_slot_gradient` and its
    tangent :func:`_slot_tangent` share (the gradient leaves ``dnum`` unused)."""
    sgn = -1.0 if form == "minus" else 1.0
    r = jnp.where(sdf > clamp, sdf, clamp)
    on = mask & (sdf <= D)
    num = jnp.where(on, (-a / D) * (3.0 * D + sgn * 2.0 * r), 0.0)
    return r, num, jnp.where(on, (-a / D) * (2.0 * sgn), 0.0)


def _to_slot(R, w):
    """``R^T w`` for three planes ``w`` (world -> slot frame)."""
    return tuple(R[0, i] * w[0] + R[1, i] * w[1] + R[2, i] * w[2] for i in range(3))


def _from_slot(R, w):
    """``R w`` for three planes ``w`` (slot frame -> world)."""
    return tuple(R[j, 0] * w[0] + R[j, 1] * w[1] + R[j, 2] * w[2] for j in range(3))


def _slot_gradient(kind: str, R, p, dims, mask, X, a, D, form: str, clamp):
    """``grad V_o`` of one obstacle slot at every point, three planes ``(m,)`` (x, y, z).

    Structure-of-arrays: every quantity is an ``(m,)`` plane (``(batch, m)`` under ``vmap``), so one
    slot is a handful of fused element-wise loops. The direction is the analytic gradient of the
    *unclamped* sdf of :mod:`redman_jax._obstacles` (E10), the magnitude ``V_o'(max(sdf, clamp))``
    (U3), zero beyond ``D`` and for masked slots.

    Laid out for XLA's CPU fusion, which has no multi-output fusion: each output loop recomputes
    whatever cheap element-wise work it depends on (:func:`_fold_families` makes the three planes
    two loops, x and y as one complex plane), while expensive ops (``sqrt``, division) with several
    users are evaluated once. So there is exactly one division per point and
    slot: ``V_o' / |n|`` (and ``1 / rho`` for cylinders) is folded into one quotient
    ``num / (r^4 |n|)`` that the three outputs share; ``max``/``min`` are compare-and-select (see
    :func:`_select_max`). Equal to the reference to rounding (tested).

    Fewer expensive ops is not faster: each one is materialised once and read by the loops that
    use it, so it is also where their shared work stops being recomputed. Measured with this
    gradient and :func:`_slot_tangent` sharing one quotient and no division at all (a box one
    ``rsqrt`` per point and slot, a cylinder two; the values equal to rounding), 40 obstacles,
    the study's flags, 2 devices, us per state in the loop layout, alternating: original velocity
    OSC 14.91 / 14.72 -> 15.50 / 15.75 (``lax.rsqrt``) and 20.00 / 15.29 (``1 / sqrt``),
    acceleration OSC 6.54 / 7.07 -> 8.48 / 7.90 and 8.66 / 7.86.
    """
    d = tuple(X[j] - p[j] for j in range(3))  # world offsets

    def num_r4(sdf):  # V_o'(r) = num / r^4, r = max(sdf, clamp)
        r, num, _ = _clamped_numerator(sdf, mask, a, D, form, clamp)
        r2 = r * r
        return num, jnp.where(r > 0, r2 * r2, 1.0)

    if kind == "spheres":
        r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        pos = r2 > 0
        rr = jnp.sqrt(jnp.where(pos, r2, 1.0))
        num, r4 = num_r4(jnp.where(pos, rr, 0.0) - dims[0])
        w = jnp.where(pos, num, 0.0) / (r4 * rr)
        return tuple(w * d[j] for j in range(3))
    xl = _to_slot(R, d)  # R^T (x - p)
    if kind == "boxes":
        u = [jnp.abs(xl[i]) - dims[i] for i in range(3)]
        o = [jnp.where(v > 0, v, 0.0) for v in u]
        on2 = o[0] * o[0] + o[1] * o[1] + o[2] * o[2]
        out = on2 > 0
        on = jnp.sqrt(jnp.where(out, on2, 1.0))
        umax = _select_max(_select_max(u[0], u[1]), u[2])
        sdf = jnp.where(out, on, jnp.where(umax < 0, umax, 0.0))
        num, r4 = num_r4(sdf)
        c = num / (r4 * jnp.where(out, on, 1.0))  # V_o' / |n| outside, V_o' inside
        pick0 = (u[0] >= u[1]) & (u[0] >= u[2])  # inside: the nearest face
        pick1 = ~pick0 & (u[1] >= u[2])
        picks = (pick0, pick1, ~pick0 & ~pick1)
        gl = tuple(jnp.where(xl[i] < 0, -c, c) * jnp.where(out, o[i], picks[i].astype(c.dtype))
                   for i in range(3))
    elif kind == "cylinders":
        rho2 = xl[0] * xl[0] + xl[1] * xl[1]
        rpos = rho2 > 0
        rho = jnp.sqrt(jnp.where(rpos, rho2, 1.0))
        d1 = jnp.where(rpos, rho, 0.0) - dims[0]
        d2 = jnp.abs(xl[2]) - dims[1]
        o1, o2 = jnp.where(d1 > 0, d1, 0.0), jnp.where(d2 > 0, d2, 0.0)
        on2 = o1 * o1 + o2 * o2
        out = on2 > 0
        on = jnp.sqrt(jnp.where(out, on2, 1.0))
        dmax = _select_max(d1, d2)
        sdf = jnp.where(out, on, jnp.where(dmax < 0, dmax, 0.0))
        num, r4 = num_r4(sdf)
        den = r4 * jnp.where(out, on, 1.0)
        w_rad = jnp.where(rpos, num * jnp.where(out, o1, (d1 >= d2).astype(on.dtype)), 0.0) / (den * rho)
        w_ax = jnp.where(xl[2] < 0, -num, num) * jnp.where(out, o2, (d1 < d2).astype(on.dtype)) / den
        gl = (w_rad * xl[0], w_rad * xl[1], w_ax)
    else:  # pragma: no cover
        raise ValueError(kind)
    return _from_slot(R, gl)


def _slot_tangent(kind: str, R, p, dims, mask, X, V, a, D, form: str, clamp):
    """The directional derivative of :func:`_slot_gradient` along point velocities ``V`` (three
    ``(m,)`` planes): ``d/dt grad V_o(x) = Hess V_o(x) xdot``, analytic.

    The gradient is ``V_o'(r) n`` with ``r = max(sdf, clamp)`` and ``n = u / rho`` the unit
    direction of the unnormalised ``u`` (sphere: ``x - p``; box outside: the outward offset ``o``
    with its signs; cylinder outside: ``(o_1 e_rho, o_2 s_z)``), ``rho = |u|``. So
    ``d/dt grad = A (n . du) n + B (du - (n . du) n)`` with ``A = V_o''`` (zero at or below the
    clamp, beyond ``D`` and on masked slots), ``B = V_o' / rho`` and ``du = du/dt`` (``v`` on the
    active components, plus ``o_1 de_rho/dt`` on a cylinder). The second term, the turning of ``n``,
    is zero where ``u`` has one active component (a box face, a cylinder's mantle or cap: ``n``
    is constant there) and is then left out rather than computed as a difference of two terms of
    order ``V_o' / rho``, which near a surface cancelled to rounding noise and in float32 overflowed
    (NaN within 2e-8 m of a face). Inside a box the normal is constant and the magnitude clamped:
    zero; inside a cylinder's mantle the curvature ``V_o' de_rho/dt`` remains (SPEC U3). One
    division per point and slot, as in :func:`_slot_gradient`. Equal to ``H v`` with ``H`` the
    forward Jacobian of the reference formulation
    :func:`~redman_jax._fields.obstacle_field_gradient` to rounding (tested).
    """
    d = tuple(X[j] - p[j] for j in range(3))

    def coefs(sdf, rho):
        """``(A, B, 1 / rho)`` from one quotient ``1 / (r^5 rho)`` (``rho > 0``)."""
        r, num, dnum = _clamped_numerator(sdf, mask, a, D, form, clamp)
        # r^5 V'' = r^5 d(num / r^4)/dr, zero where the clamp holds r
        slope5 = jnp.where(sdf > clamp, dnum * r - 4.0 * num, 0.0)
        r2 = r * r
        r5 = r2 * r2 * r
        inv = 1.0 / jnp.where(rho > 0, r5 * rho, 1.0)
        return slope5 * rho * inv, num * r * inv, r5 * inv

    if kind == "spheres":
        r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        pos = r2 > 0
        rho = jnp.where(pos, jnp.sqrt(jnp.where(pos, r2, 1.0)), 0.0)
        A, B, irho = coefs(rho - dims[0], rho)
        B = jnp.where(pos, B, 0.0)
        # (A - B)(n . v) n with n = d / rho, as one coefficient of d: (n . v) first (bounded)
        alpha = jnp.where(pos, (A - B) * ((d[0] * V[0] + d[1] * V[1] + d[2] * V[2]) * irho) * irho, 0.0)
        return tuple(alpha * d[j] + B * V[j] for j in range(3))
    xl = _to_slot(R, d)  # R^T (x - p)
    vl = _to_slot(R, V)  # R^T v
    if kind == "boxes":
        u = [jnp.abs(xl[i]) - dims[i] for i in range(3)]
        act = [v > 0 for v in u]
        o = [jnp.where(act[i], u[i], 0.0) for i in range(3)]
        so = [jnp.where(xl[i] < 0, -o[i], o[i]) for i in range(3)]  # signed offsets
        on2 = o[0] * o[0] + o[1] * o[1] + o[2] * o[2]
        out = on2 > 0
        on = jnp.where(out, jnp.sqrt(jnp.where(out, on2, 1.0)), 0.0)
        A, B, irho = coefs(on, on)
        edge = (act[0].astype(on.dtype) + act[1] + act[2]) > 1  # an edge or a corner: n turns
        B = jnp.where(edge, B, 0.0)  # on a face n is constant (inside: also the magnitude)
        alpha = jnp.where(out, (A - B) * ((so[0] * vl[0] + so[1] * vl[1] + so[2] * vl[2]) * irho) * irho, 0.0)
        tl = tuple(alpha * so[i] + jnp.where(act[i], B * vl[i], 0.0) for i in range(3))
    elif kind == "cylinders":
        rho2 = xl[0] * xl[0] + xl[1] * xl[1]
        rpos = rho2 > 0
        rho = jnp.where(rpos, jnp.sqrt(jnp.where(rpos, rho2, 1.0)), 0.0)
        irho_xy = 1.0 / jnp.where(rpos, rho, 1.0)
        e = (xl[0] * irho_xy, xl[1] * irho_xy)
        rdot = e[0] * vl[0] + e[1] * vl[1]
        de = ((vl[0] - rdot * e[0]) * irho_xy, (vl[1] - rdot * e[1]) * irho_xy)  # de_rho/dt
        d1 = rho - dims[0]
        d2 = jnp.abs(xl[2]) - dims[1]
        o1, o2 = jnp.where(d1 > 0, d1, 0.0), jnp.where(d2 > 0, d2, 0.0)
        so2 = jnp.where(xl[2] < 0, -o2, o2)
        on2 = o1 * o1 + o2 * o2
        out = on2 > 0
        on = jnp.where(out, jnp.sqrt(jnp.where(out, on2, 1.0)), 0.0)
        dmax = _select_max(d1, d2)
        sdf = jnp.where(out, on, jnp.where(dmax < 0, dmax, 0.0))
        A, B, irho = coefs(sdf, jnp.where(out, on, 1.0))  # inside: B = V'(clamp) (rho := 1)
        radial = jnp.where(out, o1, (d1 >= d2).astype(on.dtype))  # g_xy = B * radial * e_rho
        cr = jnp.where(rpos, B * radial, 0.0)  # the curvature of e_rho: B o_1 = V' n_e
        Bt = jnp.where((d1 > 0) & (d2 > 0), B, 0.0)  # on the rim n turns in the (e_rho, z) plane
        alpha = jnp.where(out, (A - Bt) * ((o1 * rdot + so2 * vl[2]) * irho) * irho, 0.0)
        w_e = jnp.where(rpos & out, alpha * o1 + Bt * rdot, 0.0)
        tl = (w_e * e[0] + cr * de[0], w_e * e[1] + cr * de[1], jnp.where(out, alpha * so2 + Bt * vl[2], 0.0))
    else:  # pragma: no cover
        raise ValueError(kind)
    return _from_slot(R, tl)


def _pack(planes: tuple) -> tuple:
    """Real planes two by two as complex planes (``a + i b``), an odd last one as it is."""
    pairs = tuple(jax.lax.complex(planes[i], planes[i + 1]) for i in range(0, len(planes) - 1, 2))
    return pairs + (planes[-1:] if len(planes) % 2 else ())


def _unpack(packed: tuple) -> tuple:
    """The real planes of :func:`_pack`."""
    out = []
    for z in packed:
        out += [jnp.real(z), jnp.imag(z)] if jnp.iscomplexobj(z) else [z]
    return tuple(out)


def _fold_families(obs, init, slot_fn, n_linear: int = 0):
    """``sum`` over every active slot of every family of ``slot_fn(kind, *slot)`` (a tuple of
    ``(m,)`` planes), one :func:`~redman_jax._obstacles.fold_slots` per family. The last
    ``n_linear`` planes (tangents, inside a JVP rule) are summed by ``jnp.sum`` one by one, which
    reverse mode can transpose; the others by :func:`_sum_leading`.

    The accumulators are complex: planes two by two as ``a + i b`` (:func:`_pack`; the tangents
    apart from the primal planes, so that a JVP rule's primal outputs never depend on its tangents).
    XLA's CPU backend has no multi-output loop fusion: every output plane of a slot step is its own
    loop, which recomputes the element-wise work the planes share (the slot frame, the sdf, the
    masks); a complex plane is one loop that computes that work once for two planes. A complex sum
    is the two real sums, so the results are the same to the bit. Measured (9-DOF arm, 40 obstacles,
    batch 1024, one core, JAX's default flags, old and new alternating; us per state): original
    velocity OSC 42.1 / 37.2 / 35.1 -> 30.3 / 30.0 / 30.9 (six tangent and primal planes in four
    loops), acceleration OSC 14.6 / 14.2 / 13.6 / 13.9 -> 12.6 / 12.8 / 12.8 / 14.1, velocity OSC
    13.5 / 13.4 -> 13.2 / 13.0. The study's units (batch 20, its XLA flags) are unchanged: 9-DOF
    agriculture gradient-guided 78.7 / 79.3 s -> 79.1 / 78.2 s, compiling included.
    Three loops instead of four (the primal z plane and the tangent z plane as one complex plane,
    which only a forward-only caller could use: reverse mode through this JVP rule needs the
    primal outputs free of the tangents) gave the same values to the bit and no gain: original
    velocity OSC, 40 obstacles, loop layout at 1024 states, the study's flags, 2 devices, four
    planes / three alternating, 14.72 / 14.15 against 14.70 / 14.73 us per state (vmap at batch
    1024: 17.95 / 16.78 against 17.43 / 17.35).

    Nor did the slot frames ``R^T (x - p)`` and ``R^T v`` computed apart from the output loops,
    which read them. Alone, the pass over 40 boxes and 36 points (1,024 states in a ``lax.map``,
    one core) took 23.1 / 22.9 -> 18.4 / 18.0 us per state (jvp) and 10.4 -> 8.6 (primal), bit for
    bit the same values. In the controllers, with the frames of all slots before the scan (not
    examined further; likely that pass, outside the loop, takes in the producers of the points,
    recomputed per slot, and under ``vmap`` its ``(slots, batch, points)`` planes leave the
    cache): original velocity OSC 14.97 / 14.69 -> 21.65 / 17.98 us per state (loop), 18.27 /
    17.44 -> 40.21 / 40.02 (vmap at 1,024), acceleration OSC 6.98 / 6.63 -> 8.16 / 7.83; with each
    slot's frames computed one step ahead in the scan's carry (values equal to rounding): 15.51 /
    14.73 -> 15.04 / 15.68 (loop), 17.94 / 17.19 -> 21.50 / 24.07 (vmap).
    """
    from ._obstacles import fold_slots

    k = len(init) - n_linear
    pack = lambda planes: _pack(planes[:k]) + _pack(planes[k:])
    head = _pack(init[:k])
    kp = len(head)  # complex or real accumulators of the primal planes
    acc = head + _pack(init[k:])
    for i, kind in enumerate(("spheres", "boxes", "cylinders")):
        if getattr(obs, kind).capacity == 0:
            continue

        def step(acc, slot, c, kind=kind):
            if c == 1:
                gs = slot_fn(kind, *slot)
            else:  # c slots at once, (c, m) planes summed over the slots
                gs = jax.vmap(lambda *sl: slot_fn(kind, *sl))(*slot)
                gs = _sum_leading(gs[:k]) + tuple(jnp.sum(x, axis=0) for x in gs[k:])
            return tuple(x + y for x, y in zip(acc, pack(gs)))

        acc = fold_slots(obs, i, acc, step)
    return _unpack(acc[:kp]) + _unpack(acc[kp:])


@jax.custom_jvp
def _sum_leading(planes: tuple) -> tuple:
    """``tuple(jnp.sum(x, axis=0) for x in planes)`` as *one* variadic ``lax.reduce``. XLA's CPU
    backend fuses the element-wise work that produces the planes into that single reduction loop,
    so what the planes share (the slot frame, the sdf, the potential's slope) is computed once per
    element; separate sums are separate loops, each recomputing its plane's whole chain (the
    backend has no multi-output loop fusion). Only grouped slot steps (``c > 1``: the warehouse's
    boxes) take this path. 9-DOF arm, warehouse seed 1 (72 boxes), batch 20, one core with the
    study's flags, the closed-loop vector field in us per state: velocity OSC 60.9 -> 37.0,
    acceleration 61.7 -> 40.8, gradient-guided 60.6 -> 44.3 (``benchmarks/bench_vector_field.py
    --case warehouse --batches 20``); the study's 9-DOF warehouse units, old and new side by side
    on a core each: 48.6 -> 37.7 s (velocity), 57.3 -> 42.4 s (acceleration), 138.4 -> 108.9 s
    (gradient-guided), compilation included. Sums in another order: results agree to rounding."""
    zero = tuple(jnp.zeros((), x.dtype) for x in planes)
    return tuple(jax.lax.reduce(tuple(planes), zero, lambda u, v: tuple(a + b for a, b in zip(u, v)), (0,)))


@_sum_leading.defjvp
def _sum_leading_jvp(primals, tangents):
    """The sum is linear: tangents summed by ``jnp.sum`` (a reduction with a transpose rule, which
    the generic variadic reduce lacks), so reverse mode works through the grouped slot steps."""
    (planes,), (dplanes,) = primals, tangents
    return _sum_leading(planes), tuple(jnp.sum(t, axis=0) for t in dplanes)


def _gradient_planes(obs, X: tuple, a, D, clamp, form: str) -> tuple:
    return _fold_families(obs, tuple(jnp.zeros_like(X[0]) for _ in range(3)),
                          lambda kind, *sl: _slot_gradient(kind, *sl, X, a, D, form, clamp))


_gradient_planes_fwd = jax.custom_jvp(_gradient_planes, nondiff_argnums=(5,))


def _gradient_planes_jvp(form, primals, tangents):
    """Along the points only (the obstacles, ``a``, ``D`` and ``clamp`` held): the primal planes
    and the analytic tangent planes (:func:`_slot_tangent`) in one fold over the slots (9-DOF arm,
    40 obstacles, batch 1024: the velocity-domain policy's jvp 12.3-13.4 against 17.5-18.0 us per
    state by forward mode through :func:`_slot_gradient`). Any other non-zero tangent: plain
    forward mode."""
    from jax.custom_derivatives import SymbolicZero

    obs, X, a, D, clamp = primals
    t_obs, t_X, t_a, t_D, t_clamp = tangents
    is_zero = lambda t: isinstance(t, SymbolicZero)
    held = jax.tree.leaves((t_obs, t_a, t_D, t_clamp), is_leaf=is_zero)
    if not all(is_zero(t) for t in held) or all(is_zero(t) for t in t_X):
        dense = jax.tree.map(lambda t: np.zeros(t.shape, t.dtype) if is_zero(t) else t, tangents,
                             is_leaf=is_zero)  # (np: integer leaves have float0 tangents)
        return jax.jvp(lambda *args: _gradient_planes(*args, form), primals, dense)
    V = tuple(jnp.zeros(t.shape, t.dtype) if is_zero(t) else t for t in t_X)
    zeros = tuple(jnp.zeros_like(X[0]) for _ in range(6))
    both = _fold_families(obs, zeros, lambda kind, *sl: (
        _slot_gradient(kind, *sl, X, a, D, form, clamp) + _slot_tangent(kind, *sl, X, V, a, D, form, clamp)),
        n_linear=3)
    return both[:3], both[3:]


_gradient_planes_fwd.defjvp(_gradient_planes_jvp, symbolic_zeros=True)


def _obstacle_gradient_planes(obs, X: tuple, a, D, form: str = "minus", clamp=1e-3) -> tuple:
    """``sum_o grad V_o`` at the points ``X = (x, y, z)`` (three ``(m,)`` planes), as three planes.

    One ``lax.scan`` per shape family over its slots, three ``(m,)`` accumulators,
    ``obs.slots_per_step`` slots per step, steps past ``obs.used`` skipped
    (:class:`~redman_jax._obstacles.ObstacleSet`, :func:`~redman_jax._obstacles.fold_slots`).
    Its forward derivative along the points (``Hess V_o xdot``, the velocity-domain policy's time
    derivative in the original velocity OSC) is analytic (:func:`_slot_tangent`)."""
    from ._fields import _check_form

    _check_form(form)
    a, D, clamp = (jnp.asarray(v, X[0].dtype) for v in (a, D, clamp))
    return _gradient_planes_fwd(obs, tuple(X), a, D, clamp, form)


def obstacle_gradients(obs, points: Float[Array, "m 3"], a, D, form: str = "minus", clamp=1e-3,
                       impl: str = "fused") -> Float[Array, "m 3"]:
    """``sum_o grad V_o(x)`` at every point, ``(m, 3)`` (SPEC section 3; the clamp of U3 on the
    magnitude only, direction from the unclamped sdf; masked slots and ``sdf > D`` contribute 0).

    ``impl="fused"`` (default) evaluates all points against one obstacle slot at a time
    (``lax.scan`` over each shape family's slots, three ``(m,)`` accumulators) with analytic sdf
    gradients (:func:`_slot_gradient`): under ``vmap`` each step is a few fused element-wise passes
    over ``(batch, points)`` planes that stay in cache, about 10x faster than the reference on CPU;
    ``impl="reference"`` vmaps :func:`redman_jax._fields.obstacle_field_gradient` over the points.
    Both agree to rounding (tested).
    """
    if impl == "reference":
        from ._fields import obstacle_field_gradient

        return jax.vmap(lambda x: obstacle_field_gradient(obs, x, a, D, form=form, clamp=clamp))(points)
    if impl != "fused":
        raise ValueError(f"obstacle_gradients: impl must be 'fused' or 'reference', got {impl!r}")
    g = _obstacle_gradient_planes(obs, tuple(points[:, j] for j in range(3)), a, D, form, clamp)
    return jnp.stack(g, axis=1)


def poi_jacobian_transpose(arm: Arm, kin: Kinematics, pois: Float[Array, "m 3"], forces
                           ) -> Float[Array, " n"]:
    """``sum_i J_poi,i^T f_i`` over the points of interest without forming their ``3 x n`` Jacobians.

    Column ``j`` of a point's Jacobian is ``v_j + w_j x p`` (zero beyond the point's link), so
    ``(v_j + w_j x p) . f = v_j . f + w_j . (p x f)`` and the product is ``v_j . F_j + w_j . T_j``
    with ``F_j``, ``T_j`` the suffix sums over the links ``>= j`` of the forces and of their moments
    about the world origin; on a prismatic (telescoping) segment the own-link terms are weighted by
    the points' fractions ``k / P``, as in :func:`~redman_jax._kinematics.poi_jacobians_from`.

    ``forces``: ``(m, 3)`` or three ``(m,)`` planes. Structure-of-arrays (about 4x cheaper than the
    Jacobians and an einsum under ``vmap`` on CPU); equal to ``einsum("mjn,mj->n", poi_jacobians_from
    (...), f)`` to rounding (tested).
    """
    n, P = arm.n_dof, arm.points_per_link
    pri = arm.prismatic_mask
    if not isinstance(forces, tuple):
        forces = tuple(forces[:, c] for c in range(3))
    f = forces
    p = tuple(pois[:, c] for c in range(3))
    t = (p[1] * f[2] - p[2] * f[1], p[2] * f[0] - p[0] * f[2], p[0] * f[1] - p[1] * f[0])
    comps = f + t  # force (x, y, z), then moment (x, y, z)

    def link_sum(x, link, weighted):
        out = None
        for k in range(P):
            v = x[link * P + k]
            if weighted:
                v = v * ((k + 1) / P)
            out = v if out is None else out + v
        return out

    S = kin.S  # rows (w, v)
    h = [None] * n
    beyond = None  # sums over the links after the current one
    for link in reversed(range(n)):
        full = [link_sum(x, link, False) for x in comps]
        own = [link_sum(x, link, True) for x in comps] if pri[link] else full
        tot = own if beyond is None else [b + o for b, o in zip(beyond, own)]
        h[link] = (S[link, 3] * tot[0] + S[link, 4] * tot[1] + S[link, 5] * tot[2]
                   + S[link, 0] * tot[3] + S[link, 1] * tot[4] + S[link, 2] * tot[5])
        beyond = full if beyond is None else [b + x for b, x in zip(beyond, full)]
    return jnp.stack(h)


def _link_midpoint_jacobians(arm: Arm, kin: Kinematics, pois) -> tuple:
    """Segment midpoints ``(n, 3)`` and rigid link Jacobians (position part) there ``(n, 3, n)``."""
    n, P = arm.n_dof, arm.points_per_link
    X = pois.reshape(n, P, 3)
    end = X[:, -1]
    if P > 1:
        start = (P * X[:, 0] - end) / (P - 1)  # poi_k = start + (k / P)(end - start)
    else:
        start = kin.frames[:, :3, 3]
    mid = 0.5 * (start + end)
    S = kin.S
    cols = S[None, :, 3:] + jnp.cross(S[None, :, :3], mid[:, None, :])  # (link, joint, 3)
    mask = (jnp.arange(n)[None, :] <= jnp.arange(n)[:, None]).astype(S.dtype)
    return mid, jnp.swapaxes(cols * mask[:, :, None], 1, 2)


def obstacle_policy(arm: Arm, kin: Kinematics, q, obs, gain, a, D, mode: str = "point", *,
                    pois=None, poi_jac=None, form: str = "minus") -> Float[Array, " n"]:
    """Obstacle-avoidance policy (3.34 corrected, E9):
    ``q_dd_obs = sum_{i,k} J_{poi,i,k}^T (-gamma sum_o grad V_o(x_{poi,i,k}))``.

    Arguments:
        arm, kin, q: the arm, its shared forward-kinematics pass and configuration.
        obs: :class:`~redman_jax.ObstacleSet`.
        gain: ``gamma`` (1000 acceleration domain, 10 velocity domain); a, D: potential amplitude and
            range (0.05, 0.75 m).
        mode: ``"point"`` (default: each point's own 3 x n Jacobian, exact on a telescoping prismatic
            segment) or ``"link"`` (the thesis: the forces of a link's points summed and applied
            through one rigid link Jacobian at the segment midpoint; moments ignored).
        pois, poi_jac: precomputed point positions (else computed from ``kin``) / point Jacobians
            (if given, ``J^T f`` is their einsum; else :func:`poi_jacobian_transpose`, which never
            forms them).
        form: obstacle potential form (``"minus"``, SPEC E4).
    """
    if pois is None:
        pois = poi_positions_from(arm, kin, q)
    if mode == "point" and poi_jac is None:  # forces as planes, J^T f by suffix sums
        g = _obstacle_gradient_planes(obs, tuple(pois[:, j] for j in range(3)), a, D, form)
        return poi_jacobian_transpose(arm, kin, pois, tuple(-gain * gj for gj in g))
    f = -gain * obstacle_gradients(obs, pois, a, D, form)  # (m, 3) forces, one fused evaluation
    if mode == "point":
        return jnp.einsum("mjn,mj->n", poi_jac, f)
    if mode == "link":
        _, Jl = _link_midpoint_jacobians(arm, kin, pois)
        F = f.reshape(arm.n_dof, arm.points_per_link, 3).sum(1)
        return jnp.einsum("ljn,lj->n", Jl, F)
    raise ValueError(f"obstacle_policy: mode must be 'point' or 'link', got {mode!r}")


def joint_limit_policy(arm: Arm, q: Float[Array, " n"], a, outside) -> Float[Array, " n"]:
    """Joint-limit avoidance (3.35, exact simplification E12):
    ``-a u / (h^2 - u^2)^(3/2)`` for ``|u| < h`` and ``-sign(u) * outside`` beyond the limits,
    with ``u = q - (q_min + q_max)/2`` and ``h = (q_max - q_min)/2``; zero for unlimited joints.
    It equals ``-d/dq [a (h^2 - u^2)^(-1/2)]`` and always pushes inward. NaN-free gradients (double
    ``where``).

    Inside the limits the magnitude is capped at ``outside``: the barrier grows without bound as a
    joint nears its limit (about 1e25 for a joint that sits on its limit up to rounding, e.g. a URDF
    start pose clipped onto a limit), which no projector or solver survives; the thesis's value
    beyond the limits is the natural saturation, and the cap makes the policy continuous there.
    Below the cap the formula is unchanged.
    """
    q_mid = 0.5 * (arm.q_min + arm.q_max)
    h = 0.5 * (arm.q_max - arm.q_min)
    u = q - q_mid
    inside = jnp.abs(u) < h
    den = jnp.where(inside, h * h - u * u, 1.0)
    barrier = jnp.clip(-a * u / (den * jnp.sqrt(den)), -outside, outside)
    val = jnp.where(inside, barrier, -jnp.sign(u) * outside)
    return jnp.where(arm.limited, val, 0.0)


def damping_policy(qd: Float[Array, " n"], gain) -> Float[Array, " n"]:
    """Null-space damping (3.36): ``-G_d q_d``."""
    return -gain * qd


def nullspace_policy(arm: Arm, kin: Kinematics, q, qd, obs, gains: PolicyGains, mode: str = "point",
                     *, pois=None, poi_jac=None, form: str = "minus") -> Float[Array, " n"]:
    """The summed policy ``h`` of 3.33: obstacles + joint limits + damping (``gains`` selects the
    acceleration- or velocity-domain variant; ``qd`` may be zeros for the velocity domain)."""
    h_obs = obstacle_policy(arm, kin, q, obs, gains.gamma, gains.obs_a, gains.obs_D, mode,
                            pois=pois, poi_jac=poi_jac, form=form)
    return h_obs + joint_limit_policy(arm, q, gains.jl_a, gains.jl_outside) + damping_policy(qd, gains.damping)
