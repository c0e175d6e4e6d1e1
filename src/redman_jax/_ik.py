"""Trajectory inverse kinematics and scenario validation (thesis 2.7, 3.3.6, 3.4; SPEC section 8).

The IK turns an operational-space :class:`~redman_jax.Reference` into the joint trajectory
``(q_d, q_dot_d, q_ddot_d)`` the joint-space controller tracks. It runs offline, one sample at a
time, as **one** ``lax.scan`` over ``k = 0 .. N-1`` with state ``(q_k, q_dot_d[k-1])`` from
``(q0, 0)``; a batch of scenarios (the 20 seeds of a case) is one ``vmap`` of that scan.

Optimisation-based IK (``method="qp"``, 3.37-3.41 as corrected by SPEC section 8), at sample ``k``:

* task (3.13, 3.38 corrected, E1): with ``e_p = p_d[k] - p(q_k)`` (the sample ``q_k`` was meant to
  reach) and ``e_o = vec(Q_d[k] (x) Q(q_k)^-1)``::

      x_dot_ref = [ v_d[k] + e_p / ts ;  omega_d[k] + K_r clip(e_o, 0.075) ]   (rot = 1)
                = [ v_d[k] + e_p / ts ]                                          (rot = 0)

  and ``J_s = [S_t J_v; S_r J_w]`` (rows only, ``S_t = 1``, ``S_r = 0.2``; the reference is not
  scaled, E7). Orientation switching keeps fixed shapes: the rotational rows are zeroed when
  ``rot = 0`` (they then contribute nothing to the objective, the pseudo-inverse or its damping);
* null space (3.41, 3.29-3.32): ``v_ns = alpha (I - J# J_s) h_IK(q_k)``,
  ``h_IK = q_dot_obs + q_dot_jl`` with the velocity-domain gains (gamma 10, joint limit a = 1 / 50
  outside, alpha 0.1; E17, U23) from :mod:`redman_jax._nullspace`;
* objective (3.37): ``u* = argmin |J_s u - x_dot_ref|^2 + w |u|^2``, ``w = 1e-4`` (U6), i.e. the
  QP ``1/2 u^T (J_s^T J_s + w I) u - (J_s^T x_dot_ref)^T u``;
* bounds (3.39-3.40 corrected, E16; 40 rad/s^2 [T], 40 m/s^2 for the lift)::

      ub = min(q_dot_d[k-1] + 40 ts, (q_max - q_k) / ts),  lb = max(q_dot_d[k-1] - 40 ts, (q_min - q_k) / ts)

  (unlimited joints, Rz: the acceleration terms only; ``lb > ub``: both set to their mean), applied
  to the total velocity (U24): ``lb - v_ns <= u <= ub - v_ns``;
* obstacles (U7): on the ``n_pairs = 16`` closest (point of interest, obstacle) pairs with signed
  distance ``d_j < 0.3`` m, the linearised constraint
  ``d_j + ts grad_q d_j . (u + v_ns) >= 0.11`` with ``grad_q d_j = grad_x sdf_j(x_i)^T J_poi,i``;
* ``q_dot_d[k] = u* + v_ns``, ``q_{k+1} = q_k + ts q_dot_d[k]``,
  ``q_ddot_d[k] = (q_dot_d[k] - q_dot_d[k-1]) / ts``.

The QP is solved by :func:`redman_jax._qp.solve_qp` (interior point + active-set polish; its primal
and dual residuals are logged per sample). After the last valid sample ``n - 1`` the state is
frozen and ``(q_dot_d, q_ddot_d) = 0`` (SPEC section 6: the controller holds ``(q_{N-1}, 0, 0)``),
so padded samples repeat the final configuration at rest.

For comparison (thesis 2.7.1-2.7.2):

* ``method="pinv"`` (2.42): ``q_dot_d = J_s^+ x_dot_d + alpha (I - J_s^+ J_s) h`` with the
  Moore-Penrose inverse and the feed-forward ``x_dot_d = [v_d; omega_d]`` only (the thesis's
  "drift"); ``pinv_feedback=True`` adds the 3.38 error terms.
* ``method="dls"`` (2.43): a position step toward the next sample,
  ``dq = J_s^T (J_s J_s^T + lam^2 I)^-1 e_d + ts alpha (I - J# J_s) h``,
  ``e_d = [p_d[k+1] - p(q_k); S_r-free e_o(Q_d[k+1], Q(q_k))]`` with the adaptive ``lam`` (3.32),
  ``q_dot_d[k] = dq / ts``.

Neither enforces bounds or obstacle constraints.

Validation (SPEC section 8; the reseed rule is thesis 3.4): an IK trajectory is valid when every
point of interest keeps at least its link width (0.10 m) from every obstacle at every valid sample,
every limited joint stays within its limits, the final end-effector position is within 0.10 m of
the final reference sample, and nothing is NaN. :func:`validated_scenarios` returns, for each
requested seed, the first valid scenario among ``seed, seed + 1000, seed + 2000, ...``, running
the IK of all pending seeds of a retry round as one batch.
"""

