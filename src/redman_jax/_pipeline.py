"""The two units of work of a sweep (thesis Fig. 3.10): build a case, run a controller on it.

:func:`build_case` generates, plans and IK-validates the scenarios of every requested seed of one
(arm, case) at once; :func:`run_controller` simulates one controller on all of them at once and
turns the results into table rows and per-sample traces. Both return plain dicts of NumPy arrays
(what :class:`~redman_jax._store.UnitStore` pickles).

Timing (thesis 3.5, SPEC section 10): planning and IK are measured as the warm wall time of one
batched call divided by the number of samples it produced; the controller and the local-minima
estimator likewise, one jitted call over a run's samples one after another divided by their
number (``controller_time_per_sample``, :func:`_lme_time`). These are warm timings; each unit's
compile time is measured by the sweep around it (``DIR/timing.csv``,
:func:`~redman_jax._study.write_timing`).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._distributed import is_multiprocess, to_host
from ._host import put, take, to_device
from ._obstacles import compact_obstacles

__all__ = ["build_case", "run_controller", "make_gains", "shard_batch", "study_shapes", "pad_case"]


def _block(tree):
    return jax.block_until_ready(tree)


def _take(tree, i):
    return jax.tree.map(lambda x: take(x, i), tree)


def shard_batch(tree):
    """Place a batch (leading axis) across every JAX device with a 1-D mesh.

    The batch is split along its leading axis (``NamedSharding(mesh, P("batch"))``); with one device
    this is a no-op. Callers pad the batch to a multiple of the device count first
    (:func:`_pad_batch`). Under ``jit`` the computation then runs data-parallel on all devices,
    those of every process in a ``jax.distributed`` run (:mod:`redman_jax._distributed`), where
    every process must pass the same batch; :func:`~redman_jax.simulate_batch` recognises such a
    batch and lets each device step its own members (``shard_map``).
    """
    devices = jax.devices()
    if len(devices) == 1:
        return tree
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

    mesh = Mesh(np.array(devices), ("batch",))

    multi = is_multiprocess()

    def put(x):
        if not hasattr(x, "ndim") or x.ndim == 0:
            return x
        spec = P("batch", *([None] * (x.ndim - 1)))
        # several processes (jax.distributed): each passes the whole batch from the host and keeps
        # its devices' rows
        return jax.device_put(np.asarray(x) if multi else x, NamedSharding(mesh, spec))

    return jax.tree.map(put, tree)


def _pad_batch(tree, multiple: int):
    """Pad the leading axis to a multiple of ``multiple`` by repeating the last member."""
    leaves = jax.tree.leaves(tree)
    if not leaves:
        return tree, 0
    R = leaves[0].shape[0]
    extra = (-R) % multiple
    if extra == 0:
        return tree, R

    def pad(x):
        if not hasattr(x, "ndim") or x.ndim == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    return jax.tree.map(pad, tree), R


def build_case(arm, case: str, seeds, *, ts: float = 0.01, max_retries: int = 20) -> dict:
    """Scenarios, IK trajectories and timings of one (arm, case) for every seed (batched)."""
    from ._cases import CaseParams, make_scenarios
    from ._ik import IKParams, ik_trajectory, validated_scenarios

    seeds = [int(s) for s in seeds]
    case_params = CaseParams(ts=ts)
    t0 = time.perf_counter()
    scen, ik = validated_scenarios(case, seeds, arm, max_retries, IKParams(), case_params=case_params)
    _block((scen, ik))
    t_build = time.perf_counter() - t0
    n_samples = np.asarray(scen.reference.n_samples)
    total = float(n_samples.sum())
    # Warm re-timing of the final seeds (compiled by now): the per-sample cost the thesis reports.
    used = [int(s) for s in np.asarray(scen.seed_used)]
    t0 = time.perf_counter()
    again = make_scenarios(case, used, arm, params=case_params, max_retries=0)
    _block(again)
    t_plan = time.perf_counter() - t0
    # compiled and run already by the validation's retry rounds (same batch shape): no warm-up call
    t0 = time.perf_counter()
    _block(ik_trajectory(arm, scen, IKParams()))
    t_ik = time.perf_counter() - t0
    return {
        "scenarios": scen,
        "ik": ik,
        "timings": {
            "build_s": t_build,
            "planning_s": t_plan,
            "ik_s": t_ik,
            "t_planning_per_sample": t_plan / max(total, 1.0),
            "t_ik_per_sample": t_ik / max(total, 1.0),
            "total_samples": total,
        },
    }


def make_gains(controller, overrides: dict | None):
    """The controller's default gains with ``{field: value}`` overrides (arrays; unknown -> ValueError)."""
    gains = controller.default_gains()
    if not overrides:
        return gains
    for name, value in overrides.items():
        if not hasattr(gains, name):
            fields = [f for f in getattr(gains, "__dataclass_fields__", {})]
            raise ValueError(f"gains: {type(gains).__name__} has no field {name!r} (fields: {fields})")
        old = getattr(gains, name)
        where = f"gains: {type(gains).__name__}.{name}"
        if isinstance(value, bool) or np.asarray(value).dtype == bool:  # JSON true read as a gain of 1
            raise ValueError(f"{where}: expected a number, got {value!r}")
        try:
            new = jnp.asarray(value, dtype=jnp.asarray(old).dtype)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: expected a number (or an array of shape {jnp.shape(old)}), "
                             f"got {value!r}") from None
        if new.shape != jnp.shape(old):
            raise ValueError(f"{where}: expected shape {jnp.shape(old)}, got {new.shape}")
        if not np.all(np.isfinite(np.asarray(new))):  # every run with it would be NaN
            raise ValueError(f"{where}: expected finite values, got {value!r}")
        gains = eqx.tree_at(lambda g: getattr(g, name), gains, new)
    return gains


