"""Evaluation measures of the study (thesis 3.5 and 4; SPEC section 10).

Everything here is a pure function of per-sample arrays, so it runs on one run or, under ``vmap``,
on a whole batch. Conventions (SPEC section 10):

* **Position error of sample k** ``e_k = |p(t_{k+1}) - p_d[k]|``: taken at the *end* of the sample
  against the sample still held (the simulator saves the state at ``t_{k+1} = (k+1) t_s``, so
  index ``k`` of the saved arrays is already aligned with reference sample ``k``).
* **Orientation error** ``|e_o| = |vec(Q_d (x) Q^-1)| = sin(phi / 2)`` (E19, unclipped), counted only
  on samples with ``rot = 1``.
* **Failure**: obstacle collision or final position error of 0.10 m or more (joint-limit contact is logged,
  not a failure). Gradient-guided runs: success once ``|p - x_g| < 0.10`` held for 1 s
  (``hold_samples = 100`` sample ends), otherwise the final error at the 6 s stop decides (U26).
* **Pooled vs per-run** aggregation of the errors over the runs of one (case, model, controller):
  ``pooled`` = mean over all valid samples of all successful runs (the thesis's "average per sample
  over all runs"), ``per_run`` = mean over successful runs of each run's mean.

Compute-time helpers measure like the thesis, sample-based, every component the same way: the wall
time of one compiled call over many samples divided by their number (IK and planning: one batched
call over the case's trajectories; the controller: one call that evaluates the control law at a
run's samples one after another, :func:`controller_time_per_sample`). The latency of a single
jitted call (:func:`controller_call_time`) is mostly JAX's and XLA's per-call overhead, not the
control law (measured there), so it is kept apart.
"""

from __future__ import annotations

import functools
import time
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._math import check_count, quat_error, safe_norm

__all__ = [
    "position_errors",
    "orientation_errors",
    "masked_mean",
    "RunMetrics",
    "run_metrics",
    "GuidanceTermination",
    "guidance_termination",
    "path_length",
    "pooled_mean",
    "per_run_mean",
    "aggregate_errors",
    "failure_rate",
    "time_per_call",
    "controller_time_per_sample",
    "controller_call_time",
    "wall_time_per_sample",
    "SUCCESS_RADIUS",
    "HOLD_TIME",
]

SUCCESS_RADIUS = 0.10  # [m] final position error bound of a successful run (thesis 3.5)
HOLD_TIME = 1.0  # [s] gradient-guided: the goal must be held this long (thesis 3.3.3)


def _norm_forward(x):
    """:func:`_norm`'s value without its second ``where`` (a NaN's partial is NaN): for comparisons
    that carry no gradient (the guided runs' stop rule inside their stepping loop, whose compiled
    arithmetic the extra select changed by rounding, moving 49 values of the guided rows)."""
    return jnp.where(jnp.isnan(jnp.sum(x, axis=-1)), jnp.nan, safe_norm(x, axis=-1))


def _norm(x):
    """Norm along the last axis with a zero gradient at ``x = 0`` (:func:`safe_norm`) that keeps a
    NaN: a non-finite pose (a run whose solve stopped) gives a NaN error, never an error of 0.
    Double ``where``: the norm is taken of 0 there, so its zero cotangent stays 0 (the NaN partial
    of the norm of NaN made the shared gains' gradient of a batch NaN for every member)."""
    bad = jnp.isnan(jnp.sum(x, axis=-1))
    return jnp.where(bad, jnp.nan, safe_norm(jnp.where(bad[..., None], 0.0, x), axis=-1))


def position_errors(p: Float[Array, "N 3"], p_d: Float[Array, "N 3"]) -> Float[Array, " N"]:
    """``e_k = |p(t_{k+1}) - p_d[k]|`` for every sample (``p`` saved at sample ends; NaN where
    ``p`` is NaN)."""
    return _norm(p - p_d)


def goal_errors(p: Float[Array, "N 3"], goal_p: Float[Array, "3"]) -> Float[Array, " N"]:
    """``|p_k - goal_p|`` per sample, ``inf`` where ``p`` is not finite (a stopped solve's rows
    never count as at the goal): the gradient-guided runs' error."""
    e = position_errors(p, jnp.broadcast_to(goal_p, p.shape))
    return jnp.where(jnp.isfinite(e), e, jnp.inf)


