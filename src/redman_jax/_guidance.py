"""Local-minima estimator, virtual-obstacle buffer and the "perfect controller" gradient-descent ODE
(thesis 2.8.1, 3.3.3, 3.4; SPEC section 9, E13-E15, E22, U4, U8, U26).

**Estimator (3.24 with E22, U8).** At the start of every sample the end-effector position ``x``
gives one Newton step on the total field ``V = V_g + sum V_o + sum V_v`` (3.22, with the *current*
buffer of virtual obstacles):

``x_min = x - (H(x) + mu I)^-1 g(x)``,  ``mu = 1e-6``,

skipped when non-finite or ``|x_min - x| > 2 m``. Far from obstacles ``H = 2 I`` and the step lands
exactly on the goal (the goal attractor is quadratic, E13), where a virtual obstacle has zero
amplitude (``A = 0.1 |x - x_g|^2``, E15/U4). Every accepted estimate is pushed into a FIFO ring
buffer of the last 20 (3.25-3.27), whose members are the virtual obstacles of the field for the
whole next sample (discrete-time update; the gradient itself is evaluated continuously).

**Perfect controller (3.18).** ``x_dot = x_dot_g(x; buffer) = -a tanh(|x - x_g|/b) g/|g|``
(``a = 0.5 m/s``, ``b = 0.1 m``), the end effector as a point that follows the guidance velocity
exactly, with the same estimator and the same termination (goal within 10 cm held for 1 s, or
6 s). Used to tune the estimator and for Figure 3.7.

Everything has fixed shapes (600 samples, 20 slots, masks), so it jits and vmaps over scenes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import diffrax
from jaxtyping import Array, Bool, Float, Int

from ._fields import FieldParams, guidance_velocity, total_gradient, total_hessian
from ._math import (as_float, as_float_or_none, cast_floating, check_count, check_positive, check_shape_finite,
                    check_same_precision, check_tolerances, floating_dtype, resolve_tolerances, safe_norm)
from ._metrics import GuidanceTermination, goal_errors, guidance_termination, path_length
from ._obstacles import ObstacleSet

__all__ = [
    "VirtualBuffer",
    "estimate_local_minimum",
    "estimator_update",
    "goal_field_minimum",
    "field_params_or_default",
    "PerfectParams",
    "PerfectResult",
    "perfect_controller",
    "perfect_controller_batch",
]


class VirtualBuffer(eqx.Module):
    """FIFO ring buffer of virtual obstacles: positions ``p`` ``(B, 3)``, active ``mask`` ``(B,)``
    and the slot ``head`` the next estimate overwrites (the oldest one once the buffer is full)."""

    p: Float[Array, "B 3"]
    mask: Bool[Array, " B"]
    head: Int[Array, ""]

    @staticmethod
    def empty(size: int = 20, dtype=None) -> "VirtualBuffer":
        dtype = jnp.zeros(()).dtype if dtype is None else dtype
        return VirtualBuffer(p=jnp.zeros((size, 3), dtype), mask=jnp.zeros((size,), bool),
                             head=jnp.zeros((), jnp.int32))

    def push(self, x: Float[Array, "3"], valid: Bool[Array, ""]) -> "VirtualBuffer":
        """Write ``x`` into slot ``head`` if ``valid`` (else leave the buffer unchanged)."""
        B = self.p.shape[0]
        p = jnp.where(valid, self.p.at[self.head].set(x), self.p)
        mask = jnp.where(valid, self.mask.at[self.head].set(True), self.mask)
        head = jnp.where(valid, (self.head + 1) % B, self.head).astype(jnp.int32)
        return VirtualBuffer(p=p, mask=mask, head=head)


def field_params_or_default(field, gains=None) -> FieldParams:
    """The guidance field parameters: ``field`` if given, else ``gains.field`` if the controller's
    gains carry one, else the thesis defaults."""
    if field is not None:
        return field
    g_field = getattr(gains, "field", None)
    if isinstance(g_field, FieldParams):
        return g_field
    return FieldParams()


def estimate_local_minimum(x: Float[Array, "3"], goal_p: Float[Array, "3"], obs: ObstacleSet,
                           virtual_p: Float[Array, "B 3"], virtual_mask: Bool[Array, " B"],
                           params: FieldParams, mu=1e-6, max_jump=2.0):
    """One regularised Newton step on the total field (3.24, E22, U8).

    ``x_min = x - (H + mu I)^-1 g`` with ``g``, ``H`` the gradient and Hessian of the total field
    (goal, obstacles and the current virtual obstacles) at ``x``. Returns ``(x_min, valid)``;
    ``valid`` is False when ``x_min`` is non-finite or ``|x_min - x| > max_jump``.
    """
    g = total_gradient(x, goal_p, obs, virtual_p, virtual_mask, params)
    H = total_hessian(x, goal_p, obs, virtual_p, virtual_mask, params)
    eye = jnp.eye(3, dtype=H.dtype)
    step = jnp.linalg.solve(H + mu * eye, g)
    x_min = x - step
    valid = jnp.all(jnp.isfinite(x_min)) & (safe_norm(x_min - x) <= max_jump)
    x_min = jnp.where(jnp.isfinite(x_min), x_min, x)
    return x_min, valid


def estimator_update(x, goal_p, obs, buf: VirtualBuffer, params: FieldParams, mu=1e-6, max_jump=2.0):
    """Estimate at ``x`` with the current buffer and push the estimate if valid.

    Returns ``(new_buffer, x_min, valid)``."""
    x_min, valid = estimate_local_minimum(x, goal_p, obs, buf.p, buf.mask, params, mu, max_jump)
    return buf.push(x_min, valid), x_min, valid


def _newton_step_3(H, g):
    """``(H_s^-1 g, H_s positive definite)`` for a 3x3 ``H`` (``H_s = (H + H^T) / 2``), by an
    unrolled ``L D L^T`` factorisation: ``H_s`` is positive definite exactly when the three pivots
    are positive (Sylvester), so one factorisation gives both. The step is finite where that holds
    (pivots of the untaken branch are replaced by 1, so neither value nor gradient sees a 0 / 0).

    In place of ``jnp.linalg.solve`` and ``jnp.linalg.eigvalsh``: two independent LAPACK calls per
    step, which under a large ``vmap`` (20,000 goals) hung the process in jaxlib 0.10's CPU kernels
    (each batched call splits its batch over XLA's thread pool and blocks a pool thread waiting
    for the parts; two at once on a two-thread pool wait for each other; README, "Known issues")."""
    Hs = 0.5 * (H + H.T)
    one = jnp.ones((), Hs.dtype)
    d1 = Hs[0, 0]
    ok1 = d1 > 0
    d1s = jnp.where(ok1, d1, one)
    l21, l31 = Hs[1, 0] / d1s, Hs[2, 0] / d1s
    d2 = Hs[1, 1] - l21 * l21 * d1s
    ok2 = ok1 & (d2 > 0)
    d2s = jnp.where(ok2, d2, one)
    l32 = (Hs[2, 1] - l31 * l21 * d1s) / d2s
    d3 = Hs[2, 2] - l31 * l31 * d1s - l32 * l32 * d2s
    ok3 = ok2 & (d3 > 0)
    d3s = jnp.where(ok3, d3, one)
    # L y = g, D z = y, L^T x = z
    y1 = g[0]
    y2 = g[1] - l21 * y1
    y3 = g[2] - l31 * y1 - l32 * y2
    x3 = y3 / d3s
    x2 = y2 / d2s - l32 * x3
    x1 = y1 / d1s - l21 * x2 - l31 * x3
    dx = jnp.stack([x1, x2, x3])
    return dx, ok3 & jnp.all(jnp.isfinite(dx))


def goal_field_minimum(goal_p: Float[Array, "3"], obs: ObstacleSet, params: FieldParams | None = None,
                       *, n_iter: int = 400, max_step=0.02):
    """The minimum of the guidance field (goal + obstacles, no virtual obstacles) that the goal
    falls into: damped Newton descent from the goal (steps of at most ``max_step`` [m]).

    With obstacles within the field's range ``D`` of the goal, the obstacles' push moves the
    minimum off the goal (thesis 4.9, "the global minimum displaced"). A run that follows the
    field ends near this point, so ``shift > 0.10 m`` (the success radius) is a failure no
    controller avoids; the local-minima estimator cannot help either, since a virtual obstacle's
    amplitude ``0.1 |x - x_g|^2`` is about 1e-3 there.

    Returns ``(x_min, shift, grad_norm)``: the point, its distance to the goal [m] and the field
    gradient's norm there (about 0 when the descent converged).

    Raises ``ValueError`` for a ``goal_p`` not of shape ``(3,)`` or (where concrete) not finite
    (a NaN goal came back as a converged minimum, shift and gradient 0), ``n_iter < 0`` or a
    ``max_step`` that is not positive (a negative one stepped uphill).
    """
    params = FieldParams() if params is None else params
    goal_p = jnp.asarray(goal_p)
    goal_p = goal_p.astype(floating_dtype(goal_p))
    check_shape_finite("goal_p", goal_p, (3,))
    check_count("n_iter", n_iter, 0)
    check_positive("max_step", max_step)
    dtype = goal_p.dtype
    vp = jnp.zeros((1, 3), dtype)
    vm = jnp.zeros((1,), bool)
    max_step = jnp.asarray(max_step, dtype)

    def step(x, _):
        g = total_gradient(x, goal_p, obs, vp, vm, params)
        H = total_hessian(x, goal_p, obs, vp, vm, params)
        # Newton where the field is convex, the (scaled) gradient otherwise
        dx, convex = _newton_step_3(H, g)
        dx = jnp.where(convex, dx, g / 2.0)
        n = safe_norm(dx)
        return x - dx * jnp.minimum(1.0, max_step / jnp.maximum(n, 1e-12)), None

    x, _ = jax.lax.scan(step, goal_p, None, length=n_iter)
    g = total_gradient(x, goal_p, obs, vp, vm, params)
    return x, safe_norm(x - goal_p), safe_norm(g)


# --------------------------------------------------------------------------------------------
# perfect controller


def _arr(x):
    return as_float(x)


class PerfectParams(eqx.Module):
    """Options of the perfect-controller ODE. Arrays: guidance speed ``a`` [m/s] and slow-down
    distance ``b`` [m] (3.18, [T] 0.5 / 0.1), ``ts`` [s], estimator ``mu`` and ``max_jump`` [m]
    (U8), success ``radius`` [m], tolerances ``rtol``/``atol`` (None, the default: by the point's
    precision, 1e-5 / 1e-7 in float64, 1e-4 / 1e-5 in float32, as ``SimParams``;
    :data:`~redman_jax._math.DEFAULT_TOLERANCES`); ``field``: :class:`FieldParams`.
    Static: ``n_samples`` (600 = 6 s), ``hold_samples`` (100 = 1 s), ``buffer_size`` (20),
    ``estimator`` (False gives plain gradient descent, for comparison) and
    ``max_steps_per_sample``."""

    a: Float[Array, ""] = eqx.field(default=0.5, converter=_arr)
    b: Float[Array, ""] = eqx.field(default=0.1, converter=_arr)
    ts: Float[Array, ""] = eqx.field(default=0.01, converter=_arr)
    mu: Float[Array, ""] = eqx.field(default=1e-6, converter=_arr)
    max_jump: Float[Array, ""] = eqx.field(default=2.0, converter=_arr)
    radius: Float[Array, ""] = eqx.field(default=0.10, converter=_arr)
    rtol: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    atol: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    field: FieldParams = eqx.field(default_factory=FieldParams)
    n_samples: int = eqx.field(static=True, default=600)
    hold_samples: int = eqx.field(static=True, default=100)
    buffer_size: int = eqx.field(static=True, default=20)
    estimator: bool = eqx.field(static=True, default=True)
    max_steps_per_sample: int = eqx.field(static=True, default=64)

    def __check_init__(self):  # the numbers where concrete (built under a trace: the caller's)
        for name in ("a", "b", "ts", "max_jump", "radius"):
            check_positive(f"PerfectParams.{name}", getattr(self, name))
        check_positive("PerfectParams.mu", self.mu, allow_zero=True)
        check_tolerances("PerfectParams", *resolve_tolerances(self.rtol, self.atol, "float64"))
        for name, least in (("n_samples", 1), ("hold_samples", 1), ("buffer_size", 1),
                            ("max_steps_per_sample", 1)):
            check_count(f"PerfectParams.{name}", getattr(self, name), least)


class PerfectResult(eqx.Module):
    """Perfect-controller run: ``x`` ``(N, 3)`` positions at the sample ends, ``estimates``
    ``(N, 3)`` and ``estimate_valid`` ``(N,)`` (made at each sample start; every one is kept for
    Figure 3.7), ``buffers`` ``(N, B, 3)`` / ``buffer_masks`` ``(N, B)`` (the virtual obstacles
    active during each sample), ``goal_err`` ``(N,)`` (``inf`` where ``x`` is not finite),
    ``termination`` (:class:`~redman_jax._metrics.GuidanceTermination`; its ``success`` is False
    after a collision or a failed solve), ``path_length`` [m] up to the stop, ``min_dist`` ``(N,)``
    (signed distance of ``x`` to the closest obstacle), ``collided`` (``x`` entered an obstacle,
    ``min_dist < 0``, up to the stop: the point has no extent), ``failed`` (a per-sample solve
    stopped short, e.g. out of ``max_steps_per_sample``, before the point entered the goal for
    good: the run's timing, and so its outcome, is not to be trusted), ``n_short`` (samples whose
    solve stopped short, up to the stop) and ``n_steps``.

    Inside the goal radius solves can stop short without harm: at the field's minimum the guidance
    direction ``g / |g|`` flips (3.18), the point chatters in place and a sample can take more than
    ``max_steps_per_sample`` steps (the simple-obstacle scene of the tests, seed 3: 3 of its 100
    held samples). There the point is left where its solve stopped, inside the radius, so those
    count in ``n_short`` only."""

    x: Float[Array, "N 3"]
    estimates: Float[Array, "N 3"]
    estimate_valid: Bool[Array, " N"]
    buffers: Float[Array, "N B 3"]
    buffer_masks: Bool[Array, "N B"]
    goal_err: Float[Array, " N"]
    termination: GuidanceTermination
    path_length: Float[Array, ""]
    min_dist: Float[Array, " N"]
    collided: Bool[Array, ""]
    failed: Bool[Array, ""]
    n_short: Int[Array, ""]
    n_steps: Int[Array, ""]

    @property
    def success(self):
        return self.termination.success


def _perfect_core(x0, goal_p, obs, params: PerfectParams) -> PerfectResult:
    from ._obstacles import min_distance

    dtype = x0.dtype
    ts = params.ts.astype(dtype)
    buf0 = VirtualBuffer.empty(params.buffer_size, dtype)
    fp = params.field

    def vf(t, x, buf):
        return guidance_velocity(x, goal_p, obs, buf.p, buf.mask, fp, params.a, params.b)

    term = diffrax.ODETerm(vf)
    solver = diffrax.Tsit5()
    rtol, atol = resolve_tolerances(params.rtol, params.atol, dtype)
    pid = diffrax.PIDController(rtol=rtol, atol=atol)

    def body(carry, k):
        x, buf, dt0 = carry
        if params.estimator:
            buf, x_min, valid = estimator_update(x, goal_p, obs, buf, fp, params.mu, params.max_jump)
        else:
            x_min, valid = x, jnp.asarray(False)
        t0 = ts * k.astype(dtype)
        sol = diffrax.diffeqsolve(term, solver, t0, t0 + ts, dt0, x, args=buf,
                                  saveat=diffrax.SaveAt(t1=True), stepsize_controller=pid,
                                  max_steps=params.max_steps_per_sample, throw=False)
        x1 = sol.ys[-1]
        acc = sol.stats["num_accepted_steps"]
        dt_next = jnp.minimum(ts / jnp.maximum(acc, 1).astype(dtype), ts)
        stopped = sol.result != diffrax.RESULTS.successful
        return (x1, buf, dt_next), (x1, x_min, valid, buf.p, buf.mask, sol.stats["num_steps"], stopped)

    _, (xs, est, ok, bp, bm, nsteps, stopped) = jax.lax.scan(body, (x0, buf0, ts), jnp.arange(params.n_samples))
    finite = jnp.all(jnp.isfinite(xs), axis=-1)
    goal_err = goal_errors(xs, goal_p)  # as the simulator's guided runs
    dmin = jax.vmap(lambda x: min_distance(obs, x))(xs)
    # the stop ignoring failures first, then collisions and failed solves up to it (the same
    # order as the simulator's guided runs: what happens after the stop does not count)
    term0 = guidance_termination(goal_err, ts, False, hold_samples=params.hold_samples, radius=params.radius)
    rows = term0.mask
    collided = jnp.any(rows & ~(dmin >= 0.0))  # NaN distances count as inside
    short = rows & (stopped | ~finite)
    k = jnp.arange(params.n_samples)
    # the approach: the samples before the held streak's first one (time_to_goal = (k + 1) ts)
    enter = jnp.where(term0.held, jnp.round(term0.time_to_goal / ts).astype(jnp.int32) - 1, params.n_samples)
    failed = jnp.any(short & (k < enter))
    term = guidance_termination(goal_err, ts, collided | failed, hold_samples=params.hold_samples,
                                radius=params.radius)
    return PerfectResult(x=xs, estimates=est, estimate_valid=ok, buffers=bp, buffer_masks=bm,
                         goal_err=goal_err, termination=term,
                         path_length=path_length(x0, xs, term.mask), min_dist=dmin, collided=collided,
                         failed=failed, n_short=jnp.sum(short).astype(jnp.int32),
                         n_steps=jnp.sum(nsteps).astype(jnp.int32))


_perfect_jit = eqx.filter_jit(_perfect_core)


def perfect_controller(x0, goal_p, obs: ObstacleSet, params: PerfectParams | None = None) -> PerfectResult:
    """Gradient descent of a point ``x`` on the guided field with the local-minima estimator
    ("perfect controller", thesis 3.4, eq. 3.18), over ``params.n_samples`` samples of ``ts``.

    **Arguments**: start ``x0`` ``(3,)`` (the end-effector start), ``goal_p`` ``(3,)``, obstacles,
    :class:`PerfectParams`. **Returns** :class:`PerfectResult` (jit-compiled; vmaps, see
    :func:`perfect_controller_batch`). **Raises** ``ValueError`` for wrongly shaped or (where
    concrete) non-finite points.
    """
    x0, goal_p, params = _in_points_precision(x0, goal_p, obs, params)
    _check_points(x0, goal_p, (3,))
    return _perfect_jit(x0, goal_p, obs, params)


def _in_points_precision(x0, goal_p, obs, params):
    """``(x0, goal_p, params)`` in the points' floating precision (integer points: the default
    float): our ``params`` are cast to it (its float64 defaults failed a float32 batch inside
    diffrax, and promoted a float32 single run to float64); obstacles of another floating
    precision are an error naming them, as in the simulator."""
    params = PerfectParams() if params is None else params
    x0, goal_p = jnp.asarray(x0), jnp.asarray(goal_p)
    dtype = floating_dtype(x0, goal_p)  # one float type: mixed precisions promoted
    check_same_precision("obs", obs, dtype, f"{jnp.dtype(dtype).name} points")
    return x0.astype(dtype), goal_p.astype(dtype), cast_floating(params, dtype)


def _check_points(x0, goal_p, shape) -> None:
    """The perfect controller's start and goal: of ``shape`` and, where concrete, finite (a NaN
    start or goal ran the descent in NaN and reported a silent failure)."""
    for name, x in (("x0", x0), ("goal_p", goal_p)):
        check_shape_finite(name, x, shape)


def perfect_controller_batch(x0, goal_p, obs: ObstacleSet, params: PerfectParams | None = None) -> PerfectResult:
    """:func:`perfect_controller` over a batch of scenes: ``x0``, ``goal_p`` ``(S, 3)`` and stacked
    obstacle sets (one ``jit(vmap)``). **Raises** ``ValueError`` for wrongly shaped or (where
    concrete) non-finite points."""
    x0, goal_p, params = _in_points_precision(x0, goal_p, obs, params)
    if x0.ndim != 2 or x0.shape[1] != 3:
        raise ValueError(f"x0: expected shape (S, 3), got {tuple(x0.shape)}")
    _check_points(x0, goal_p, tuple(x0.shape))
    return _perfect_batch_jit(x0, goal_p, obs, params)


@eqx.filter_jit
def _perfect_batch_jit(x0, goal_p, obs, params):
    return jax.vmap(_perfect_core, in_axes=(0, 0, 0, None))(x0, goal_p, obs, params)