from __future__ import annotations

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._kinematics import jacobian_from, kinematics, poi_jacobians_from, poi_link_index, poi_positions, poi_positions_from
from ._math import as_float, check_finite, check_initial_state, check_positive
from ._math import cast_floating, clip_norm, quat_error, rot_to_quat
from ._nullspace import PolicyGains, damped_pinv, ik_policy_gains, joint_limit_policy, nullspace_projector
from ._fields import DISTANCE_CLAMP, obstacle_potential_dr, points_sdf_and_normals
from ._obstacles import ObstacleSet, obstacle_distances
from ._qp import QPSettings, solve_qp
from ._robot import Arm
from ._scenario import Reference, Scenario, check_reference_values

__all__ = [
    "IKParams",
    "IKResult",
    "ik_reference",
    "ik_trajectory",
    "ik_step_qp",
    "validate_ik",
    "validated_scenarios",
    "METHODS",
]

METHODS = ("qp", "pinv", "dls")


def _arr(x):
    return as_float(x)


class IKParams(eqx.Module):
    """IK settings (SPEC section 8). Numbers are arrays (never recompile); structure is static.

    * ``w``: Tikhonov weight of 3.37 (1e-4, U6); ``K_r``: orientation gain of 3.38 (40, U5);
      ``S_t``, ``S_r``: Jacobian row scaling of 3.13 (1, 0.2); ``ori_clip``: 3.15 clip (0.075).
    * ``acc_limit``: joint acceleration bound of 3.39-3.40 (40 rad/s^2, and m/s^2 for the lift).
    * ``margin``: obstacle constraint distance (0.11 m); ``activation``: pairs farther than this are
      not constrained (0.3 m); ``obstacle_rate``: ``xi`` in ``ts grad_q d . q_dot >= -xi (d - margin)``
      (1: SPEC U7's ``d + ts grad_q d . q_dot >= margin``; ``< 1`` a velocity damper).
    * ``policy``: null-space gains (:func:`~redman_jax._nullspace.ik_policy_gains`: alpha 0.1,
      gamma 10, joint limit a 1 / 50, no damping; pseudo-inverse damping 0.1 sigma_min, floor 0.01).
    * ``ns_speed_limit``: the null-space velocity ``v_ns`` is scaled down (direction kept, so it stays
      in the null space) to at most this joint speed (2 rad/s; PROPOSAL, ``inf`` disables). The
      velocity-domain obstacle policy grows like ``1/r^4`` (``|v_ns|`` ~7 rad/s at 0.3 m, 1e3 rad/s at
      0.1 m); with the bounds shifted by ``v_ns`` (U24) the QP variable ``u`` must then cancel it,
      and the Tikhonov term ``w |u|^2`` drags the tracking (measured: 5 cm errors and infeasible QPs).
    * ``goal_tolerance``: final end-effector error for a valid IK (0.10 m); ``limit_tolerance``:
      allowed joint-limit overshoot in validation (1e-6, above the QP tolerance times ts).
    * static: ``n_pairs`` (16), ``method`` (``"qp"``, ``"pinv"``, ``"dls"``), ``jac_scaling``
      (``"rows_only"`` as the thesis, or ``"consistent"``: the rotational reference scaled by
      ``S_r`` too, E7), ``pinv_feedback`` (add the 3.38 error terms to 2.42), ``braking`` (position
      bounds also limit the speed toward a limit to what the acceleration bound can stop in time;
      PROPOSAL, default on; off = 3.39-3.40 literally), ``qp`` settings.
    """

    w: Float[Array, ""] = eqx.field(default=1e-4, converter=_arr)
    K_r: Float[Array, ""] = eqx.field(default=40.0, converter=_arr)
    S_t: Float[Array, ""] = eqx.field(default=1.0, converter=_arr)
    S_r: Float[Array, ""] = eqx.field(default=0.2, converter=_arr)
    ori_clip: Float[Array, ""] = eqx.field(default=0.075, converter=_arr)
    acc_limit: Float[Array, ""] = eqx.field(default=40.0, converter=_arr)
    margin: Float[Array, ""] = eqx.field(default=0.11, converter=_arr)
    activation: Float[Array, ""] = eqx.field(default=0.3, converter=_arr)
    obstacle_rate: Float[Array, ""] = eqx.field(default=1.0, converter=_arr)
    ns_speed_limit: Float[Array, ""] = eqx.field(default=2.0, converter=_arr)
    policy: PolicyGains = eqx.field(default_factory=ik_policy_gains)
    goal_tolerance: Float[Array, ""] = eqx.field(default=0.10, converter=_arr)
    limit_tolerance: Float[Array, ""] = eqx.field(default=1e-6, converter=_arr)
    n_pairs: int = eqx.field(static=True, default=16)
    method: str = eqx.field(static=True, default="qp")
    jac_scaling: str = eqx.field(static=True, default="rows_only")
    pinv_feedback: bool = eqx.field(static=True, default=False)
    braking: bool = eqx.field(static=True, default=True)
    qp: QPSettings = eqx.field(default_factory=QPSettings)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"IKParams.method: expected one of {METHODS}, got {self.method!r}")
        if self.jac_scaling not in ("rows_only", "consistent"):
            raise ValueError(f"IKParams.jac_scaling: expected 'rows_only' or 'consistent', got {self.jac_scaling!r}")
        if not isinstance(self.n_pairs, int) or self.n_pairs < 1:
            raise ValueError(f"IKParams.n_pairs: expected a positive int, got {self.n_pairs!r}")
        # numbers, where concrete (not traced): a zero or NaN acceleration bound made the position
        # bounds NaN and every candidate silently invalid
        # (``activation < 0`` is allowed: it switches the constraint rows off)
        for name in ("acc_limit", "goal_tolerance", "S_t", "S_r", "ori_clip"):
            check_positive(f"IKParams.{name}", getattr(self, name))
        check_positive("IKParams.ns_speed_limit", self.ns_speed_limit, allow_inf=True)
        for name in ("w", "limit_tolerance", "K_r", "obstacle_rate"):
            check_positive(f"IKParams.{name}", getattr(self, name), allow_zero=True)
        # where concrete: a NaN margin or activation makes the obstacle rows of every QP NaN
        for name in ("margin", "activation"):
            check_finite(f"IKParams.{name}", getattr(self, name))