def _timing_rows(res, K: int):
    """The run timed (the batch's first that did not diverge, the first if all did) and its valid
    sample indices repeated in turn up to ``K`` rows."""
    div = np.asarray(res.diverged)
    i = int(np.argmin(div)) if div.size else 0
    n_valid = max(int(np.asarray(res.mask[i]).sum()), 1)
    return i, np.arange(K) % n_valid


def _timing_samples(arm, scen, jref, controller, res):
    """The samples the controller is timed at (:func:`~redman_jax._metrics.controller_time_per_sample`):
    the states a run of the batch saved at its sample ends, with the reference samples held then,
    and the environment, as the simulator sets them.

    The run is the batch's first that did not diverge (the first if all did). Its valid samples
    are repeated in turn up to the reference capacity (:func:`_timing_rows`), so the cases that share a compilation
    (:func:`study_shapes`) share the timing program too. The controller state is
    ``controller.init_state`` at each saved state (the velocity OSC's ``q_r``: the state's ``q``;
    the run's own ``q_r`` is not saved); the joint reference (joint space) is the IK's."""
    from ._control_types import ControlState, make_environment
    from ._obstacles import used_bound_jit, with_used
    from ._sim import _goal_sample, _ref_sample, joint_reference

    K = scen.reference.capacity
    i, idx = _timing_rows(res, K)
    s = _take(scen, i)
    ref = s.reference
    dtype = np.asarray(res.q).dtype
    q = put(np.asarray(res.q[i])[idx])
    qd = put(np.asarray(res.qd[i])[idx])
    k = put(idx)
    t = put(idx * float(np.asarray(ref.ts)))
    z = jax.vmap(lambda a, b: controller.init_state(arm, a, b))(q, qd)
    states = ControlState(t=t, q=q, qd=qd, z=z)
    n = arm.n_dof
    if controller.uses_guidance:
        rot = put(np.asarray(res.rot[i])[idx])
        refs = jax.vmap(lambda r: _goal_sample(s.goal_p, s.goal_quat, r, n, dtype))(rot)
    else:
        jr = None if jref is None else joint_reference(tuple(x[i] for x in jref), K)
        refs = jax.vmap(lambda kk: _ref_sample(ref, jr, kk, n, dtype))(k)
    # the bound on the used slots, as the simulator sets it (the padded slots of pad_case skipped)
    env = make_environment(with_used(s.obstacles, used_bound_jit(s.obstacles)), s.goal_p, s.goal_quat)
    return states, refs, env