def orientation_errors(quat: Float[Array, "N 4"], quat_d: Float[Array, "N 4"]) -> Float[Array, " N"]:
    """``|e_o| = |vec(Q_d (x) Q^-1)| = sin(phi/2)`` per sample, unclipped (E19; hemisphere-checked)."""
    return _norm(jax.vmap(quat_error)(quat_d, quat))


def masked_mean(x: Float[Array, " N"], mask: Bool[Array, " N"]) -> Float[Array, ""]:
    """Mean of ``x`` over ``mask``; NaN when the mask is empty (nothing to average)."""
    m = mask.astype(x.dtype)
    cnt = jnp.sum(m)
    s = jnp.sum(jnp.where(mask, x, 0.0))
    return jnp.where(cnt > 0, s / jnp.where(cnt > 0, cnt, 1.0), jnp.nan)


def path_length(p0: Float[Array, "3"], p: Float[Array, "N 3"], mask: Bool[Array, " N"]) -> Float[Array, ""]:
    """End-effector path length ``sum_k |p_{k+1} - p_k|`` over the sample ends in ``mask``
    (starting from ``p0``, the position at ``t = 0``; NaN if a position in ``mask`` is NaN)."""
    prev = jnp.concatenate([p0[None], p[:-1]], axis=0)
    return jnp.sum(jnp.where(mask, _norm(p - prev), 0.0))


class RunMetrics(eqx.Module):
    """Per-run summary of a trajectory-tracking run (all scalars).

    ``mean_pos_err`` [m] and ``mean_ori_err`` (sin(phi/2), rot = 1 samples only; NaN if none),
    ``final_pos_err`` [m] (end-effector to goal at the last valid sample), ``collided`` (obstacle flag
    grew), ``joint_limit`` (joint-limit flag grew), ``success`` (no collision, final error < 0.10 m and
    not diverged), ``cause``: 0 success, 1 collision, 2 goal not reached, 3 diverged.
    """

    mean_pos_err: Float[Array, ""]
    mean_ori_err: Float[Array, ""]
    final_pos_err: Float[Array, ""]
    collided: Bool[Array, ""]
    joint_limit: Bool[Array, ""]
    success: Bool[Array, ""]
    cause: Int[Array, ""]


def _cause(collided, reached, diverged):
    return jnp.where(diverged, 3, jnp.where(collided, 1, jnp.where(reached, 0, 2))).astype(jnp.int32)


def run_metrics(pos_err, ori_err, rot, mask, final_pos_err, f_obs_final, f_jl_final, diverged,
                radius=SUCCESS_RADIUS) -> RunMetrics:
    """Summaries of one run from its per-sample errors (see :class:`RunMetrics`).

    ``mask`` marks the valid samples, ``rot`` the samples with orientation control on; the flags are
    the final values of the integrated collision states (``> 0`` means the condition held for a
    positive time, thesis 3.5).
    """
    collided = f_obs_final > 0
    joint_limit = f_jl_final > 0
    reached = final_pos_err < radius
    diverged = jnp.asarray(diverged)
    success = (~collided) & reached & (~diverged)
    return RunMetrics(
        mean_pos_err=masked_mean(pos_err, mask),
        mean_ori_err=masked_mean(ori_err, mask & (rot > 0.5)),
        final_pos_err=final_pos_err,
        collided=collided,
        joint_limit=joint_limit,
        success=success,
        cause=_cause(collided, reached, diverged),
    )


class GuidanceTermination(eqx.Module):
    """Termination of a gradient-guided run (SPEC section 9, U26), fixed-length friendly.

    * ``n_samples``: samples up to and including the stop (the hold's last sample, or all ``N``).
    * ``held``: the goal was held within ``radius`` for ``hold`` consecutive sample ends.
    * ``success``: ``held`` or, without a hold, the final error ``< radius`` (never with a collision).
    * ``time_to_goal`` [s]: time of the first sample end of the held streak (entering the ball for
      good); ``inf`` if the goal was not held (nor reached at the end).
    * ``mask`` ``(N,)``: samples that count (``k < n_samples``).
    * ``final_err`` [m]: ``|p - x_g|`` at the stop.
    """

    n_samples: Int[Array, ""]
    held: Bool[Array, ""]
    success: Bool[Array, ""]
    time_to_goal: Float[Array, ""]
    mask: Bool[Array, " N"]
    final_err: Float[Array, ""]


