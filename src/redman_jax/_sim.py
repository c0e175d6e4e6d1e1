"""Closed-loop simulation of an arm, a controller and a scenario with diffrax (thesis 3.3.1, 3.5;
SPEC sections 5, 9, 10).

**The hybrid system.** The controller is part of the vector field (continuous in time, as in the
thesis); the reference is a zero-order hold of the samples at ``t_s``: sample ``k`` is held on the
left-closed interval ``[k t_s, (k+1) t_s)`` (E29). The ODE state is

``y = (q, qd, z, f)``,  ``q_dot = qd``,  ``qd_dot = M^-1(tau - tau_lim - c - g)`` (3.5/3.7, E8),
``z_dot = dz`` (the controller's integrated state, e.g. the velocity OSC's ``q_r``) and three flag
states (thesis 3.5): ``f_obs_dot = 1`` while the smallest point-of-interest signed distance is below
the link width (0.10 m), ``f_jl_dot = 1`` while a limited joint is outside its limits, and
``f_bad_dot = 1`` while the vector field is non-finite or the state exceeds the divergence bounds.
The flags are excluded from the error norm of the step-size controller (SPEC section 10) and are read
by absolute value (``_final_flags``, ``_diverged``): a stage weight of the solver can be negative.

**Integration (measured, see ``benchmarks/bench_sim.py``).** Trajectory runs are *one*
``diffeqsolve`` over the whole horizon ``[0, N t_s]`` (``mode="horizon"``): the step-size
controller is a PID controller wrapped in a ``ClipStepSizeController`` with ``jump_ts`` at every
sample boundary, so the solver steps to just before each boundary and restarts just after it (the
FSAL stage is re-evaluated, no step straddles a reference jump), and the held sample is found from
``t`` by comparing against the *same* boundary array (``searchsorted(..., side="right")``: a time
``prevbefore(b_k)`` still holds sample ``k-1``, ``nextafter(b_k)`` holds sample ``k``). The step
size proposed by the PID controller carries over the boundaries, so no step-size search restarts at
every sample. ``mode="per_sample"`` is a ``lax.scan`` over samples with one warm-started
``diffeqsolve`` per sample (``dt0`` = the previous sample's mean accepted step), a cross-check.
Under ``vmap`` a single horizon solve costs ``max_members(total steps)`` loop iterations, while a
scan over per-sample solves costs ``sum_k max_members(steps in sample k)`` (4x more on the
simple case's 20 gradient-guided seeds, ``benchmarks/bench_guided.py``).

**Gradient-guided runs** change a discrete state at every sample start (the local-minima
estimator's virtual-obstacle buffer and the orientation latch), which a single ``diffeqsolve``
cannot express. In ``mode="horizon"`` they run in :func:`_solve_guided_stepper`: diffrax's solver
step and PID controller in our own ``while_loop``, the update applied after the step that lands on
a sample end, so one loop covers the horizon (forward only). :func:`simulate_batch` drives that
loop from the host in calls of 512 iterations and moves its last stragglers to a smaller batch
(``SimParams.compact``; 8-DOF warehouse, 20 seeds: 2.0x less run time). ``mode="per_sample"`` runs
them as the scan of per-sample solves, which is differentiable.

Default solver (``SimParams.solver="auto"``): the controller's ``auto_solver``, ``Tsit5`` for the
acceleration OSC and the gradient-guided controller, ``Dopri5`` for joint space, velocity OSC and a
controller that does not say, all with ``rtol = 1e-5``, ``atol = 1e-7`` in float64 (SPEC U9:
adaptive, non-stiff, a little tighter than MATLAB's ``ode113`` defaults 1e-3/1e-6) and ``1e-4`` /
``1e-5`` in float32 (:data:`DEFAULT_TOLERANCES`: float64's sit at float32's rounding, where the
error estimate is noise and the steps stop growing). SPEC U9 proposes Tsit5 throughout.

*Why Dopri5 for joint space and velocity OSC.* It needs fewer steps at the same tolerances
(``benchmarks/bench_solvers.py``, 9-DOF arm, seeds 1-4, batch maximum): warehouse velocity OSC
2,212 against 4,118 steps, agriculture 2,577 against 3,639, simple 3,557 against 3,971, joint space
within 1 % there; inspection joint space is the one row where it takes more (1,264 against 1,125);
welding is a draw. Over the whole study on identical scenarios (``redman-jax sweep --solver
tsit5`` beside the then default) it took 1.15x fewer steps for the velocity OSC. Accuracy
(``benchmarks/bench_tolerance.py``, against a Tsit5 reference at rtol 1e-9 / atol 1e-11): the
velocity OSC on all 20 seeds of 9-DOF agriculture within 3.1e-4 per seed (5.0e-6 over the seed
means); the trajectory runs of simple and agriculture (seeds 1-4) within 6.1e-4 per seed and
warehouse (seeds 1-2) within 2.3e-5, every success, collision and joint-limit flag equal. On all
20 seeds of every 9-DOF case (2026-12-06, ``--seeds 1-20 --ref-budget 1024``): joint space within
4.0e-5 per seed (4.9e-6 over the seed means), the velocity OSC within 2.4e-3 per seed (welding;
2.8e-4 over the seed means) in all five; every flag equal.

*Why Tsit5 for the acceleration-level OSCs.* Their runs press joints into the limit contact (3.6),
where many steps are rejected (seed 6 below); why Dopri5's accepted steps there are less accurate
than Tsit5's is measured, not explained. On all 20 seeds of each 9-DOF case (``bench_tolerance.py --seeds 1-20 --controllers acceleration
--candidates 1e-5/1e-7``, once with ``--solver dopri5`` and once with ``--solver tsit5``;
2026-12-06) Dopri5 misses the 1 % in agriculture: up to 0.33 per seed (final position) and 1.9e-2
over the seed means, and seed 14 collides where the reference does not. Tighter tolerances do not
cure it: at rtol 1e-6 / 1e-7 seed 16's final position is 1.9e-2 / 0.31 off and seed 6 (a wrist
joint held 1 s against its limit, two thirds of the steps rejected) takes 48,494 / 319,815 steps;
Dopri5 reaches the reference only at rtol 1e-9 (seeds 14 and 16: 0.020650 / 0.421366 m against the
reference's 0.020619 / 0.421499, and Tsit5 at 1e-10 0.020617 / 0.421390: the reference checked by
another method and a tighter tolerance). A PI step-size controller (0.4, 0.3) keeps Dopri5's
flags and seed means within 1 % there (6.4e-3) but seed 14 still 0.57 off. Tsit5 at the default
tolerances, against Dopri5 (largest deviation per seed / of the seed means; steps batch max):
agriculture 1.3e-2 / 2.5e-4, flags equal (Dopri5 0.33 / 1.9e-2, a flag differs), 16,188 against
8,146 steps; warehouse 1.3e-3 / 1.3e-5 (4.4e-4 / 2.3e-5), 7,879 against 4,233; inspection 7.6e-6 /
1.1e-6 (6.1e-6 / 1.3e-6), 1,810 against 1,686; welding 5.6e-2 / 4.3e-3 (0.13 / 9.3e-3), 11,543
against 11,842; simple 8.8e-4 / 7.7e-6 (1.0e-3 / 3.7e-6), 5,782 against 4,991; every flag equal
but Dopri5's agriculture one. So it costs up to 1.9x the steps (warehouse) for the accuracy the
study needs. The gradient-guided runs (the same acceleration-level command) had Tsit5 already:
with Dopri5 they took about as many steps (warehouse 6,785 against 6,598 at the batch maximum,
slower wall time) and their goal-stop metric deviated more (simple: 1.2e-2 per seed). With Tsit5,
against the reference (seeds 1-4, a291e76): final position per seed up to 3.9e-2 / 7.9e-2 / 4.9e-3
(agriculture / warehouse / simple; the stop rule moves by a sample), 4.4e-3 / 6.3e-3 / 4.2e-4 over
the seed means; mean position and orientation errors within 2.7e-3 per seed; every flag equal.
On all 20 seeds of agriculture (2026-12-06) the final position deviates by up to 3.9e-2 per seed
and 3.5e-4 over the seed means, but one success flag differs: seed 18, whose guidance field has its
minimum about 10.1 cm from the goal, ends 0.0995 m from it (a success) against the reference's
0.1022 m. That end point is set by rounding as much as by the tolerance: at the same tolerance, in
the same batch, the run ends 0.1038 m away with XLA's CPU thread pool two threads wide instead of
one (other seeds move by up to 3.6 mm too), and 0.0997 m simulated alone. The reference moves as
much: on two threads it ends 0.1002 m away, on one 0.1035 m, alone 0.1022 m (seed 1: 0.1426 against
0.1369 m; the slowest run takes 173,454 against 244,335 steps). The estimator's discrete updates
(3.24-3.27) pass rounding on, so a guided run's end point is defined to some millimetres at any
tolerance, and the success of a run that stops this close to the 10 cm radius is not decided by
the integration's accuracy. Simple and warehouse, all 20 seeds (2026-12-06; the simulations of
``bench_tolerance.py --controllers gradient --cases simple,warehouse --seeds 1-20 --candidates
1e-5/1e-7 --ref-budget 1024``, their metrics saved per seed; one core,
``--xla_cpu_multi_thread_eigen=false``): simple within 1.2e-2 per seed (final position: seed 7, 0.4 mm of
32 mm) and 2.2e-4 over the seed means, every flag equal. In the warehouse every run fails, in the
reference as at the default tolerances (flags equal); where the failed runs end after 6 s is
rounding's: two references at rtol 1e-9 that differ only in XLA's flags (one thread without
Eigen's pool, or JAX's defaults) end seed 13 (a collided run) 7.09 and 0.34 m from the goal, the
uncollided seed 20 0.42 and 0.56 m, their seed means of the final distance 20 % apart, while the
default tolerances' run lies between them (seed 13 4.67 m, seed 20 0.36 m; 7.4e-2 from the first
reference over the seed means).

The tracking controllers on the 7- and 8-DOF arms (agriculture, welding and simple, velocity and
acceleration OSC, all 20 seeds, ``bench_tolerance.py --dof 7|8 --seeds 1-20 --cases
agriculture,welding,simple --controllers acceleration,velocity --candidates 1e-5/1e-7
--ref-budget 1024``; 2026-12-06): within 1.9e-3 / 2.7e-3 per seed, 4.2e-4 / 3.5e-4 over the seed
means and 1.5e-6 / 3.1e-5 in the table's mean error over successes; every flag equal.

Looser tolerances do not pay off: at rtol 1e-4 / atol 1e-6 (9-DOF, seeds 1-4, batch maximum) joint
space and velocity OSC take more steps, not fewer (simple 3,739 / 3,786 against 2,787 / 3,557;
welding joint space 4,589 against 2,983). The references take minutes per cell (9-DOF, 20 seeds:
agriculture acceleration 167,088 steps, 583 s; warehouse 120,622 steps, 907 s, which needs
``--ref-budget 1024``).

**Adjoint.** ``RecursiveCheckpointAdjoint`` (discretise-then-optimise): gradients are exact for the
computed discrete trajectory, memory is bounded by binomial checkpointing over ``max_steps``,
and it works with the jump times, the flags and the divergence guard. ``BacksolveAdjoint`` would
re-integrate the stiff contact dynamics backwards (unstable, and only as accurate as the solver
tolerance) and ``DirectAdjoint`` is only needed for forward mode (its memory grows with
``max_steps``); both are available through ``SimParams.adjoint``.

**Failure is a value.** Solves run with ``throw=False``; the vector field of a member whose state
turns non-finite or leaves the bounds is zeroed (``f_bad`` starts to grow), so that member freezes,
is flagged ``diverged`` in its result and never affects the other members of a batch.
"""