def study_shapes(cases, ts: float = 0.01, every_case: bool = False) -> dict:
    """``{case: (N, (spheres, boxes, cylinders))}``: the shapes each case is simulated at, from
    the generators' fixed capacities.

    By default, cases whose obstacle families all hold fewer than 32 slots share one shape, the
    largest reference and obstacle capacities among them, so that one compilation per arm and
    controller serves all of them (:func:`run_controller`); a case with a larger family (the
    warehouse's 146 box slots) keeps its own. Its boxes are laid out in groups of slots
    (:func:`~redman_jax._obstacles.slot_steps`) and the null-space policy's pass over them, with its
    derivatives, is the costly part of the program to compile: a program shared with the small
    cases holds their one-slot passes as well. Measured with a run-time switch between the two
    (the small cases folding their few boxes one by one; 7733e19, reverted), velocity and
    acceleration OSC, all five cases in one program per arm: its compilation took about as long as
    the two programs had (9-DOF acceleration OSC, 31 against 18 + 19 s), the small cases' closed
    loop cost 5-10 % more per evaluation, and the default study's tracking units took 733 s against
    730 s (in a run whose unchanged gradient-guided units took 5-9 % longer than in the other).

    ``every_case=True`` (controllers whose vector field has no obstacle policy, the joint-space
    controller: only the collision flag passes over the slots, for a smallest distance, which no
    layout regroups into other sums): one shape for all of ``cases``, the warehouse included. The
    9-DOF joint-space units of the five cases (``sweep --arms 9 --controllers joint_space --jobs
    1``), side by side with the default on a core each, twice with the cores swapped: 51.5 and
    55.8 s against 42.7 and 46.3 s (the warehouse's compilation, 16-19 s, saved); the other cases'
    rows the same bit for bit, the warehouse's to 4e-16 (up to 0.26 % other step counts: its
    reference padded from 320 to 2,000 samples), every outcome the same.

    The gradient-guided runs' guidance field and estimator evaluate every slot at the end effector,
    padded ones included, which costs them run time (8-DOF simple, compacted (4, 1, 1) -> shared
    (4, 5, 21): vector field 91 -> 120 us at batch 20; at (4, 97, 21): 205 us)."""
    from ._cases import CaseParams, obstacle_capacities

    P = CaseParams(ts=ts)
    own = {c: (int(P.case(c).capacity), tuple(obstacle_capacities(c, P))) for c in cases}
    shared = [c for c in cases if every_case or max(own[c][1]) < _SHARED_MAX_SLOTS]
    if shared:
        N = max(own[c][0] for c in shared)
        caps = tuple(max(own[c][1][i] for c in shared) for i in range(3))
        own.update({c: (N, caps) for c in shared})
    return own


_SHARED_MAX_SLOTS = 32


def pad_case(scen, ik, shapes):
    """Scenarios (batched) and IK results (an ``IKResult`` or ``(q, qd, qdd)``) padded to ``shapes = (N, caps)``: reference and joint
    reference rows past the capacity are invalid samples (``mask`` False, the last row repeated;
    the simulator freezes the loop there), obstacle slots are masked. The scene's static case name
    becomes ``"custom"`` (the simulator never reads it), so every case shares one compilation."""
    from ._scenario import pad_rows, pad_scenario

    N, caps = shapes
    N = max(int(N), scen.reference.capacity)
    caps = tuple(max(a, b) for a, b in zip(caps, scen.obstacles.capacities))
    scen = pad_scenario(scen, N, caps)
    q, qd, qdd = (put(x) for x in (ik if isinstance(ik, (tuple, list)) else (ik.q, ik.qd, ik.qdd)))
    ik = (pad_rows(q, N, 1), pad_rows(qd, N + qd.shape[1] - q.shape[1], 1),
          pad_rows(qdd, N + qdd.shape[1] - q.shape[1], 1))
    return scen, ik