class IKResult(eqx.Module):
    """Joint trajectory and per-sample diagnostics of one IK run (``N`` = reference capacity).

    * ``q``, ``qd``, ``qdd`` ``(N, n)``: ``q_d[k]`` (the configuration at sample k), ``q_dot_d[k]``,
      ``q_ddot_d[k]``; zero velocity and acceleration from sample ``n_samples - 1`` on.
    * ``mask`` ``(N,)``, ``n_samples``: valid samples (copied from the reference).
    * ``ee_error`` ``(N,)``: ``|p_d[k] - p(q_k)|``; ``ori_error`` ``(N,)``: unclipped ``|e_o|`` on
      ``rot = 1`` samples (0 elsewhere); ``min_distance`` ``(N,)``: smallest point-of-interest
      signed distance at ``q_k``; ``clearance`` ``(N,)``: smallest ``d - link width`` (< 0: collision).
    * ``qp_primal``, ``qp_dual`` ``(N,)``: QP residuals (infinity norms; 0 for pinv / dls);
      ``qp_converged`` ``(N,)``; ``qp_iterations`` ``(N,)``; ``n_constrained`` ``(N,)``: obstacle
      pairs within the activation distance.
    * ``final_error``: ``|p_d[n-1] - p(q_{n-1})|``.
    * ``collision_free``, ``within_limits``, ``reached``, ``finite``: the validation criteria;
      ``valid``: all four.
    """

    q: Float[Array, "N n"]
    qd: Float[Array, "N n"]
    qdd: Float[Array, "N n"]
    mask: Bool[Array, " N"]
    n_samples: Int[Array, ""]
    ee_error: Float[Array, " N"]
    ori_error: Float[Array, " N"]
    min_distance: Float[Array, " N"]
    clearance: Float[Array, " N"]
    qp_primal: Float[Array, " N"]
    qp_dual: Float[Array, " N"]
    qp_converged: Bool[Array, " N"]
    qp_iterations: Int[Array, " N"]
    n_constrained: Int[Array, " N"]
    final_error: Float[Array, ""]
    collision_free: Bool[Array, ""]
    within_limits: Bool[Array, ""]
    reached: Bool[Array, ""]
    finite: Bool[Array, ""]
    valid: Bool[Array, ""]


# ----------------------------------------------------------------------------------------------
# One sample


class _Sample(eqx.Module):
    p: Array
    v: Array
    quat: Array
    omega: Array
    rot: Array
    p_next: Array
    quat_next: Array
    moving: Array  # k < n_samples - 1: a step is taken
    valid: Array  # k < n_samples
    ts: Array
    active: Array  # the run is still wanted (see ``stop_on_invalid``); set by the scan's body


def _task(arm: Arm, kin, ref: _Sample, params: IKParams, feedback: bool = True):
    """Scaled, switched task Jacobian ``J_s`` (6, n), its row mask and ``x_dot_ref`` (3.13, 3.38)."""
    dtype = kin.ee.dtype
    J = jacobian_from(kin)
    p = kin.ee[:3, 3]
    quat = rot_to_quat(kin.ee[:3, :3])
    e_p = ref.p - p
    e_o = quat_error(ref.quat, quat)
    ts_inv = 1.0 / ref.ts
    on = ref.rot > 0.5
    row_mask = jnp.concatenate([jnp.ones(3, bool), jnp.broadcast_to(on, (3,))])
    scale = jnp.concatenate([jnp.broadcast_to(params.S_t, (3,)), jnp.broadcast_to(params.S_r, (3,))]).astype(dtype)
    J_s = jnp.where(row_mask[:, None], scale[:, None] * J, 0.0)
    lin = ref.v + (e_p * ts_inv if feedback else 0.0)
    ang = ref.omega + (params.K_r * clip_norm(e_o, params.ori_clip) if feedback else 0.0)
    if params.jac_scaling == "consistent":
        lin, ang = params.S_t * lin, params.S_r * ang
    xdot = jnp.where(row_mask, jnp.concatenate([lin, ang]), 0.0)
    return J_s, row_mask, xdot, e_p, jnp.where(on, e_o, 0.0), p, quat


