"""Differentiable gain auto-tuning through the simulator (thesis 3.3.2, Figure 3.6, chapters 5-6;
SPEC U28).

The thesis tuned the joint-space, velocity-OSC and acceleration-OSC gains *by hand* so that all three
settle at the same time after a step (Figure 3.6) and recommends tuning for dynamic references and
bounded actuation instead (chapters 5-6). Here the gains are tuned by gradient descent through
:func:`~redman_jax._sim.simulate` (``RecursiveCheckpointAdjoint``).

**Step experiment (SPEC U28).** From the start pose ``p_0 = p(q_0)`` the operational reference is the
*constant* pose ``p_d = p_0 + (0.05, 0, 0)`` m, ``Q_d = Q(q_0)``, ``rot = 0``, held for ``T = 1`` s
(``N = T / t_s = 100`` samples; no obstacles: every slot of a ``(1, 1, 1)`` obstacle set is masked).
The joint-space controller needs a joint reference; its *equivalent* step is the constant joint
reference ``(q*, 0, 0)`` with ``p(q*) = p_d``, found by damped-least-squares Newton iterations on the
position from ``q_0`` (the minimum-norm joint step; :func:`joint_step_target`),

``q_{i+1} = q_i + J_v^T (J_v J_v^T + mu^2 I)^{-1} (p_d - p(q_i))``,  ``mu = 1e-3``.

The study's IK (:func:`~redman_jax._ik.ik_reference`) is available as ``joint_target="ik"``: its last
sample for the constant reference (the IK also moves the null space through its policies, so ``q*``
is then not the minimum-norm step).

**Settling time (2 % band).** With the per-sample error ``e_k = |p(t_{k+1}) - p_d|`` saved at the
sample ends ``t_{k+1} = (k + 1) t_s`` and the band ``b = 0.02 * 0.05 m = 1 mm``,

``T_s = inf { t : |e(t')| <= b for all t' >= t }``,

evaluated on the samples: if ``k*`` is the last sample with ``e_k > b``, ``T_s`` is the band crossing
linearly interpolated between ``t_{k*+1}`` and ``t_{k*+2}`` (``T_s = 0`` if no sample exceeds the band;
a run still outside the band at the horizon is *not settled* and gets ``T_s = T``).

**Smooth surrogate.** A soft indicator of being outside the band, in log-error (scale-free: an
exponentially settling error crosses ``log b`` at a constant rate), integrated over time:

``T_soft = t_s * sum_k sigmoid((log(e_k + eps) - log b) / w)``,  ``w = 0.25``, ``eps = 1e-9`` m.

For ``e = e_0 exp(-a t)`` it equals ``T_s + O(w / a)`` (the sigmoid's mass is symmetric about the
crossing), is smooth in the gains and counts time outside the band; it is monotone with ``T_s`` on
monotone families of gains (tested). The tuner uses it for the *gradient* only: the loss sees the
bias-corrected value ``T_hat = T_soft + stop_gradient(T_s - T_soft)``, whose value is the true ``T_s``
and whose gradient is the surrogate's, so the fixed point of the optimisation is ``T_s = T_target``.

**Tuning.** The log-gains ``theta = log g`` of the controller's tunable fields (:data:`TUNABLE`;
gains stay positive) minimise the least-squares loss ``L = |R|^2 / 2`` of the residuals

``R = [ (T_hat - T*) / T* ,  r_tau ,  sqrt(rho) (theta - theta_0) ,  stability box ]``

with ``rho = 1e-3`` (among the many gains giving the same settling time, the smallest change),
``r_tau`` the optional torque bound (below) and a soft box on the damping ratios of
:data:`RATIO_BOUNDS` (a stable, non-oscillatory loop). The default step is Levenberg-Marquardt,
``d = (J^T J + mu tr(J^T J)/k I)^-1 J^T R`` (``J`` from one reverse pass through the simulator per
simulator residual), passed through an optax trust region (``clip_by_global_norm(0.3)``: at most a
35 % gain change per iteration). A scalar settling-time equation is a root-finding problem, for which
the Gauss-Newton step converges in a few iterations; ``method="adam"`` (optax Adam on ``J^T R``) is
available but its momentum, built up while the run is still far from the target, overshoots the
root by tens of percent (measured). A step whose run diverges or whose residual is not finite
(``SimResult.diverged``) is rejected: the gains go back to the last good point and the step is
halved. The objective ``"tracking"`` replaces the settling residual by the RMS position error on a
smooth moving reference (a 0.1 m circle, :func:`circle_scenario`) relative to 1 mm; it requires a
torque bound (without one the optimum is infinite gains).

**Torque bound.** The controller is wrapped (:class:`TorqueMonitor`) so that the ODE also integrates
``sum_i (tau_i / tau_max)^p`` (``p = 8``); the smooth maximum ``m = (1/T int sum_i (tau_i /
tau_max)^p dt)^(1/p)`` (an ``L^p`` norm over time and joints, which tends to ``max |tau_i| /
tau_max`` as ``p`` grows and is ``<= n^(1/p)`` times it; an average, so a short peak counts less
than its height) enters as the residual ``r_tau = sqrt(c) 0.05 softplus((m - 1) / 0.05)``, ``c = 10``.

Everything numeric is an array (targets, bounds, learning rate): changing them never recompiles;
the step function is jitted once per (arm structure, controller) and vmapped over several initial
guesses or several arms of the same structure (:func:`tune_gains_batch`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
import sys
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from ._math import as_float, check_count, check_initial_state, check_positive, concrete
from ._control_types import AbstractController, ControlOutput, ControlState
from ._controllers import CONTROLLERS, make_controller
from ._kinematics import end_effector_pose, jacobian, kinematics
from ._obstacles import make_obstacles
from ._robot import Arm, thesis_arm
from ._scenario import Reference, Scenario
from ._sim import SimParams, SimResult, simulate

__all__ = [
    "STEP",
    "BAND_FRACTION",
    "TUNABLE",
    "RATIO_BOUNDS",
    "StepExperiment",
    "TorqueMonitor",
    "TuneSettings",
    "TuneResult",
    "step_scenario",
    "circle_scenario",
    "joint_step_target",
    "step_experiment",
    "tracking_experiment",
    "settling_time",
    "soft_settling_time",
    "step_response",
    "experiment_settling_time",
    "target_settling_time",
    "get_gains",
    "strong_gains",
    "set_gains",
    "gains_from_dict",
    "gains_to_dict",
    "settling_gradient",
    "tune_gains",
    "tune_gains_batch",
    "write_gains_json",
    "step_response_figure",
    "tune_cli",
]

STEP: tuple[float, float, float] = (0.05, 0.0, 0.0)
"""The Figure 3.6 step (SPEC U28): 0.05 m in +x from the start pose, rot = 0."""

BAND_FRACTION = 0.02
"""Settling band as a fraction of the step size (2 %)."""

TUNABLE: dict[str, tuple[str, ...]] = {
    "joint_space": ("kp", "kd"),
    "pid": ("kp", "kd"),
    "velocity": ("kp", "kpq", "kdq"),
    "velocity_original": ("kp", "kpq", "kdq"),
    "acceleration": ("kp", "kd"),
    "impedance": ("kp", "kd"),
}
"""Gains tuned per controller. Only the translational gains: the step has ``rot = 0``, so the
rotational gains (``kpr``, ``kdr``) do not act on it (their gradient is exactly zero). The
gradient-guided controller has no tracking reference (its set-point is the guidance field's goal)
and is not tuned here."""

RATIO_BOUNDS: dict[str, tuple[tuple[str, str, float, float, float], ...]] = {
    # (numerator, denominator, power of the denominator, lower, upper): lo <= g_a / g_b^c <= hi
    "joint_space": (("kd", "kp", 0.5, 2 * 0.7, 2 * 10.0),),  # zeta = kd / (2 sqrt kp) in [0.7, 10]
    "pid": (("kd", "kp", 0.5, 2 * 0.7, 2 * 10.0),),
    "acceleration": (("kd", "kp", 0.5, 2 * 0.7, 2 * 10.0),),
    "velocity": (("kdq", "kpq", 0.5, 2 * 0.7, 2 * 50.0),  # inner loop zeta in [0.7, 50]
                 ("kdq", "kp", 1.0, 2.0, 1e4)),  # inner bandwidth >= 2x the outer task rate
    "velocity_original": (("kdq", "kpq", 0.5, 2 * 0.7, 2 * 50.0),),
    "impedance": (),
}
"""Soft stability box of the tuner (damping ratios of the error dynamics; the thesis gains are well
inside: JS zeta 1.58, acceleration 0.98, velocity inner 15.8 with ``kdq / kp = 10``)."""


def _arr(x):
    return as_float(x)


# ----------------------------------------------------------------------------------------------
# experiments


class StepExperiment(eqx.Module):
    """One experiment: the operational ``scenario``, the joint reference ``(q, qd, qdd)`` for
    joint-space controllers (``(N, n)`` each), the band ``band`` [m], the start ``q0`` ``(n,)`` the
    reference was built from (every run starts there, at rest) and ``kind`` (static): ``"step"``
    (settling time) or ``"tracking"`` (RMS tracking error)."""

    scenario: Scenario
    joint_q: Float[Array, "N n"]
    joint_qd: Float[Array, "N n"]
    joint_qdd: Float[Array, "N n"]
    band: Float[Array, ""]
    q0: Float[Array, " n"]
    kind: str = eqx.field(static=True, default="step")

    @property
    def joint_reference(self):
        return (self.joint_q, self.joint_qd, self.joint_qdd)


def _constant_reference(p, quat, n_samples: int, ts, rot=0.0) -> Reference:
    p = jnp.asarray(p)
    z3 = jnp.zeros((n_samples, 3), p.dtype)
    return Reference(p=jnp.broadcast_to(p, (n_samples, 3)), v=z3, a=z3,
                     quat=jnp.broadcast_to(jnp.asarray(quat, p.dtype), (n_samples, 4)), omega=z3,
                     omega_dot=z3, rot=jnp.full((n_samples,), rot, p.dtype),
                     mask=jnp.ones((n_samples,), bool), n_samples=jnp.asarray(n_samples),
                     ts=jnp.asarray(ts, p.dtype))


def _n_samples(horizon: float, ts: float) -> int:
    if not (ts > 0):
        raise ValueError(f"ts: sample time must be > 0, got {ts}")
    if not (horizon >= 2 * ts):
        raise ValueError(f"horizon: must cover at least 2 samples of {ts} s, got {horizon}")
    return int(round(horizon / ts))


def _scenario(ref: Reference, goal_p, goal_quat, case="custom") -> Scenario:
    obs = make_obstacles(capacities=(1, 1, 1))  # all slots masked: free space
    z = jnp.asarray(0)
    return Scenario(obstacles=obs, goal_p=jnp.asarray(goal_p), goal_quat=jnp.asarray(goal_quat),
                    reference=ref, seed=z, seed_used=z, valid=jnp.asarray(True), case=case)


def step_scenario(arm: Arm, step=STEP, horizon: float = 1.0, ts: float = 0.01, q0=None) -> Scenario:
    """The static set-point step of Figure 3.6 (SPEC U28): the constant reference
    ``p_d = p(q_0) + step``, ``Q_d = Q(q_0)``, ``rot = 0``, over ``horizon / ts`` samples, no obstacles.

    **Raises** ``ValueError`` for a step that is not a finite 3-vector or a horizon shorter than 2 samples.
    """
    step = np.asarray(step, float)
    if step.shape != (3,) or not np.all(np.isfinite(step)) or np.linalg.norm(step) == 0:
        raise ValueError(f"step: expected a finite, non-zero 3-vector [m], got {step!r}")
    N = _n_samples(horizon, ts)
    q0 = arm.q0 if q0 is None else jnp.asarray(q0)
    p0, quat0 = end_effector_pose(arm, q0)
    p_d = p0 + jnp.asarray(step, p0.dtype)
    return _scenario(_constant_reference(p_d, quat0, N, ts), p_d, quat0)


def circle_scenario(arm: Arm, radius: float = 0.1, period: float = 2.0, ramp: float = 0.25,
                    horizon: float = 1.0, ts: float = 0.01, q0=None) -> Scenario:
    """A smooth moving reference (dynamic-reference objective): a circle of ``radius`` in the
    horizontal plane through ``p(q_0)``, starting there at rest. The angle follows
    ``phi(t) = Omega (t - ramp/2)`` after a quintic-blend speed ramp of ``ramp`` s
    (``phi' = Omega s(t / ramp)``, ``s`` the smoothstep ``3u^2 - 2u^3``, so ``phi'' `` is continuous),
    ``Omega = 2 pi / period`` (0.31 m/s at the defaults). ``p = c + r(cos phi, sin phi, 0)``,
    ``c = p_0 - (r, 0, 0)``; ``v, a`` analytic; constant orientation ``Q(q_0)``, ``rot = 0``.
    """
    if not (radius > 0 and period > 0 and ramp > 0):
        raise ValueError(f"circle_scenario: radius, period and ramp must be > 0, got {radius}, {period}, {ramp}")
    N = _n_samples(horizon, ts)
    q0 = arm.q0 if q0 is None else jnp.asarray(q0)
    p0, quat0 = end_effector_pose(arm, q0)
    dtype = p0.dtype
    t = ts * np.arange(N)
    W = 2 * np.pi / period
    u = np.clip(t / ramp, 0.0, 1.0)
    s = 3 * u**2 - 2 * u**3
    ds = np.where(t < ramp, (6 * u - 6 * u**2) / ramp, 0.0)
    # phi = W * int_0^t s: for u < 1, int = ramp (u^3 - u^4 / 2); afterwards ramp/2 + (t - ramp)
    phi = W * np.where(t < ramp, ramp * (u**3 - 0.5 * u**4), 0.5 * ramp + (t - ramp))
    dphi, ddphi = W * s, W * ds
    r = radius
    c = np.asarray(p0) - np.array([r, 0.0, 0.0])
    p = c + r * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1)
    v = r * dphi[:, None] * np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], 1)
    a = (r * ddphi[:, None] * np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], 1)
         - r * dphi[:, None] ** 2 * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1))
    z3 = jnp.zeros((N, 3), dtype)
    ref = Reference(p=jnp.asarray(p, dtype), v=jnp.asarray(v, dtype), a=jnp.asarray(a, dtype),
                    quat=jnp.broadcast_to(quat0, (N, 4)), omega=z3, omega_dot=z3,
                    rot=jnp.zeros((N,), dtype), mask=jnp.ones((N,), bool), n_samples=jnp.asarray(N),
                    ts=jnp.asarray(ts, dtype))
    return _scenario(ref, ref.p[-1], quat0)


@eqx.filter_jit
def _newton_dls(arm, q0, p_d, mu, iterations: int):
    def body(q, _):
        p = kinematics(arm, q).ee[:3, 3]
        J = jacobian(arm, q)[:3]
        e = p_d - p
        A = J @ J.T + (mu * mu) * jnp.eye(3, dtype=J.dtype)
        return q + J.T @ jnp.linalg.solve(A, e), None

    q, _ = jax.lax.scan(body, q0, None, length=iterations)
    return q


def joint_step_target(arm: Arm, p_target, q0=None, iterations: int = 30, mu: float = 1e-3):
    """``q*`` with ``p(q*) = p_target``: damped-least-squares Newton iterations on the position from
    ``q_0`` (``q <- q + J_v^T (J_v J_v^T + mu^2 I)^-1 (p_target - p(q))``), i.e. close to the
    minimum-norm joint step. Returns ``(q*, residual [m])``."""
    q0 = arm.q0 if q0 is None else jnp.asarray(q0)
    p_target = jnp.asarray(p_target, q0.dtype)
    q = _newton_dls(arm, q0, p_target, jnp.asarray(mu, q0.dtype), iterations)
    res = jnp.linalg.norm(kinematics(arm, q).ee[:3, 3] - p_target)
    return q, res


def _ik_step_target(arm: Arm, sc: Scenario, q0):
    from ._ik import ik_reference

    ik = ik_reference(arm, sc.reference, sc.obstacles, q0=q0)
    return ik.q[-1], ik.final_error


def step_experiment(arm: Arm, step=STEP, horizon: float = 1.0, ts: float = 0.01,
                    band_fraction: float = BAND_FRACTION, joint_target: str = "newton",
                    q0=None) -> StepExperiment:
    """The Figure 3.6 step (:func:`step_scenario`) and its joint-space equivalent, the constant joint
    reference ``(q*, 0, 0)`` (``joint_target="newton"``: :func:`joint_step_target`; ``"ik"``: the
    last sample of the study's IK on the constant reference). Band ``band_fraction * |step|``.

    **Raises** ``ValueError`` for an unknown ``joint_target``, a bad band, a ``q0`` of the wrong
    shape or not finite, or a ``q*`` that does not reach the stepped position (residual above 1e-6
    m)."""
    if joint_target not in ("newton", "ik"):
        raise ValueError(f"joint_target: expected 'newton' or 'ik', got {joint_target!r}")
    if not (0 < band_fraction < 1):
        raise ValueError(f"band_fraction: must be in (0, 1), got {band_fraction}")
    check_initial_state("q0", q0, arm.n_dof)
    sc = step_scenario(arm, step, horizon, ts, q0)
    q0 = arm.q0 if q0 is None else jnp.asarray(q0)
    band = band_fraction * float(np.linalg.norm(np.asarray(step, float)))
    if joint_target == "newton":
        q_star, res = joint_step_target(arm, sc.goal_p, q0)
        tol = 1e-6
    else:
        q_star, res = _ik_step_target(arm, sc, q0)
        # a tenth of the settling band: a q* off by the band itself would settle late or never
        tol = 0.1 * band
    if not float(res) < tol:
        raise ValueError(f"joint_target: {joint_target!r} did not reach the stepped position "
                         f"(residual {float(res):.2e} m)")
    N = sc.reference.capacity
    q_ref = jnp.broadcast_to(q_star, (N, arm.n_dof))
    zero = jnp.zeros_like(q_ref)
    return StepExperiment(scenario=sc, joint_q=q_ref, joint_qd=zero, joint_qdd=zero,
                          band=jnp.asarray(band, q_ref.dtype), q0=jnp.asarray(q0, q_ref.dtype), kind="step")


def tracking_experiment(arm: Arm, radius: float = 0.1, period: float = 2.0, horizon: float = 1.0,
                        ts: float = 0.01, q0=None) -> StepExperiment:
    """The dynamic-reference experiment: :func:`circle_scenario`; the joint reference of joint-space
    controllers comes from the study's IK (:func:`~redman_jax._ik.ik_reference`). ``band`` is the
    error scale of the tracking loss (1 mm)."""
    from ._ik import ik_reference

    check_initial_state("q0", q0, arm.n_dof)
    sc = circle_scenario(arm, radius, period, horizon=horizon, ts=ts, q0=q0)
    ik = ik_reference(arm, sc.reference, sc.obstacles, q0=q0)
    q0 = arm.q0 if q0 is None else jnp.asarray(q0)
    return StepExperiment(scenario=sc, joint_q=ik.q, joint_qd=ik.qd, joint_qdd=ik.qdd,
                          band=jnp.asarray(1e-3, ik.q.dtype), q0=jnp.asarray(q0, ik.q.dtype), kind="tracking")


# ----------------------------------------------------------------------------------------------
# settling time and its surrogate


def settling_time(err: Float[Array, " N"], t: Float[Array, " N"], band, mask=None):
    """True settling time (module docstring): the last exit from the band ``|e| <= band``, linearly
    interpolated between the saved samples. ``t[k]`` is the time of ``err[k]`` (sample ends);
    ``mask`` marks valid samples. Returns ``(T_s, settled)``: ``T_s = 0`` if no sample exceeds the
    band, ``T_s = t[last valid]`` and ``settled = False`` if the last valid sample is outside it.
    Non-finite errors count as outside."""
    err = jnp.asarray(err)
    t = jnp.asarray(t, err.dtype)
    N = err.shape[-1]
    mask = jnp.ones((N,), bool) if mask is None else mask
    idx = jnp.arange(N)
    out = (~(err <= band)) & mask  # NaN counts as outside
    any_out = jnp.any(out)
    k = jnp.max(jnp.where(out, idx, -1))  # last sample outside
    last = jnp.max(jnp.where(mask, idx, 0))
    settled = k < last
    kn = jnp.clip(k + 1, 0, N - 1)
    e0 = jnp.where(jnp.isfinite(err[jnp.clip(k, 0, N - 1)]), err[jnp.clip(k, 0, N - 1)], 1.0)
    e1 = err[kn]
    t0, t1 = t[jnp.clip(k, 0, N - 1)], t[kn]
    frac = jnp.clip((e0 - band) / jnp.where(e0 - e1 > 0, e0 - e1, 1.0), 0.0, 1.0)
    T = jnp.where(settled, t0 + frac * (t1 - t0), t[last])
    T = jnp.where(any_out, T, 0.0)
    return T, settled | ~any_out


def soft_settling_time(err: Float[Array, " N"], ts, band, width=0.25, mask=None, eps=1e-9):
    """Smooth surrogate ``T_soft = t_s sum_k sigmoid((log(e_k + eps) - log band) / width)`` (module
    docstring): time spent outside the band, with a soft indicator in log-error. Differentiable
    everywhere (``e_k >= 0``; ``eps`` keeps the log finite at a zero error)."""
    err = jnp.asarray(err)
    x = (jnp.log(err + eps) - jnp.log(band)) / width
    s = jax.nn.sigmoid(x)
    if mask is not None:
        s = jnp.where(mask, s, 0.0)
    return ts * jnp.sum(s)


# ----------------------------------------------------------------------------------------------
# torque monitor (smooth max |tau| as an integrated state)


TORQUE_POWER = 8


class TorqueMonitor(AbstractController):
    """Wraps a controller and integrates ``sum_i (tau_i / tau_max_i)^p`` (``p = 8``) as an extra
    state: ``z = (z_inner, acc)`` with ``z_inner`` a zero-size array for stateless controllers. The
    torque scale ``tau_max`` rides in the gains: ``gains = (inner_gains, tau_max)``."""

    inner: AbstractController

    def default_gains(self):
        return (self.inner.default_gains(), jnp.asarray(1.0))

    def init_state(self, arm, q0, qd0):
        z = self.inner.init_state(arm, q0, qd0)
        dtype = jnp.asarray(q0).dtype
        z = jnp.zeros((0,), dtype) if not jax.tree.leaves(z) else z
        return (z, jnp.zeros((), dtype))

    @property
    def needs_joint_reference(self) -> bool:
        return self.inner.needs_joint_reference

    @property
    def uses_guidance(self) -> bool:
        return self.inner.uses_guidance

    def __call__(self, gains, arm, state, ref, env) -> ControlOutput:
        inner_gains, tau_max = gains
        z_in, _ = state.z
        stateless = isinstance(z_in, jax.Array) and z_in.shape == (0,)
        st = ControlState(t=state.t, q=state.q, qd=state.qd, z=() if stateless else z_in)
        out = self.inner(inner_gains, arm, st, ref, env)
        dz_in = jnp.zeros((0,), state.q.dtype) if stateless else out.dz
        r = out.tau / tau_max
        dacc = jnp.sum(r**TORQUE_POWER)
        return ControlOutput(tau=out.tau, dz=(dz_in, dacc), diag=out.diag)


def _smooth_max_torque_ratio(acc, horizon):
    """``m = (acc / T)^(1/p)`` from the integrated ``sum_i (tau_i/tau_max)^p``."""
    return (jnp.maximum(acc, 1e-300) / horizon) ** (1.0 / TORQUE_POWER)


# ----------------------------------------------------------------------------------------------
# gains <-> vectors, JSON


def _check_controller_name(name: str):
    if name not in TUNABLE:
        raise ValueError(f"controller: cannot tune {name!r}; tunable controllers are {sorted(TUNABLE)} "
                         "(the gradient-guided controller has no tracking reference to step)")


def controller_name(controller) -> str:
    """Registry name of a controller instance or name."""
    if isinstance(controller, str):
        return controller
    for k, cls in CONTROLLERS.items():
        if type(controller) is cls:
            return k
    raise ValueError(f"controller: {type(controller).__name__} is not in the CONTROLLERS registry")


def strong_gains(gains):
    """``gains`` with every array leaf *strongly* typed. The gains Modules convert Python floats with
    ``jnp.asarray``, which makes weakly-typed scalars; a jitted function called once with default
    (weak) and once with tuned (strong) gains would compile twice. The tuner, the figure and the
    settling-time helpers pass gains through this."""
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.asarray(x).dtype) if eqx.is_array(x) else x, gains)


def get_gains(gains, fields) -> Float[Array, " k"]:
    """The tunable ``fields`` of a gains Module as a vector."""
    return jnp.stack([jnp.asarray(getattr(gains, f)) for f in fields])


def set_gains(gains, fields, values):
    """A copy of ``gains`` with ``fields`` set to ``values`` (a vector, same order)."""
    return eqx.tree_at(lambda g: tuple(getattr(g, f) for f in fields), gains,
                       tuple(values[i] for i in range(len(fields))))


def gains_from_dict(controller, overrides: dict | None):
    """The controller's default gains with the top-level scalar fields of ``overrides``
    (``{gain_field: value}``, the format of ``tuned_gains.json`` and the study's ``--gains``)."""
    g = controller.default_gains()
    if not overrides:
        return g
    names = [f.name for f in dataclasses.fields(g)]
    for k, v in overrides.items():
        cur = getattr(g, k, None)
        if k not in names or not isinstance(cur, jax.Array) or cur.ndim != 0:
            raise ValueError(f"gains.{k}: not a scalar gain of {type(g).__name__} (fields: {names})")
        if not math.isfinite(float(v)):
            raise ValueError(f"gains.{k}: must be finite, got {v!r}")
    dtype = jnp.asarray(getattr(g, names[0])).dtype
    return eqx.tree_at(lambda gg: tuple(getattr(gg, k) for k in overrides), g,
                       tuple(jnp.asarray(float(v), dtype) for v in overrides.values()))


def gains_to_dict(gains, fields) -> dict:
    return {f: float(getattr(gains, f)) for f in fields}


def write_gains_json(path, tuned: dict) -> Path:
    """Write ``{controller_name: {gain_field: value}}`` (what the study's ``--gains`` reads).
    A value that is not a finite number (a tuning that diverged) is refused, naming it: the study
    would refuse it on reading, and JSON has no NaN."""
    path = Path(path)
    for ctrl, gains in tuned.items():
        for k, v in gains.items():
            if not math.isfinite(float(v)):
                raise ValueError(f"write_gains_json: {ctrl}.{k} must be finite, got {v!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(tuned, indent=2, sort_keys=True, allow_nan=False))
    return path


# ----------------------------------------------------------------------------------------------
# running an experiment


def _sim_params(params):
    return SimParams() if params is None else params


def step_response(arm: Arm, controller, gains, experiment: StepExperiment, params=None) -> SimResult:
    """Simulate ``controller`` with ``gains`` on ``experiment`` (joint reference for joint-space
    controllers)."""
    ik = experiment.joint_reference if controller.needs_joint_reference else None
    return simulate(arm, experiment.scenario, controller, strong_gains(gains), ik=ik,
                    params=_sim_params(params), q0=experiment.q0)


def experiment_settling_time(arm, controller, gains, experiment: StepExperiment, params=None):
    """``(T_s, settled, SimResult)`` of one run of the step experiment."""
    res = step_response(arm, controller, gains, experiment, params)
    T, ok = settling_time(res.pos_err, res.t, experiment.band, res.mask)
    return float(T), bool(ok) and not bool(res.diverged), res


def target_settling_time(arm: Arm, experiment: StepExperiment | None = None, params=None) -> float:
    """The default target: the joint-space controller's settling time with the thesis gains
    (K_p = 1000, K_d = 100) on the step experiment."""
    experiment = step_experiment(arm) if experiment is None else experiment
    js = make_controller("joint_space")
    T, ok, _ = experiment_settling_time(arm, js, js.default_gains(), experiment, params)
    if not ok:
        raise ValueError("target: the joint-space reference run did not settle within the horizon")
    return T


# ----------------------------------------------------------------------------------------------
# the tuner


class TuneSettings(eqx.Module):
    """Numbers of the tuner (arrays; changing them never recompiles). ``width``: surrogate sigmoid
    width in log-error; ``reg``: pull of the log-gains toward the start; ``ratio_weight``: stability
    box weight; ``torque_weight``; ``stop_rtol``: stop once ``|T_s - T*| <= stop_rtol T*`` (settling
    objective) and, with a torque bound, the torque ratio is at most ``1 + torque_rtol``; iterates
    over that ratio are never returned while one within it was accepted."""

    learning_rate: Float[Array, ""] = eqx.field(default=1.0, converter=_arr)
    width: Float[Array, ""] = eqx.field(default=0.25, converter=_arr)
    reg: Float[Array, ""] = eqx.field(default=1e-3, converter=_arr)
    ratio_weight: Float[Array, ""] = eqx.field(default=1.0, converter=_arr)
    torque_weight: Float[Array, ""] = eqx.field(default=10.0, converter=_arr)
    stop_rtol: Float[Array, ""] = eqx.field(default=0.02, converter=_arr)
    torque_rtol: Float[Array, ""] = eqx.field(default=0.02, converter=_arr)
    lm_damping: Float[Array, ""] = eqx.field(default=1e-3, converter=_arr)


class TuneResult(NamedTuple):
    """Result of :func:`tune_gains` (a leading batch axis from :func:`tune_gains_batch`).

    * ``gains``: the tuned gains Module (best accepted iterate); ``fields``: the tuned fields;
    * ``settling_time`` [s] and ``settled`` of the tuned gains; ``target`` [s];
    * ``initial_settling_time`` [s]; ``tracking_rms`` [m] (tracking objective; nan otherwise);
    * ``max_torque_ratio``: smooth max of ``|tau| / tau_max`` (nan without a bound);
    * ``history``: dict of per-iteration arrays ``loss``, ``settling_time``, ``log_gains``
      ``(steps, k)``, ``accepted``;
    * ``iterations``: evaluations of the loss (simulation and reverse pass) made, at most
      ``steps + 1``: each optimiser step and a last one that scores the final gains;
      ``wall_time`` [s] and ``compile_time`` [s].
    """

    gains: object
    fields: tuple
    settling_time: object
    settled: object
    target: object
    initial_settling_time: object
    tracking_rms: object
    max_torque_ratio: object
    history: dict
    iterations: int
    wall_time: float
    compile_time: float


class _Aux(NamedTuple):
    T: Array
    T_soft: Array
    settled: Array
    rms: Array
    torque: Array
    bad: Array


def _sim_residuals(theta, arm, controller, base_gains, experiment, params, fields, objective,
                   use_torque, target, tau_max, settings):
    """The simulator-dependent residuals ``(r_main, r_tau)`` at log-gains ``theta`` and auxiliaries.

    ``r_main = (T_hat - T*) / T*`` with ``T_hat = T_soft + stop_gradient(T_s - T_soft)`` (settling) or
    ``rms(e_p) / 1 mm`` (tracking); ``r_tau = sqrt(c) 0.05 softplus((m - 1) / 0.05)`` (0 without a
    torque bound)."""
    gains = set_gains(base_gains, fields, jnp.exp(theta))
    ctrl = TorqueMonitor(controller) if use_torque else controller
    g = (gains, tau_max) if use_torque else gains
    ik = experiment.joint_reference if controller.needs_joint_reference else None
    res = simulate(arm, experiment.scenario, ctrl, g, ik=ik, params=params, q0=experiment.q0)
    err, mask = res.pos_err, res.mask
    ref = experiment.scenario.reference
    ts = ref.ts.astype(err.dtype)
    horizon = ts * ref.n_samples.astype(err.dtype)
    T, settled = settling_time(jax.lax.stop_gradient(err), res.t, experiment.band, mask)
    T_soft = soft_settling_time(err, ts, experiment.band, settings.width, mask)
    rms = jnp.sqrt(jnp.sum(jnp.where(mask, err**2, 0.0)) / jnp.maximum(jnp.sum(mask), 1))
    if objective == "settling":
        T_hat = T_soft + jax.lax.stop_gradient(T - T_soft)
        r_main = (T_hat - target) / target
    else:
        r_main = rms / experiment.band
    if use_torque:
        m = _smooth_max_torque_ratio(res.z[1], horizon)
        s = 0.05
        r_tau = jnp.sqrt(settings.torque_weight) * s * jax.nn.softplus((m - 1.0) / s)
    else:
        m = jnp.asarray(jnp.nan, err.dtype)
        r_tau = jnp.zeros((), err.dtype)
    R = jnp.stack([r_main, r_tau])
    bad = res.diverged | ~jnp.all(jnp.isfinite(R))
    return R, _Aux(T=T, T_soft=T_soft, settled=settled, rms=rms, torque=m, bad=bad)


def _prior_residuals(theta, theta0, name, fields, settings):
    """Analytic residuals: ``sqrt(rho) (theta - theta_0)`` and the stability box of
    :data:`RATIO_BOUNDS` (``sqrt(w) 0.1 softplus(log-violation / 0.1)`` each side)."""
    out = [jnp.sqrt(settings.reg) * (theta - theta0)]
    for a, b, c, lo, hi in RATIO_BOUNDS.get(name, ()):
        if a not in fields or b not in fields:
            continue
        r = theta[fields.index(a)] - c * theta[fields.index(b)]
        s = 0.1
        out.append(jnp.sqrt(settings.ratio_weight) * s * jnp.stack(
            [jax.nn.softplus((math.log(lo) - r) / s), jax.nn.softplus((r - math.log(hi)) / s)]))
    return jnp.concatenate(out)


class _State(NamedTuple):
    theta: Array  # the point evaluated next
    good: Array  # last accepted point, its merit, residuals and Jacobian
    good_merit: Array
    good_R: Array
    good_J: Array
    opt: object
    scale: Array  # trust-region multiplier (x0.5 on a rejected step, x1.5 up to 1 on an accepted one)
    done: Array


def _optimizer(method):
    """optax transformation applied to the descent direction: ``"lm"`` takes the
    Levenberg-Marquardt step as is (trust region: global norm <= 0.3 in log-gain, i.e. at most a
    35 % gain change per iteration); ``"adam"`` gets the gradient ``J^T R``."""
    if method == "lm":
        return optax.chain(optax.clip_by_global_norm(0.3), optax.scale(-1.0))
    return optax.adam(1.0)  # the learning rate is applied by hand (lr * scale)


def _init_state(theta, n_res, method, dtype):
    k = theta.shape[-1]
    return _State(theta=theta, good=theta, good_merit=jnp.asarray(jnp.inf, dtype),
                  good_R=jnp.zeros((n_res,), dtype), good_J=jnp.zeros((n_res, k), dtype),
                  opt=_optimizer(method).init(theta), scale=jnp.ones((), dtype), done=jnp.zeros((), bool))


def _n_residuals(name, fields):
    return 2 + len(fields) + 2 * sum(1 for a, b, *_ in RATIO_BOUNDS.get(name, ()) if a in fields and b in fields)


def _step(state: _State, arm, base_gains, experiment, target, theta0, tau_max, settings, params, *,
          controller, name, fields, objective, use_torque, method):
    """One iteration. The residuals ``R = [r_main, r_tau, prior]`` and their Jacobian at ``theta``
    (one forward simulation, a reverse pass per simulator residual, batched); ``L = |R|^2 / 2``.

    Acceptance (a trust-region Levenberg-Marquardt): the point is accepted if its run is good and
    its merit does not exceed the last accepted one. The merit is ``L`` with the settling residual
    evaluated at ``T_m = T_s`` if settled, ``T + T_soft`` if not (``T`` the horizon), so every
    settled point beats every unsettled one and unsettled points are ranked by the surrogate.
    From the accepted point (or, after a rejection, from the last accepted one with its stored
    ``R, J`` and half the trust region):

    * ``"lm"``: ``d = (J^T J + lam I)^-1 J^T R``, ``lam = mu tr(J^T J) / k`` (``mu`` =
      ``settings.lm_damping``), clipped to the trust region, ``theta <- theta - lr scale d``;
    * ``"adam"``: ``theta <- theta + lr scale adam(J^T R)``.

    Converged members (settled, ``|T_s - T*| <= stop_rtol T*``) stay put."""
    fn = lambda th: _sim_residuals(th, arm, controller, base_gains, experiment, params, fields,
                                   objective, use_torque, target, tau_max, settings)
    R_sim, pullback, aux = jax.vjp(fn, state.theta, has_aux=True)
    J_sim = jax.vmap(lambda ct: pullback(ct)[0])(jnp.eye(R_sim.shape[0], dtype=R_sim.dtype))
    R_pri = _prior_residuals(state.theta, theta0, name, fields, settings)
    J_pri = jax.jacfwd(_prior_residuals)(state.theta, theta0, name, fields, settings)
    R = jnp.concatenate([R_sim, R_pri])
    J = jnp.concatenate([J_sim, J_pri])
    J_finite = jnp.all(jnp.isfinite(J_sim))
    R = jnp.where(jnp.isfinite(R), R, 0.0)
    J = jnp.where(jnp.isfinite(J), J, 0.0)
    loss = 0.5 * jnp.sum(R * R)
    if objective == "settling":
        ref = experiment.scenario.reference
        horizon = ref.ts.astype(R.dtype) * ref.n_samples.astype(R.dtype)
        T_m = jnp.where(aux.settled, aux.T, horizon + aux.T_soft)
        merit = loss + 0.5 * (((T_m - target) / target) ** 2 - R[0] ** 2)
    else:
        merit = loss
    bad = aux.bad | ~jnp.isfinite(merit) | ~J_finite  # a NaN reverse pass is no direction to take
    accept = (~bad) & (merit <= state.good_merit)
    scale = jnp.where(accept, jnp.minimum(1.5 * state.scale, 1.0), 0.5 * state.scale)
    R_use = jnp.where(accept, R, state.good_R)
    J_use = jnp.where(accept, J, state.good_J)
    origin = jnp.where(accept, state.theta, state.good)
    opt = _optimizer(method)
    grad = J_use.T @ R_use
    if method == "lm":
        k = state.theta.shape[0]
        JTJ = J_use.T @ J_use
        lam = settings.lm_damping * jnp.trace(JTJ) / k + 1e-12
        d = jnp.linalg.solve(JTJ + lam * jnp.eye(k, dtype=J.dtype), grad)
        updates, opt_new = opt.update(d, state.opt, origin)
    else:
        updates, opt_new = opt.update(grad, state.opt, origin)
    theta_new = origin + settings.learning_rate * scale * updates
    converged = _converged(objective, use_torque, accept, aux, target, settings)
    done = state.done | converged
    hold = lambda old, new: jnp.where(state.done, old, new)
    new = _State(theta=hold(state.theta, jnp.where(converged, state.theta, theta_new)),
                 good=hold(state.good, origin),
                 good_merit=hold(state.good_merit, jnp.where(accept, merit, state.good_merit)),
                 good_R=hold(state.good_R, R_use), good_J=hold(state.good_J, J_use),
                 # a rejected point retries the last accepted one's step at half the trust region:
                 # Adam's moments and count advance on accepted points only
                 opt=jax.tree.map(lambda o, n: jnp.where(state.done | ~accept, o, n), state.opt, opt_new),
                 scale=hold(state.scale, scale), done=done)
    # d T_soft / d theta (settling: r_main = (T_hat - T*) / T*); exposed for the gradient checks
    dT_soft = J_sim[0] * target if objective == "settling" else jnp.zeros_like(state.theta)
    return new, (loss, aux, state.theta, accept, dT_soft)


def _converged(objective, use_torque, accept, aux, target, settings):
    """The tuner stops at an accepted iterate that settles within ``stop_rtol`` of the target and,
    with a torque bound, keeps the torque ratio within ``1 + torque_rtol`` (settling objective;
    the tracking objective runs all its steps)."""
    if objective != "settling":
        return jnp.zeros((), bool)
    ok = accept & aux.settled & (jnp.abs(aux.T - target) <= settings.stop_rtol * target)
    if use_torque:
        ok = ok & (aux.torque <= 1.0 + settings.torque_rtol)
    return ok


@functools.lru_cache(maxsize=None)
def _jitted_step(controller, name, fields, objective, use_torque, method, batched, arms_batched):
    """The jitted (and, for batches, vmapped) :func:`_step`; cached so that repeated tunings with
    the same structure reuse one compilation."""
    fn = functools.partial(_step, controller=controller, name=name, fields=fields, objective=objective,
                           use_torque=use_torque, method=method)
    if batched:
        ax = 0 if arms_batched else None
        fn = eqx.filter_vmap(fn, in_axes=(0, ax, 0, ax, 0, 0, None, None, None))
    return eqx.filter_jit(fn)


def _prepare(arm, controller, objective, torque_bound, target, experiment, params, gains):
    if isinstance(controller, str):
        controller = make_controller(controller)
    name = controller_name(controller)
    _check_controller_name(name)
    if objective not in ("settling", "tracking"):
        raise ValueError(f"objective: expected 'settling' or 'tracking', got {objective!r}")
    if objective == "tracking" and torque_bound is None:
        raise ValueError("torque_bound: the tracking objective needs a torque bound (without one the "
                         "optimum is infinite gains)")
    if torque_bound is not None:
        tb = np.asarray(torque_bound, float)
        if np.any(~np.isfinite(tb)) or np.any(tb <= 0) or tb.shape not in ((), (arm.n_dof,)):
            raise ValueError(f"torque_bound: expected a positive scalar or ({arm.n_dof},) [N m / N], "
                             f"got {torque_bound!r}")
    if experiment is None:
        experiment = step_experiment(arm) if objective == "settling" else tracking_experiment(arm)
    if objective == "settling" and experiment.kind != "step":
        raise ValueError("experiment: the settling objective needs a step experiment")
    params = _sim_params(params)
    if target is None:
        target = target_settling_time(arm, experiment, params) if objective == "settling" else 1.0
    _check_target(target)
    base = controller.default_gains() if gains is None else gains
    _check_start_gains(base, name)
    return controller, name, experiment, params, float(target), base


def _check_target(target) -> None:
    """Finite settling times > 0, each (+inf let every run count as settled at once)."""
    t = np.asarray(target, float)
    if t.size == 0 or not np.all(np.isfinite(t) & (t > 0)):
        raise ValueError(f"target: settling time(s) must be finite and > 0 s, got {target}")


def _check_start_gains(gains, name) -> None:
    """The tuned gains start finite and > 0, where concrete: the tuner steps in ``log g`` (a
    negative gain gave NaN and was handed back as tuned, a zero one never moved)."""
    fields = TUNABLE[name]
    for f in fields:
        v = concrete(getattr(gains, f))
        if v is not None and not np.all(np.isfinite(v) & (v > 0)):
            raise ValueError(f"gains.{f}: the tuner works on log-gains and needs finite values > 0 to "
                             f"start from, got {v}")


def settling_gradient(arm: Arm, controller, gains, experiment: StepExperiment, params=None,
                      width: float = 0.25):
    """``(T_s, T_soft, dT_soft / d log g)`` at ``gains`` for the tunable fields of ``controller``,
    through the tuner's own compiled iteration (so checking it checks what the tuner uses).
    ``params`` may differ from the tuner's in its numbers (e.g. tighter tolerances) without a
    recompilation."""
    if isinstance(controller, str):
        controller = make_controller(controller)
    name = controller_name(controller)
    _check_controller_name(name)
    fields = TUNABLE[name]
    gains = strong_gains(gains)
    dtype = jnp.asarray(gains.kp).dtype
    theta = jnp.asarray(jnp.log(get_gains(gains, fields)), dtype)
    settings = TuneSettings(width=width)
    settings = eqx.tree_at(lambda s: s.learning_rate, settings, jnp.asarray(1.0, dtype))
    state = _init_state(theta, _n_residuals(name, fields), "lm", dtype)
    jstep = _jitted_step(controller, name, fields, "settling", False, "lm", False, False)
    tau_max = jnp.ones((arm.n_dof,), dtype)
    _, (_, aux, _, _, dT) = jstep(state, arm, gains, experiment, jnp.asarray(1.0, dtype), theta, tau_max,
                                  settings, _sim_params(params))
    return aux.T, aux.T_soft, dT


def tune_gains(arm: Arm, controller, target=None, steps: int = 30, learning_rate: float | None = None,
               torque_bound=None, objective: str = "settling", *, method: str = "lm", gains=None,
               experiment=None, params: SimParams | None = None, settings: TuneSettings | None = None,
               verbose: bool = False) -> TuneResult:
    """Tune the gains of ``controller`` (an instance or a registry name) on ``arm``.

    **Arguments**
    * ``target``: settling time [s] to reach (default: the joint-space controller's with K_p 1000,
      K_d 100 on the same experiment, :func:`target_settling_time`);
    * ``steps``: at most this many optimiser steps (each one simulation and its reverse pass, plus
      one last evaluation of the final gains; stops earlier once settled within ``stop_rtol`` of
      the target); ``learning_rate``: multiplier of
      the step (default 1 for ``method="lm"``, 0.1 for ``"adam"``); ``method``: ``"lm"``
      (Levenberg-Marquardt, default) or ``"adam"``;
    * ``torque_bound``: ``tau_max`` (scalar or per joint) for the smooth-max torque penalty;
    * ``objective``: ``"settling"`` (default) or ``"tracking"`` (RMS error on the circle);
    * ``gains``: starting gains (default: the thesis gains); ``experiment``: a
      :class:`StepExperiment` (default :func:`step_experiment` / :func:`tracking_experiment`);
      ``params``: :class:`~redman_jax._sim.SimParams`; ``settings``: :class:`TuneSettings`.

    **Returns** a :class:`TuneResult` (the best accepted iterate: for the settling objective the one
    with the smallest ``|T_s - T*|`` among settled iterates, for tracking the smallest loss).

    **Raises** ``ValueError`` for an untunable controller, an unknown objective, a tracking
    objective without torque bound, a bad torque bound or target, ``steps`` that is not an int
    >= 0 or a ``learning_rate`` that is not finite and positive.
    """
    _check_schedule(steps, learning_rate)
    controller, name, experiment, params, target, base = _prepare(
        arm, controller, objective, torque_bound, target, experiment, params, gains)
    return _tune(arm, controller, name, base, experiment, params, target, steps, learning_rate,
                 torque_bound, objective, settings, batched=False, verbose=verbose, method=method)


def tune_gains_batch(arm: Arm, controller, inits, target=None, steps: int = 30,
                     learning_rate: float | None = None, torque_bound=None, objective: str = "settling",
                     *, method: str = "lm", arms_batched: bool = False, experiments=None, params=None,
                     settings=None) -> TuneResult:
    """:func:`tune_gains` for a batch in one ``jit(vmap(...))`` per iteration: ``inits`` is a gains
    Module with a leading axis ``B`` (several initial guesses; e.g. ``jax.tree.map(lambda *x:
    jnp.stack(x), *list_of_gains)``). With ``arms_batched=True`` ``arm`` is a stack of ``B`` arms of
    the same structure and ``experiments`` their stacked experiments (default: built per arm).
    ``target``: a scalar or ``(B,)`` (default: each arm's joint-space settling time)."""
    _check_schedule(steps, learning_rate)
    if objective not in ("settling", "tracking"):  # before any experiment is built (an IK run)
        raise ValueError(f"objective: expected 'settling' or 'tracking', got {objective!r}")
    if target is not None:
        _check_target(target)
    if isinstance(controller, str):
        controller = make_controller(controller)
    B = jax.tree.leaves(inits)[0].shape[0]
    if arms_batched:
        arm_list = [jax.tree.map(lambda x: x[i] if isinstance(x, jax.Array) else x, arm) for i in range(B)]
    else:
        arm_list = [arm] * B
    if experiments is None:
        exps = [step_experiment(a) if objective == "settling" else tracking_experiment(a) for a in
                (arm_list if arms_batched else arm_list[:1])]
        experiments = jax.tree.map(lambda *x: jnp.stack(x), *exps) if arms_batched else exps[0]
    if target is None:
        if objective == "settling":
            if arms_batched:
                ex_list = [jax.tree.map(lambda x: x[i], experiments) for i in range(B)]
                target = np.array([target_settling_time(a, e, params) for a, e in zip(arm_list, ex_list)])
            else:
                target = target_settling_time(arm, experiments, params)
        else:
            target = 1.0
    ex0 = jax.tree.map(lambda x: x[0], experiments) if arms_batched else experiments
    controller, name, _, params, _, _ = _prepare(arm_list[0], controller, objective, torque_bound,
                                                 1.0, ex0, params, None)
    _check_target(target)
    _check_start_gains(inits, name)
    return _tune(arm, controller, name, inits, experiments, params,
                 np.broadcast_to(np.asarray(target, float), (B,)), steps, learning_rate, torque_bound,
                 objective, settings, batched=True, arms_batched=arms_batched, method=method)


def _check_schedule(steps, learning_rate) -> None:
    """Before anything is simulated (the default target is a simulation): ``steps`` an int >= 0
    (0 only scores the starting gains), ``learning_rate`` None or finite and positive."""
    check_count("steps", steps, 0)
    if learning_rate is not None:
        check_positive("learning_rate", learning_rate)


def _tune(arm, controller, name, base, experiment, params, target, steps, learning_rate,
          torque_bound, objective, settings, batched, arms_batched=False, verbose=False, method="lm"):
    if method not in ("lm", "adam"):
        raise ValueError(f"method: expected 'lm' or 'adam', got {method!r}")
    fields = TUNABLE[name]
    settings = TuneSettings() if settings is None else settings
    if learning_rate is None:
        learning_rate = 1.0 if method == "lm" else 0.1
    dtype = jnp.asarray(base.kp).dtype
    settings = eqx.tree_at(lambda s: s.learning_rate, settings, jnp.asarray(float(learning_rate), dtype))
    use_torque = torque_bound is not None
    tau_max = jnp.broadcast_to(jnp.asarray(1.0 if torque_bound is None else torque_bound, dtype),
                               (arm.q0.shape[-1],))
    jstep = _jitted_step(controller, name, fields, objective, use_torque, method, batched, arms_batched)
    base = strong_gains(base)
    theta0 = jnp.asarray(jnp.log(jnp.stack([jnp.asarray(getattr(base, f)) for f in fields], axis=-1)), dtype)
    target = jnp.asarray(target, dtype)

    def init(th):
        return _init_state(th, _n_residuals(name, fields), method, dtype)

    state = jax.vmap(init)(theta0) if batched else init(theta0)
    args = (arm, base, experiment, target, theta0, tau_max, settings, params)
    times = []
    hist = {"loss": [], "settling_time": [], "soft_settling_time": [], "log_gains": [], "accepted": [],
            "settled": [], "tracking_rms": [], "torque_ratio": []}
    t0 = time.perf_counter()
    it = 0
    for it in range(1, steps + 2):  # the last evaluation only scores the final point
        t1 = time.perf_counter()
        state, (loss, aux, theta, ok, _) = jstep(state, *args)
        jax.block_until_ready(state)
        times.append(time.perf_counter() - t1)
        hist["loss"].append(np.asarray(loss))
        hist["settling_time"].append(np.asarray(aux.T))
        hist["soft_settling_time"].append(np.asarray(aux.T_soft))
        hist["log_gains"].append(np.asarray(theta))
        hist["accepted"].append(np.asarray(ok))
        hist["settled"].append(np.asarray(aux.settled))
        hist["tracking_rms"].append(np.asarray(aux.rms))
        hist["torque_ratio"].append(np.asarray(aux.torque))
        if verbose:
            print(f"[tune {name}] it {it}: loss {np.asarray(loss)} T_s {np.asarray(aux.T)} "
                  f"T_soft {np.asarray(aux.T_soft)} gains {np.exp(np.asarray(theta))} ok {np.asarray(ok)}",
                  flush=True)
        if bool(jnp.all(state.done)):
            break
    wall = time.perf_counter() - t0
    # compile time: the first call's excess over the median of the others (0 when cached)
    compile_time = max(times[0] - float(np.median(times[1:])), 0.0) if len(times) > 1 else times[0]
    hist = {k: np.stack(v) for k, v in hist.items()}
    hist["iteration_time"] = np.asarray(times)
    best = _best_iterate(hist, np.asarray(target), objective,
                         np.asarray(settings.torque_rtol) if use_torque else None)  # (B,) or ()
    th = np.take_along_axis(hist["log_gains"], best[None, ..., None], axis=0)[0] if batched else \
        hist["log_gains"][int(best)]
    pick = lambda a: (np.take_along_axis(a, best[None], axis=0)[0] if batched else a[int(best)])
    tuned_vals = jnp.exp(jnp.asarray(th, dtype))
    if batched:
        gains = jax.vmap(lambda g, v: set_gains(g, fields, v))(base, tuned_vals)
    else:
        gains = set_gains(base, fields, tuned_vals)
    return TuneResult(
        gains=gains, fields=fields, settling_time=pick(hist["settling_time"]),
        settled=pick(hist["settled"] & hist["accepted"]),
        target=np.asarray(target), initial_settling_time=hist["settling_time"][0],
        tracking_rms=pick(hist["tracking_rms"]) if objective == "tracking" else np.full_like(pick(hist["tracking_rms"]), np.nan),
        max_torque_ratio=pick(hist["torque_ratio"]), history=hist, iterations=it, wall_time=wall,
        compile_time=compile_time)


def _best_iterate(hist, target, objective, torque_rtol=None):
    """Index of the best accepted iterate per batch member. With a torque bound (``torque_rtol``
    given) an iterate whose torque ratio exceeds ``1 + torque_rtol`` ranks after every one within
    it (among those over it, the lower ratio first)."""
    ok = hist["accepted"].astype(bool)
    if objective == "settling":
        # unsettled iterates carry T_s = horizon, so they score worse than any settled one near T*
        score = np.abs(hist["settling_time"] - target) + np.where(hist["settled"], 0.0, 1e3)
    else:
        score = hist["loss"]
    if torque_rtol is not None:
        ratio = hist["torque_ratio"]
        score = score + np.where(ratio <= 1.0 + torque_rtol, 0.0, 1e6 * (1.0 + ratio))
    score = np.where(ok & np.isfinite(score), score, np.inf)
    return np.argmin(score, axis=0)


# ----------------------------------------------------------------------------------------------
# figure and CLI


FIG_CONTROLLERS = ("joint_space", "velocity", "acceleration")
_LABELS = {"joint_space": "joint space (joint step)", "velocity": "velocity OSC",
           "acceleration": "acceleration OSC", "pid": "PID", "impedance": "impedance",
           "velocity_original": "velocity OSC (original)"}


def step_responses(arm: Arm, gains_by_controller: dict | None = None, controllers=FIG_CONTROLLERS,
                   experiment: StepExperiment | None = None, params=None) -> dict:
    """``{name: (t, |e_p|, T_s, settled)}`` of the step experiment for each controller, with the
    gains of ``gains_by_controller[name]`` (a gains Module or a ``{field: value}`` dict; default: the
    thesis gains)."""
    experiment = step_experiment(arm) if experiment is None else experiment
    out = {}
    for name in controllers:
        ctrl = make_controller(name)
        g = (gains_by_controller or {}).get(name)
        g = gains_from_dict(ctrl, g) if (g is None or isinstance(g, dict)) else g
        T, ok, res = experiment_settling_time(arm, ctrl, g, experiment, params)
        t = np.concatenate([[0.0], np.asarray(res.t)])
        e0 = float(np.linalg.norm(np.asarray(experiment.scenario.reference.p[0])
                                  - np.asarray(end_effector_pose(arm, experiment.q0)[0])))
        e = np.concatenate([[e0], np.asarray(res.pos_err)])
        out[name] = (t, e, T, ok)
    return out


def step_response_figure(arm: Arm, out_png, gains_by_controller: dict | None = None,
                         controllers=FIG_CONTROLLERS, title: str | None = None, responses=None) -> dict:
    """Figure 3.6: ``|e_p|(t)`` over the 1 s step for each controller (log scale, 2 % band dashed,
    settling times marked). Returns the responses of :func:`step_responses`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    responses = step_responses(arm, gains_by_controller, controllers) if responses is None else responses
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    band = None
    for name, (t, e, T, ok) in responses.items():
        lab = f"{_LABELS.get(name, name)}: T_s = {T:.3f} s" + ("" if ok else " (not settled)")
        line, = ax.semilogy(t, np.maximum(e, 1e-7), label=lab)
        if ok:
            ax.axvline(T, color=line.get_color(), lw=0.8, ls=":")
        band = BAND_FRACTION * e[0]
    if band is not None:
        ax.axhline(band, color="k", ls="--", lw=0.8, label="2 % band")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("|e_p| [m]")
    ax.set_xlim(0, max(t[-1] for t, *_ in responses.values()))
    ax.set_title(title or f"Step response, {arm.n_dof}-DOF arm (0.05 m step in +x)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=120)
    plt.close(fig)
    return responses


def tune_cli(args) -> dict:
    """``redman-jax tune``: tune ``args.controllers`` (comma list) on the thesis arm ``args.arm`` to
    the joint-space settling time with ``args.steps`` iterations; write ``tuned_gains.json``,
    ``fig3_6_before.png`` and ``fig3_6_after.png`` to ``args.out`` and print a table.

    Python's garbage collector is set for tracing first (:func:`redman_jax._study.tune_gc`): the
    tuner traces reverse-mode simulations. Measured (``tune --arm 7 --controllers velocity --steps
    3``, the two settings side by side on one core each, then on swapped cores): tracing and lowering
    16.3 / 17.3 -> 12.7 / 13.8 s, the whole command 93.1 / 99.1 -> 89.1 / 97.4 s, the same
    ``tuned_gains.json``."""
    from ._cli import parse_name_list
    from ._study import tune_gc

    try:
        dof = int(str(args.arm).strip())
        arm = thesis_arm(dof)
    except (TypeError, ValueError):
        raise ValueError(f"--arm: expected a thesis DOF (7, 8 or 9), got {args.arm!r}") from None
    names = parse_name_list(args.controllers, "controllers", tuple(sorted(TUNABLE)))
    if args.steps < 1:
        raise ValueError(f"--steps: must be >= 1, got {args.steps}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tune_gc()
    exp = step_experiment(arm)
    target = target_settling_time(arm, exp)
    fig_ctrls = tuple(dict.fromkeys(("joint_space",) + tuple(names)))
    before = step_response_figure(arm, out / "fig3_6_before.png", None, fig_ctrls,
                                  title=f"Before tuning (thesis gains), {dof}-DOF")
    tuned, rows = {}, []
    for name in names:
        r = tune_gains(arm, name, target, steps=args.steps, experiment=exp)
        tuned[name] = gains_to_dict(r.gains, r.fields)
        rows.append((name, before[name][2], float(r.settling_time), r.iterations, r.compile_time,
                     r.wall_time - r.compile_time, tuned[name], bool(np.all(np.asarray(r.settled)))))
    write_gains_json(out / "tuned_gains.json", tuned)
    step_response_figure(arm, out / "fig3_6_after.png", tuned, fig_ctrls,
                         title=f"After tuning (target {target:.3f} s), {dof}-DOF")
    print(f"target settling time (joint space, Kp 1000, Kd 100): {target:.3f} s")
    print(f"{'controller':<18}{'before [s]':>11}{'after [s]':>11}{'iters':>7}{'compile [s]':>13}"
          f"{'run [s]':>9}{'settled':>9}  gains")
    for name, Tb, Ta, it, ct, wt, g, ok in rows:
        gs = ", ".join(f"{k}={v:.4g}" for k, v in g.items())
        print(f"{name:<18}{Tb:>11.3f}{Ta:>11.3f}{it:>7d}{ct:>13.1f}{wt:>9.1f}{'yes' if ok else 'NO':>9}  {gs}")
    print(f"wrote {out / 'tuned_gains.json'}, {out / 'fig3_6_before.png'}, {out / 'fig3_6_after.png'}")
    unsettled = [r[0] for r in rows if not r[7]]
    if unsettled:  # e.g. PID without gravity compensation: its step never settles, the gradient vanishes
        # with no iterate settled every iterate scores the same (_best_iterate): the start is kept
        print(f"warning: {', '.join(unsettled)} did not settle within the experiment in any iterate; "
              f"tuned_gains.json keeps their starting gains, not a tuned result", file=sys.stderr)
    return tuned