def run_controller(arm, scen_payload: dict, ctrl_name: str, gain_overrides: dict | None = None,
                   *, sim_params=None, timing_repeats: int = 5, shapes=None) -> dict:
    """Simulate ``ctrl_name`` on every scenario of a built case; rows and traces for the table.

    ``shapes``: ``(N, caps)``, this case's entry of :func:`study_shapes`; the case is simulated
    padded to it (:func:`pad_case`), so one compilation serves the cases of an arm and controller
    that share it (in one process).
    The rows and traces are the same as without (to rounding: the padded obstacle slots change the
    grouping of the sum over slots)."""
    from ._controllers import CONTROLLERS
    from ._metrics import controller_time_per_sample
    from ._sim import SimParams, simulate_batch

    controller = CONTROLLERS[ctrl_name]()
    gains = make_gains(controller, gain_overrides)
    scen = to_device(scen_payload["scenarios"])
    # active obstacle slots first, capacity cut to the largest count (warehouse: 146 -> <= 97 boxes)
    scen = eqx.tree_at(lambda s: s.obstacles, scen, compact_obstacles(scen.obstacles))
    ik = to_device(scen_payload["ik"])
    N0 = scen.reference.capacity
    if shapes is not None and tuple(shapes[1]) == scen_payload["scenarios"].obstacles.capacities:
        # Obstacles stay compacted where the case keeps its own shapes (warehouse). The small cases
        # share theirs, the guided runs too: their guidance field and estimator evaluate every
        # slot at the end-effector, padded ones included, which costs run time (8-DOF simple,
        # compacted (4, 1, 1) -> shared (4, 5, 21): vector field 91 -> 120 us at batch 20), but
        # much less than a compilation (9-DOF simple in the study: unit 48.2 -> 7.3 s, its run
        # 6.5 -> 6.7 s). Padded to the warehouse's box slots they would cost more (8-DOF simple at
        # (4, 97, 21): 205 us), so the warehouse keeps its own (study_shapes).
        shapes = (shapes[0], scen.obstacles.capacities)
    if shapes is not None:
        scen_sim, ik_sim = pad_case(scen, ik, shapes)
    else:
        scen_sim, ik_sim = scen, (ik.q, ik.qd, ik.qdd)
    params = SimParams() if sim_params is None else sim_params
    ndev = len(jax.devices())
    scen_p, R = _pad_batch(scen_sim, ndev)
    ik_p, _ = _pad_batch(ik_sim, ndev)
    scen_p, ik_p = shard_batch(scen_p), shard_batch(ik_p)
    ik_arg = ik_p if controller.needs_joint_reference else None
    t0 = time.perf_counter()
    # one chunk whatever the cores this process may use: simulate_batch's default splits the batch
    # over them (2 x 10 on 2 free cores, 1 x 20 in a pinned worker), and the batch size changes
    # the rounding, so a unit would depend on where it ran (--jobs 1 against 2, a resumed sweep)
    res = _block(simulate_batch(arm, scen_p, controller, gains, ik=ik_arg, params=params, threads=1))
    t_sim = time.perf_counter() - t0
    res = jax.tree.map(lambda x: x[:R], to_host(res))  # gathered from every process's devices
    if not controller.uses_guidance:  # the padded samples back off (invalid, never reported)
        N1 = scen_sim.reference.capacity
        res = jax.tree.map(lambda x: x[:, :N0] if x.ndim >= 2 and x.shape[1] == N1 else x, res)
    states, refs, env = _timing_samples(arm, scen_sim, None if ik_arg is None else ik_sim, controller, res)
    t_ctrl = controller_time_per_sample(controller, gains, arm, states, refs, env, repeats=timing_repeats)
    t_lme = float("nan")
    field_shift = np.full(R, np.nan)
    if controller.uses_guidance:
        t_lme = _lme_time(scen_sim, res, timing_repeats, params, gains)
        field_shift = _goal_field_shift(scen_sim, params, gains)[:R]
    timings = scen_payload["timings"]
    rows = []
    m = res.metrics
    valid = np.asarray(scen_payload["scenarios"].valid)
    for i in range(R):
        gradient = controller.uses_guidance
        rows.append({
            "case": scen_payload["scenarios"].case,
            "seed": int(np.asarray(scen_payload["scenarios"].seed)[i]),
            "seed_used": int(np.asarray(scen_payload["scenarios"].seed_used)[i]),
            "scenario_valid": bool(valid[i]),
            "controller": ctrl_name,
            "success": bool(m.success[i]),
            "collided": bool(m.collided[i]),
            "joint_limit_hit": bool(m.joint_limit[i]),
            "reached": bool(m.final_pos_err[i] < params.goal_radius),
            "cause": int(m.cause[i]),
            "final_pos_error": float(m.final_pos_err[i]),
            "mean_pos_error": float(m.mean_pos_err[i]),
            "mean_ori_error": float(m.mean_ori_err[i]),
            "n_samples": int(res.n_samples[i]),
            "t_controller_per_sample": t_ctrl,
            "t_ik_per_sample": float("nan") if gradient or not controller.needs_joint_reference
            else timings["t_ik_per_sample"],
            "t_planning_per_sample": float("nan") if gradient else timings["t_planning_per_sample"],
            "t_lme_per_sample": t_lme,
            "min_distance": float(np.min(np.where(res.mask[i], res.min_dist[i], np.inf))),
            "time_to_goal": float(res.time_to_goal[i]),
            "path_length": float(res.path_length[i]),
            "diverged": bool(res.diverged[i]),
            "out_of_steps": bool(res.out_of_steps[i]),
            "n_steps": int(res.n_steps[i]),
            "goal_field_shift": float(field_shift[i]),
            "sim_wall_s": t_sim / R,
        })
    ref = scen_payload["scenarios"].reference
    traces = {
        "seed": np.asarray(scen_payload["scenarios"].seed),
        "t": np.asarray(res.t[0]),
        "mask": res.mask,
        "pos_err": res.pos_err,
        "ori_err": res.ori_err,
        "rot": res.rot,
        "p": res.p.astype(np.float32),
        "min_dist": res.min_dist.astype(np.float32),
        "f_obs": res.f_obs,
    }
    if controller.uses_guidance:
        traces["goal_err"] = res.pos_err
        traces["estimates"] = res.estimates.astype(np.float32)
        traces["estimate_valid"] = res.estimate_valid
    else:
        traces["p_d"] = np.asarray(ref.p).astype(np.float32)
    # where the batch ran: devices of how many processes (jax.distributed) it was sharded over
    return {"rows": rows, "traces": traces, "timings": {"sim_s": t_sim, "t_controller_per_sample": t_ctrl,
                                                        "devices": ndev, "processes": jax.process_count()}}