def _braking_speed(gap, acc, ts):
    """Largest speed toward a limit ``gap`` away from which a joint decelerating by ``acc ts`` per
    sample still stops before it. The distance of the discrete stop ``ts sum_i max(v - i acc ts, 0)``
    is at most ``v^2 / (2 acc) + v ts / 2 + acc ts^2 / 8`` (maximum over the number of braking
    samples), so ``v = acc (sqrt(ts^2 / 4 + 2 (gap - acc ts^2 / 8) / acc) - ts / 2)`` is safe."""
    gap = jnp.maximum(gap - 0.125 * acc * ts * ts, 0.0)
    return acc * (jnp.sqrt(0.25 * ts * ts + 2.0 * gap / acc) - 0.5 * ts)


def _bounds(arm: Arm, q, qd_prev, ts, params: IKParams):
    """Velocity bounds of 3.39-3.40 (corrected, E16); Rz: acceleration only; ``lb > ub`` -> mean.

    With ``params.braking`` the position terms also include the braking speed (PROPOSAL): the
    one-step terms ``(q_max - q) / ts`` let a joint arrive at a limit faster than the acceleration
    bound can stop it, ``lb > ub`` at the next sample and the mean then overshoots the limit
    (measured on warehouse scenes)."""
    acc = params.acc_limit * ts
    ub = qd_prev + acc
    lb = qd_prev - acc
    up = (arm.q_max - q) / ts
    down = (arm.q_min - q) / ts
    if params.braking:
        up = jnp.minimum(up, _braking_speed(arm.q_max - q, params.acc_limit, ts))
        down = jnp.maximum(down, -_braking_speed(q - arm.q_min, params.acc_limit, ts))
    ub = jnp.where(arm.limited, jnp.minimum(ub, up), ub)
    lb = jnp.where(arm.limited, jnp.maximum(lb, down), lb)
    bad = lb > ub
    mid = 0.5 * (lb + ub)
    return jnp.where(bad, mid, lb), jnp.where(bad, mid, ub)


def _policy(arm: Arm, q, D, normals, poi_jac, pol: PolicyGains):
    """``h_IK = q_dot_obs + q_dot_jl`` (3.34 corrected E9, 3.35; IK gains, no damping, 3.3.6).

    ``q_dot_obs = sum_i J_poi,i^T (-gamma sum_o V_o'(max(d_io, 1e-3)) n_io)`` is evaluated from the
    distances ``D`` ``(m, K)`` and unit normals ``(m, K, 3)`` the step already has (the same formula
    as :func:`redman_jax._nullspace.obstacle_policy`, tested equal; it saves a second pass over all
    (point, obstacle) pairs, the dominant cost with the warehouse's 146 boxes).

    The joint-limit term is capped at its out-of-range value (``pol.jl_outside``, 50): 3.35 grows
    like ``(h^2 - u^2)^{-3/2}`` and exceeds that value within ~0.03 rad (revolute) / 0.04 m (lift)
    of a limit, reaching 1e14 when the QP's position bound puts a joint on its limit; then
    ``q_dot_d = u + v_ns`` loses every digit of ``u`` (measured: 3 cm end-effector jumps).
    """
    slope = jnp.where(D <= pol.obs_D, obstacle_potential_dr(jnp.maximum(D, DISTANCE_CLAMP), pol.obs_a, pol.obs_D), 0.0)
    force = -pol.gamma * jnp.einsum("mk,mkj->mj", slope, normals)
    h_obs = jnp.einsum("mjn,mj->n", poi_jac, force)
    h_jl = jnp.clip(joint_limit_policy(arm, q, pol.jl_a, pol.jl_outside), -pol.jl_outside, pol.jl_outside)
    return h_obs + h_jl


def _geometry(arm: Arm, kin, q, obs: ObstacleSet):
    """Points of interest, their Jacobians, and distances / unit normals to every obstacle slot."""
    pois = poi_positions_from(arm, kin, q)
    poi_jac = poi_jacobians_from(arm, kin, pois)
    D, normals = points_sdf_and_normals(obs, pois)  # every (point, slot) pair, one fused pass
    return pois, poi_jac, D, normals


def _cap(v, limit):
    """Scale ``v`` so that ``|v|_inf <= limit`` (direction kept)."""
    big = jnp.max(jnp.abs(v))
    return v * jnp.where(big > limit, limit / jnp.where(big > limit, big, 1.0), 1.0)


def _pair_distances(obs: ObstacleSet, pois):
    """Signed distances of every point of interest to every obstacle slot, ``(m, K)``."""
    return jax.vmap(lambda x: obstacle_distances(obs, x))(pois)


def _k_smallest(x: Float[Array, " N"], k: int):
    """The ``k`` smallest entries of ``x`` in ascending order and their indices (ties: lowest
    index first), as ``jax.lax.top_k(-x, k)`` gives them (tested), by ``k`` passes of two plain
    reductions (the minimum, then the lowest index holding it). XLA's CPU ``top_k`` sorts the whole
    array and its ``argmin`` is a slow variadic reduction; for the IK's 16 closest of 5328
    (point, obstacle) pairs (the warehouse) this is 16x faster than ``top_k``."""
    iota = jnp.arange(x.shape[0])

    def pick(x, _):
        v = jnp.min(x)
        i = jnp.min(jnp.where(x == v, iota, x.shape[0] - 1))
        return jnp.where(iota == i, jnp.inf, x), (v, i)

    _, (vals, idx) = jax.lax.scan(pick, x, None, length=k)
    return vals, idx


