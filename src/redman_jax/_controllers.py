"""Every controller of the study behind the one interface of :mod:`redman_jax._control_types`
(thesis 2.3-2.4, 3.3.2-3.3.5; SPEC sections 6-7).

``out = controller(gains, arm, ControlState(t, q, qd, z), RefSample, Environment)`` returns the joint
torques, ``dz/dt`` of the controller's integrated state and diagnostics. Controllers hold static
options only; their numbers live in a gains Module of arrays (``controller.default_gains()`` gives the
thesis values, Python floats are converted), so sweeps and gradients over gains never recompile.

Common elements (SPEC section 6):

* ``p, Q`` from one shared forward-kinematics pass (:func:`~redman_jax.kinematics`), from which the
  end-effector Jacobian, the points of interest and their Jacobians, ``M`` and ``c + g`` and
  ``J_dot q_dot`` (3.17, from the same link twists, equal to the jvp form) are all assembled.
* ``e_p = p_d - p``; orientation error ``e_o = vec(Q_d (x) Q^-1)`` with a hemisphere check and
  positive gains (E1), clipped to ``|e_o| <= 0.075`` (3.15).
* Task Jacobian (3.13): ``J_s = [S_t J_v; S_r J_w]`` with ``S_t = 1``, ``S_r = 0.2``. Orientation
  switching (``ref.rot``, an array: no recompilation) zeroes the rotational rows and the rotational
  reference instead of changing shapes; the damped pseudo-inverse of
  :mod:`~redman_jax._nullspace` is exactly the 3-row one then (tested). ``jac_scaling="rows_only"``
  (default, literal 3.14, E7) leaves the reference unscaled; ``"consistent"`` scales it by the same
  ``S``.
* One adaptive damped ``J# = J_s^T (J_s J_s^T + lam^2 I)^-1`` (3.29, 3.32) serves the task term
  and the projector (U21): ``J# b + alpha (I - J# J_s) h = alpha h + J_s^T Y^-1 (b - alpha J_s h)``
  with ``Y = J_s J_s^T + lam^2 I`` -- one ``k x k`` factorisation, no explicit ``J#``.
* Null-space policies ``h`` (3.33-3.36) from :func:`~redman_jax._nullspace.nullspace_policy`.
* ``nullspace="actuator"`` (2.4.4, 2.20) adds ``P_tau tau_0`` with ``tau_0 = alpha M h`` instead:
  ``P_tau = I - J_s^T J#^T`` (``actuator_projector="orthogonal"``) or the dynamically consistent
  ``I - J^T (J M^-1 J^T + lam^2 I)^-1 J M^-1`` (``"dynamic"``, the oblique projector of 2.36 with
  ``W = M``).

Controllers (registry :data:`CONTROLLERS`):

* ``"joint_space"`` :class:`JointSpaceID` (2.5, E2): ``tau = M(qdd_d + K_d(qd_d - qd) + K_p(q_d - q)) + c + g``
  (K_p 1000, K_d 100; needs the IK's joint reference).
* ``"pid"`` :class:`PID` (2.4, E2): ``tau = K_p e + K_d (qd_d - qd) + K_i int e`` (1000/100/0; state
  ``z = int e``; optional gravity compensation).
* ``"velocity"`` :class:`VelocityOSC` (alternative method 2.12-2.14, 3.10-3.15 corrected, E6/E20/E23):
  ``xd_r = [pd_d + K_p e_p; w_d + K_pr clip(e_o)]``, ``qd_r = J# xd_r``, ``dq_r/dt = qd_r``,
  ``qdd_r = K_pq (q_r - q) + K_dq (qd_r - qd) + alpha N h``, ``tau = M qdd_r + c + g``
  (10, 40, 10, 100; state ``z = q_r``, ``q_r(0) = q(0)``).
* ``"velocity_original"`` :class:`VelocityOSCOriginal` (2.7-2.11): ``qd_r = J# xd_r + alpha N h_v(q)``
  (velocity-domain policies), ``qdd_r = d qd_r / dt`` exactly (a jvp along ``qd`` and the reference's
  own rates), ``tau = M qdd_r + c + g + K_qd (qd_r - qd) + K_qp (q_r - q)`` (joint feedback weighted
  by ``M`` by default, see the class).
* ``"acceleration"`` :class:`AccelerationOSC` (2.15-2.17, 3.16-3.17):
  ``xdd_r = [pdd_d + K_d(pd_d - pd) + K_p e_p; wd_d + K_dr(w_d - w) + K_pr clip(e_o)]``,
  ``qdd_r = J#(xdd_r - J_s_dot qd) + alpha N h``, ``tau = M qdd_r + c + g`` (250, 2000, 31, 100).
* ``"impedance"`` :class:`Impedance` (2.18-2.19): ``F = [K_p e_p + K_d(pd_d - pd); K_pr clip(e_o) +
  K_dr(w_d - w)]``, ``tau = J^T F + g(q) + P_tau tau_0`` (2000 N/m, 200 Ns/m; rotational 200/20 and
  gravity compensation are proposals).
* ``"gradient"`` :class:`GradientGuided` (3.28, E30): the acceleration structure with
  ``xdd_r = [K_d(xd_g - pd); -K_dr w + K_pr clip(e_o)]``, ``xd_g`` the guidance velocity of
  :func:`~redman_jax._fields.guidance_velocity` (a = 0.5 m/s, b = 0.1 m), ``Q_d`` the goal
  orientation; orientation on when ``ref.rot`` is (the simulator latches it within 0.5 m of the goal).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_factor, cho_solve
from jaxtyping import Array, Float

from ._control_types import AbstractController, ControlOutput, ControlState, Environment, RefSample
from ._dynamics import dynamics_terms, prefix_sum, rnea
from ._kinematics import Kinematics, jacobian_from, kinematics, poi_positions_from
from ._math import as_float, check_finite_fields, clip_norm, quat_error, quat_mul, rot_to_quat
from ._nullspace import (
    PolicyGains,
    damped_solve,
    damping_factor,
    ik_policy_gains,
    nullspace_policy,
    _cho_solve_rows,
    _cholesky_rows,
    _pivot_floor,
)
from ._robot import Arm

__all__ = [
    "JointSpaceGains",
    "PIDGains",
    "VelocityGains",
    "AccelerationGains",
    "ImpedanceGains",
    "GradientGains",
    "JointSpaceID",
    "PID",
    "VelocityOSC",
    "VelocityOSCOriginal",
    "AccelerationOSC",
    "Impedance",
    "GradientGuided",
    "CONTROLLERS",
    "make_controller",
    "jdot_qdot_from",
    "task_jacobian",
]


def _arr(x):
    return as_float(x)


def _f(default):
    return eqx.field(default=default, converter=_arr)


# ----------------------------------------------------------------------------------------------
# Gains (thesis values as defaults)
# ----------------------------------------------------------------------------------------------


class _Gains(eqx.Module):
    """Gains built with concrete numbers are checked to be finite (a NaN gain is a NaN run)."""

    def __check_init__(self):
        check_finite_fields(self)


class JointSpaceGains(_Gains):
    """Inverse-dynamics gains (3.3.2 [T]): ``kp`` 1000, ``kd`` 100 (error poles -11.3, -88.7).
    ``policy`` is used only with ``nullspace="actuator"``."""

    kp: Float[Array, ""] = _f(1000.0)
    kd: Float[Array, ""] = _f(100.0)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)


class PIDGains(_Gains):
    """PID gains (2.4; SPEC proposal 1000 / 100 / 0)."""

    kp: Float[Array, ""] = _f(1000.0)
    kd: Float[Array, ""] = _f(100.0)
    ki: Float[Array, ""] = _f(0.0)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)


class VelocityGains(_Gains):
    """Velocity OSC gains (3.3.2 [T]): ``kp`` 10, ``kpr`` 40, ``kpq`` 10, ``kdq`` 100; Jacobian scaling
    ``s_trans`` 1, ``s_rot`` 0.2 (3.13); orientation clip 0.075 (3.15); null-space ``policy``."""

    kp: Float[Array, ""] = _f(10.0)
    kpr: Float[Array, ""] = _f(40.0)
    kpq: Float[Array, ""] = _f(10.0)
    kdq: Float[Array, ""] = _f(100.0)
    s_trans: Float[Array, ""] = _f(1.0)
    s_rot: Float[Array, ""] = _f(0.2)
    rot_clip: Float[Array, ""] = _f(0.075)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)


class AccelerationGains(_Gains):
    """Acceleration OSC gains (3.3.2 [T]): ``kp`` 250, ``kpr`` 2000, ``kd`` 31, ``kdr`` 100; scaling,
    clip and null-space ``policy`` as :class:`VelocityGains`."""

    kp: Float[Array, ""] = _f(250.0)
    kpr: Float[Array, ""] = _f(2000.0)
    kd: Float[Array, ""] = _f(31.0)
    kdr: Float[Array, ""] = _f(100.0)
    s_trans: Float[Array, ""] = _f(1.0)
    s_rot: Float[Array, ""] = _f(0.2)
    rot_clip: Float[Array, ""] = _f(0.075)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)


class ImpedanceGains(_Gains):
    """Impedance gains (2.18; SPEC proposal ``kp`` 2000 N/m, ``kd`` 200 Ns/m; rotational ``kpr`` 200,
    ``kdr`` 20 are our proposal). ``s_trans``/``s_rot`` scale the Jacobian of the null-space
    projector only (the force map ``J^T F`` uses the physical Jacobian)."""

    kp: Float[Array, ""] = _f(2000.0)
    kd: Float[Array, ""] = _f(200.0)
    kpr: Float[Array, ""] = _f(200.0)
    kdr: Float[Array, ""] = _f(20.0)
    s_trans: Float[Array, ""] = _f(1.0)
    s_rot: Float[Array, ""] = _f(0.2)
    rot_clip: Float[Array, ""] = _f(0.075)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)


def _default_field():
    from ._fields import FieldParams

    return FieldParams()


class GradientGains(_Gains):
    """Gradient-guided gains (3.28; U22: ``kd`` 31, ``kdr`` 100, ``kpr`` 2000), guidance magnitude
    ``guide_a`` 0.5 m/s and ``guide_b`` 0.1 m (3.19 [T]), the guidance ``field``
    (:class:`~redman_jax._fields.FieldParams`), scaling, clip and null-space ``policy``."""

    kd: Float[Array, ""] = _f(31.0)
    kdr: Float[Array, ""] = _f(100.0)
    kpr: Float[Array, ""] = _f(2000.0)
    guide_a: Float[Array, ""] = _f(0.5)
    guide_b: Float[Array, ""] = _f(0.1)
    s_trans: Float[Array, ""] = _f(1.0)
    s_rot: Float[Array, ""] = _f(0.2)
    rot_clip: Float[Array, ""] = _f(0.075)
    policy: PolicyGains = eqx.field(default_factory=PolicyGains)
    field: eqx.Module = eqx.field(default_factory=_default_field)


# ----------------------------------------------------------------------------------------------
# Shared pieces
# ----------------------------------------------------------------------------------------------


def jdot_qdot_from(kin: Kinematics, qd: Float[Array, " n"]) -> Float[Array, "6"]:
    """``J_dot q_dot`` of the end-effector Jacobian (3.17) from the shared FK pass.

    With the world twists of the joint screws ``S_j`` and the link twists
    ``V_{j-1} = sum_{i<j} S_i qd_i``, ``S_j_dot = ad_{V_{j-1}} S_j``; the spatial acceleration at
    ``qdd = 0`` is ``A = (alpha, a_s) = sum_j S_j_dot qd_j`` and the end-effector point ``p``
    (``pd = v_s + w x p``) has ``pdd = a_s + alpha x p + w x pd``. Equals
    ``jax.jvp(jacobian, (q,), (qd,))[1] @ qd`` (tested) at a fraction of its cost.
    """
    S = kin.S
    w, v = S[:, :3], S[:, 3:]
    tw = S * qd[:, None]
    V = prefix_sum(tw)
    Vp = V - tw  # V_{j-1}
    wV, vV = Vp[:, :3], Vp[:, 3:]
    sd_w = jnp.cross(wV, w)
    sd_v = jnp.cross(vV, w) + jnp.cross(wV, v)
    alpha = sd_w.T @ qd
    a_s = sd_v.T @ qd
    omega, v_s = V[-1, :3], V[-1, 3:]
    p = kin.ee[:3, 3]
    pd = v_s + jnp.cross(omega, p)
    return jnp.concatenate([a_s + jnp.cross(alpha, p) + jnp.cross(omega, pd), alpha])


class _Frame(NamedTuple):
    kin: Kinematics
    p: Array  # (3,)
    quat: Array  # (4,)
    J: Array  # (6, n) [linear; angular]
    xd: Array  # (6,) [p_dot; omega]


def _frame(arm: Arm, q, qd) -> _Frame:
    kin = kinematics(arm, q)
    J = jacobian_from(kin)
    return _Frame(kin=kin, p=kin.ee[:3, 3], quat=rot_to_quat(kin.ee[:3, :3]), J=J, xd=J @ qd)


def _rot_mask(rot):
    on = jnp.asarray(rot) > 0.5
    return jnp.concatenate([jnp.ones((3,), bool), jnp.broadcast_to(on, (3,))])


def _row_scale(s_trans, s_rot, dtype):
    return jnp.concatenate([jnp.broadcast_to(s_trans, (3,)), jnp.broadcast_to(s_rot, (3,))]).astype(dtype)


def task_jacobian(J: Float[Array, "6 n"], rot, s_trans=1.0, s_rot=0.2):
    """Scaled, switched task Jacobian of 3.13 at fixed shape: ``J_s = diag(S) J`` with the rotational
    rows zeroed when ``rot`` is 0. Returns ``(J_s, row_mask, S)``."""
    m = _rot_mask(rot)
    S = _row_scale(s_trans, s_rot, J.dtype)
    return jnp.where(m[:, None], S[:, None] * J, 0.0), m, S


def _task_vector(b, m, S, jac_scaling):
    b = S * b if jac_scaling == "consistent" else b
    return jnp.where(m, b, 0.0)


def _policy(arm, fr: _Frame, q, qd, env: Environment, pg: PolicyGains, mode, form):
    pois = poi_positions_from(arm, fr.kin, q)
    return nullspace_policy(arm, fr.kin, q, qd, env.obstacles, pg, mode, pois=pois, form=form)


def _actuator_null(J_s, m, lam, M, tau0, projector):
    """``P_tau tau_0``: orthogonal ``tau0 - J_s^T Y^-1 J_s tau0`` or dynamically consistent
    ``tau0 - J_s^T (J_s M^-1 J_s^T + lam^2 I)^-1 J_s M^-1 tau0``."""
    if projector == "orthogonal":
        return tau0 - damped_solve(J_s, (J_s @ tau0)[:, None], lam)[:, 0]
    cf = cho_factor(M, lower=True)
    MiJt = cho_solve(cf, J_s.T)  # (n, k)
    A = J_s @ MiJt + (lam * lam) * jnp.eye(J_s.shape[0], dtype=J_s.dtype)
    L, inv_diag = _cholesky_rows(A, _pivot_floor(A))
    y = _cho_solve_rows(L, inv_diag, (MiJt.T @ tau0)[:, None])[:, 0]
    return tau0 - J_s.T @ y


def _orientation_error(q_d, quat, clip):
    return clip_norm(quat_error(q_d, quat), clip)


_NULLSPACE_MODES = ("acceleration", "actuator", "none")


def _check_choice(cls, field, value, choices):
    if value not in choices:
        raise ValueError(f"{cls}.{field}: expected one of {choices}, got {value!r}")


class _OSCOptions(AbstractController):
    """Static options shared by the operational-space controllers."""

    nullspace: str = eqx.field(static=True, default="acceleration")
    actuator_projector: str = eqx.field(static=True, default="orthogonal")
    poi_jacobian: str = eqx.field(static=True, default="point")
    jac_scaling: str = eqx.field(static=True, default="rows_only")
    obstacle_form: str = eqx.field(static=True, default="minus")
    sigma_method: str = eqx.field(static=True, default="laguerre")

    def __check_init__(self):
        name = type(self).__name__
        _check_choice(name, "nullspace", self.nullspace, self._nullspace_modes())
        _check_choice(name, "actuator_projector", self.actuator_projector, ("orthogonal", "dynamic"))
        _check_choice(name, "poi_jacobian", self.poi_jacobian, ("point", "link"))
        _check_choice(name, "jac_scaling", self.jac_scaling, ("rows_only", "consistent"))
        _check_choice(name, "obstacle_form", self.obstacle_form, ("minus", "plus"))
        _check_choice(name, "sigma_method", self.sigma_method, ("laguerre", "eigvalsh", "svd"))

    def _nullspace_modes(self):
        return _NULLSPACE_MODES

    @property
    def reads_obstacles(self) -> bool:
        """Only through a null-space policy (``nullspace`` other than ``"none"``) or guidance."""
        return self.uses_guidance or self.nullspace != "none"

    def _lam(self, J_s, m, pg: PolicyGains):
        return damping_factor(J_s, pg.lam_ratio, pg.lam_floor, row_mask=m, method=self.sigma_method)

    def _acc_command(self, arm, fr, q, qd, env, pg, J_s, m, b):
        """``(qdd_r, qdd_null, lam)`` for the task acceleration ``b`` (already minus ``J_s_dot qd``).

        ``qdd_r = alpha h + J_s^T Y^-1 (b - alpha J_s h)`` = ``J# b + alpha N h``.
        """
        lam = self._lam(J_s, m, pg)
        if self.nullspace == "acceleration":
            h = pg.alpha * _policy(arm, fr, q, qd, env, pg, self.poi_jacobian, self.obstacle_form)
            X = damped_solve(J_s, jnp.stack([b, J_s @ h], axis=1), lam)
            null = h - X[:, 1]
            return X[:, 0] + null, null, lam
        return damped_solve(J_s, b[:, None], lam)[:, 0], jnp.zeros_like(q), lam

    def _finish(self, arm, fr, q, qd, env, pg, J_s, m, lam, tau, null_acc):
        """Add the actuator-level null-space torque if selected; diagnostics.

        ``M`` is formed only for ``nullspace="actuator"``; otherwise the diagnostic ``tau_null = M
        qdd_null`` is one gravity-free RNEA pass (dropped by XLA when unused).
        """
        if self.nullspace == "actuator":
            M, _ = dynamics_terms(arm, q, qd, kin=fr.kin)
            h = _policy(arm, fr, q, qd, env, pg, self.poi_jacobian, self.obstacle_form)
            tau_null = _actuator_null(J_s, m, lam, M, M @ (pg.alpha * h), self.actuator_projector)
            tau = tau + tau_null
        elif null_acc is None:
            tau_null = jnp.zeros_like(q)
        else:
            zero = jnp.zeros_like(q)
            tau_null = rnea(arm, q, zero, null_acc, gravity=False, kin=fr.kin)
        return tau, {"tau_null": tau_null, "lam": lam}


# ----------------------------------------------------------------------------------------------
# Joint space
# ----------------------------------------------------------------------------------------------


class JointSpaceID(_OSCOptions):
    """Joint-space inverse dynamics (2.5 with E2): ``tau = M(qdd_d + K_d(qd_d - qd) + K_p(q_d - q)) + c + g``.

    ``nullspace``: ``"none"`` (default; the IK resolves redundancy) or ``"actuator"`` (2.4.4).
    """

    nullspace: str = eqx.field(static=True, default="none")

    def _nullspace_modes(self):
        return ("none", "actuator")

    def default_gains(self) -> JointSpaceGains:
        return JointSpaceGains()

    def init_state(self, arm, q0, qd0):
        return ()

    @property
    def needs_joint_reference(self) -> bool:
        return True

    def __call__(self, gains: JointSpaceGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd = state.q, state.qd
        kin = kinematics(arm, q)
        qdd = ref.qdd + gains.kd * (ref.qd - qd) + gains.kp * (ref.q - q)
        tau = rnea(arm, q, qd, qdd, kin=kin)  # = M qdd + c + g without forming M
        diag = {"tau_null": jnp.zeros_like(q)}
        if self.nullspace == "actuator":
            J = jacobian_from(kin)
            fr = _Frame(kin=kin, p=kin.ee[:3, 3], quat=jnp.zeros((4,), q.dtype), J=J, xd=J @ qd)
            J_s, m, _ = task_jacobian(J, ref.rot, 1.0, 1.0)
            lam = self._lam(J_s, m, gains.policy)
            tau, diag = self._finish(arm, fr, q, qd, env, gains.policy, J_s, m, lam, tau, None)
        return ControlOutput(tau=tau, dz=(), diag=diag)


class PID(_OSCOptions):
    """P(I)D joint control (2.4 with E2): ``tau = K_p e + K_d (qd_d - qd) + K_i int e``, ``e = q_d - q``.

    State ``z = int_0^t e dt``. ``gravity_compensation`` adds ``g(q)`` (not in 2.4; off by default).
    """

    nullspace: str = eqx.field(static=True, default="none")
    gravity_compensation: bool = eqx.field(static=True, default=False)

    def _nullspace_modes(self):
        return ("none", "actuator")

    def default_gains(self) -> PIDGains:
        return PIDGains()

    def init_state(self, arm, q0, qd0):
        return jnp.zeros_like(jnp.asarray(q0))

    @property
    def needs_joint_reference(self) -> bool:
        return True

    def __call__(self, gains: PIDGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd = state.q, state.qd
        e = ref.q - q
        tau = gains.kp * e + gains.kd * (ref.qd - qd) + gains.ki * state.z
        kin = kinematics(arm, q)
        if self.gravity_compensation:
            tau = tau + rnea(arm, q, jnp.zeros_like(q), jnp.zeros_like(q), kin=kin)
        diag = {"tau_null": jnp.zeros_like(q)}
        if self.nullspace == "actuator":
            J = jacobian_from(kin)
            fr = _Frame(kin=kin, p=kin.ee[:3, 3], quat=jnp.zeros((4,), q.dtype), J=J, xd=J @ qd)
            J_s, m, _ = task_jacobian(J, ref.rot, 1.0, 1.0)
            lam = self._lam(J_s, m, gains.policy)
            tau, diag = self._finish(arm, fr, q, qd, env, gains.policy, J_s, m, lam, tau, None)
        return ControlOutput(tau=tau, dz=e, diag=diag)


# ----------------------------------------------------------------------------------------------
# Operational space
# ----------------------------------------------------------------------------------------------


class VelocityOSC(_OSCOptions):
    """Velocity-based OSC, the thesis's "alternative method" (2.12-2.14, 3.10-3.15 corrected).

    ``xd_r = [pd_d + K_p e_p; w_d + K_pr clip(e_o)]`` (rot = 1) or ``pd_d + K_p e_p`` (rot = 0),
    ``qd_r = J# xd_r`` (3.11 without ``gamma_n``, E6), ``dq_r/dt = qd_r`` (state ``z = q_r``),
    ``qdd_r = K_pq (q_r - q) + K_dq (qd_r - qd) + alpha N h`` and ``tau = M qdd_r + c + g``.
    """

    def default_gains(self) -> VelocityGains:
        return VelocityGains()

    def init_state(self, arm, q0, qd0):
        return jnp.asarray(q0)

    def __call__(self, gains: VelocityGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd, q_r = state.q, state.qd, state.z
        pg = gains.policy
        fr = _frame(arm, q, qd)
        J_s, m, S = task_jacobian(fr.J, ref.rot, gains.s_trans, gains.s_rot)
        e_o = _orientation_error(ref.quat, fr.quat, gains.rot_clip)
        xd_r = jnp.concatenate([ref.v + gains.kp * (ref.p - fr.p), ref.omega + gains.kpr * e_o])
        b = _task_vector(xd_r, m, S, self.jac_scaling)
        lam = self._lam(J_s, m, pg)
        if self.nullspace == "acceleration":
            h = pg.alpha * _policy(arm, fr, q, qd, env, pg, self.poi_jacobian, self.obstacle_form)
            X = damped_solve(J_s, jnp.stack([b, J_s @ h], axis=1), lam)
            qd_r, null = X[:, 0], h - X[:, 1]
        else:
            qd_r, null = damped_solve(J_s, b[:, None], lam)[:, 0], jnp.zeros_like(q)
        qdd_r = gains.kpq * (q_r - q) + gains.kdq * (qd_r - qd) + null
        tau = rnea(arm, q, qd, qdd_r, kin=fr.kin)  # M qdd_r + c + g
        tau, diag = self._finish(arm, fr, q, qd, env, pg, J_s, m, lam, tau, null)
        return ControlOutput(tau=tau, dz=qd_r, diag=diag)


class VelocityOSCOriginal(_OSCOptions):
    """Original velocity-based OSC (2.7-2.11).

    ``qd_r = J# xd_r + alpha N h_v(q)`` (velocity-domain policies, default gains
    :func:`~redman_jax._nullspace.ik_policy_gains`; ``nullspace="velocity"``), ``q_r = int qd_r``
    (state), ``qdd_r = d qd_r/dt`` computed exactly by one forward-mode jvp along ``(qd, reference
    rates)``: ``p_d' = v_d``, ``v_d' = a_d``, ``Q_d' = 1/2 (0, w_d) (x) Q_d``, ``w_d' = wd_d``;
    ``tau = M qdd_r + c + g + K_qd (qd_r - qd) + K_qp (q_r - q)`` (2.11, ``joint_gains="torque"``).
    Default ``joint_gains="inertia"`` (our proposal) weights the joint feedback by ``M``,
    ``tau = M(qdd_r + K_qd (qd_r - qd) + K_qp (q_r - q)) + c + g``: the literal torque gains act on
    link inertias from 2e-3 to 10 kg m^2, so ``K_qd = 100`` makes the loop stiff (poles to -5e4 1/s,
    explicit solvers stall) while the inertia-weighted loop has the same poles on every joint.
    """

    nullspace: str = eqx.field(static=True, default="velocity")
    joint_gains: str = eqx.field(static=True, default="inertia")

    def __check_init__(self):
        _check_choice("VelocityOSCOriginal", "joint_gains", self.joint_gains, ("inertia", "torque"))

    def _nullspace_modes(self):
        return ("velocity", "actuator", "none")

    def default_gains(self) -> VelocityGains:
        return VelocityGains(policy=ik_policy_gains())

    def init_state(self, arm, q0, qd0):
        return jnp.asarray(q0)

    def __call__(self, gains: VelocityGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd, q_r = state.q, state.qd, state.z
        pg = gains.policy

        def qd_ref(qq, p_d, v_d, quat_d, w_d):
            fr = _frame(arm, qq, jnp.zeros_like(qq))
            J_s, m, S = task_jacobian(fr.J, ref.rot, gains.s_trans, gains.s_rot)
            e_o = _orientation_error(quat_d, fr.quat, gains.rot_clip)
            xd_r = jnp.concatenate([v_d + gains.kp * (p_d - fr.p), w_d + gains.kpr * e_o])
            b = _task_vector(xd_r, m, S, self.jac_scaling)
            lam = self._lam(J_s, m, pg)
            if self.nullspace == "velocity":
                h = pg.alpha * _policy(arm, fr, qq, jnp.zeros_like(qq), env, pg, self.poi_jacobian,
                                       self.obstacle_form)
                X = damped_solve(J_s, jnp.stack([b, J_s @ h], axis=1), lam)
                out = X[:, 0] + h - X[:, 1]
            else:
                out = damped_solve(J_s, b[:, None], lam)[:, 0]
            return out, (fr.kin, fr.J, J_s, m, lam)

        z3 = jnp.zeros((1,), ref.quat.dtype)
        quat_rate = 0.5 * quat_mul(jnp.concatenate([z3, ref.omega]), ref.quat)
        primals = (q, ref.p, ref.v, ref.quat, ref.omega)
        tangents = (qd, ref.v, ref.a, quat_rate, ref.omega_dot)
        qd_r, qdd_r, (kin, J, J_s, m, lam) = jax.jvp(qd_ref, primals, tangents, has_aux=True)
        fb = gains.kdq * (qd_r - qd) + gains.kpq * (q_r - q)
        if self.joint_gains == "torque":  # 2.11 literally: stiff (K_dq / I_min ~ 5e4 1/s here)
            tau = rnea(arm, q, qd, qdd_r, kin=kin) + fb
        else:  # K -> M K: error dynamics e'' + K_dq e' + K_pq e = 0 on every joint
            tau = rnea(arm, q, qd, qdd_r + fb, kin=kin)
        diag = {"tau_null": jnp.zeros_like(q), "lam": lam}
        if self.nullspace == "actuator":
            fr = _Frame(kin=kin, p=kin.ee[:3, 3], quat=jnp.zeros((4,), q.dtype), J=J, xd=J @ qd)
            tau, diag = self._finish(arm, fr, q, qd, env, pg, J_s, m, lam, tau, None)
        return ControlOutput(tau=tau, dz=qd_r, diag=diag)


class AccelerationOSC(_OSCOptions):
    """Acceleration-based OSC (2.15-2.17, 3.16-3.17).

    ``xdd_r = [pdd_d + K_d(pd_d - pd) + K_p e_p; wd_d + K_dr(w_d - w) + K_pr clip(e_o)]`` (rows 4-6 only
    when rot = 1), ``qdd_r = J#(xdd_r - J_s_dot qd) + alpha N h``, ``tau = M qdd_r + c + g``.
    """

    @property
    def auto_solver(self) -> str:
        """Tsit5: at the default tolerances Dopri5 integrates this closed loop less accurately (see
        :mod:`redman_jax._sim`)."""
        return "tsit5"

    def default_gains(self) -> AccelerationGains:
        return AccelerationGains()

    def init_state(self, arm, q0, qd0):
        return ()

    def __call__(self, gains: AccelerationGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd = state.q, state.qd
        pg = gains.policy
        fr = _frame(arm, q, qd)
        J_s, m, S = task_jacobian(fr.J, ref.rot, gains.s_trans, gains.s_rot)
        e_o = _orientation_error(ref.quat, fr.quat, gains.rot_clip)
        xdd_r = jnp.concatenate([
            ref.a + gains.kd * (ref.v - fr.xd[:3]) + gains.kp * (ref.p - fr.p),
            ref.omega_dot + gains.kdr * (ref.omega - fr.xd[3:]) + gains.kpr * e_o,
        ])
        jdqd = jdot_qdot_from(fr.kin, qd)
        if self.jac_scaling == "consistent":
            b = jnp.where(m, S * (xdd_r - jdqd), 0.0)
        else:
            b = jnp.where(m, xdd_r - S * jdqd, 0.0)
        qdd_r, null, lam = self._acc_command(arm, fr, q, qd, env, pg, J_s, m, b)
        tau = rnea(arm, q, qd, qdd_r, kin=fr.kin)  # M qdd_r + c + g
        tau, diag = self._finish(arm, fr, q, qd, env, pg, J_s, m, lam, tau, null)
        return ControlOutput(tau=tau, dz=(), diag=diag)


class Impedance(_OSCOptions):
    """Impedance (force) control (2.18-2.19): ``F = [K_p e_p + K_d(pd_d - pd); K_pr clip(e_o) +
    K_dr(w_d - w)]`` (rotation rows when rot = 1), ``tau = J^T F + comp + P_tau (alpha M h)``.

    ``compensation``: ``"gravity"`` (default proposal: ``+ g(q)``), ``"bias"`` (``+ c + g``) or
    ``"none"`` (2.19 literally). ``nullspace``: ``"actuator"`` (default, 2.19) or ``"none"``.
    """

    nullspace: str = eqx.field(static=True, default="actuator")
    compensation: str = eqx.field(static=True, default="gravity")

    def __check_init__(self):
        _check_choice("Impedance", "compensation", self.compensation, ("gravity", "bias", "none"))

    def _nullspace_modes(self):
        return ("actuator", "none")

    def default_gains(self) -> ImpedanceGains:
        return ImpedanceGains()

    def init_state(self, arm, q0, qd0):
        return ()

    def __call__(self, gains: ImpedanceGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        q, qd = state.q, state.qd
        pg = gains.policy
        fr = _frame(arm, q, qd)
        m = _rot_mask(ref.rot)
        e_o = _orientation_error(ref.quat, fr.quat, gains.rot_clip)
        F = jnp.concatenate([
            gains.kp * (ref.p - fr.p) + gains.kd * (ref.v - fr.xd[:3]),
            gains.kpr * e_o + gains.kdr * (ref.omega - fr.xd[3:]),
        ])
        tau = fr.J.T @ jnp.where(m, F, 0.0)
        zero = jnp.zeros_like(q)
        if self.compensation == "gravity":
            tau = tau + rnea(arm, q, zero, zero, kin=fr.kin)
        elif self.compensation == "bias":
            tau = tau + rnea(arm, q, qd, zero, kin=fr.kin)
        diag = {"tau_null": zero}
        if self.nullspace == "actuator":
            J_s, m, _ = task_jacobian(fr.J, ref.rot, gains.s_trans, gains.s_rot)
            lam = self._lam(J_s, m, pg)
            tau, diag = self._finish(arm, fr, q, qd, env, pg, J_s, m, lam, tau, None)
        return ControlOutput(tau=tau, dz=(), diag=diag)


class GradientGuided(_OSCOptions):
    """Gradient-guided controller (3.28; E30: the acceleration form).

    ``xdd_r = [K_d(xd_g - pd); -K_dr w + K_pr clip(e_o)]`` (rotation rows when ``ref.rot`` = 1; the
    simulator latches it within 0.5 m of the goal), ``xd_g`` from
    :func:`~redman_jax._fields.guidance_velocity` at the end effector with the current virtual-obstacle
    buffer of ``env``; ``Q_d = env.goal_quat``; then as :class:`AccelerationOSC`.
    """

    auto_solver = AccelerationOSC.auto_solver  # the same acceleration-level command

    def default_gains(self) -> GradientGains:
        return GradientGains()

    def init_state(self, arm, q0, qd0):
        return ()

    @property
    def uses_guidance(self) -> bool:
        return True

    def __call__(self, gains: GradientGains, arm: Arm, state: ControlState, ref: RefSample,
                 env: Environment) -> ControlOutput:
        from ._fields import guidance_velocity

        q, qd = state.q, state.qd
        pg = gains.policy
        fr = _frame(arm, q, qd)
        J_s, m, S = task_jacobian(fr.J, ref.rot, gains.s_trans, gains.s_rot)
        xd_g = guidance_velocity(fr.p, env.goal_p, env.obstacles, env.virtual_p, env.virtual_mask,
                                 gains.field, a=gains.guide_a, b=gains.guide_b)
        e_o = _orientation_error(env.goal_quat, fr.quat, gains.rot_clip)
        xdd_r = jnp.concatenate([gains.kd * (xd_g - fr.xd[:3]), -gains.kdr * fr.xd[3:] + gains.kpr * e_o])
        jdqd = jdot_qdot_from(fr.kin, qd)
        if self.jac_scaling == "consistent":
            b = jnp.where(m, S * (xdd_r - jdqd), 0.0)
        else:
            b = jnp.where(m, xdd_r - S * jdqd, 0.0)
        qdd_r, null, lam = self._acc_command(arm, fr, q, qd, env, pg, J_s, m, b)
        tau = rnea(arm, q, qd, qdd_r, kin=fr.kin)  # M qdd_r + c + g
        tau, diag = self._finish(arm, fr, q, qd, env, pg, J_s, m, lam, tau, null)
        diag["xd_g"] = xd_g
        return ControlOutput(tau=tau, dz=(), diag=diag)


CONTROLLERS: dict[str, type[AbstractController]] = {
    "joint_space": JointSpaceID,
    "velocity": VelocityOSC,
    "acceleration": AccelerationOSC,
    "gradient": GradientGuided,
    "pid": PID,
    "velocity_original": VelocityOSCOriginal,
    "impedance": Impedance,
}


def make_controller(name: str, **options) -> AbstractController:
    """Controller ``name`` of :data:`CONTROLLERS` with static ``options`` (e.g. ``nullspace=``)."""
    if name not in CONTROLLERS:
        raise ValueError(f"controller: expected one of {sorted(CONTROLLERS)}, got {name!r}")
    return CONTROLLERS[name](**options)