from __future__ import annotations

import dataclasses
import inspect

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import diffrax
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ._control_types import AbstractController, ControlState, RefSample, make_environment
from ._dynamics import LimitContact, forward_dynamics
from ._kinematics import kinematics, poi_link_index, poi_positions_from
from ._math import (DEFAULT_TOLERANCES, as_float, as_float_or_none, cast_floating, check_count,
                    check_finite, check_initial_state, check_positive, check_same_precision, check_tolerances,
                    check_unit_quaternions, concrete, resolve_tolerances)
from ._math import rot_to_quat
from ._metrics import (
    RunMetrics,
    _norm_forward,
    goal_errors,
    guidance_termination,
    orientation_errors,
    path_length,
    position_errors,
    run_metrics,
)
from . import _host
from ._obstacles import points_min_distance, used_bound, used_bound_jit, with_used
from ._robot import Arm
from ._scenario import Reference, Scenario, check_reference_values

__all__ = ["SimParams", "SimResult", "JointReference", "simulate", "simulate_batch", "simulate_dense",
           "joint_reference", "tolerances", "DEFAULT_TOLERANCES"]


def _arr(x):
    return as_float(x)


def tolerances(params: "SimParams", dtype) -> tuple:
    """``(rtol, atol)`` of ``params`` for states of ``dtype``: the given ones, or where None the
    :data:`DEFAULT_TOLERANCES` of that precision (float64's for any other)."""
    return resolve_tolerances(params.rtol, params.atol, jnp.dtype(dtype))


class SimParams(eqx.Module):
    """Options of :func:`simulate`. Numbers are arrays (changing them never recompiles); the
    choices marked static are structure.

    * ``rtol``, ``atol``: tolerances of the PID step-size controller; None (default): by the
      states' precision, 1e-5 / 1e-7 in float64 (SPEC U9), 1e-4 / 1e-5 in float32
      (:data:`DEFAULT_TOLERANCES`, :func:`tolerances`).
    * ``pcoeff``, ``icoeff``: PID coefficients (``0, 1`` = the classic I controller). Against the PI
      controllers diffrax suggests for non-smooth error estimates it takes the fewest steps over the
      study's rows (9-DOF, 6 seeds: 316k steps; (0.2, 0.4) 351k, (0.4, 0.3) 365k), though it rejects
      30-50 % of its steps in the obstacle-rich cases; ``benchmarks/bench_stepsize.py``.
    * ``q_bound`` [rad or m], ``qd_bound`` [rad/s]: a state beyond these counts as diverged.
    * ``contact``: joint-limit contact model (3.6).
    * ``goal_radius`` [m]: success radius (0.10); ``guidance_rot_radius`` [m]: orientation switches
      on within this distance of the goal for the gradient-guided controller (0.5 m [T]).
    * ``lme_mu``, ``lme_max_jump``: local-minima estimator regularisation and largest accepted step
      (U8: 1e-6, 2 m).
    * static ``solver``: ``"auto"`` (default: the controller's ``auto_solver``, ``"tsit5"`` for the
      acceleration OSC and gradient-guided runs, ``"dopri5"`` for the others; see the module
      docstring), ``"dopri5"``, ``"tsit5"``, ``"dopri8"``,
      ``"bosh3"``;
      ``mode``: ``"horizon"`` or ``"per_sample"`` (see the module docstring);
      ``adjoint``: ``"recursive"`` (default), ``"direct"``, ``"backsolve"``;
      ``max_steps_per_sample``: step budget per sample (``max_steps = N *`` this);
      ``guidance_samples``: horizon of gradient-guided runs (600 = 6 s); ``hold_samples``: the
      hold before a gradient-guided run stops (100 = 1 s); ``buffer_size``: virtual obstacles (20);
      ``even_steps``: split the rest of each sample into equal steps (horizon mode, see
      ``_EvenSplit``); ``slots_per_step``: obstacle slots per step of the per-point passes
      (:class:`~redman_jax.ObstacleSet`; None: :func:`~redman_jax._obstacles.auto_slots_per_step`
      of the batch size and the points of interest: up to 45 slots per step for 20 9-DOF states,
      one at a time from batch 57 on; the same results to rounding, the warehouse closed loop
      1.6x cheaper at batch 20); ``stop_early``: a gradient-guided member stops stepping at the stop
      rule (horizon mode; the results are the same, see :func:`_solve_guided_stepper`);
      ``compact``: :func:`simulate_batch` of a gradient-guided controller in horizon mode moves the
      last quarter of its members still stepping to a batch of just those (host-driven, outside any
      ``jit``; the same steps and results to rounding, see ``_simulate_guided_compacting``).
    * ``field``: :class:`~redman_jax._fields.FieldParams` of the guidance field of a gradient-guided
      run, for both the controller's guidance velocity and the local-minima estimator (it replaces
      the gains' own ``field``, which a gradient with respect to the gains then does not see);
      None (default): the gains' ``field`` drives both.
    """

    rtol: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    atol: Float[Array, ""] | None = eqx.field(default=None, converter=as_float_or_none)
    pcoeff: Float[Array, ""] = eqx.field(default=0.0, converter=_arr)
    icoeff: Float[Array, ""] = eqx.field(default=1.0, converter=_arr)
    q_bound: Float[Array, ""] = eqx.field(default=100.0, converter=_arr)
    qd_bound: Float[Array, ""] = eqx.field(default=1e3, converter=_arr)
    contact: LimitContact = eqx.field(default_factory=LimitContact)
    goal_radius: Float[Array, ""] = eqx.field(default=0.10, converter=_arr)
    guidance_rot_radius: Float[Array, ""] = eqx.field(default=0.5, converter=_arr)
    lme_mu: Float[Array, ""] = eqx.field(default=1e-6, converter=_arr)
    lme_max_jump: Float[Array, ""] = eqx.field(default=2.0, converter=_arr)
    field: PyTree = None
    solver: str = eqx.field(static=True, default="auto")
    mode: str = eqx.field(static=True, default="horizon")
    adjoint: str = eqx.field(static=True, default="recursive")
    max_steps_per_sample: int = eqx.field(static=True, default=64)
    guidance_samples: int = eqx.field(static=True, default=600)
    hold_samples: int = eqx.field(static=True, default=100)
    buffer_size: int = eqx.field(static=True, default=20)
    even_steps: bool = eqx.field(static=True, default=True)
    slots_per_step: int | None = eqx.field(static=True, default=None)
    stop_early: bool = eqx.field(static=True, default=True)
    compact: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        from ._fields import FieldParams

        if self.field is not None and not isinstance(self.field, FieldParams):
            raise ValueError(f"SimParams.field: expected a FieldParams or None, got {type(self.field).__name__}")
        if not isinstance(self.contact, LimitContact):
            raise ValueError(f"SimParams.contact: expected a LimitContact, got {type(self.contact).__name__}")
        if self.slots_per_step is not None and (not isinstance(self.slots_per_step, int)
                                                or self.slots_per_step < 1):
            raise ValueError(f"SimParams.slots_per_step: expected None (auto) or a positive int, "
                             f"got {self.slots_per_step!r}")
        if self.solver not in SOLVER_CHOICES:
            raise ValueError(f"SimParams.solver: expected one of {list(SOLVER_CHOICES)}, "
                             f"got {self.solver!r}")
        if self.mode not in ("horizon", "per_sample"):
            raise ValueError(f"SimParams.mode: expected 'horizon' or 'per_sample', got {self.mode!r}")
        if self.adjoint not in ("recursive", "direct", "backsolve"):
            raise ValueError(f"SimParams.adjoint: expected 'recursive', 'direct' or 'backsolve', "
                             f"got {self.adjoint!r}")
        for name in ("max_steps_per_sample", "guidance_samples", "hold_samples", "buffer_size"):
            check_count(f"SimParams.{name}", getattr(self, name), 1)
        # the numbers, where concrete (a SimParams built under a trace is checked by its caller)
        check_tolerances("SimParams", *tolerances(self, "float64"))
        for name in ("guidance_rot_radius", "lme_mu"):
            check_positive(f"SimParams.{name}", getattr(self, name), allow_zero=True)
        for name in ("goal_radius", "lme_max_jump"):
            check_positive(f"SimParams.{name}", getattr(self, name))
        for name in ("q_bound", "qd_bound"):  # inf: no bound
            check_positive(f"SimParams.{name}", getattr(self, name), allow_inf=True)
        for name in ("pcoeff", "icoeff"):
            v = concrete(getattr(self, name))
            if v is not None and not np.all(np.isfinite(v)):
                raise ValueError(f"SimParams.{name}: expected a finite value, got {v}")


_SOLVERS = {
    "tsit5": diffrax.Tsit5,
    "dopri5": diffrax.Dopri5,
    "dopri8": diffrax.Dopri8,
    "bosh3": diffrax.Bosh3,
}
SOLVER_CHOICES = ("auto", *_SOLVERS)  # what ``SimParams.solver`` (and ``sweep --solver``) accepts


class JointReference(eqx.Module):
    """Joint-space reference from the IK, ``(N, n)`` each: ``q`` (``q_k`` for ``k = 0..N-1``),
    ``qd``, ``qdd`` (``qd_d[k]``, ``qdd_d[k]``; rows ``>= n_samples - 1`` are not used)."""

    q: Float[Array, "N n"]
    qd: Float[Array, "N n"]
    qdd: Float[Array, "N n"]


def joint_reference(ik, n_rows: int | None = None) -> JointReference:
    """A :class:`JointReference` from an ``IKResult`` (attributes ``q, qd, qdd``) or a tuple
    ``(q, qd, qdd)``; ``qd``/``qdd`` with one row fewer than ``q`` are padded with zeros."""
    if isinstance(ik, JointReference):
        return ik
    if isinstance(ik, (tuple, list)):
        q, qd, qdd = ik
    else:
        q, qd, qdd = ik.q, ik.qd, ik.qdd
    q, qd, qdd = jnp.asarray(q), jnp.asarray(qd), jnp.asarray(qdd)
    N = q.shape[-2] if n_rows is None else n_rows

    def pad(x, name):
        if x.shape[-2] == N:
            return x
        if x.shape[-2] == N - 1:
            z = jnp.zeros(x.shape[:-2] + (1, x.shape[-1]), x.dtype)
            return jnp.concatenate([x, z], axis=-2)
        raise ValueError(f"ik.{name}: expected {N} or {N - 1} rows, got shape {x.shape}")

    if q.shape[-2] != N:
        raise ValueError(f"ik.q: expected {N} rows (one per reference sample), got shape {q.shape}")
    return JointReference(q=q, qd=pad(qd, "qd"), qdd=pad(qdd, "qdd"))