def _obstacle_rows(D, normals, poi_jac, v_ns, ts, params: IKParams):
    """Linearised collision constraints (U7) on the ``n_pairs`` closest pairs within the activation
    distance: rows ``A_j = ts grad_q d_j`` (``grad_q d_j = n_j^T J_poi``, ``n_j`` the sdf gradient)
    and lower bounds ``-xi (d_j - margin) - A_j . v_ns`` (``-inf`` for unused rows)."""
    m, K = D.shape
    k = min(params.n_pairs, m * K)
    d, idx = _k_smallest(D.reshape(-1), k)
    i_poi = idx // K
    grad_x = normals.reshape(m * K, 3)[idx]
    grad_q = jnp.einsum("kj,kjn->kn", grad_x, poi_jac[i_poi])
    A = ts * grad_q
    on = d < params.activation
    lo = -params.obstacle_rate * (d - params.margin) - A @ v_ns
    lo = jnp.where(on, lo, -jnp.inf)
    A = jnp.where(on[:, None], A, 0.0)
    return A, lo, on


def ik_step_qp(arm: Arm, obs: ObstacleSet, q, qd_prev, ref, params: IKParams):
    """One optimisation-based IK sample (3.37-3.41, see the module docstring).

    Returns ``(q_dot_d, diagnostics)``. ``ref`` carries ``p, v, quat, omega, rot, ts`` of sample k.
    """
    dtype = q.dtype
    n = arm.n_dof
    ts = ref.ts
    kin = kinematics(arm, q)
    J_s, row_mask, xdot, e_p, e_o, _, _ = _task(arm, kin, ref, params)
    pol = params.policy
    J_pinv, _ = damped_pinv(J_s, pol.lam_ratio, pol.lam_floor, row_mask=row_mask)
    N = nullspace_projector(J_s, J_pinv)
    pois, poi_jac, D, normals = _geometry(arm, kin, q, obs)
    h = _policy(arm, q, D, normals, poi_jac, pol)
    v_ns = _cap(pol.alpha * (N @ h), params.ns_speed_limit)
    lb, ub = _bounds(arm, q, qd_prev, ts, params)
    A, lo, on = _obstacle_rows(D, normals, poi_jac, v_ns, ts, params)
    P = J_s.T @ J_s + params.w * jnp.eye(n, dtype=dtype)
    c = -(J_s.T @ xdot)
    hi = jnp.full(lo.shape, jnp.inf, dtype)
    sol = solve_qp(P, c, A, lo, hi, lb - v_ns, ub - v_ns, params.qp, active=ref.active)
    qd = sol.x + v_ns
    diag = dict(ee_error=jnp.linalg.norm(e_p), ori_error=jnp.linalg.norm(e_o),
                min_distance=jnp.min(D), clearance=_clearance(arm, D), qp_primal=sol.primal_residual, qp_dual=sol.dual_residual,
                qp_converged=sol.converged, qp_iterations=sol.iterations,
                n_constrained=jnp.sum(on).astype(jnp.int32))
    return qd, diag


def _step_pinv(arm: Arm, obs, q, qd_prev, ref, params: IKParams):
    """2.42: ``q_dot_d = J_s^+ x_dot_d + alpha (I - J_s^+ J_s) h`` (Moore-Penrose; tiny floor)."""
    kin = kinematics(arm, q)
    J_s, row_mask, xdot, e_p, e_o, _, _ = _task(arm, kin, ref, params, feedback=params.pinv_feedback)
    pol = params.policy
    J_plus, _ = damped_pinv(J_s, 0.0, 1e-9, row_mask=row_mask)
    _, poi_jac, D, normals = _geometry(arm, kin, q, obs)
    h = _policy(arm, q, D, normals, poi_jac, pol)
    qd = J_plus @ xdot + _cap(pol.alpha * (nullspace_projector(J_s, J_plus) @ h), params.ns_speed_limit)
    return qd, _simple_diag(arm, D, e_p, e_o)


def _step_dls(arm: Arm, obs, q, qd_prev, ref, params: IKParams):
    """2.43: ``dq = J_s^T (J_s J_s^T + lam^2 I)^-1 e_d + ts alpha (I - J# J_s) h`` toward sample k+1."""
    kin = kinematics(arm, q)
    nxt = eqx.tree_at(lambda r: (r.p, r.quat), ref, (ref.p_next, ref.quat_next))
    J_s, row_mask, _, _, _, p, quat = _task(arm, kin, nxt, params, feedback=False)
    _, _, _, e_p, e_o, _, _ = _task(arm, kin, ref, params, feedback=False)
    pol = params.policy
    J_pinv, _ = damped_pinv(J_s, pol.lam_ratio, pol.lam_floor, row_mask=row_mask)
    # pose error as a displacement: position, and the rotation vector ~ 2 e_o; scaled like J_s
    # (the rows of J_s are scaled, so the error must be too, or the rotation overshoots 1 / S_r x)
    e_d = jnp.concatenate([params.S_t * (ref.p_next - p), params.S_r * 2.0 * quat_error(ref.quat_next, quat)])
    e_d = jnp.where(row_mask, e_d, 0.0)
    _, poi_jac, D, normals = _geometry(arm, kin, q, obs)
    h = _policy(arm, q, D, normals, poi_jac, pol)
    dq = J_pinv @ e_d + ref.ts * _cap(pol.alpha * (nullspace_projector(J_s, J_pinv) @ h), params.ns_speed_limit)
    return dq / ref.ts, _simple_diag(arm, D, e_p, e_o)