def guidance_termination(goal_err: Float[Array, " N"], ts, collided=False, *, hold_samples: int = 100,
                         radius=SUCCESS_RADIUS) -> GuidanceTermination:
    """Stop rule of the gradient-guided runs from the goal errors at the sample ends.

    ``goal_err[k] = |p(t_{k+1}) - x_g|``. The run stops at the first sample end where the error has
    been below ``radius`` for ``hold_samples`` consecutive sample ends (1 s at ``t_s = 0.01``), or
    at the end of the horizon (6 s = 600 samples). Since stopping does not change what happened
    before, this post-hoc rule is exact for a simulation run over the full horizon.
    """
    N = goal_err.shape[-1]
    inside = goal_err < radius

    def step(run, x):
        run = jnp.where(x, run + 1, 0)
        return run, run

    _, runs = jax.lax.scan(step, jnp.zeros((), jnp.int32), inside)
    hit = runs >= hold_samples
    held = jnp.any(hit)
    k_stop = jnp.where(held, jnp.argmax(hit), N - 1)
    n_samples = (k_stop + 1).astype(jnp.int32)
    final_err = goal_err[k_stop]
    success = (held | (final_err < radius)) & (~jnp.asarray(collided))
    # first sample end of the streak that is current at the stop
    streak = runs[k_stop]
    k_enter = k_stop - streak + 1
    ttg = jnp.where(streak > 0, (k_enter + 1) * ts, jnp.inf)
    mask = jnp.arange(N) < n_samples
    return GuidanceTermination(n_samples=n_samples, held=held, success=success,
                               time_to_goal=jnp.asarray(ttg, goal_err.dtype), mask=mask,
                               final_err=final_err)


# --------------------------------------------------------------------------------------------
# aggregation over runs


def pooled_mean(err: Float[Array, "R N"], mask: Bool[Array, "R N"], run_ok: Bool[Array, " R"]):
    """Pooled mean over all ``mask``-ed samples of the runs with ``run_ok`` (thesis: "average per
    sample over all runs")."""
    m = mask & run_ok[:, None]
    return masked_mean(err.reshape(-1), m.reshape(-1))


def per_run_mean(err: Float[Array, "R N"], mask: Bool[Array, "R N"], run_ok: Bool[Array, " R"]):
    """Mean over the runs with ``run_ok`` of each run's mean over its ``mask``-ed samples."""
    means = jax.vmap(masked_mean)(err, mask)
    ok = run_ok & jnp.isfinite(means)
    return masked_mean(jnp.where(ok, means, 0.0), ok)


def aggregate_errors(err, mask, run_ok, pooling: str = "pooled"):
    """``pooling="pooled"`` (default, SPEC section 10) or ``"per_run"``."""
    if pooling == "pooled":
        return pooled_mean(err, mask, run_ok)
    if pooling == "per_run":
        return per_run_mean(err, mask, run_ok)
    raise ValueError(f"pooling: expected 'pooled' or 'per_run', got {pooling!r}")


def failure_rate(success: Bool[Array, " R"], valid: Bool[Array, " R"] | None = None):
    """Failed / number of (valid) runs; NaN where there is no valid run (it read as 0 %, a
    perfect score, as ``masked_mean`` of an empty mask is NaN)."""
    success = jnp.asarray(success)
    valid = jnp.ones_like(success) if valid is None else jnp.asarray(valid)
    n = jnp.sum(valid)
    return jnp.where(n > 0, jnp.sum(valid & ~success) / jnp.maximum(n, 1), jnp.nan)


# --------------------------------------------------------------------------------------------
# compute time, measured sample-based (SPEC section 10)


@functools.lru_cache(maxsize=32)
def _filter_jit_cached(fn):
    return eqx.filter_jit(fn)


def time_per_call(fn: Callable, *args, n_calls: int = 1000, warmup: int = 3) -> float:
    """Mean wall time [s] of one call of ``jit(fn)(*args)`` over ``n_calls`` calls after warm-up
    (each call synchronised with ``block_until_ready``: the latency a sample-based controller sees).
    The jitted wrapper of ``fn`` is kept, so timing the same function again with arguments of the
    same shapes does not compile again. ``n_calls >= 1``, ``warmup >= 0`` (ints; 0 calls divided
    by zero, a negative count returned a negative time)."""
    check_count("n_calls", n_calls, 1)
    check_count("warmup", warmup, 0)
    f = _filter_jit_cached(fn)
    for _ in range(warmup):
        jax.block_until_ready(f(*args))
    t0 = time.perf_counter()
    for _ in range(n_calls):
        jax.block_until_ready(f(*args))
    return (time.perf_counter() - t0) / n_calls