class SimResult(eqx.Module):
    """Result of one run (a leading batch axis under :func:`simulate_batch`).

    Per sample ``k`` (``N`` rows, saved at the sample end ``t_{k+1}``): ``t``, ``q``, ``qd``, ``p``,
    ``quat`` (end-effector pose), ``pos_err`` (against the held sample ``k``; gradient-guided: against
    the goal), ``ori_err`` (``sin(phi/2)``; meaningful where ``rot = 1``), ``min_dist`` (smallest POI
    signed distance), ``f_obs``, ``f_jl`` (integrated flags: nonzero once a solver stage of nonzero
    weight has been in contact; read them by absolute value, since a Runge-Kutta step's negative
    stage weight can leave them below zero, see ``_final_flags``), ``rot``, ``mask`` (valid samples; for
    gradient-guided runs, up to the stop).

    Per run: ``metrics`` (:class:`~redman_jax._metrics.RunMetrics`), ``n_samples``, ``path_length``
    [m], ``time_to_goal`` [s] (gradient-guided; ``inf`` otherwise), diagnostics ``n_steps``,
    ``n_accepted``, ``n_rejected``, ``status`` (0 = every solve successful, else a diffrax
    ``RESULTS`` code), ``diverged`` (the run is not to be trusted: a state left the bounds or was
    not finite, or the solver stopped), ``out_of_steps`` (of those, the solver used up its step
    budget, ``SimParams.max_steps_per_sample`` times the samples, before the run's end: a run that
    may not have blown up at all, e.g. one chattering along a discontinuity of its control law),
    and the final controller state ``z``.

    Gradient-guided runs also keep every estimate of the local-minima estimator (``estimates``
    ``(N, 3)``, ``estimate_valid`` ``(N,)``, the estimate made at the start of sample ``k``) and the
    final virtual-obstacle buffer (``virtual_p``, ``virtual_mask``); zeros otherwise.
    """

    t: Float[Array, " N"]
    q: Float[Array, "N n"]
    qd: Float[Array, "N n"]
    p: Float[Array, "N 3"]
    quat: Float[Array, "N 4"]
    pos_err: Float[Array, " N"]
    ori_err: Float[Array, " N"]
    min_dist: Float[Array, " N"]
    f_obs: Float[Array, " N"]
    f_jl: Float[Array, " N"]
    rot: Float[Array, " N"]
    mask: Bool[Array, " N"]
    metrics: RunMetrics
    n_samples: Int[Array, ""]
    path_length: Float[Array, ""]
    time_to_goal: Float[Array, ""]
    n_steps: Int[Array, ""]
    n_accepted: Int[Array, ""]
    n_rejected: Int[Array, ""]
    status: Int[Array, ""]
    diverged: Bool[Array, ""]
    out_of_steps: Bool[Array, ""]
    z: PyTree
    estimates: Float[Array, "N 3"]
    estimate_valid: Bool[Array, " N"]
    virtual_p: Float[Array, "B 3"]
    virtual_mask: Bool[Array, " B"]

    @property
    def success(self):
        return self.metrics.success


class _Y(eqx.Module):
    """ODE state: joints, controller state and the flags ``(f_obs, f_jl, f_bad)``."""

    q: Array
    qd: Array
    z: PyTree
    f: Array


def _pack_z(z, dtype):
    """diffrax cannot carry an empty subtree in the state: a controller without integrated state
    (``z = ()``) is carried as a zero-size array and handed back as ``()``."""
    return jnp.zeros((0,), dtype) if not jax.tree.leaves(z) else z


def _unpack_z(z):
    return () if isinstance(z, jax.Array) and z.shape == (0,) else z


def _state_norm(y: _Y):
    """RMS norm of the scaled error over ``q, qd, z``: the flag states are excluded (SPEC 10)."""
    return optx.rms_norm((y.q, y.qd, y.z))


# --------------------------------------------------------------------------------------------
# reference zero-order hold


def _ref_sample(ref: Reference, jref: JointReference | None, k, n: int, dtype) -> RefSample:
    """The sample held during sample ``k`` (clipped to the valid range). Joint space (SPEC 6):
    ``(q_k, qd_d[k], qdd_d[k])`` for ``k <= N_s - 2`` and ``(q_{N_s-1}, 0, 0)`` afterwards."""
    last = ref.n_samples - 1
    kk = jnp.clip(k, 0, last)
    if jref is None:
        zq = jnp.zeros((n,), dtype)
        jq, jqd, jqdd = zq, zq, zq
    else:
        moving = k < last
        jq = jref.q[kk]
        jqd = jnp.where(moving, jref.qd[kk], 0.0)
        jqdd = jnp.where(moving, jref.qdd[kk], 0.0)
    return RefSample(p=ref.p[kk], v=ref.v[kk], a=ref.a[kk], quat=ref.quat[kk], omega=ref.omega[kk],
                     omega_dot=ref.omega_dot[kk], rot=ref.rot[kk].astype(dtype), q=jq, qd=jqd, qdd=jqdd)


def _goal_sample(goal_p, goal_quat, rot, n, dtype) -> RefSample:
    """Held 'reference' of the gradient-guided controller: the goal pose, at rest."""
    z3 = jnp.zeros((3,), dtype)
    zq = jnp.zeros((n,), dtype)
    return RefSample(p=goal_p, v=z3, a=z3, quat=goal_quat, omega=z3, omega_dot=z3,
                     rot=jnp.asarray(rot, dtype), q=zq, qd=zq, qdd=zq)


# --------------------------------------------------------------------------------------------
# vector field


def _poi_thresholds(arm: Arm, dtype):
    return arm.widths.astype(dtype)[jnp.asarray(poi_link_index(arm))]


def _min_poi_distance(arm: Arm, kin, q, obstacles):
    pois = poi_positions_from(arm, kin, q)
    return points_min_distance(obstacles, pois)  # (m,), one fused pass per obstacle slot


def _all_finite(tree) -> Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


# Traced once, called from every place diffrax evaluates the vector field (initial FSAL stage, the
# stages, the re-evaluation after a jump: 3 to 4 places per solve), so the closed loop is traced and
# lowered once instead of at each (measured: lowering 35 % faster, the same compiled program).
@eqx.filter_jit
def _closed_loop(t, y: _Y, rs: RefSample, env, active, arm, controller, gains, params: SimParams) -> _Y:
    """``dy/dt`` of the closed loop for the held sample ``rs``; zero when ``active`` is False or the
    member diverged (see the module docstring)."""
    dtype = y.q.dtype
    # A NaN state or reference (a diverged member, a poisoned seed) is read as 0 and the member
    # flagged below: the closed loop's partials then stay finite there, so in reverse mode the
    # member's zero cotangent gives it a zero gradient instead of NaN (0 * NaN), which the shared
    # gains summed over the batch would pass to every member. Identity on finite inputs.
    finite_in = _all_finite((y.q, y.qd, y.z, rs))
    clean = lambda x: jnp.where(jnp.isfinite(x), x, 0.0).astype(x.dtype)  # noqa: E731
    q, qd, z = clean(y.q), clean(y.qd), jax.tree.map(clean, y.z)  # z: an array or a pytree
    rs = jax.tree.map(clean, rs)
    out = controller(gains, arm, ControlState(t=t, q=q, qd=qd, z=_unpack_z(z)), rs, env)
    dz = _pack_z(out.dz, dtype)
    qdd = forward_dynamics(arm, q, qd, out.tau, params.contact)
    kin = kinematics(arm, q)
    dmin = _min_poi_distance(arm, kin, q, env.obstacles)
    in_collision = jnp.any(dmin < _poi_thresholds(arm, dtype))
    outside = jnp.any(arm.limited & ((q < arm.q_min) | (q > arm.q_max)))
    ok = (finite_in & _all_finite((qdd, dz))
          & jnp.all(jnp.abs(q) < params.q_bound) & jnp.all(jnp.abs(qd) < params.qd_bound))
    on = ok & active
    gate = lambda x: jnp.where(on, jnp.where(jnp.isfinite(x), x, 0.0), 0.0).astype(x.dtype)
    f = jnp.stack([on & in_collision, on & outside, active & ~ok]).astype(dtype)
    return _Y(q=gate(qd), qd=gate(qdd), z=jax.tree.map(gate, dz), f=f)


def solver_name(params: SimParams, controller) -> str:
    """The solver ``params.solver`` selects for ``controller``: the name itself, or for ``"auto"``
    the controller's ``auto_solver``: ``"tsit5"`` for the acceleration OSC and the gradient-guided
    controller, ``"dopri5"`` for the others (measured, see the module docstring)."""
    if params.solver == "auto":
        return controller.auto_solver
    return params.solver


def _make_solver(params: SimParams, controller):
    return _SOLVERS[solver_name(params, controller)]()


def _make_adjoint(params: SimParams):
    if params.adjoint == "recursive":
        return diffrax.RecursiveCheckpointAdjoint()
    if params.adjoint == "direct":
        return diffrax.DirectAdjoint()
    return diffrax.BacksolveAdjoint()


class _EvenSplit(diffrax.AbstractAdaptiveStepSizeController):
    """Wraps a ``ClipStepSizeController`` with ``jump_ts`` at the sample ends: a proposed step
    ``h`` from ``t`` is shortened to ``(b - t) / ceil((b - t) / h)``, ``b`` the next sample end,
    so that the remainder of a sample is covered by equal steps. Without it a step of 0.8 t_s is
    followed by a clipped sliver of 0.2 t_s and the PID controller restarts from that sliver after
    the boundary (measured: about 25 % more steps). Only ever shortens steps, so the error control
    is unchanged."""

    inner: diffrax.ClipStepSizeController
    ends: Array

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def wrap(self, direction):
        return _EvenSplit(inner=self.inner.wrap(direction), ends=self.ends)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return self.inner.init(terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        keep, next_t0, next_t1, made_jump, state, result = self.inner.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state)
        i = jnp.minimum(jnp.searchsorted(self.ends, next_t0, side="right"), self.ends.shape[0] - 1)
        b = self.ends[i]
        finite = jnp.isfinite(b)  # ends past the run's last valid sample are +inf: no split there
        h = next_t1 - next_t0
        rem = jnp.where(finite, b - next_t0, 0.0)
        n = jnp.ceil(rem / jnp.where(h > 0, h, 1.0) - 1e-6)
        even = next_t0 + rem / jnp.maximum(n, 1.0)
        # A step the clip ends one float before b (``prevbefore(b)``) reaches b: never split it.
        # Otherwise, once that float is more than 1e-6 of the step (float32: any step under 2 ms
        # at t = 0.02 s; float64: under about 2e-9 s at t = 10 s), the margin above makes two
        # pieces, and every halving makes the next one certain (7-DOF simple, velocity OSC,
        # float32: 16,578 steps against 3,568 with this check).
        reaches = b - next_t1 <= 4 * jnp.finfo(b.dtype).eps * jnp.abs(b)
        split = finite & (h > 0) & (rem > h) & (b > next_t0) & ~reaches
        next_t1 = jnp.where(split, jnp.minimum(next_t1, even), next_t1)
        return keep, next_t0, next_t1, made_jump, state, result