def _clearance(arm: Arm, D):
    """Smallest ``d - width`` over all (point, obstacle) pairs (< 0: a point within its link width)."""
    width = arm.widths[jnp.asarray(poi_link_index(arm))]
    return jnp.min(D - width[:, None])


def _simple_diag(arm, D, e_p, e_o):
    z = jnp.zeros((), D.dtype)
    return dict(ee_error=jnp.linalg.norm(e_p), ori_error=jnp.linalg.norm(e_o), min_distance=jnp.min(D),
                clearance=_clearance(arm, D),
                qp_primal=z, qp_dual=z, qp_converged=jnp.asarray(True), qp_iterations=jnp.asarray(0, jnp.int32),
                n_constrained=jnp.asarray(0, jnp.int32))


_STEPS = {"qp": ik_step_qp, "pinv": _step_pinv, "dls": _step_dls}


# ----------------------------------------------------------------------------------------------
# The trajectory


def _check_reference(arm: Arm, ref: Reference, q0):
    N = ref.p.shape[-2]
    for name, shape in (("p", (N, 3)), ("v", (N, 3)), ("quat", (N, 4)), ("omega", (N, 3)), ("rot", (N,)),
                        ("mask", (N,))):
        got = tuple(getattr(ref, name).shape)
        if got != shape:
            raise ValueError(f"Reference.{name}: expected shape {shape}, got {got}")
    if N < 2:
        raise ValueError(f"Reference: needs at least 2 samples of capacity, got {N}")
    check_initial_state("q0", q0, arm.n_dof)


def _in_limits(arm: Arm, q, tol):
    """Per joint (``q``: ``(n,)`` or ``(N, n)``): within its limits up to ``tol``, or unlimited."""
    return ((q >= arm.q_min - tol) & (q <= arm.q_max + tol)) | ~arm.limited


def _ik_single(arm: Arm, obs: ObstacleSet, ref: Reference, q0, params: IKParams, stop=False) -> IKResult:
    dtype = jnp.result_type(ref.p.dtype, arm.q0.dtype)
    params = cast_floating(params, dtype)  # float64 defaults would promote a float32 scan's carry
    N = ref.p.shape[0]
    n_s = jnp.clip(ref.n_samples, 1, N)
    k = jnp.arange(N)
    nxt = jnp.minimum(k + 1, n_s - 1)
    ts = jnp.asarray(ref.ts, dtype)
    xs = _Sample(p=ref.p.astype(dtype), v=ref.v.astype(dtype), quat=ref.quat.astype(dtype),
                   omega=ref.omega.astype(dtype), rot=ref.rot.astype(dtype),
                   p_next=ref.p[nxt].astype(dtype), quat_next=ref.quat[nxt].astype(dtype),
                   moving=k < n_s - 1, valid=k < n_s, ts=jnp.broadcast_to(ts, (N,)),
                   active=jnp.ones((N,), bool))
    step_fn = _STEPS[params.method]
    tol = params.limit_tolerance
    stop = jnp.asarray(stop, bool)

    def body(carry, s):
        q, qd_prev, alive = carry
        s = eqx.tree_at(lambda r: r.active, s, alive)
        qd, diag = step_fn(arm, obs, q, qd_prev, s, params)
        qd = jnp.where(s.moving & alive, qd, 0.0)  # a stopped run holds its configuration
        qdd = jnp.where(s.moving, (qd - qd_prev) / s.ts, 0.0)
        q_next = q + s.ts * qd
        # the validity criteria at this sample (as below): a run that breaks one cannot be valid
        ok = (jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd)) & (diag["clearance"] >= 0.0)
              & jnp.all(_in_limits(arm, q, tol)))
        alive = alive & (ok | ~s.valid | ~stop)
        return (q_next, qd, alive), (q, qd, qdd, diag)

    q0 = (arm.q0 if q0 is None else jnp.asarray(q0)).astype(dtype)
    _, (q, qd, qdd, diag) = jax.lax.scan(body, (q0, jnp.zeros_like(q0), jnp.asarray(True)), xs)
    valid_s = xs.valid
    zero_f = lambda x: jnp.where(valid_s, x, 0.0)
    last = n_s - 1
    final_error = jnp.linalg.norm(ref.p[last].astype(dtype) - _ee(arm, q[last]))
    res = IKResult(
        q=q, qd=qd, qdd=qdd, mask=valid_s, n_samples=n_s,
        ee_error=zero_f(diag["ee_error"]), ori_error=zero_f(diag["ori_error"]),
        min_distance=jnp.where(valid_s, diag["min_distance"], jnp.inf),
        clearance=jnp.where(valid_s, diag["clearance"], jnp.inf),
        qp_primal=zero_f(diag["qp_primal"]), qp_dual=zero_f(diag["qp_dual"]),
        qp_converged=diag["qp_converged"] | ~valid_s,
        qp_iterations=jnp.where(valid_s, diag["qp_iterations"], 0),
        n_constrained=jnp.where(valid_s, diag["n_constrained"], 0), final_error=final_error,
        collision_free=jnp.asarray(False), within_limits=jnp.asarray(False), reached=jnp.asarray(False),
        finite=jnp.asarray(False), valid=jnp.asarray(False),
    )
    # validity from the step's own distances at every q_k (validate_ik recomputes independently)
    finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd)) & jnp.all(jnp.isfinite(qdd))
    clear = jnp.all(jnp.where(valid_s, diag["clearance"] >= 0.0, True)) & finite
    within = jnp.all(_in_limits(arm, q, tol) | ~valid_s[:, None]) & finite
    reached = (final_error < params.goal_tolerance) & finite
    return eqx.tree_at(lambda r: (r.collision_free, r.within_limits, r.reached, r.finite, r.valid), res,
                       (clear, within, reached, finite, clear & within & reached))