def _goal_field_shift(scen, params, gains) -> np.ndarray:
    """Per scenario: distance [m] from the goal to the guidance field's minimum near it
    (:func:`~redman_jax._guidance.goal_field_minimum`); above 0.10 m no guided run can succeed."""
    from ._guidance import field_params_or_default

    fp = field_params_or_default(params.field, gains)
    return np.asarray(_field_shifts(scen.goal_p, scen.obstacles, fp))


@eqx.filter_jit
def _field_shifts(goal_p, obstacles, fp):
    """Module-level, so the cases that share their shapes share its compilation."""
    from ._guidance import goal_field_minimum

    return jax.vmap(lambda g, o: goal_field_minimum(g, o, fp)[1])(goal_p, obstacles)


def _lme_time(scen, res, repeats: int, params, gains) -> float:
    """Local-minima-estimator time per sample [s]: one jitted call that runs the update the
    simulation runs at every sample start (Hessian of the total field, estimate, buffer push;
    :func:`~redman_jax._guidance.estimator_update` with the run's field parameters, ``lme_mu``,
    ``lme_max_jump`` and a buffer of ``buffer_size``) along the end-effector positions a run saved
    (as :func:`_timing_samples` picks them), the buffer carried from sample to sample, divided by
    the samples (the least of ``repeats`` calls; ``params``: the run's ``SimParams``)."""
    from ._guidance import VirtualBuffer, field_params_or_default
    from ._metrics import wall_time_per_sample

    K = scen.reference.capacity
    i, idx = _timing_rows(res, K)
    s = _take(scen, i)
    xs = put(np.asarray(res.p[i])[idx])
    buf = VirtualBuffer.empty(params.buffer_size, s.goal_p.dtype)
    fp = field_params_or_default(params.field, gains)
    return wall_time_per_sample(_lme_scan, xs, s.goal_p, s.obstacles, buf, fp, params.lme_mu,
                                params.lme_max_jump, n_samples=K, repeats=repeats)


@eqx.filter_jit
def _lme_scan(xs, goal_p, obstacles, buf, fp, mu, max_jump):
    """The estimator's update at each of ``xs`` in turn, the buffer carried (module-level, so that
    the cases that share their shapes share its compilation)."""
    from ._guidance import estimator_update

    def step(b, x):
        b, x_min, valid = estimator_update(x, goal_p, obstacles, b, fp, mu, max_jump)
        return b, (x_min, valid)

    return jax.lax.scan(step, buf, xs)