def _pid(params: SimParams, dtype, jump_ts=None, ends=None):
    rtol, atol = tolerances(params, dtype)
    pid = diffrax.PIDController(rtol=rtol, atol=atol, pcoeff=params.pcoeff,
                                icoeff=params.icoeff, norm=_state_norm)
    if jump_ts is None:
        return pid
    clip = diffrax.ClipStepSizeController(pid, jump_ts=jump_ts)
    if ends is None or not params.even_steps:
        return clip
    return _EvenSplit(inner=clip, ends=ends)


# --------------------------------------------------------------------------------------------
# integration drivers


def _solve_horizon(arm, controller, gains, ref, jref, env, y0, params, save_ts=None, dense=False):
    """One ``diffeqsolve`` over ``[0, N t_s]`` with ``jump_ts`` at every sample boundary."""
    N = ref.capacity
    n = arm.n_dof
    dtype = y0.q.dtype
    ts = ref.ts.astype(dtype)
    ends = ts * jnp.arange(1, N + 1, dtype=dtype)  # sample ends (k+1) t_s
    bounds = ends[:-1]  # jump times, the same floats the ZOH index is computed against
    t1 = ends[-1]
    # Past the end of the run's last valid sample the field is zero: no jumps there, so the solver
    # crosses the padding to the capacity in a few growing steps instead of one or more per padded
    # sample (the steps up to the last valid sample are unchanged).
    valid = jnp.arange(N) < ref.n_samples
    jumps = jnp.where(valid[:-1], bounds, jnp.inf)
    step_ends = jnp.where(valid, ends, jnp.inf)

    def vf(t, y, args):
        k = jnp.searchsorted(bounds, t, side="right")
        rs = _ref_sample(ref, jref, k, n, dtype)
        # frozen after the last valid sample; decided on the index (the final stage of the last
        # step is evaluated at t = N t_s exactly, which still belongs to sample N - 1)
        return _closed_loop(t, y, rs, env, k < ref.n_samples, arm, controller, gains, params)

    saveat = diffrax.SaveAt(ts=ends if save_ts is None else save_ts, dense=dense)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), _make_solver(params, controller), t0=jnp.zeros((), dtype), t1=t1, dt0=ts, y0=y0,
        saveat=saveat, stepsize_controller=_pid(params, dtype, jump_ts=jumps if N > 1 else None,
                                                ends=step_ends),
        adjoint=_make_adjoint(params), max_steps=params.max_steps_per_sample * N, throw=False)
    stats = (sol.stats["num_steps"], sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"])
    return sol, stats, sol.result._value


# A per-sample solve cannot borrow steps from quiet samples as the horizon solve does, so a stiff
# start-up transient (the null-space joint-limit push on the lift, thesis 3.35) would exhaust a
# budget of ``max_steps_per_sample`` and be reported as a failed run; it gets this many times more.
_PER_SOLVE_FACTOR = 16


def _solve_sample(arm, controller, gains, rs, env, y, k, ts, dt0, active, params):
    """One warm-started ``diffeqsolve`` over sample ``k``, ``[k t_s, (k+1) t_s]``."""
    dtype = y.q.dtype
    t0 = ts * k.astype(dtype)
    t1 = ts * (k + 1).astype(dtype)

    def vf(t, yy, args):
        return _closed_loop(t, yy, rs, env, active, arm, controller, gains, params)

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), _make_solver(params, controller), t0=t0, t1=t1, dt0=dt0, y0=y,
        saveat=diffrax.SaveAt(t1=True), stepsize_controller=_pid(params, dtype),
        adjoint=_make_adjoint(params), max_steps=_PER_SOLVE_FACTOR * params.max_steps_per_sample,
        throw=False)
    y1 = jax.tree.map(lambda x: x[-1], sol.ys)
    acc = sol.stats["num_accepted_steps"]
    dt_next = jnp.minimum(ts / jnp.maximum(acc, 1).astype(dtype), ts)
    stats = jnp.stack([sol.stats["num_steps"], acc, sol.stats["num_rejected_steps"]]).astype(jnp.int32)
    return y1, dt_next, stats, sol.result._value


def _solve_per_sample(arm, controller, gains, ref, jref, env, y0, params):
    """``lax.scan`` over samples, one warm-started solve each (``dt0`` = previous mean step)."""
    N = ref.capacity
    n = arm.n_dof
    dtype = y0.q.dtype
    ts = ref.ts.astype(dtype)

    def body(carry, k):
        y, dt0 = carry
        rs = _ref_sample(ref, jref, k, n, dtype)
        y1, dt_next, stats, status = _solve_sample(arm, controller, gains, rs, env, y, k, ts, dt0,
                                                   k < ref.n_samples, params)
        return (y1, dt_next), (y1, stats, status)

    _, (ys, stats, status) = jax.lax.scan(body, (y0, ts), jnp.arange(N))
    return ys, stats.sum(0), jnp.max(status)


def _guided_update(arm, scenario, fparams, params, y, buf, rot):
    """The discrete update at a sample start of a gradient-guided run (thesis 3.24-3.27): one
    estimate from the end-effector position pushed into the virtual-obstacle buffer, and the
    orientation latch (on within ``guidance_rot_radius`` of the goal, never off again).
    Returns ``(buf, rot, x_min, valid)``."""
    from ._guidance import estimator_update

    x = kinematics(arm, y.q).ee[:3, 3]
    buf, x_min, valid = estimator_update(x, scenario.goal_p, scenario.obstacles, buf, fparams,
                                         params.lme_mu, params.lme_max_jump)
    rot = jnp.maximum(rot, (jnp.linalg.norm(x - scenario.goal_p) < params.guidance_rot_radius)
                      .astype(rot.dtype))
    return buf, rot, x_min, valid


def _guided_args(scenario, env0, buf, rot, n: int):
    """What a gradient-guided sample holds: the goal at rest as the reference sample, and the
    environment with the buffer as its virtual obstacles. Returns ``(rs, env)``."""
    env = eqx.tree_at(lambda e: (e.virtual_p, e.virtual_mask), env0, (buf.p, buf.mask))
    return _goal_sample(scenario.goal_p, scenario.goal_quat, rot, n, rot.dtype), env


def _guided_stepper_fns(arm, controller, gains, scenario, env0, fparams, params, N, ts):
    """The pieces of :func:`_solve_guided_stepper` for one member: ``init(y0) -> carry``,
    ``cond(carry)`` (still stepping), ``body(carry) -> carry`` (one step) and ``outputs(carry)``."""
    from ._guidance import VirtualBuffer

    dtype = scenario.goal_p.dtype
    n = arm.n_dof
    solver = _make_solver(params, controller)
    pid = _pid(params, dtype)
    on = jnp.asarray(True)

    def vf(t, y, args):
        rs, env = args
        return _closed_loop(t, y, rs, env, on, arm, controller, gains, params)

    term = diffrax.ODETerm(vf)
    error_order = solver.error_order(term)

    def sample_start(y, buf, rot):
        return _guided_update(arm, scenario, fparams, params, y, buf, rot)

    def held_args(buf, rot):
        return _guided_args(scenario, env0, buf, rot, n)

    def init(y0):
        buf, rot, x_min, valid = sample_start(y0, VirtualBuffer.empty(params.buffer_size, dtype),
                                              jnp.zeros((), dtype))
        args0 = held_args(buf, rot)
        t0 = jnp.zeros((), dtype)
        tnext, cstate = pid.init(term, t0, ts, y0, ts, args0, solver.func, error_order)
        sstate = solver.init(term, t0, tnext, y0, args0)
        zeros_like_rows = lambda x: jnp.zeros((N,) + x.shape, x.dtype)
        return dict(
            k=jnp.zeros((), jnp.int32), t=t0, tnext=tnext, y=y0, sstate=sstate, cstate=cstate,
            made_jump=jnp.asarray(False), buf=buf, rot=rot,
            ys=jax.tree.map(zeros_like_rows, y0),
            est=jnp.zeros((N, 3), dtype).at[0].set(x_min), est_ok=jnp.zeros((N,), bool).at[0].set(valid),
            rots=jnp.zeros((N,), dtype).at[0].set(rot),
            steps=jnp.zeros((3,), jnp.int32), hold=jnp.zeros((), jnp.int32))

    max_steps = params.max_steps_per_sample * N

    def cond(c):
        go = (c["k"] < N) & (c["steps"][0] < max_steps)
        return go & (c["hold"] < params.hold_samples) if params.stop_early else go

    def body(c):
        k, t, y = c["k"], c["t"], c["y"]
        args = held_args(c["buf"], c["rot"])
        b = ts * (k + 1).astype(dtype)  # the end of the held sample
        h = c["tnext"] - t
        rem = b - t
        pieces = jnp.ceil(rem / jnp.where(h > 0, h, 1.0) - 1e-6)
        split = (h > 0) & (rem > h) & (pieces > 1)
        t1 = jnp.where(split, t + rem / jnp.where(split, pieces, 1.0), b)
        y1, y_err, _, sstate1, _ = solver.step(term, t, t1, y, args, c["sstate"], c["made_jump"])
        y_err = jax.tree.map(lambda e: jnp.where(jnp.isnan(e), jnp.inf, e), y_err)
        keep, _, tnext, _, cstate, _ = pid.adapt_step_size(t, t1, y, y1, args, y_err, error_order,
                                                         c["cstate"])
        at_end = keep & (t1 == b)
        sel = lambda a, b_: jax.tree.map(lambda u, v: jnp.where(keep, u, v), a, b_)
        y = sel(y1, y)
        sstate = sel(sstate1, c["sstate"])
        t = jnp.where(keep, t1, t)
        # the sample's end state, then the next sample's discrete update from it
        row = jnp.where(at_end, k, N)  # out of range: dropped (an in-place scatter, no copy)
        ys = jax.tree.map(lambda rows, v: rows.at[row].set(v, mode="drop"), c["ys"], y)
        buf, rot, x_min, valid = sample_start(y, c["buf"], c["rot"])
        k1 = jnp.minimum(k + 1, N - 1)
        nxt = at_end & (k + 1 < N)
        pick = lambda a, b_: jax.tree.map(lambda u, v: jnp.where(nxt, u, v), a, b_)
        buf, rot = pick((buf, rot), (c["buf"], c["rot"]))
        row1 = jnp.where(nxt, k1, N)
        est = c["est"].at[row1].set(x_min, mode="drop")
        est_ok = c["est_ok"].at[row1].set(valid, mode="drop")
        rots = c["rots"].at[row1].set(rot, mode="drop")
        made_jump = jnp.where(keep, at_end, c["made_jump"])
        steps = c["steps"] + jnp.stack([1, keep.astype(jnp.int32), (~keep).astype(jnp.int32)])
        # the stop rule (guidance_termination): consecutive sample ends within the goal radius
        p_end = kinematics(arm, y.q).ee[None, :3, 3]
        inside = _norm_forward(p_end - scenario.goal_p[None])[0] < params.goal_radius  # no gradient
        hold = jnp.where(at_end, jnp.where(inside, c["hold"] + 1, 0), c["hold"])
        return dict(k=k + at_end.astype(jnp.int32), t=t, tnext=tnext, y=y, sstate=sstate,
                    cstate=cstate, made_jump=made_jump, buf=buf, rot=rot, ys=ys, est=est,
                    est_ok=est_ok, rots=rots, steps=steps, hold=hold)


    def outputs(c):
        # Stopped by the rule, or out of steps: the rows not reached hold the last state. After the
        # rule's stop that is the state at the stop, inside the radius, so the post-hoc rule of
        # _simulate_guided finds the same stop; out of steps is flagged through the status of each
        # row not reached (per sample, so a stop before them, with stop_early=False, is unaffected).
        reached = jnp.arange(N) < c["k"]
        ys = jax.tree.map(lambda rows, v: jnp.where(reached.reshape((N,) + (1,) * v.ndim), rows, v),
                          c["ys"], c["y"])
        stopped = (c["hold"] >= params.hold_samples) & params.stop_early
        status = jnp.where(~reached & ~stopped, diffrax.RESULTS.max_steps_reached._value, 0)
        return ys, c["steps"], status, c["est"], c["est_ok"], c["rots"], c["buf"]

    return init, cond, body, outputs