def _ee(arm, q):
    return kinematics(arm, q).ee[:3, 3]


def _validate_one(arm: Arm, obs: ObstacleSet, ref: Reference, res: IKResult, params: IKParams):
    """Independent recomputation of the validation criteria from ``res.q`` (SPEC section 8)."""
    mask = res.mask
    finite = (jnp.all(jnp.isfinite(res.q)) & jnp.all(jnp.isfinite(res.qd)) & jnp.all(jnp.isfinite(res.qdd)))
    q = jnp.where(jnp.isfinite(res.q), res.q, 0.0)
    pois = jax.vmap(lambda qq: poi_positions(arm, qq))(q)  # (N, m, 3)
    D = jax.vmap(lambda P: _pair_distances(obs, P))(pois)  # (N, m, K)
    width = arm.widths[jnp.asarray(poi_link_index(arm))]  # (m,)
    clear = jnp.all((D >= width[None, :, None]) | ~mask[:, None, None])
    within = jnp.all(_in_limits(arm, q, params.limit_tolerance) | ~mask[:, None])
    last = res.n_samples - 1
    err = jnp.linalg.norm(ref.p[last] - _ee(arm, q[last]))
    reached = err < params.goal_tolerance
    ok = finite & clear & within & reached
    return clear & finite, within & finite, reached & finite, finite, ok


def ik_reference(arm: Arm, reference: Reference, obstacles: ObstacleSet, params: IKParams | None = None,
                 q0=None, *, stop_on_invalid=False) -> IKResult:
    """IK of one reference (or a batch: a leading axis on ``reference`` and ``obstacles``).

    **Arguments:** ``arm``; ``reference`` (:class:`~redman_jax.Reference`, ``N`` samples);
    ``obstacles`` (:class:`~redman_jax.ObstacleSet`); ``params`` (:class:`IKParams`); ``q0``
    (default ``arm.q0``); ``stop_on_invalid`` (a bool, traced: either value runs the same
    compiled program): a run that breaks a validity criterion at a valid sample (a point of
    interest within its link width of an obstacle, a joint beyond its limit, a non-finite value)
    takes no further QP iteration and holds its configuration from the next sample on. Its
    ``valid`` is false either way, its trajectory after that sample is not the IK's. Under
    ``vmap`` every sample's QP iterates until the batch's slowest member converges, and a candidate
    in collision is typically that member: :func:`validated_scenarios` screens its candidates this
    way (7-DOF welding's retry rounds: 46 % fewer QP iterations of the batch).

    **Returns:** :class:`IKResult` (batched like the inputs).

    **Raises:** ``ValueError`` naming the field for inconsistent shapes and, where concrete, for
    a reference that cannot be run (:func:`~redman_jax._scenario.check_reference_values`: sample
    count, sample time, non-finite values (one reference; in a batch they are that member's
    failure), ``rot`` flags, quaternions that are not unit) or a non-finite ``q0``.
    """
    params = IKParams() if params is None else params
    batched = reference.p.ndim == 3
    # shapes only (an eager x[0] would compile a slice per leaf shape)
    ref0 = jax.eval_shape(lambda r: jax.tree.map(lambda x: x[0], r), reference) if batched else reference
    _check_reference(arm, ref0, q0)
    check_reference_values(reference, "Reference", batch=batched)
    return _ik_jit(arm, reference, obstacles, params, q0, batched, jnp.asarray(stop_on_invalid, bool))


@eqx.filter_jit
def _ik_jit(arm, reference, obstacles, params, q0, batched, stop):
    fn = lambda r, o: _ik_single(arm, o, r, q0, params, stop)
    if batched:
        return jax.vmap(fn)(reference, obstacles)
    return fn(reference, obstacles)


def ik_trajectory(arm: Arm, scenario: Scenario, params: IKParams | None = None, q0=None, *,
                  stop_on_invalid=False) -> IKResult:
    """IK of a :class:`~redman_jax.Scenario` (its reference among its obstacles); a stacked batch of
    scenarios is solved as one ``vmap`` (one compiled scan for all seeds). See :func:`ik_reference`."""
    return ik_reference(arm, scenario.reference, scenario.obstacles, params, q0,
                        stop_on_invalid=stop_on_invalid)