def _control_torque(controller, g, a, s, r, e):
    return controller(g, a, s, r, e).tau


def control_torques(controller, gains, arm, states, refs, env):
    """The control law at ``K`` samples one after another (``lax.map``, as a sample loop runs it):
    ``states`` and ``refs`` carry a leading sample axis; returns the ``(K, n)`` torques."""
    return jax.lax.map(lambda sr: _control_torque(controller, gains, arm, sr[0], sr[1], env), (states, refs))


def _leading(tree) -> set:
    return {x.shape[0] if getattr(x, "ndim", 0) else None for x in jax.tree.leaves(tree)}


def controller_time_per_sample(controller, gains, arm, states, refs, env, repeats: int = 5) -> float:
    """Controller compute time per sample [s] (SPEC section 10, R1): the wall time of one jitted
    call that evaluates the control law (kinematics, dynamics, null space) at each of ``K`` samples
    in turn (:func:`control_torques`), divided by ``K``; the least of ``repeats`` calls after a
    warm-up call. ``states`` (a ``ControlState``) and ``refs`` (a ``RefSample``) hold the ``K``
    samples along a leading axis, e.g. a run's saved states and its reference's samples; they
    should differ from sample to sample, as a run's do (XLA moves work that does not depend on
    the loop's input out of the loop). The environment is the same at every sample.

    Why not the mean latency of single jitted calls (:func:`controller_call_time`, SPEC's
    proposal): with the study's XLA flags, one call of the 9-DOF acceleration OSC takes 205 us
    (127 us through ``jax.jit`` on flattened arrays), one sample of this loop 8.8 us; joint space
    148 (85) against 1.7 us (agriculture, one core). The single call measures JAX's dispatch and
    XLA's per-call runtime, about the same for every controller and arm, and it moved by 30-40 %
    between processes, so the study's orderings and ratios between controllers and arms came out
    as noise. IK and planning are timed the same way
    (batched, per sample: :func:`wall_time_per_sample`).

    Raises ``ValueError`` where ``states.q`` is not ``(K, n)`` or ``refs`` has another number of
    samples, and for ``repeats < 1``."""
    check_count("repeats", repeats, 1)
    q = states.q
    if getattr(q, "ndim", 0) != 2 or q.shape[1] != arm.n_dof:
        raise ValueError(f"controller_time_per_sample: states.q must have shape (K, {arm.n_dof}) "
                         f"(K samples of this {arm.n_dof}-DOF arm), got {getattr(q, 'shape', None)}")
    K = q.shape[0]
    if _leading(states) != {K} or _leading(refs) != {K}:
        raise ValueError(f"controller_time_per_sample: every array of states and refs must have the "
                         f"leading sample axis of states.q ({K}), got {sorted(_leading((states, refs)), key=str)}")
    return wall_time_per_sample(_filter_jit_cached(control_torques), controller, gains, arm, states, refs,
                                env, n_samples=K, repeats=repeats)


def controller_call_time(controller, gains, arm, state, ref, env, n_calls: int = 1000) -> float:
    """Latency [s] of one jitted control-law evaluation at one sample, averaged over ``n_calls``
    after warm-up (each call synchronised with ``block_until_ready``). Mostly per-call overhead
    (see :func:`controller_time_per_sample`, which the study reports); one module-level function,
    so equal controllers and shapes reuse its compilation."""
    return time_per_call(_control_torque, controller, gains, arm, state, ref, env, n_calls=n_calls)


def wall_time_per_sample(fn: Callable, *args, n_samples, warmup: int = 1, repeats: int = 1) -> float:
    """Wall time of one (already compiled after ``warmup`` calls) call of ``fn(*args)`` divided by
    the number of samples it produced (``n_samples``: one run's count, or a batch's per-run counts,
    which are summed); with ``repeats > 1`` the least of that many calls (the others were slowed
    by something else). The IK, planning and controller compute time per sample."""
    check_count("warmup", warmup, 0)
    check_count("repeats", repeats, 1)
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best / float(np.asarray(n_samples).sum())