def _solve_guided_stepper(arm, controller, gains, scenario, env0, y0, fparams, params, N, ts):
    """Gradient-guided run as *one* adaptive integration over ``[0, N t_s]`` (``mode="horizon"``).

    diffrax's solver step (``params.solver``) and ``PIDController`` driven by our own
    ``lax.while_loop``, so that the discrete update at every sample start (estimator ->
    virtual-obstacle buffer, orientation latch; thesis 3.24-3.27) can be applied between two steps:
    a step never straddles a sample end (the rest of a sample is split into equal steps, as
    ``_EvenSplit`` does), and after the step that lands on an end the buffer is updated from the
    state there and the first stage is re-evaluated (``made_jump``), exactly as the per-sample
    solves restart. The step size proposed by the PID controller carries across the sample ends (a
    per-sample solve restarts from the previous sample's mean step instead), so the steps differ
    from ``mode="per_sample"`` only at the tolerance level.

    A member stops at the stop rule (the goal error below ``goal_radius`` at ``hold_samples``
    consecutive sample ends, :func:`~redman_jax._metrics.guidance_termination`): what comes after
    the stop is never reported, and a run that reaches the goal no longer steps on to 6 s (under
    ``vmap`` the loop runs for its slowest member).

    Why: under ``vmap`` a scan of per-sample solves costs ``sum_k max_members(steps in sample
    k)`` loop iterations; this loop costs ``max_members(total steps)`` (9-DOF simple case, 20
    seeds: 18514 against 4590, ``benchmarks/bench_guided.py``). Forward only: differentiate gradient-guided runs
    with ``mode="per_sample"`` (diffrax's checkpointed adjoint).
    """
    init, cond, body, outputs = _guided_stepper_fns(arm, controller, gains, scenario, env0, fparams,
                                                    params, N, ts)
    return outputs(jax.lax.while_loop(cond, body, init(y0)))


# --------------------------------------------------------------------------------------------
# results


def _ee_pose_batch(arm, q):
    def one(qq):
        T = kinematics(arm, qq).ee
        return T[:3, 3], rot_to_quat(T[:3, :3])

    return jax.vmap(one)(q)


def _min_dist_batch(arm, q, obstacles):
    return jax.vmap(lambda qq: jnp.min(_min_poi_distance(arm, kinematics(arm, qq), qq, obstacles)))(q)


def _initial_state(arm, controller, q0, qd0, dtype):
    q0 = arm.q0.astype(dtype) if q0 is None else jnp.asarray(q0, dtype)
    qd0 = jnp.zeros_like(q0) if qd0 is None else jnp.asarray(qd0, dtype)
    z0 = _pack_z(controller.init_state(arm, q0, qd0), dtype)
    return _Y(q=q0, qd=qd0, z=z0, f=jnp.zeros((3,), dtype))


def _diverged(ys: _Y, status, rows=None):
    """The run diverged: its divergence flag is nonzero, a state is not finite or the solver
    stopped (``status``). ``rows`` ``(N,)``: count only these saved rows (default all; a guided run
    up to its stop). The flag is read by absolute value, as the others (``_final_flags``): a stage
    out of bounds that only a negative Runge-Kutta weight sees leaves it below zero."""
    rows = jnp.ones(ys.q.shape[0], bool) if rows is None else rows
    finite = jnp.all(jnp.where(rows[:, None], jnp.isfinite(ys.q) & jnp.isfinite(ys.qd), True))
    # NaN never compares > 0: caught by finite
    flag = jnp.max(jnp.where(rows, jnp.abs(ys.f[:, 2]), 0.0)) > 0
    return flag | (~finite) | (status != 0)


def _out_of_steps(status):
    """The solver stopped at its step budget: ``status`` (a scalar, or one per sample) holds
    diffrax's ``max_steps_reached``."""
    return jnp.any(jnp.asarray(status) == diffrax.RESULTS.max_steps_reached._value)


def _final_flags(f, rows):
    """The obstacle and joint-limit flags (columns 0 and 1 of the integrated flag states) over
    ``rows``: their largest finite *absolute* value there.

    A flag's derivative is 1 at a state in contact and 0 otherwise, but a Runge-Kutta step sums
    its stages with weights of both signs (the fifth of Dopri5 and of Tsit5 is negative), so a
    contact seen at that stage alone lowers the flag, and read by its largest value the contact
    would be lost. Any nonzero value means that a stage was in contact (one with weight 0, such as
    Dopri5's second, leaves no trace). In the default study 6 of the 1,080 runs dip below zero, by
    up to 6.4e-4 (7-DOF welding, joint space), all of them flagged by a positive value as well.
    A solve that stopped early (``throw=False``) fills the rows it did not reach with ``inf``; read
    there they would report a collision and a joint-limit hit that never happened."""
    ok = rows[:, None] & jnp.isfinite(f[:, :2])
    return jnp.max(jnp.where(ok, jnp.abs(f[:, :2]), 0.0), axis=0)


def _simulate_tracking(arm, scenario, controller, gains, jref, q0, qd0, params) -> SimResult:
    ref = scenario.reference
    dtype = ref.p.dtype
    env = make_environment(scenario.obstacles, scenario.goal_p, scenario.goal_quat, params.buffer_size)
    y0 = _initial_state(arm, controller, q0, qd0, dtype)
    N = ref.capacity
    if params.mode == "horizon":
        sol, (ns, na, nr), status = _solve_horizon(arm, controller, gains, ref, jref, env, y0, params)
        ys = sol.ys
        steps = jnp.stack([ns, na, nr]).astype(jnp.int32)
    else:
        ys, steps, status = _solve_per_sample(arm, controller, gains, ref, jref, env, y0, params)
    status = jnp.asarray(status, jnp.int32)
    p, quat = _ee_pose_batch(arm, ys.q)
    mask = ref.mask & (jnp.arange(N) < ref.n_samples)
    pos_err = position_errors(p, ref.p)
    ori_err = orientation_errors(quat, ref.quat)
    last = ref.n_samples - 1
    diverged = _diverged(ys, status)
    d_final = p[last] - scenario.goal_p
    ok_final = jnp.all(jnp.isfinite(d_final))  # double where: no NaN partial behind the inf
    final_err = jnp.where(ok_final, jnp.linalg.norm(jnp.where(ok_final, d_final, 0.0)), jnp.inf)
    flags = _final_flags(ys.f, jnp.arange(N) < ref.n_samples)
    metrics = run_metrics(pos_err, ori_err, ref.rot, mask, final_err, flags[0], flags[1],
                          diverged, params.goal_radius)
    p0, _ = _ee_pose_batch(arm, y0.q[None])
    B = params.buffer_size
    return SimResult(
        t=ref.ts.astype(dtype) * jnp.arange(1, N + 1, dtype=dtype), q=ys.q, qd=ys.qd, p=p, quat=quat,
        pos_err=pos_err, ori_err=ori_err, min_dist=_min_dist_batch(arm, ys.q, scenario.obstacles),
        f_obs=ys.f[:, 0], f_jl=ys.f[:, 1], rot=ref.rot.astype(dtype), mask=mask, metrics=metrics,
        n_samples=ref.n_samples.astype(jnp.int32), path_length=path_length(p0[0], p, mask),
        time_to_goal=jnp.asarray(jnp.inf, dtype), n_steps=steps[0], n_accepted=steps[1],
        n_rejected=steps[2], status=status, diverged=diverged,
        out_of_steps=_out_of_steps(status), z=_unpack_z(jax.tree.map(lambda x: x[last], ys.z)),
        estimates=jnp.zeros((N, 3), dtype), estimate_valid=jnp.zeros((N,), bool),
        virtual_p=jnp.zeros((B, 3), dtype), virtual_mask=jnp.zeros((B,), bool),
    )


def _simulate_guided(arm, scenario, controller, gains, q0, qd0, params) -> SimResult:
    """Gradient-guided run (thesis 3.3.3, SPEC 9): at each sample start the local-minima
    estimator pushes an estimate into the virtual-obstacle buffer and the orientation latch switches
    on within ``guidance_rot_radius`` of the goal. ``mode="horizon"``: one adaptive integration
    with the discrete updates between steps (:func:`_solve_guided_stepper`, forward only);
    ``mode="per_sample"``: a scan of per-sample solves (differentiable), which runs the full 6 s
    horizon. The stop rule is applied afterwards in both modes (exact, as stopping does not change
    the past); the horizon stepper also stops each member there, which saves its steps."""
    from ._guidance import VirtualBuffer

    dtype, N, ts, fparams, env0, y0 = _guided_setup(arm, scenario, controller, gains, q0, qd0, params)
    n = arm.n_dof
    buf0 = VirtualBuffer.empty(params.buffer_size, dtype)

    def body(carry, k):
        y, dt0, buf, rot = carry
        buf, rot, x_min, valid = _guided_update(arm, scenario, fparams, params, y, buf, rot)
        rs, env = _guided_args(scenario, env0, buf, rot, n)
        y1, dt_next, stats, status = _solve_sample(arm, controller, gains, rs, env, y, k, ts, dt0,
                                                   jnp.asarray(True), params)
        return (y1, dt_next, buf, rot), (y1, stats, status, x_min, valid, rot)

    if params.mode == "horizon":
        ys, steps, status, est, est_ok, rots, buf = _solve_guided_stepper(
            arm, controller, gains, scenario, env0, y0, fparams, params, N, ts)
    else:
        carry0 = (y0, ts, buf0, jnp.zeros((), dtype))
        (_, _, buf, _), (ys, stats, status, est, est_ok, rots) = jax.lax.scan(body, carry0,
                                                                              jnp.arange(N))
        steps = stats.sum(0)
    return _guided_result(arm, scenario, params, y0, N, ts, ys, steps, status, est, est_ok, rots, buf)