def validate_ik(arm: Arm, scenario: Scenario, ik_result: IKResult, params: IKParams | None = None):
    """Validation of an IK trajectory (SPEC section 8): ``True`` where no point of interest comes
    within its link width (0.10 m) of an obstacle at any valid sample, every limited joint stays
    within its limits (up to ``params.limit_tolerance``), the final end-effector position is within
    ``params.goal_tolerance`` of the last reference sample and nothing is NaN. Recomputed from
    ``ik_result.q`` (independent of the IK's own diagnostics). Returns a bool array: shape ``()`` for
    one scenario, ``(B,)`` for a batch."""
    params = IKParams() if params is None else params
    batched = ik_result.q.ndim == 3
    fn = lambda s, r: _validate_one(arm, s.obstacles, s.reference, r, params)[-1]
    return _validate_jit(fn, scenario, ik_result, batched)


@eqx.filter_jit
def _validate_jit(fn, scenario, ik_result, batched):
    return jax.vmap(fn)(scenario, ik_result) if batched else fn(scenario, ik_result)


# ----------------------------------------------------------------------------------------------
# Scenario pipeline with reseeding (thesis 3.4)


def _pad_batch(tree, size: int):
    """Pad a stacked pytree along its leading axis to ``size`` by repeating its last member (a
    fixed batch size, so every retry round reuses one compilation)."""
    def pad(x):  # on the host: eager jnp ops would compile once per leaf shape (~5 s per build)
        x = np.asarray(x)
        extra = size - x.shape[0]
        return x if extra <= 0 else np.concatenate([x, np.repeat(x[-1:], extra, axis=0)])
    return jax.tree.map(pad, tree)


def validated_scenarios(case: str, seeds, arm: Arm, max_retries: int = 20, params: IKParams | None = None,
                        case_params=None, stats: dict | None = None, screen: bool = True):
    """For each requested seed, the first valid scenario among ``seed, seed + 1000, ...`` (thesis 3.4).

    A candidate is accepted when its generation (and, for the RRT cases, planning) succeeded and its
    IK trajectory passes :func:`validate_ik`. The candidates come from
    :func:`redman_jax._cases.make_scenarios`, which moves a seed on by 1000 on a generation
    failure and calls back here with every retry round's candidates stacked (the next attempt of
    every pending seed, the room left filled with their later attempts): the IK of a round runs as
    one batch, padded to ``len(seeds)`` so that all rounds share one compilation. The outcome is the
    one of trying each seed's attempts in order. With ``screen`` (default) the rounds run with
    ``stop_on_invalid`` (:func:`ik_reference`): a candidate stops iterating at its first collision
    or limit violation, and a seed left without a valid candidate gets its last candidate's full IK
    (the same program). The results are the same either way (``benchmarks/bench_ik.py --rounds``).

    **Returns:** ``(scenarios, ik_results)`` stacked in the order of ``seeds``; ``scenario.seed`` is
    the requested seed, ``seed_used`` the seed that produced it, ``valid`` whether one was found
    within ``max_retries`` moves (if not, the last candidate comes back with ``valid = False``).
    ``stats`` (a dict), if given, receives the generator's rejection counts, ``ik_rounds`` (the
    IK batches run) and ``ik_batch_qp_iterations`` (over those batches and their samples, the
    largest QP iteration count in the batch: what a ``vmap`` of the IK steps through).
    """
    from ._cases import _check_seed, _stack, make_scenarios

    params = IKParams() if params is None else params
    seeds = [_check_seed(s) for s in np.atleast_1d(np.asarray(seeds))]  # int() truncated 2.5 to 2
    if not seeds:
        raise ValueError("validated_scenarios: seeds is empty")
    if max_retries < 0:
        raise ValueError(f"validated_scenarios: max_retries must be >= 0, got {max_retries}")
    B = len(seeds)
    cache: dict = {}

    def run(batch: Scenario, screened: bool):
        b = int(batch.seed.shape[0])
        res = jax.tree.map(np.asarray, ik_trajectory(arm, _pad_batch(batch, B), params, stop_on_invalid=screened))
        counts["ik_rounds"] += 1
        counts["ik_batch_qp_iterations"] += int(res.qp_iterations.max(axis=0).sum())
        seed, used = np.asarray(batch.seed), np.asarray(batch.seed_used)
        for j in range(b):
            if not screened or res.valid[j]:  # a screened invalid run stopped early: not its IK
                cache[(int(seed[j]), int(used[j]))] = jax.tree.map(lambda x, j=j: x[j], res)
        return res, b

    def validate(batch: Scenario):
        res, b = run(batch, screen)
        return np.asarray(res.valid)[:b]

    counts = collections.Counter()
    scen = make_scenarios(case, seeds, arm, params=case_params, validate=validate, max_retries=max_retries,
                          stats=counts)
    keys = list(zip(np.asarray(scen.seed).tolist(), np.asarray(scen.seed_used).tolist()))
    missing = [j for j, k in enumerate(keys) if k not in cache]
    if missing:  # no valid candidate, or generation never succeeded: the full IK for the record
        run(jax.tree.map(lambda x: x[np.asarray(missing)], scen), False)
    if stats is not None:
        stats.update(counts)
    results = [cache[k] for k in keys]
    return scen, _stack(results)