def _guided_setup(arm, scenario, controller, gains, q0, qd0, params):
    """``(dtype, N, ts, fparams, env0, y0)`` of a gradient-guided run."""
    from ._guidance import field_params_or_default

    dtype = scenario.goal_p.dtype
    N = params.guidance_samples
    ts = scenario.reference.ts.astype(dtype)
    fparams = field_params_or_default(params.field, gains)
    env0 = make_environment(scenario.obstacles, scenario.goal_p, scenario.goal_quat, params.buffer_size)
    y0 = _initial_state(arm, controller, q0, qd0, dtype)
    return dtype, N, ts, fparams, env0, y0


def _guided_result(arm, scenario, params, y0, N, ts, ys, steps, status, est, est_ok, rots, buf):
    """The :class:`SimResult` of a gradient-guided run from its per-sample states and counters."""
    dtype = ts.dtype
    p, quat = _ee_pose_batch(arm, ys.q)
    goal_err = goal_errors(p, scenario.goal_p)
    ori_err = orientation_errors(quat, jnp.broadcast_to(scenario.goal_quat, quat.shape))
    # Collisions and divergence up to the stop only (what happens after it does not count, in
    # either mode): first find the stop ignoring both, then read them on the rows up to it. A run
    # that diverges never holds the goal afterwards (its errors are inf), so this stop is its own.
    term0 = guidance_termination(goal_err, ts, False, hold_samples=params.hold_samples,
                                 radius=params.goal_radius)
    last = term0.n_samples - 1
    rows = jnp.arange(N) <= last
    status = jnp.asarray(status)
    if status.ndim:  # one status per sample (per-sample solves; rows the stepper did not reach)
        status = jnp.max(jnp.where(rows, status, 0))
    status = status.astype(jnp.int32)
    diverged = _diverged(ys, status, rows)
    flags = _final_flags(ys.f, rows)
    collided = flags[0] > 0
    term = guidance_termination(goal_err, ts, collided | diverged, hold_samples=params.hold_samples,
                                radius=params.goal_radius)
    metrics = run_metrics(goal_err, ori_err, rots, term.mask, term.final_err, flags[0], flags[1],
                          diverged, params.goal_radius)
    metrics = eqx.tree_at(lambda m: (m.success, m.cause), metrics,
                          (term.success, jnp.where(diverged, 3, jnp.where(collided, 1, jnp.where(
                              term.success, 0, 2))).astype(jnp.int32)))
    p0 = kinematics(arm, y0.q).ee[:3, 3]
    return SimResult(
        t=ts * jnp.arange(1, N + 1, dtype=dtype), q=ys.q, qd=ys.qd, p=p, quat=quat, pos_err=goal_err,
        ori_err=ori_err, min_dist=_min_dist_batch(arm, ys.q, scenario.obstacles), f_obs=ys.f[:, 0],
        f_jl=ys.f[:, 1], rot=rots, mask=term.mask, metrics=metrics, n_samples=term.n_samples,
        path_length=path_length(p0, p, term.mask), time_to_goal=term.time_to_goal,
        n_steps=steps[0], n_accepted=steps[1], n_rejected=steps[2], status=status, diverged=diverged,
        out_of_steps=_out_of_steps(status),
        z=_unpack_z(jax.tree.map(lambda x: x[last], ys.z)), estimates=est, estimate_valid=est_ok,
        virtual_p=buf.p, virtual_mask=buf.mask,
    )


def _simulate_core(arm, scenario, controller, gains, jref, q0, qd0, params) -> SimResult:
    if scenario.obstacles.used is None:  # a single run (the batch sets it over all members)
        scenario = _with_used_bound(scenario, used_bound(scenario.obstacles))
    if controller.uses_guidance:
        return _simulate_guided(arm, scenario, controller, gains, q0, qd0, params)
    return _simulate_tracking(arm, scenario, controller, gains, jref, q0, qd0, params)


_simulate_jit = eqx.filter_jit(_simulate_core)


def _check_inputs(arm, scenario, controller, ik, batched: bool, q0=None, qd0=None, gains=None,
                  batch_gains: bool = False):
    if not isinstance(arm, Arm):
        raise ValueError(f"arm: expected an Arm, got {type(arm).__name__}")
    if not isinstance(scenario, Scenario):
        raise ValueError(f"scenario: expected a Scenario, got {type(scenario).__name__}")
    if not isinstance(controller, AbstractController):
        raise ValueError(f"controller: expected an AbstractController, got {type(controller).__name__}")
    if controller.needs_joint_reference and ik is None:
        raise ValueError(f"ik: {type(controller).__name__} is a joint-space controller and needs the "
                         "IK's joint reference (ik=IKResult or (q, qd, qdd))")
    nd = 2 if batched else 1
    if scenario.reference.p.ndim != nd + 1:
        raise ValueError(f"scenario.reference.p: expected {nd + 1} dimensions "
                         f"({'batched' if batched else 'single'} scenario), got shape "
                         f"{scenario.reference.p.shape}")
    R = scenario.reference.p.shape[0] if batched else None
    for name, x in (("q0", q0), ("qd0", qd0)):
        check_initial_state(name, x, arm.n_dof, R)
    # one run: its values finite; a batch: a member's non-finite values are its own flagged failure
    check_reference_values(scenario.reference, "scenario.reference", batch=batched)
    if not batched:  # a NaN goal ran (make_environment's check is inside the jit) as "goal not reached"
        check_finite("scenario.goal_p", scenario.goal_p)
        check_finite("scenario.goal_quat", scenario.goal_quat)
    check_unit_quaternions("scenario.goal_quat", scenario.goal_quat, plural=True)
    _check_gains(controller, gains, R if batch_gains else None)


def _check_joint_reference(jref, n: int, N: int, R) -> None:
    """The joint reference's shape, ``(N, n)`` (``(R, N, n)`` in a batch of ``R``: a wrong column
    count failed inside the closed loop with a broadcasting error, an unbatched one in a batch
    with "vmap got inconsistent sizes"); for one run, where concrete, finite values (a NaN ran as
    a divergence). In a batch a member's non-finite reference (the IK of a scene that failed
    validation) stays that member's flagged divergence and leaves the others intact."""
    if jref is None:
        return
    shape = (N, n) if R is None else (R, N, n)
    about = f" ({N} reference samples, {n}-DOF arm{'' if R is None else f', {R} runs'})"
    for name in ("q", "qd", "qdd"):
        x = getattr(jref, name)
        if tuple(np.shape(x)) != shape:
            raise ValueError(f"ik.{name}: expected shape {shape}{about}, got {tuple(np.shape(x))}")
        if R is None:
            check_finite(f"ik.{name}", x)


def _with_sim_field(gains, params, batch_gains: bool, R):
    """The gains with ``params.field`` as their guidance field where both exist (one field for the
    controller and the estimator; a batch of gains gets it on every member)."""
    from ._fields import FieldParams

    if params.field is None or not isinstance(getattr(gains, "field", None), FieldParams):
        return gains
    field = params.field  # in the run's precision already (_in_precision)
    if batch_gains:  # its own structure: its static choices (form, ...) may differ from the gains'
        field = jax.tree.map(lambda f: jnp.broadcast_to(f, (R,) + jnp.shape(f)), field)
    return eqx.tree_at(lambda g: g.field, gains, field)


def _check_gains(controller, gains, R) -> None:
    """Gains of the controller's own class (where its :meth:`default_gains` is a Module: the gains
    of another controller failed inside the control law with an ``AttributeError``), and with
    ``batch_gains`` (``R`` runs) a leading axis ``R`` on every array."""
    default = controller.default_gains()
    if isinstance(default, eqx.Module) and not isinstance(gains, type(default)):  # None, a dict, ...
        raise ValueError(f"gains: {type(controller).__name__} takes {type(default).__name__}, "
                         f"got {type(gains).__name__}")
    if R is not None:
        for path, x in jax.tree_util.tree_leaves_with_path(gains):
            if not jnp.shape(x) or jnp.shape(x)[0] != R:
                raise ValueError(f"gains{jax.tree_util.keystr(path)}: batch_gains=True needs a leading "
                                 f"axis of {R} runs, got shape {tuple(jnp.shape(x))}")


def _in_precision(arm, scenario, gains, ik, params: SimParams) -> SimParams:
    """A run is integrated in its scenario's precision (float64 or float32). ``params`` (our
    settings) gets that precision's default tolerances where None and is cast to it; an arm, gains
    or joint reference of another floating dtype is an error naming it (mixed, they would promote
    the vector field and fail deep inside the solver). Weakly typed numbers (Python scalars) take
    the run's precision and pass."""
    dtype = jnp.dtype(scenario.reference.p.dtype)
    for name, tree in (("arm", arm), ("gains", gains), ("ik", ik), ("scenario.obstacles", scenario.obstacles),
                       ("scenario.goal_p", scenario.goal_p), ("scenario.goal_quat", scenario.goal_quat)):
        check_same_precision(name, tree, dtype, f"a {dtype.name} scenario")
    if params.rtol is None or params.atol is None:  # arguments of the compiled run, not constants
        params = dataclasses.replace(params, **dict(zip(("rtol", "atol"), tolerances(params, dtype))))
    return cast_floating(params, dtype)


def _with_layout(arm: Arm, scenario: Scenario, params: SimParams, batch: int) -> Scenario:
    """``scenario`` with its obstacles laid out for ``batch`` members (:func:`obstacle_layout`)."""
    return eqx.tree_at(lambda sc: sc.obstacles, scenario,
                       obstacle_layout(arm, scenario.obstacles, params, batch))


def obstacle_layout(arm: Arm, obstacles, params: SimParams, batch: int):
    """``obstacles`` with the work layout set from ``params.slots_per_step`` (None: from the batch
    size and the arm's points of interest), each family padded to the capacity that its slot groups
    fill (:func:`~redman_jax._obstacles.pad_to_layout`: once here, not at every vector-field
    evaluation; 9-DOF warehouse, 97 box slots, velocity OSC, 20 seeds: 62 -> 58 s median of 4,
    bit-identical runs)."""
    from ._obstacles import auto_slots_per_step, pad_to_layout, with_slots_per_step

    s = params.slots_per_step
    if s is None:
        s = auto_slots_per_step(batch, arm.n_dof * arm.points_per_link)
    return pad_to_layout(with_slots_per_step(obstacles, s))


def simulate(arm: Arm, scenario: Scenario, controller: AbstractController, gains, ik=None,
             params: SimParams | None = None, *, q0=None, qd0=None) -> SimResult:
    """Simulate one closed-loop run (jit-compiled; see the module docstring).

    **Arguments**
    * ``arm``, ``scenario`` (unbatched), ``controller`` and its ``gains``;
    * ``ik``: the joint-space reference for joint-space controllers (an ``IKResult`` or
      ``(q, qd, qdd)`` with ``N`` rows, see :func:`joint_reference`);
    * ``params``: :class:`SimParams`; ``q0``, ``qd0``: initial state (default ``arm.q0``, rest).

    **Returns** a :class:`SimResult`. Differentiable w.r.t. ``gains``, ``q0``, ``qd0`` and the
    scenario's numbers (``RecursiveCheckpointAdjoint``), except a gradient-guided controller in the
    default ``mode="horizon"``, whose stepping loop is forward only: differentiate those with
    ``SimParams(mode="per_sample")``.

    **Raises** ``ValueError`` for a wrong argument type, a missing joint reference, gains of
    another controller's class, or a ``q0`` / ``qd0`` of the wrong shape or (where concrete) not
    finite.
    """
    params = SimParams() if params is None else params
    _check_inputs(arm, scenario, controller, ik, batched=False, q0=q0, qd0=qd0, gains=gains)
    params = _in_precision(arm, scenario, gains, ik, params)
    gains = _with_sim_field(gains, params, False, None)
    jref = None if ik is None else joint_reference(ik, scenario.reference.capacity)
    _check_joint_reference(jref, arm.n_dof, scenario.reference.capacity, None)
    scenario = _with_layout(arm, scenario, params, 1)
    q0, qd0 = _as_state(q0, scenario), _as_state(qd0, scenario)
    return _simulate_jit(arm, scenario, controller, gains, jref, q0, qd0, params)


def _as_state(x, scenario):
    """An initial state as an array in the run's precision (None kept): a list or tuple of Python
    floats would be static to the compiled run and recompile it for every new value."""
    return None if x is None else jnp.asarray(x, scenario.reference.p.dtype)


def _with_used_bound(scenario, used):
    """``scenario`` with ``used`` as its bound on the used obstacle slots (:func:`used_bound`; in a
    batch the bound over all members, see :func:`_simulate_batch_jit`)."""
    return eqx.tree_at(lambda sc: sc.obstacles, scenario, with_used(scenario.obstacles, used))


def _batch_mesh(scenarios):
    """``(mesh, axis)`` where a batch's leading axis is split over several devices by a
    ``NamedSharding`` in equal parts (``_pipeline.shard_batch``: ``P("batch")``), else None."""
    x = scenarios.reference.p
    sharding = getattr(x, "sharding", None)
    if isinstance(x, jax.core.Tracer) or not isinstance(sharding, jax.sharding.NamedSharding):
        return None
    spec = tuple(sharding.spec)
    axis = spec[0] if spec else None
    if not isinstance(axis, str) or any(a is not None for a in spec[1:]):
        return None
    n = sharding.mesh.shape[axis]
    return (sharding.mesh, axis) if n > 1 and x.shape[0] % n == 0 else None


def _map_batch(one, shared, batch, in_axes, mesh):
    """``jax.vmap(lambda *b: one(shared, *b), in_axes)(*batch)``: ``one`` mapped over the batch,
    ``shared`` (a pytree, not mapped) passed to every member. With ``mesh = (mesh, axis)``
    (:func:`_batch_mesh`) inside ``shard_map``: each device maps its own rows of the batch,
    ``shared`` and the unmapped arguments (``in_axes`` None) replicated.

    Why not ``jit``'s automatic partitioning of the same program: the batch's ``while_loop`` then
    asks every device at every iteration whether any member still steps (a collective per step)
    and every device iterates as long as the slowest member of the whole batch. Two processes on
    one core (``jax.distributed``, 7-DOF simple, 3 seeds padded to 4, joint space): 104 s against
    20 s for the unit, of which 16-18 s compiling either way. ``benchmarks/bench_sharded.py``."""
    def run(shared, *batch):
        return jax.vmap(lambda *b: one(shared, *b), in_axes=in_axes)(*batch)

    if mesh is None:
        return run(shared, *batch)
    from jax.sharding import PartitionSpec as P

    shard_map = getattr(jax, "shard_map", None)
    if shard_map is None:  # an older jax
        from jax.experimental.shard_map import shard_map
    check = "check_vma" if "check_vma" in inspect.signature(shard_map).parameters else "check_rep"
    mesh, axis = mesh
    dynamic, static = eqx.partition((shared, *batch), eqx.is_array)
    specs = (P(),) + tuple(P(axis) if a == 0 else P() for a in in_axes)

    def local(dynamic):
        return run(*eqx.combine(dynamic, static))

    return shard_map(local, mesh=mesh, in_specs=(specs,), out_specs=P(axis), **{check: False})(dynamic)


@eqx.filter_jit
def _simulate_batch_jit(arm, scenarios, controller, gains, jref, q0, qd0, params, gains_axis, q0_axis,
                        mesh=None):
    # one bound on the used obstacle slots for the whole batch: unbatched, so the slot passes skip
    # the padded steps with a real branch (per member it would be a select, which skips nothing)
    used = used_bound(scenarios.obstacles)

    def one(shared, s, g, j, q, qd):
        arm, controller, params, used = shared
        return _simulate_core(arm, _with_used_bound(s, used), controller, g, j, q, qd, params)

    in_axes = (0, gains_axis, None if jref is None else 0, q0_axis, q0_axis)
    return _map_batch(one, (arm, controller, params, used), (scenarios, gains, jref, q0, qd0), in_axes,
                      mesh)


# --------------------------------------------------------------------------------------------
# gradient-guided batches: straggler compaction (host-driven, forward only)

# A guided batch under ``vmap`` steps until its slowest member stops (7-DOF simple, 20 seeds: 926 to
# 2902 steps; in 8-DOF warehouse two members take 35,717 and 38,400 steps, the others at most
# 9,727). The host advances the batch ``_CHECK_ITERS`` loop iterations per call; once at most
# ``ceil(R / _COMPACT_FRACTION)`` members are still stepping and have stepped ``_RENT_ITERS`` more
# iterations at full size (about what compiling the smaller program costs: ski rental), they move to
# a batch of exactly those members (no padding rows: a member costs about as much as a row of the
# vmapped loop, 8-DOF warehouse 0.63 / 1.19 / 2.12 ms per iteration at 1 / 2 / 5 rows, so 2
# stragglers padded to 5 rows ran 1.8x slower). The switch depends on step counts only, never on
# wall time, so the same inputs give the same results. The members take the same steps as in one
# ``vmap`` over the whole batch and agree with it to rounding (separately compiled programs: 3e-12
# relative in tests/test_sim_guided.py). A member that chatters through its step budget can amplify that: the
# 8-DOF warehouse member above ends 5.6e-14 rad apart at this switch point, 4.6e-4 rad at an
# earlier one, with the same steps and outcome.
_COMPACT_FRACTION = 4
_CHECK_ITERS = 512
_RENT_ITERS = 2048


def _guided_member(shared, s, g, q0, qd0):
    """One member's set-up and stepper functions; ``shared = (arm, controller, params, used)``."""
    arm, controller, params, used = shared
    s = _with_used_bound(s, used)
    dtype, N, ts, fparams, env0, y0 = _guided_setup(arm, s, controller, g, q0, qd0, params)
    return s, y0, N, ts, _guided_stepper_fns(arm, controller, g, s, env0, fparams, params, N, ts)


@eqx.filter_jit
def _compact_init(arm, scen, controller, gains, q0, qd0, params, used, axes, mesh=None):
    def one(shared, s, g, q, qd):
        _, y0, _, _, (init, cond, _, _) = _guided_member(shared, s, g, q, qd)
        c = init(y0)
        return c, cond(c)

    return _map_batch(one, (arm, controller, params, used), (scen, gains, q0, qd0), (0,) + axes, mesh)


@eqx.filter_jit
def _compact_advance(arm, scen, controller, gains, q0, qd0, params, used, axes, carry, cap, mesh=None):
    def one(shared, s, g, q, qd, c):
        member, cap = shared
        _, _, _, _, (_, cond, body, _) = _guided_member(member, s, g, q, qd)
        c = jax.lax.while_loop(lambda c: cond(c) & (c["steps"][0] < cap), body, c)
        return c, cond(c)

    return _map_batch(one, ((arm, controller, params, used), cap), (scen, gains, q0, qd0, carry),
                      (0,) + axes + (0,), mesh)


@eqx.filter_jit
def _compact_finish(arm, scen, controller, gains, q0, qd0, params, used, axes, carry, mesh=None):
    def one(shared, s, g, q, qd, c):
        arm, _, params, _ = shared
        s, y0, N, ts, (_, _, _, outputs) = _guided_member(shared, s, g, q, qd)
        return _guided_result(arm, s, params, y0, N, ts, *outputs(c))

    return _map_batch(one, (arm, controller, params, used), (scen, gains, q0, qd0, carry),
                      (0,) + axes + (0,), mesh)


def _take_rows(tree, idx, axis_batched=True):
    return tree if not axis_batched else jax.tree.map(lambda x: _host.put(np.asarray(x)[idx]), tree)


def _simulate_guided_compacting(arm, scenarios, controller, gains, q0, qd0, params, gains_axis,
                                q0_axis, stats=None) -> SimResult:
    """:func:`simulate_batch` of a gradient-guided controller in ``mode="horizon"`` with straggler
    compaction (see ``_COMPACT_FRACTION``). ``stats`` (a dict), if given, records what happened."""
    R = int(scenarios.goal_p.shape[0])
    used = used_bound_jit(scenarios.obstacles)
    axes = (gains_axis, q0_axis, q0_axis)
    args = (arm, scenarios, controller, gains, q0, qd0, params, used, axes)
    small = -(-R // _COMPACT_FRACTION)
    max_steps = params.max_steps_per_sample * params.guidance_samples
    mesh = _batch_mesh(scenarios)  # the stragglers' batch below is held by one device
    carry, active = _compact_init(*args, mesh=mesh)
    done, few_since, compacted, calls, sub_rows = 0, None, 0, 0, None
    while True:
        act = np.asarray(active)
        n_act = int(act.sum())
        if n_act == 0 or done >= max_steps:
            break
        if R > small and n_act <= small:
            few_since = done if few_since is None else few_since
            if done - few_since >= _RENT_ITERS:
                idx = np.flatnonzero(act)  # the members still stepping, and only those
                sub = (arm, _take_rows(scenarios, idx), controller,
                       _take_rows(gains, idx, gains_axis == 0), _take_rows(q0, idx, q0_axis == 0),
                       _take_rows(qd0, idx, q0_axis == 0), params, used, axes)
                sub_carry, _ = _compact_advance(*sub, _take_rows(carry, idx),
                                                jnp.asarray(max_steps, jnp.int32))

                def put(full, part):
                    full = np.array(full)
                    full[idx] = np.asarray(part)
                    return _host.put(full)

                carry = jax.tree.map(put, carry, sub_carry)
                compacted = idx.size
                sub_rows = int(sub_carry["k"].shape[0])
                break
        done = min(done + _CHECK_ITERS, max_steps)
        carry, active = _compact_advance(*args, carry, jnp.asarray(done, jnp.int32), mesh=mesh)
        calls += 1
    if stats is not None:
        stats.update(full_batch_calls=calls, compacted=compacted, compacted_at=done if compacted else None,
                     batch=R, small=small, sub_batch=sub_rows)
    return _compact_finish(*args, carry, mesh=mesh)


def simulate_batch(arm: Arm, scenarios: Scenario, controller: AbstractController, gains, ik=None,
                   params: SimParams | None = None, *, batch_gains: bool = False, q0=None,
                   qd0=None, threads: int | None = None) -> SimResult:
    """Simulate a batch of runs in one ``jit(vmap(...))`` call (per thread, see ``threads``).

    ``scenarios``: stacked scenarios (leading axis ``R``; :func:`~redman_jax.stack_scenarios`);
    ``ik``: joint references with a leading axis ``R`` (or None); ``batch_gains``: ``gains`` has a
    leading axis ``R`` too (a sweep); ``q0``: per-run initial configurations ``(R, n)`` (or None).
    Each member keeps its own step sizes; a member that diverges is frozen and flagged and does not
    change the others (they are bit-identical to a batch without it). Returns a :class:`SimResult`
    with a leading axis ``R``.

    A gradient-guided controller in ``mode="horizon"`` (forward only) is stepped by a few jitted
    calls driven from the host, so that its last stragglers can move to a smaller batch
    (``params.compact``; see ``_simulate_guided_compacting``); called with tracers (inside the
    caller's ``jit``) or with a batch sharded over several processes (``jax.distributed``) it is
    one ``jit(vmap)`` program as for the other controllers.

    A batch whose leading axis is split over several devices (a ``NamedSharding`` over one mesh
    axis, in equal parts: :func:`~redman_jax._pipeline.shard_batch`, the sweep's path) runs in
    ``shard_map``: each device steps its own members in a loop of its own, with no collective per
    step, and stops with its own slowest member (``benchmarks/bench_sharded.py``, 7-DOF simple, 20
    seeds, 2 CPU devices, warm: 1.2-3.1x faster than ``jit``'s automatic partitioning of the same
    program; the same steps, results to rounding).

    ``threads``: on a CPU backend, called eagerly, the batch is split into ``threads`` equal
    chunks (the last one padded with copies of its last member, dropped from the result), each
    simulated by the same compiled program on a host thread of its own, at once. None (default):
    one chunk per core this process may run on (``os.sched_getaffinity``), at most one per
    ``_MIN_CHUNK`` members, and 1 on other backends, under a trace or for a batch sharded over
    several devices or processes (where ``threads`` must be None or 1). Why: at the study's batch
    of 20, a program's operations are small and XLA's CPU runtime spends most of its time
    dispatching them, so one program cannot keep two cores busy; two programs of half the batch
    can (2-core CPU, 9-DOF simple case, joint space, 20 seeds, warm: 6.0 s in one call, 3.1 s in
    two threads; ``benchmarks/bench_sim.py --threads``). Each member takes the same steps and
    flags as in one call and agrees with it to rounding (the programs are compiled for another
    batch size). A process started with the CPU split into devices
    (``XLA_FLAGS=--xla_force_host_platform_device_count=2``) and the batch sharded over them
    (:func:`~redman_jax._pipeline.shard_batch`, see above) is faster still: the same case 1.9-2.1
    s against 3.1-3.2 s in two threads (``bench_sim.py --devices 2`` against the default, two runs
    each, in turn).

    **Raises** ``ValueError`` as :func:`simulate` does, for unbatched scenarios, a ``q0`` / ``qd0``
    not of shape ``(R, n)``, or with ``batch_gains`` a gains leaf without the leading axis ``R``.
    """
    params = SimParams() if params is None else params
    _check_inputs(arm, scenarios, controller, ik, batched=True, q0=q0, qd0=qd0, gains=gains,
                  batch_gains=batch_gains)
    params = _in_precision(arm, scenarios, gains, ik, params)
    R = int(scenarios.reference.p.shape[0])
    gains = _with_sim_field(gains, params, batch_gains, R)
    jref = None if ik is None else joint_reference(ik, scenarios.reference.capacity)
    _check_joint_reference(jref, arm.n_dof, scenarios.reference.capacity, R)
    q0, qd0 = _as_state(q0, scenarios), _as_state(qd0, scenarios)
    if q0 is None and qd0 is not None:  # each member from the arm's q0 (qd0 takes q0's axis)
        q0 = jnp.broadcast_to(arm.q0.astype(qd0.dtype), (R, arm.n_dof))
    if q0 is not None and qd0 is None:
        qd0 = jnp.zeros_like(jnp.asarray(q0))
    gains_axis, q0_axis = 0 if batch_gains else None, None if q0 is None else 0
    k = _chunks(threads, R, (scenarios, gains, jref, q0, qd0, params))
    if k == 1:
        return _simulate_members(arm, scenarios, controller, gains, jref, q0, qd0, params,
                                 gains_axis, q0_axis)
    from concurrent.futures import ThreadPoolExecutor

    rows = _chunk_rows(R, k)
    take = lambda tree, idx, batched=True: (  # noqa: E731
        jax.tree.map(lambda x: _host.take(x, idx), tree) if batched and tree is not None else tree)
    with ThreadPoolExecutor(max_workers=k, thread_name_prefix="redman-sim") as pool:
        parts = [pool.submit(_simulate_members, arm, take(scenarios, idx), controller,
                             take(gains, idx, batch_gains), take(jref, idx), take(q0, idx),
                             take(qd0, idx, q0_axis == 0), params, gains_axis,
                             q0_axis) for idx in rows]
        parts = [f.result() for f in parts]
    return jax.tree.map(lambda *xs: _host.take(_host.concatenate(xs), slice(0, R)), *parts)


_MIN_CHUNK = 8  # members per thread of simulate_batch, at least (below, dispatch costs dominate)


def _chunk_rows(R: int, k: int) -> list:
    """The rows of each of the ``k`` chunks :func:`simulate_batch` splits a batch of ``R`` into:
    contiguous, equal in size, the last padded with copies of row ``R - 1``."""
    size = -(-R // k)
    return [np.minimum(np.arange(i * size, (i + 1) * size), R - 1) for i in range(k)]


def _chunks(threads, R: int, tree) -> int:
    """How many chunks :func:`simulate_batch` splits a batch of ``R`` into (see its ``threads``)."""
    import os

    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, (int, np.integer))
                                or threads < 1):
        raise ValueError(f"simulate_batch: threads must be a positive int or None, got {threads!r}")
    # where the batch is one program: under a trace, or sharded over several processes or devices
    one_program = ("concrete inputs (called under a trace, the batch is one program)" if _has_tracer(tree)
                   else "a batch held by this process (it is sharded over several processes: one program)"
                   if _spans_processes(tree) else
                   "a batch held by one device (it is sharded over several: each steps its own members)"
                   if _spans_devices(tree) else None)
    if one_program is not None:
        if threads not in (None, 1):
            raise ValueError(f"simulate_batch: threads={threads} needs {one_program}; pass threads=None or 1")
        return 1
    if threads is None:
        if jax.default_backend() != "cpu":
            return 1
        try:
            cores = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            cores = os.cpu_count() or 1
        threads = min(cores, R // _MIN_CHUNK)
    return int(max(1, min(threads, R)))


def _simulate_members(arm, scenarios, controller, gains, jref, q0, qd0, params, gains_axis, q0_axis):
    scenarios = _with_layout(arm, scenarios, params, scenarios.reference.p.shape[0])
    if (controller.uses_guidance and params.mode == "horizon" and params.compact
            and not _has_tracer((scenarios, gains, q0, qd0, params))
            and not _spans_processes((scenarios, gains, q0, qd0))):
        return _simulate_guided_compacting(arm, scenarios, controller, gains, q0, qd0, params,
                                           gains_axis, q0_axis)
    return _simulate_batch_jit(arm, scenarios, controller, gains, jref, q0, qd0, params,
                               gains_axis, q0_axis, _batch_mesh(scenarios))


def _has_tracer(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def _spans_devices(tree) -> bool:
    """Whether an array of ``tree`` is split over several devices (a sharded batch runs as one
    program, in ``shard_map`` where :func:`_batch_mesh` recognises it: chunks taken on the host
    for threads would undo that layout; 9-DOF simple, joint space, 20 seeds on 2 CPU devices:
    3.2-3.5 s in two threads against 1.9-2.2 s sharded)."""
    return any(len(x.sharding.device_set) > 1 for x in _concrete_arrays(tree))


def _spans_processes(tree) -> bool:
    """Whether an array of ``tree`` is sharded over devices of several processes (``jax.distributed``):
    the host cannot read it, so the batch runs as one program (no threads, no straggler compaction)."""
    return any(not x.is_fully_addressable for x in _concrete_arrays(tree))


def _concrete_arrays(tree):
    """The leaves of ``tree`` that are JAX arrays with data (not tracers): those with a sharding."""
    return (x for x in jax.tree.leaves(tree)
            if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer))


@eqx.filter_jit
def _simulate_dense_jit(arm, scenario, controller, gains, jref, q0, qd0, params, points_per_sample):
    ref = scenario.reference
    dtype = ref.p.dtype
    N = ref.capacity
    m = points_per_sample
    ts = ref.ts.astype(dtype)
    k = jnp.repeat(jnp.arange(N), m)
    frac = jnp.tile(jnp.arange(1, m + 1, dtype=dtype) / m, N)
    grid = ts * (k.astype(dtype) + frac)
    grid = grid.at[m - 1::m].set(ts * jnp.arange(1, N + 1, dtype=dtype))  # exact sample ends
    env = make_environment(scenario.obstacles, scenario.goal_p, scenario.goal_quat, params.buffer_size)
    y0 = _initial_state(arm, controller, q0, qd0, dtype)
    sol, _, status = _solve_horizon(arm, controller, gains, ref, jref, env, y0, params, save_ts=grid)
    p, quat = _ee_pose_batch(arm, sol.ys.q)
    kk = jnp.clip(k, 0, ref.n_samples - 1)
    return grid, k, sol.ys.q, p, quat, position_errors(p, ref.p[kk]), orientation_errors(quat, ref.quat[kk])


def simulate_dense(arm, scenario, controller, gains, ik=None, params: SimParams | None = None, *,
                   points_per_sample: int = 20, q0=None, qd0=None):
    """Re-simulate one tracking run and sample it ``points_per_sample`` times per sample (the
    last point of each sample is its end). Saving extra times does not change the steps taken, so
    the trajectory is the one of :func:`simulate`.

    Returns ``(t, k, q, p, quat, pos_err, ori_err)`` on the fine grid; ``k`` is the sample held on
    ``(k t_s, (k+1) t_s]`` and the errors are against that held sample (Figure 4.3).
    """
    params = SimParams() if params is None else params
    if params.mode != "horizon":
        params = dataclasses.replace(params, mode="horizon")
    _check_inputs(arm, scenario, controller, ik, batched=False, q0=q0, qd0=qd0, gains=gains)
    params = _in_precision(arm, scenario, gains, ik, params)
    if controller.uses_guidance:
        raise ValueError("controller: simulate_dense supports trajectory-tracking controllers only")
    check_count("points_per_sample", points_per_sample, 1)
    jref = None if ik is None else joint_reference(ik, scenario.reference.capacity)
    _check_joint_reference(jref, arm.n_dof, scenario.reference.capacity, None)
    scenario = _with_layout(arm, scenario, params, 1)
    q0, qd0 = _as_state(q0, scenario), _as_state(qd0, scenario)
    return _simulate_dense_jit(arm, scenario, controller, gains, jref, q0, qd0, params, points_per_sample)
