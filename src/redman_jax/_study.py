"""The study: sweeps over arms x cases x seeds x controllers, resumable, with a tidy results table.

Pipeline per (arm, case) (thesis Fig. 3.10, SPEC section 10):

1. generate the scenarios of all requested seeds and plan their trajectories (timed);
2. run the IK on all of them at once and keep, per seed, the first valid one among
   ``seed, seed + 1000, ...`` (timed);
3. simulate every applicable controller on all seeds at once (one ``jit(vmap)`` call per arm, case
   and controller, the batch sharded over every JAX device), the cases with few obstacle slots
   padded to common shapes so that one compilation per arm and controller serves them
   (:func:`~redman_jax._pipeline.study_shapes`);
4. store per-run rows and per-sample traces (atomic writes; a rerun computes only what is missing:
   a unit is keyed by its configuration, a URDF arm by its file's content, a simulation also by
   the solver it integrates with and the shapes it is padded to, so ``--solver``, a change of the
   default or another set of cases recomputes the runs it affects and nothing else).

``jobs > 1`` runs the groups in that many worker processes (``spawn``, the same ones for both
phases): first the builds (one group per arm and case), then the simulations (one group per arm
and controller, its cases in one process so that they share the compilation). XLA compiles on one
thread, so on a CPU machine two workers keep two cores busy through the compile-heavy parts; each
worker is pinned to a core of its own (two unpinned XLA processes contend for both cores: 1.3-1.7x
slower, see :func:`_worker_start`).
The results are the same as with one process, value for value: each unit is a deterministic
function of its configuration, computed under the workers' XLA flags (the command line gives its
own process those too, :func:`adopt_worker_xla_flags`), with its batch in one chunk whatever the
cores (``simulate_batch(threads=1)``), and a phase with one group left still runs in a worker.
Tested on real units (slow) and on stand-ins. (A Python caller whose process started JAX before
``run_sweep`` computes ``jobs=1`` units under its own flags, which round differently.)

``distributed`` (``--distributed``): several processes, one per node, run the same sweep
through ``jax.distributed`` (:mod:`redman_jax._distributed`). Each simulation's batch is sharded
over the devices of all of them; process 0 decides which units are missing, hands every process
the scenarios it stored, and alone writes ``DIR`` (the others may pass any ``--out``).

At the end ``DIR/runs.csv`` and ``DIR/runs.parquet`` (without pandas and pyarrow: no parquet, and an
older one is removed) hold one row per run, ``DIR/traces/`` the
per-sample traces (compressed ``.npz``), ``DIR/config.json`` the configuration, ``DIR/timing.csv``
each unit's wall time and the part of it spent tracing, lowering and compiling (:func:`write_timing`,
summed on the console), and (unless ``--no-figures``) ``DIR/figures/`` and ``DIR/report.md``
compare the numbers with the thesis.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import json
import time
from pathlib import Path

import numpy as np

from ._distributed import barrier, broadcast_object, is_leader
from ._progress import Progress
from ._scenario import CASES
from ._store import UnitStore, atomic_write_bytes, atomic_write_text, config_hash

SEED_MAX = 2**31 - 1  # a seed and its retries seed + 1000 k become JAX PRNG keys (int32 without x64)

__all__ = ["SweepConfig", "run_sweep", "load_runs", "RUN_COLUMNS", "GRADIENT_CASES", "arm_from_spec"]

GRADIENT_CASES = ("agriculture", "warehouse", "simple")
THESIS_CONTROLLERS = ("joint_space", "velocity", "acceleration", "gradient")

RUN_COLUMNS = (
    "arm", "case", "seed", "seed_used", "controller", "success", "collided", "joint_limit_hit",
    "reached", "final_pos_error", "mean_pos_error", "mean_ori_error", "n_samples",
    "t_controller_per_sample", "t_ik_per_sample", "t_planning_per_sample", "t_lme_per_sample",
    "min_distance", "time_to_goal", "path_length", "diverged", "out_of_steps", "n_steps",
    "goal_field_shift",
)


def arm_from_spec(spec: str, option: str = "--arms"):
    """``"7"``/``"8"``/``"9"`` -> the thesis arm; ``"urdf:PATH:TIP"`` -> :func:`from_urdf`.
    ``option``: the command-line option named in the error message."""
    from ._robot import thesis_arm

    spec = str(spec).strip()
    if spec.startswith("urdf:"):
        from ._urdf import from_urdf

        path, tip = _urdf_parts(spec, option)
        return from_urdf(path, tip_link=tip)
    try:
        dof = int(spec)
    except ValueError:
        raise ValueError(f"{option}: {spec!r} is neither a thesis DOF (7, 8, 9) nor urdf:PATH:TIP") from None
    return thesis_arm(dof)


def _urdf_parts(spec: str, option: str = "arms") -> tuple[str, str]:
    """``(PATH, TIP_LINK)`` of a ``urdf:PATH:TIP_LINK`` arm spec (``ValueError`` naming ``option``
    if malformed)."""
    parts = spec.split(":")
    if len(parts) != 3 or not parts[1] or not parts[2]:
        raise ValueError(f"{option}: URDF arms are given as urdf:PATH:TIP_LINK, got {spec!r}")
    return parts[1], parts[2]


def _arm_label(spec: str) -> str:
    if spec.startswith("urdf:"):
        path, tip = _urdf_parts(spec)
        return Path(path).stem + "-" + tip
    return f"{spec}dof"


def _check_arm_spec(spec: str) -> None:
    """``arms`` entries: ``7``, ``8``, ``9`` or ``urdf:PATH:TIP_LINK`` with an existing file."""
    if spec in ("7", "8", "9"):
        return
    if not spec.startswith("urdf:"):
        raise ValueError(f"arms: {spec!r} is neither 7, 8, 9 nor urdf:PATH:TIP_LINK")
    path, _ = _urdf_parts(spec)
    if not Path(path).is_file():
        raise ValueError(f"arms: URDF file {path!r} of {spec!r} not found")


def _arm_identity(spec: str):
    """What identifies an arm in a unit's key: the spec of a thesis arm; for a URDF arm also the
    file's content (an edited file is another arm), read when the key is made."""
    if not spec.startswith("urdf:"):
        return spec
    import hashlib

    return {"spec": spec, "sha256": hashlib.sha256(Path(_urdf_parts(spec)[0]).read_bytes()).hexdigest()}


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep runs. ``study`` is a sweep with the thesis defaults."""

    out: str = "results"
    arms: tuple[str, ...] = ("7", "8", "9")
    cases: tuple[str, ...] = CASES
    seeds: tuple[int, ...] = tuple(range(1, 21))
    controllers: tuple[str, ...] = THESIS_CONTROLLERS
    gradient_cases: tuple[str, ...] = GRADIENT_CASES
    gains: dict | None = None
    ts: float = 0.01
    max_retries: int = 20
    solver: str = "auto"
    figures: bool = True
    progress: bool = True
    jobs: int = 1
    distributed: bool = False

    def __post_init__(self):
        from ._controllers import CONTROLLERS

        for name in ("arms", "cases", "controllers", "seeds"):
            values = tuple(getattr(self, name))
            if not values:
                raise ValueError(f"{name}: empty")
            if len(set(values)) != len(values):
                raise ValueError(f"{name}: repeated entries in {values}")
        for c in self.cases:
            if c not in CASES:
                raise ValueError(f"cases: unknown case {c!r}; choose from {list(CASES)}")
        for c in self.controllers:
            if c not in CONTROLLERS:
                raise ValueError(f"controllers: unknown controller {c!r}; choose from {sorted(CONTROLLERS)}")
        if not self.seeds or any(int(s) < 0 for s in self.seeds):
            raise ValueError(f"seeds: need non-negative integers, got {self.seeds}")
        if self.max_retries < 0 or 1000 * self.max_retries > SEED_MAX:  # not even seed 0 could retry
            raise ValueError(f"max_retries: must be 0 to {SEED_MAX // 1000} (the retries seed + 1000 k "
                             f"must stay below 2**31), got {self.max_retries}")
        top = SEED_MAX - 1000 * self.max_retries  # the retries are seed + 1000 k, k <= max_retries
        if max(int(s) for s in self.seeds) > top:
            raise ValueError(f"seeds: at most {top} with max_retries={self.max_retries} (the retries "
                             f"seed + 1000 k must stay below 2**31), got {max(int(s) for s in self.seeds)}")
        idle = [c for c in self.cases if not self.controllers_for(c)]
        if idle:  # its scenarios would be built for nothing
            raise ValueError(f"cases: {', '.join(idle)} runs none of the controllers {', '.join(self.controllers)} "
                             f"(gradient runs on {', '.join(self.gradient_cases)} only); drop it or add a controller")
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise ValueError(f"out: {str(self.out)!r} is a file, not a folder")
        if not (0 < self.ts <= 0.1):
            raise ValueError(f"ts: sample time must be in (0, 0.1] s, got {self.ts}")
        if not isinstance(self.jobs, int) or self.jobs < 1:
            raise ValueError(f"jobs: need a positive number of worker processes, got {self.jobs!r}")
        if self.distributed and self.jobs != 1:
            raise ValueError(f"jobs: a distributed sweep runs one process per node (jobs=1), "
                             f"got {self.jobs}")
        from ._sim import SOLVER_CHOICES

        if self.solver not in SOLVER_CHOICES:
            raise ValueError(f"solver: unknown solver {self.solver!r}; choose from {list(SOLVER_CHOICES)}")
        labels = {}
        for a in self.arms:
            _check_arm_spec(a)
            other = labels.setdefault(_arm_label(a), a)
            if other != a:  # their unit files and table rows would be one arm's
                raise ValueError(f"arms: {other!r} and {a!r} share the label {_arm_label(a)!r} (file stem "
                                 "and tip link); rename one of the files")
        if self.gains is not None:
            if not isinstance(self.gains, dict):
                raise ValueError(f"gains: expected {{controller: {{gain: value}}}}, got {type(self.gains).__name__}")
            from ._pipeline import make_gains

            for ctrl, g in self.gains.items():
                if ctrl not in CONTROLLERS or not isinstance(g, dict):
                    raise ValueError(f"gains: expected {{controller: {{gain: value}}}}, got key {ctrl!r}")
                make_gains(CONTROLLERS[ctrl](), g)  # unknown names or shapes fail now, not after the builds

    @classmethod
    def from_args(cls, args, *, study: bool) -> "SweepConfig":
        from ._cli import parse_int_list, parse_name_list
        from ._controllers import CONTROLLERS

        seeds = parse_int_list(args.seeds, "seeds")
        distributed = bool(getattr(args, "distributed", False))
        # distributed: one process per node, so 'auto' is 1 (any other count is refused below)
        jobs = 1 if distributed and args.jobs in (None, "auto") else _jobs(args.jobs)
        common = dict(out=args.out, seeds=seeds, max_retries=args.max_retries,
                      figures=not args.no_figures, progress=not args.quiet, jobs=jobs,
                      distributed=distributed)
        if study:
            return cls(**common)
        arms = tuple(dict.fromkeys(a.strip() for a in args.arms.split(",") if a.strip()))
        cases = parse_name_list(args.cases, "cases", CASES)
        controllers = parse_name_list(args.controllers, "controllers", tuple(sorted(CONTROLLERS)))
        gains = None
        if args.gains:
            try:
                gains = json.loads(Path(args.gains).read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ValueError(f"--gains: cannot read {args.gains!r}: {e}") from None
        return cls(arms=arms, cases=cases, controllers=controllers, gains=gains, ts=args.ts,
                   solver=args.solver, **common)

    def controllers_for(self, case: str) -> tuple[str, ...]:
        return tuple(c for c in self.controllers if c != "gradient" or case in self.gradient_cases)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("progress")
        d.pop("figures")
        d.pop("jobs")
        d.pop("distributed")
        d["precision"] = _precision()
        return d


def _precision() -> str:
    """The sweep's floating precision: ``"float64"``, or ``"float32"`` under ``REDMAN_JAX_X64=0``
    (the workers inherit the variable, so they compute in the same one)."""
    import jax

    return "float64" if jax.config.jax_enable_x64 else "float32"


def _scenario_key(cfg: SweepConfig, arm: str, case: str) -> str:
    """The key of a build unit, which every simulation unit of its scenes includes."""
    return scenario_key(arm, case, cfg.seeds, cfg.ts, cfg.max_retries, _precision())


def scenario_key(arm: str, case: str, seeds, ts, max_retries, precision: str = "float64") -> str:
    """The key of the build unit of ``arm`` (its spec) and ``case`` in a sweep of these settings
    (also rebuilt from a folder's ``config.json`` by the report). A float32 sweep draws other
    scenes and integrates at other tolerances: its precision is in the key (a float32 sweep in a
    float64 folder reused the float64 units); float64's keys are kept as they were."""
    key = {"arm": _arm_identity(arm), "case": case, "seeds": list(seeds), "ts": ts,
           "max_retries": max_retries, "v": 1}
    if precision != "float64":
        key["precision"] = precision
    return config_hash(key)


def _sim_shapes(cfg: SweepConfig, case: str, ctrl: str):
    """The shapes ``(N, (spheres, boxes, cylinders))`` a simulation unit pads its case to: shared
    with the other cases of the sweep that run ``ctrl``, all of them for a controller whose control
    law does not read the obstacles (``reads_obstacles``: joint space, with no null-space policy),
    the small ones otherwise (:func:`~redman_jax._pipeline.study_shapes`), so they depend on which
    cases the sweep holds."""
    from . import _pipeline as pipe
    from ._controllers import CONTROLLERS

    cases = [c for c in cfg.cases if ctrl in cfg.controllers_for(c)]
    every = not CONTROLLERS[ctrl]().reads_obstacles
    return pipe.study_shapes(cases, cfg.ts, every_case=every)[case]


# SPEC section 9: a gradient-guided run ends 6 s after its start or after 1 s held at the goal
GUIDANCE_HORIZON_S, GUIDANCE_HOLD_S = 6.0, 1.0


def _sim_params(cfg: SweepConfig):
    """The simulator's options of a sweep: its solver, and the gradient-guided horizon and hold
    in samples of ``cfg.ts`` (``SimParams`` counts samples: at ``--ts 0.02`` its 600 and 100
    would be 12 s and 2 s)."""
    from ._sim import SimParams

    return SimParams(solver=cfg.solver, guidance_samples=max(1, round(GUIDANCE_HORIZON_S / cfg.ts)),
                     hold_samples=max(1, round(GUIDANCE_HOLD_S / cfg.ts)))


def _run_key(cfg: SweepConfig, arm: str, case: str, ctrl: str) -> str:
    """The key of a simulation unit: its scenarios, controller, gains, the solver it integrates
    with (resolved: ``"auto"`` names the solver it picks for ``ctrl``) and the shapes it is padded
    to (:func:`_sim_shapes`; padding changes results to rounding), so a results folder of another
    solver or another set of cases is recomputed, not mixed in."""
    from ._controllers import CONTROLLERS
    from ._sim import solver_name

    gains = (cfg.gains or {}).get(ctrl)
    params = _sim_params(cfg)
    controller = CONTROLLERS[ctrl]()
    solver = solver_name(params, controller)
    N, caps = _sim_shapes(cfg, case, ctrl)
    key = {"scen": _scenario_key(cfg, arm, case), "ctrl": ctrl, "gains": gains,
           "solver": solver, "shapes": [int(N), [int(c) for c in caps]], "v": 1}
    horizon = [params.guidance_samples, params.hold_samples]
    if controller.uses_guidance and horizon != [600, 100]:  # other sample times (the default's keys kept)
        key["guidance_samples"] = horizon
    return config_hash(key)


def _jobs(value) -> int:
    """``--jobs``: an integer >= 1, or ``auto`` (the default): 2 worker processes on a CPU machine
    with at least 2 cores, else 1 (accelerators: one process owns the device)."""
    if value in (None, "auto"):
        import os

        import jax

        if jax.default_backend() != "cpu":
            return 1
        return 2 if (os.cpu_count() or 1) >= 2 else 1
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"--jobs: expected a positive integer or 'auto', got {value!r}") from None
    if n < 1:
        raise ValueError(f"--jobs: expected a positive integer or 'auto', got {value!r}")
    return n


def _units(cfg: SweepConfig):
    """The two phases of a sweep, each ``{group: [(kind, arm, case, ctrl, name, key), ...]}``:
    the scenario builds, one group per (arm, case), then the simulations, one group per (arm,
    controller) over its cases. A group runs in one process, so the simulations of an arm and
    controller share one compilation (every case is padded to the same shapes,
    :func:`~redman_jax._pipeline.run_controller`)."""
    builds, sims = {}, {}
    for arm in cfg.arms:
        label = _arm_label(arm)
        for case in cfg.cases:
            builds[(arm, case)] = [("scen", arm, case, None, f"scen_{label}_{case}",
                                    _scenario_key(cfg, arm, case))]
        for ctrl in cfg.controllers:
            g = [("run", arm, case, ctrl, f"run_{label}_{case}_{ctrl}", _run_key(cfg, arm, case, ctrl))
                 for case in cfg.cases if ctrl in cfg.controllers_for(case)]
            if g:
                sims[(arm, ctrl)] = g
    return builds, sims


# --------------------------------------------------------------------------------------------
# where a sweep's time goes: each unit's wall time and the part of it spent compiling

_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration",
                   "/jax/core/compile/backend_compile_duration")
_compile_spans: list[tuple[float, float]] = []  # (start, end), perf_counter seconds, this process
_listening = False


def _listen_to_compiles() -> None:
    """Record the span of every trace, lowering and XLA compilation in this process (once)."""
    global _listening
    if _listening:
        return
    from jax import monitoring

    def on_duration(event, seconds, **kwargs):
        if event in _COMPILE_EVENTS:  # reported as the span ends
            end = time.perf_counter()
            _compile_spans.append((end - seconds, end))

    monitoring.register_event_duration_secs_listener(on_duration)
    _listening = True


def union_seconds(spans) -> float:
    """Total length of the union of ``(start, end)`` spans: a jit traced inside another one's trace
    (and its lowering) lies within the outer span and counts once."""
    total, start, end = 0.0, None, None
    for s, e in sorted(spans):
        if end is None or s > end:
            total += 0.0 if end is None else end - start
            start, end = s, e
        else:
            end = max(end, e)
    return total + (0.0 if end is None else end - start)


TIMING_COLUMNS = ("unit", "kind", "arm", "case", "controller", "wall_s", "compile_s")


def _timing_path(store: UnitStore, name: str) -> Path:
    return store.root / "timing" / f"{name}.json"


def _run_unit(cfg: SweepConfig, store: UnitStore, arms: dict, unit) -> None:
    """Compute and save one unit; its wall time and compile time go to ``DIR/timing/NAME.json``."""
    _listen_to_compiles()
    _compile_spans.clear()
    t0 = time.perf_counter()
    _compute_unit(cfg, store, arms, unit)
    wall = time.perf_counter() - t0
    kind, arm_spec, case, ctrl, name, key = unit
    record = {"key": key, "wall_s": wall, "compile_s": union_seconds(_compile_spans)}
    if _leader(cfg):
        atomic_write_text(_timing_path(store, name), json.dumps(record))


def _compute_unit(cfg: SweepConfig, store: UnitStore, arms: dict, unit) -> None:
    from . import _pipeline as pipe

    kind, arm_spec, case, ctrl, name, key = unit
    if arm_spec not in arms:
        arms[arm_spec] = arm_from_spec(arm_spec)
    arm = arms[arm_spec]
    if kind == "scen":
        payload = pipe.build_case(arm, case, cfg.seeds, ts=cfg.ts, max_retries=cfg.max_retries)
    else:
        scen_name = f"scen_{_arm_label(arm_spec)}_{case}"
        scen = store.load(scen_name) if _leader(cfg) else None
        if cfg.distributed:  # process 0's stored scenes in every process
            scen = broadcast_object(scen)
        payload = pipe.run_controller(arm, scen, ctrl, (cfg.gains or {}).get(ctrl),
                                      sim_params=_sim_params(cfg), shapes=_sim_shapes(cfg, case, ctrl))
        payload["rows"] = [dict(r, arm=_arm_label(arm_spec)) for r in payload["rows"]]
    if _leader(cfg):
        store.save(name, key, payload)


def _leader(cfg: SweepConfig) -> bool:
    """Whether this process writes the results folder: always, but in a distributed sweep
    (:mod:`redman_jax._distributed`) only process 0."""
    return not cfg.distributed or is_leader()


def _run_group(cfg: SweepConfig, units: list, report=None) -> None:
    """Run ``units`` (the missing units of one group, in order); ``report(name, seconds)`` after
    each (the progress bar; in a worker, the parent's queue)."""
    import jax

    store = UnitStore(Path(cfg.out))
    arms = {}
    for unit in units:
        t0 = time.perf_counter()
        _run_unit(cfg, store, arms, unit)
        if report is not None:
            report((unit[4], time.perf_counter() - t0))
    # Every XLA CPU executable keeps its code in memory mappings: about 2,000-2,600 per simulation,
    # and a process that kept every group's programs reached Linux's vm.max_map_count (65,530)
    # after about 25 units ("LLVM compilation error: Cannot allocate memory"; a full study on 2
    # cores lost a worker that way twice). The units of a group share their simulation's program;
    # dropping the caches after the group returns the mappings.
    jax.clear_caches()


# expected relative cost of a group, to start the long ones first
_CASE_WEIGHT = {"warehouse": 3, "agriculture": 3, "simple": 2, "welding": 2, "inspection": 1}
_CTRL_WEIGHT = {"gradient": 4, "acceleration": 3, "velocity": 3, "velocity_original": 3}


def _weight(key) -> float:
    return _CASE_WEIGHT.get(key[1], 0) + _CTRL_WEIGHT.get(key[1], 1)


def run_sweep(cfg: SweepConfig, *, _worker_init=None) -> Path:
    """Run (or resume) a sweep; returns the results folder. (``_worker_init``: a picklable callable
    each worker process runs first; tests install their stand-in units with it.)

    The scenario builds run first, then the simulations (:func:`_units`), with ``jobs > 1`` in the
    same worker processes (:func:`_worker_pool`, closed before the results are written). Every
    group ends with ``jax.clear_caches()`` (see :func:`_run_group`): with ``jobs=1`` the groups run
    in the calling process, whose other jitted functions then compile again on their next call.
    """
    out = Path(cfg.out)
    store = UnitStore(out)
    leader = _leader(cfg)
    phases = _units(cfg)
    progress = Progress(sum(len(g) for ph in phases for g in ph.values()), "units",
                        enabled=cfg.progress and leader)
    with contextlib.ExitStack() as stack:
        workers = None  # started for the first phase with work, kept for the next
        for groups in phases:
            todo = {}
            for gk, group in groups.items() if leader else ():
                missing = [u for u in group if not store.has(u[4], u[5])]
                if len(missing) < len(group):
                    progress.skip(len(group) - len(missing))
                if missing:
                    todo[gk] = missing
            if cfg.distributed:  # every process runs process 0's list of missing units, in its order
                todo = broadcast_object(todo)
            if cfg.jobs > 1 and todo:  # even one group: in-process units would round otherwise
                if workers is None:
                    workers = stack.enter_context(_worker_pool(cfg, _worker_init))
                _run_parallel(cfg, todo, progress, workers)
            else:
                for units in todo.values():
                    _run_group(cfg, units, lambda done: progress.advance(note=f"{done[0]} ({done[1]:.1f}s)"))
    if cfg.distributed:
        barrier("redman_jax.run_sweep: units done")
    if leader:
        _write_results(cfg, out, store)
    if cfg.distributed:  # the others wait for process 0's table and report, then all leave together
        barrier("redman_jax.run_sweep: results written")
    return out


def _write_results(cfg: SweepConfig, out: Path, store: UnitStore) -> None:
    """The table, then the configuration that made it (written together at the end: a sweep
    interrupted in a folder of an earlier one leaves that one's table and configuration, which
    ``plot`` reads as a pair), the timing, and the figures and report."""
    rows = collect_rows(cfg, store)
    write_table(out, rows)
    atomic_write_text(out / "config.json", json.dumps(cfg.to_json(), indent=2, default=str))
    timing = write_timing(cfg, store)
    if cfg.progress:
        print(timing_summary(timing), flush=True)
    if cfg.figures:
        render_report(out)


def render_report(out, make=None) -> None:
    """Write the figures and ``report.md`` of the results folder ``out``
    (:func:`~redman_jax._report.make_report`, or ``make(out)``, a picklable callable).

    On a CPU backend in a spawned process started with :data:`REPORT_XLA_FLAGS` (the workers'
    emitter flags and LLVM's level 0; not :data:`LOOP_XLA_FLAGS`: the report compiles much and
    runs little) added to the ``XLA_FLAGS`` this process had before it adopted the workers' (so
    ``study`` and ``plot`` draw with the same flags): the report's figures rebuild scenes and
    re-simulate, compiling several programs. ``redman-jax plot`` on the results folder of a
    9-DOF sweep of the three tracking controllers (2 idle cores, two runs each, alternating):
    36.8 and 37.0 s with the emitter flags, 47.6 and 48.6 s with ``make_report`` in the calling
    process and JAX's own flags; the default study's folder: 34.2 and 37.0 s against 44.2 and 47.8
    s; the same ``report.md``. The rows, the table and the traces are written before and do not
    change; the figures can differ by rounding from a report drawn with other flags, and Fig.
    3.7's perfect-controller path visibly so (its local-minima estimates move). Elsewhere (an
    accelerator, whose memory a second process would claim too) in this process.

    Two such processes draw the figures (:func:`~redman_jax._report.draw_figures`): one the
    figures with a ``prefetch`` (Fig. 3.6's step responses, which compile and simulate the most),
    the other the rest; then one of them writes ``report.md`` from what both drew. In one process
    the prefetch computes in a thread beside the other figures, and the two share Python's lock.
    Each is spawned pinned to a core of its own (as the workers, :func:`_worker_pool`; unpinned,
    the two took 23 s each where one after the other they take 21 and 19 s), and with fewer than
    two cores one process draws all. The default study's folder (``redman-jax plot``, 2 idle
    cores, alternating, twice): one process 32.8 and 31.2 s, two 29.7 and 27.2 s; the same
    figures, byte for byte, and the same ``report.md``."""
    import jax

    custom = make is not None
    if make is None:
        from ._report import make_report as make
    if jax.default_backend() != "cpu":
        make(out)
        return
    pins = [] if custom else _worker_cores(2)
    if len(set(pins)) < 2:  # one process, not pinned (as before the report was split)
        pins = []
    flags = _worker_xla_flags(REPORT_XLA_FLAGS, base=_FLAGS_BEFORE_ADOPTION)
    with _pinned_pool(2 if pins else 1, pins, flags) as (pool, pinned):
        if not pins:
            pool.submit(make, out).result()  # re-raises the report's error here
            return
        from ._report import HOOKS, draw_figures

        apart = tuple(spec.file for spec in HOOKS if spec.prefetch is not None)
        parts = [pinned.submit(functools.partial(draw_figures, out, exclude=apart)),
                 pinned.submit(functools.partial(draw_figures, out, only=apart))]
        drawn = {}
        for part in parts:
            drawn.update(part.result())
        pool.submit(make, out, drawn=drawn).result()


def _worker_cores(jobs: int) -> list[int]:
    """The CPU cores to pin ``jobs`` workers to, one each: the cores this process may run on, in
    turn (more workers than cores share them); none where the platform cannot pin (not Linux).

    Every worker is pinned, a lone one too (the last group of a resumed sweep): its XLA thread
    pool is then one thread wide, and a pool two threads wide rounds some results differently
    (7-DOF simple case, velocity OSC: 5 values of a row in the last digits), so a unit would depend
    on how many workers the sweep ran."""
    import os

    try:
        cores = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return []
    return [cores[i % len(cores)] for i in range(jobs)] if cores else []


def _pin_threads(core: int) -> bool:
    """Pin every thread of this process to CPU ``core`` (``os.sched_setaffinity(0, ...)`` pins only
    the calling thread; threads started later inherit the affinity of the thread that starts them).
    False where the platform cannot (no ``sched_setaffinity`` or no ``/proc/self/task``)."""
    import os

    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return False
    for tid in tids:
        try:
            os.sched_setaffinity(int(tid), {core})
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except (AttributeError, OSError):
            return False
    return True


def _thread_affinities() -> list[set[int]]:
    """The cores each thread of this process may run on (threads that end meanwhile are left out;
    Linux: ``/proc/self/task``)."""
    import os

    out = []
    for tid in os.listdir("/proc/self/task"):
        try:
            out.append(set(os.sched_getaffinity(int(tid))))
        except ProcessLookupError:
            continue
    return out


def _worker_start(cores, init, progress) -> None:
    """Worker initializer: pin this process to a core of its own (taken from the queue ``cores``),
    keep the parent's ``progress`` queue, then run ``init``.

    Why: each process's XLA CPU runtime keeps a thread pool as wide as the cores it may run on
    when jax is imported (it runs independent operations of a program at once), and two unpinned
    workers contend for both cores. Measured (2-core CPU, two processes at once, each pinned with
    ``taskset``: the 8-DOF warehouse velocity and acceleration simulations of 20 seeds, repeated in
    both orders): warm 37.7 and 35.3 s unpinned against 25.0 and 27.7 s pinned, cold (compilation
    included) 80-86 s against 46-50 s. Alone, unpinned was faster (19.7 against 25.0 s), but a lone
    worker is pinned too, for results that do not depend on the number of workers
    (:func:`_worker_cores`). ``taskset`` pins before jax is imported, so the pool is one thread
    wide; a worker imports jax before this initializer runs, so :func:`_worker_pool` spawns the
    workers from a thread pinned to one core (:func:`_one_core_while_spawning`) to get that."""
    global _PROGRESS

    _exit_with_parent()
    # one entry per worker the pool may start (cfg.jobs)
    if cores is not None and not cores.empty():
        _pin_threads(cores.get())
    _PROGRESS = progress
    if init is not None:
        init()
    tune_gc()


def _exit_with_parent() -> None:
    """In a process ``multiprocessing`` started (a worker): leave as soon as the parent is gone. A
    sweep's main process killed alone (``kill -9``, the OOM killer, a scheduler) otherwise left its
    workers computing their groups and then idling for ever (about 450 MB each)."""
    import multiprocessing as mp
    import os
    import threading

    parent = mp.parent_process()
    if parent is None:
        return

    def watch():
        parent.join()  # returns when the parent's end of the pipe closes: it exited or was killed
        os._exit(1)

    threading.Thread(target=watch, name="redman-jax-exit-with-parent", daemon=True).start()


@contextlib.contextmanager
def _one_core_while_spawning(core):
    """Run the body with the calling thread pinned to ``core`` (None: unchanged), then restore.

    A spawned process starts with the affinity of the thread that spawns it, and jax sizes its XLA
    CPU thread pool by the cores the process may use when jax is imported (an intra-op pool of
    that width; later pinning does not shrink it). Spawned from a thread pinned to one core, each
    worker gets a one-thread pool and runs a program's operations in sequence on its own core,
    which is what ``taskset`` gave in the measurement of :func:`_worker_start`. With the pool two
    threads wide but both threads pinned to one core, every hand-off between them is a context
    switch (2-core CPU, 9-DOF simple case, joint space, 20 seeds, warm, one process: 4.3 s
    ``taskset -c 0``, 6.1 s unpinned, 6.4 s two-wide pool pinned to one core after import)."""
    import os

    if core is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {core})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


# XLA flags the workers and the report start with (each unless XLA_FLAGS names it already). Measured on one core,
# as a worker runs (9-DOF simple case, 20 seeds, compile s / warm s, default -> these flags): joint
# space 10.4 / 4.42 -> 6.3 / 3.58, acceleration 15.5 / 9.68 -> 8.1 / 7.80, velocity
# -> 9.53 / 7.88 warm. The older (LLVM IR) loop emitters compile about twice as fast and, at these
# small batches, run faster too; YNNPACK's fusions of the small dots cost more per call than XLA's
# own. Results differ from the default flags' by rounding only (the same steps on these runs).
# They suit these small batches only: at batch 1024 (benchmarks/bench_controllers.py, 2 cores) they
# are about 2x slower (velocity OSC 9.4 -> 16.0, original velocity OSC 20.7 -> 42.7 us per state).
# bench_sim.py --xla-flags study runs the simulation benchmark with them (20 seeds, 2 threads of 10:
# the speed-up over SciPy from min 39x / median 77x to 48x / 112x in one run each, though the three
# agriculture rows came out slower, e.g. velocity 181x -> 148x).
# Per unit, the fusion emitters (the XLA default) run the obstacle-heavy units faster but compile
# them about twice as long, so the flags win in every unit of the study, cold: the 9-DOF sweep of
# all cases, one process per core, both at once (s, unit wall = compiling + running, these flags
# against --xla_cpu_use_fusion_emitters=true): warehouse gradient-guided 148.5 = 35.9 + 112.6
# against 163.2 = 68.3 + 94.9, agriculture gradient-guided 103.6 against 121.5, warehouse
# acceleration 57.6 against 67.1; all 18 units 597 against 686. The compile time is the emitters'
# (9-DOF velocity OSC, simple case, one core: 7.9 s with both flags, 8.1 s with the emitters off
# alone, 16.7 s with YNNPACK's fusions off alone).
# Measured and left off: --xla_cpu_multi_thread_eigen=false (each dot on the calling thread instead
# of Eigen's pool). At batch 10 on one core it makes the joint-space vector field 8-15 % cheaper,
# at batch 20 no different; on the 9-DOF sweep of the three tracking controllers (5 builds + 15
# simulations, these two workers, idle machine, one run each) units 353.0 -> 361.2 s, of which
# running 212.4 -> 207.3 s, wall 206 -> 212 s: no gain. And its dots round differently: the IK
# validation kept other retry seeds for 5 of the 100 scenes and 6 of the 300 runs changed success.
EMITTER_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_experimental_ynn_fusion_type=")

# Besides, the workers hoist every while loop XLA can compile into one function (the CPU backend's
# SmallWhileLoopHoistingPass, whose byte threshold is 1 kB by default): a simulation's stepping loop
# then runs as one compiled function instead of a sequence of kernels (thunks) per step, which at
# these batches (one core, 20 seeds) is most of a step's cost; LLVM's optimisation level 1 (of 3)
# takes back about a third of the longer compilation of those large functions and ran as fast.
# A loop holding a custom call, scatter, sort or custom fusion stays as it was: with YNNPACK's
# fusions on (the emitter flags turn them off) every loop with a dot would.
# Measured (one core each, side by side, 2 runs each with the cores swapped; units of the study on
# its stored scenes): 7-DOF simple velocity OSC warm 6.6-8.4 -> 4.0-4.2 s, compiling 15.6-21.0 ->
# 35.1-44.0 s with the hoisting alone, 24.0 s with level 1 too (warm 4.1 s); 8-DOF agriculture
# gradient-guided warm 47.0/47.3 -> 20.5/21.6 s, compiling 32.4-32.8 -> 52.7-57.1 s, the unit
# 81.2/83.9 -> 76.9/78.7 s with the hoisting alone (with level 1: 22.4, 54.7, 79.7 s). The 9-DOF sweep (5 builds, 18 simulations, 2 workers, one after the
# other on an idle machine): 330 -> 281 s; units 612.8 -> 506.5 s, of which compiling 224.8 ->
# 261.0 s. Rounding differs (other machine code), as with the emitter flags above.
# And LLVM drops its ScalarEvolution cache wholesale after each loop it unrolls. By default it
# forgets the cached results of the top-most loop around the unrolled one, walking all of it; a
# hoisted stepping loop holds the whole step, and each of its many small fused loops unrolled in
# turn walks it again: quadratic, the largest single cost in profiles of these compilations
# (ScalarEvolution, mostly visitAndClearUsers and forgetLoop, 18 % of a 9-DOF warehouse
# gradient-guided unit's process time; 12 % with the option, the rest from LoopRotate, below).
# ``-forget-scev-loop-unroll=true`` (LLVM's own option, passed through the extra options; its help:
# "sometimes preferred to reduce compile time") forgets everything at once instead. A cache only,
# so the machine code is the same: the units' traces and the study's table are equal to the bit.
# Measured (one core each, side by side, units of the study on its stored scenes, backend compile
# s): 9-DOF agriculture velocity OSC 31.0 / 32.9 -> 23.9 / 26.4 (unit 46.8 / 48.3 -> 40.1 / 43.0
# s), 8-DOF agriculture acceleration 23.8 -> 19.1 (unit 39.8 -> 35.2 s), 9-DOF warehouse
# gradient-guided 51.6 -> 48.3; the whole study's compiling 909 / 927 -> 677 / 753 s (fresh clones
# of 43ddbbd and 960d1e1, then 51d9de7 and 57c2f14; README).
# And LLVM inlines no call that it may keep (``-inline-threshold=-20000``: a call is inlined where
# its cost is under the threshold, a function's only call gets a 15,000 bonus, so none is). XLA
# marks a hoisted loop's body, condition, reductions and other nested computations always-inline,
# which the threshold does not touch; what it keeps as calls are the tiled matrix-vector kernels of
# the dots, one function per shape and layout. The 9-DOF agriculture velocity OSC's stepping
# function calls 7 such kernels from 81 places; inlined, each place held a copy of its tiled loops
# inside the step, and for every loop it rotates LoopRotate forgets the ScalarEvolution results of
# the whole top-most loop, the step (a gdb sample of that compilation caught it there;
# ``visitAndClearUsers`` 5.8 % of a profile of that unit's process, about 2.8 s; without inlining
# 2.1 % of a profile of the unit and a warm rerun, about 1.1 s). Not inlined, the same arithmetic:
# the units' traces are equal to the bit. Measured (one core each, side by side, units of the study
# on their stored scenes; backend compile s of the simulation, warm run s in brackets): 9-DOF
# warehouse gradient-guided 52.3 -> 43.3 (65.2 -> 65.3), 9-DOF simple gradient-guided 27.8 -> 25.6,
# 9-DOF agriculture velocity OSC 31.2 -> 26.4 (15.5 -> 15.2) and 27.5 -> 24.7 (13.1 -> 13.3); whole
# units (sweeps of one case on one core, traced, lowered and compiled s): 8-DOF agriculture
# acceleration OSC 28.3 -> 27.4 and 23.7 -> 23.2, 9-DOF simple joint space 16.5 -> 16.5 and 17.7 ->
# 17.8, and their scenario builds 0.9-1.4 s longer (4 pairs, 10.3-14.5 s). Without LoopRotate
# instead (``-rotation-max-header-size=0``) the warehouse guided unit compiled in 42.9 s but ran
# 103.4 s warm against 73.2. The whole study's compiling 677 -> 635 s, its running part equal (724
# / 721 s; fresh clones of 51d9de7 and d447f74, README).
LOOP_XLA_FLAGS = ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000,"
                  "-forget-scev-loop-unroll=true,-inline-threshold=-20000",
                  "--xla_backend_optimization_level=1")

# What the report's process starts with (render_report, on a CPU backend; added to the flags this
# process had before it adopted the workers'): the emitter flags, and LLVM's optimisation level 0.
# The report compiles about 10 programs (the figures' scenes and re-simulations, Fig. 3.6's three
# step responses the largest) and runs each for a second or two. The default study's folder (2
# idle cores, the two alternating, twice; make_report in a process started with the flags):
# 39.7 / 39.6 s with the workers' flags (level 1), which the command line's report inherited
# before, 29.1 / 25.7 s with these; one core, figures in turn: backend compiling 40.8 / 37.7 ->
# 23.8 / 18.0 s. The same report.md; two figures differ, Fig. 4.9's field slice in 3 pixels and
# Fig. 3.7's perfect-controller path visibly (descending among virtual obstacles placed from
# Hessian-based estimates, it moves with the rounding).
REPORT_XLA_FLAGS = EMITTER_XLA_FLAGS + ("--xla_backend_optimization_level=0",)

# What the sweep's workers (and a --jobs 1 sweep's own process) start with on a CPU machine
# (:func:`_worker_flags`: the loop flags only where the backend will be the CPU; LLVM's level is
# also an accelerator backend's).
WORKER_XLA_FLAGS = EMITTER_XLA_FLAGS + LOOP_XLA_FLAGS

_ACCELERATOR_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_plugins.xla_cuda12",
                        "jax_plugins.xla_cuda13", "jax_rocm60_plugin", "jax_rocm7_plugin",
                        "jax_plugins.xla_rocm60", "jax_plugins.xla_rocm7", "libtpu")


def _cpu_backend_expected() -> bool:
    """Whether JAX will run on the CPU, told before its backend starts: ``JAX_PLATFORMS`` if set
    (its first entry), else whether no accelerator plugin (CUDA, ROCm, TPU) is installed."""
    import importlib.util
    import os

    platforms = os.environ.get("JAX_PLATFORMS", "").strip()
    if platforms:
        return platforms.split(",")[0].strip() == "cpu"
    for name in _ACCELERATOR_PLUGINS:
        try:
            if importlib.util.find_spec(name) is not None:
                return False
        except (ImportError, ValueError):
            continue
    return True


def _worker_flags() -> tuple:
    """:data:`WORKER_XLA_FLAGS` where the backend will be the CPU, else the emitter flags alone."""
    return WORKER_XLA_FLAGS if _cpu_backend_expected() else EMITTER_XLA_FLAGS


def _with_flags(flags: str, extra) -> str:
    for flag in extra:
        if flag.lstrip("-").split("=")[0] not in flags:
            flags = (flags + " " + flag).strip()
    return flags


@functools.lru_cache(maxsize=None)
def _xla_accepts(flags: str) -> bool:
    """Whether this jaxlib starts with ``XLA_FLAGS=flags`` (an unknown flag aborts the process)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    try:
        done = subprocess.run([sys.executable, "-c", "import jax.numpy as j; j.zeros(1).block_until_ready()"],
                              env=env, capture_output=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return False
    return done.returncode == 0


def adopt_worker_xla_flags(extra=None) -> bool:
    """Give this process the workers' XLA flags, if its XLA backend has not started yet (the
    command line calls this first): the units it computes itself (``--jobs 1``, a distributed
    sweep) then round as the workers' do, so a table does not depend on ``--jobs`` or on how a
    resumed sweep split its work. Returns whether ``XLA_FLAGS`` changed (not where the backend
    runs already, or this jaxlib refuses the flags)."""
    import os

    global _FLAGS_BEFORE_ADOPTION

    started = _backend_started()
    before = os.environ.get("XLA_FLAGS", "")
    flags = _with_flags(before, _worker_flags() if extra is None else extra)
    if started or flags == before or not _xla_accepts(flags):
        return False
    if _FLAGS_BEFORE_ADOPTION is None:
        _FLAGS_BEFORE_ADOPTION = before
    os.environ["XLA_FLAGS"] = flags
    return True


# XLA_FLAGS as this process had them before adopt_worker_xla_flags extended them (None: never)
_FLAGS_BEFORE_ADOPTION = None


def compute_here_as_a_worker() -> bool:
    """Pin this process to one core if its XLA backend has not started yet (the command line
    calls this for ``--jobs 1``): XLA sizes its CPU thread pool by the cores a process may use
    when the backend starts, and the units then round as a worker's do (:func:`_worker_cores`).
    Returns whether it pinned (not where the backend runs already or the platform cannot pin)."""
    import os

    if _backend_started():
        return False
    try:
        cores = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, cores[:1])
    except (AttributeError, OSError):
        return False
    return True


# Python's cyclic garbage collector in a process that traces JAX programs: a young-generation
# collection every 100,000 net allocations instead of 700. Set by :func:`prepare_sweep_process` (the
# sweep command's and scripts' own process, any --jobs), :func:`_worker_start` (the sweep's workers
# and the report's processes), ``redman-jax tune`` (``_tuning.tune_cli``) and the test suite.
# Tracing builds millions of short-lived objects, and with the default thresholds the collector took
# about 7.5 % of a compile-bound test (a perf profile). Measured (the 9-DOF warehouse build,
# velocity OSC and gradient-guided units, --jobs 1, the two settings side by side on one core each,
# then on swapped cores): tracing and lowering 13.4 / 11.8 s with the default thresholds, 10.3 /
# 9.7 s with these; backend compiling and running unchanged (within the pairs' noise, +-5 s of
# 160-172 s). Cycles are still collected, later; the computations are unchanged.
GC_THRESHOLDS = (100_000, 50, 100)


def tune_gc() -> None:
    """Collect once, move what is alive (the imported modules) out of the collector's reach
    (``gc.freeze``) and set :data:`GC_THRESHOLDS`."""
    import gc

    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def _backend_started() -> bool:
    """Whether this process's JAX backend has started (its XLA flags and CPU pool are fixed then);
    True where this jax cannot tell, so that nothing is changed under a running backend."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return True


def prepare_sweep_process(jobs, distributed: bool = False) -> None:
    """Call first in a process that will run a sweep (the command line and the scripts under
    ``sweeps/`` do), before any JAX work: the workers' XLA flags, and for ``jobs`` 1 (units
    computed in this process) a worker's one core, so that the table is the same for any
    ``--jobs`` (:func:`adopt_worker_xla_flags`, :func:`compute_here_as_a_worker`); and Python's
    garbage collector set for tracing (:func:`tune_gc`)."""
    adopt_worker_xla_flags()
    tune_gc()
    if str(jobs).strip() == "1" and not distributed:
        compute_here_as_a_worker()


@contextlib.contextmanager
def _worker_xla_flags(extra=None, base=None):
    """Run the body with ``XLA_FLAGS`` extended by ``extra`` in this process's environment, which
    the workers spawned meanwhile inherit (this process's backend has started; it is unaffected);
    unchanged if this jaxlib does not accept them. Restored afterwards. ``base``: the flags to
    extend instead of this process's (a string)."""
    import os

    before = os.environ.get("XLA_FLAGS")
    flags = _with_flags((before or "") if base is None else base, _worker_flags() if extra is None else extra)
    if flags != (before or "") and _xla_accepts(flags):
        os.environ["XLA_FLAGS"] = flags
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("XLA_FLAGS", None)
        else:
            os.environ["XLA_FLAGS"] = before


# the parent's end of the progress queue, in a worker (set by _worker_start)
_PROGRESS = None


@contextlib.contextmanager
def _worker_pool(cfg: SweepConfig, init=None):
    """``cfg.jobs`` spawned worker processes for every phase of a sweep (:func:`_run_parallel`),
    each pinned to a core of its own where there are enough (:func:`_worker_start`); yields
    ``(submitter, progress_queue)`` (the pool's submit, :class:`_PinnedSubmit`). The pool spawns a
    worker when a group finds none idle, so a phase of one group starts one, and the workers of the
    builds go on with the simulations.

    Why one pool: a pool per phase spawned its workers, imported jax in them and shut them down
    again between the phases, and each started a queues' manager (a process of its own, which
    imports this package: about 2 s) before its workers; meanwhile both cores were idle. A sweep
    of 4 real units (7-DOF inspection and simple cases, seeds 1-2, joint space, ``jobs=2``, 2
    idle cores, the two versions alternating, twice; with :class:`_PinnedSubmit`): the last
    build's end to the first simulation's start 5.3 / 4.9 -> 0.1 / 0.1 s, the sweep's start to its
    first unit 6.4 / 6.3 -> 2.1 / 2.0 s, the whole sweep 35.9 / 33.6 -> 25.5 / 23.6 s. The queues
    are two plain ``SimpleQueue`` objects handed to each worker as it starts (a put is written at
    once)."""
    import multiprocessing as mp

    progress = mp.get_context("spawn").SimpleQueue()
    with _pinned_pool(cfg.jobs, _worker_cores(cfg.jobs), _worker_xla_flags(), init, progress) as (_, submit):
        yield submit, progress


@contextlib.contextmanager
def _pinned_pool(workers: int, pins, flags, init=None, progress=None):
    """A spawning process pool of ``workers`` whose processes each pin themselves to one of
    ``pins`` (:func:`_worker_start`; ``[]``: no pinning), started with the ``XLA_FLAGS`` the
    context manager ``flags`` sets; yields ``(pool, submitter)`` (:class:`_PinnedSubmit`). The
    calling thread is pinned while the pool may spawn, through every submit (see
    :func:`_one_core_while_spawning`; the submitter moves it to the next core before each), then
    restored. The sweep's workers (:func:`_worker_pool`) and the report's (:func:`render_report`)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("spawn")
    cores = None
    if pins:
        cores = ctx.SimpleQueue()
        for c in pins:
            cores.put(c)
    start = functools.partial(_worker_start, cores, init, progress)
    with (_one_core_while_spawning(pins[0] if pins else None), flags,
          ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=start) as pool):
        yield pool, _PinnedSubmit(pool, pins)


class _PinnedSubmit:
    """``submit`` of a process pool that spawns its workers on demand, from the calling thread
    (Python >= 3.11, at most one per submit): the calling thread is pinned to the next of ``pins``
    in turn before each, so that the workers start on cores of their own and import jax side by
    side, not both on the first core (the 4-unit sweep of :func:`_worker_pool` with one pool: its
    start to the first unit 6.0-6.5 s, 2.1-3.2 s so; two runs each). Each worker then pins itself
    to the core the queue gives it (:func:`_worker_start`); one thread wide either way. (Python
    3.10 spawns all of them at the first submit, both from the first core, as before.)"""

    def __init__(self, pool, pins):
        self.pool, self.pins, self.n = pool, list(pins), 0

    def submit(self, fn, *args):
        import os

        if self.pins:
            os.sched_setaffinity(0, {self.pins[self.n % len(self.pins)]})
            self.n += 1
        return self.pool.submit(fn, *args)


def _run_group_in_worker(cfg: SweepConfig, units: list) -> None:
    """:func:`_run_group` in a worker of :func:`_worker_pool`, each unit reported to the parent."""
    _run_group(cfg, units, _PROGRESS.put)


def _run_parallel(cfg: SweepConfig, todo: dict, progress: Progress, workers) -> None:
    """The groups of one phase in the workers of :func:`_worker_pool` (``workers``), longest
    expected first. Units are saved by the workers as they finish, so an interrupted sweep resumes
    from there."""
    from concurrent.futures import FIRST_COMPLETED, wait

    pool, queue = workers
    order = sorted(todo, key=lambda k: -_weight(k))
    worker_cfg = dataclasses.replace(cfg, progress=False, figures=False, jobs=1)
    pending = {pool.submit(_run_group_in_worker, worker_cfg, todo[k]) for k in order}

    def drain():
        # a worker's put has reached the pipe before its group's result does (SimpleQueue writes
        # at once), so a phase's last units are read here before the next phase starts
        while not queue.empty():
            name, seconds = queue.get()
            progress.advance(note=f"{name} ({seconds:.1f}s)")

    while pending:
        finished, pending = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
        for f in finished:
            f.result()  # re-raises a worker's error here
        drain()
    drain()


def collect_rows(cfg: SweepConfig, store: UnitStore) -> list[dict]:
    rows = []
    for arm_spec in cfg.arms:
        label = _arm_label(arm_spec)
        for case in cfg.cases:
            for ctrl in cfg.controllers_for(case):
                payload = store.load(f"run_{label}_{case}_{ctrl}")
                rows.extend(payload["rows"])
                traces = payload.get("traces")
                if traces:
                    buf = io.BytesIO()
                    np.savez_compressed(buf, **traces)
                    atomic_write_bytes(store.root / "traces" / f"{label}_{case}_{ctrl}.npz", buf.getvalue())
    return rows


def write_timing(cfg: SweepConfig, store: UnitStore) -> list[dict]:
    """``DIR/timing.csv``: one row per unit of the sweep (:data:`TIMING_COLUMNS`): its wall time
    and the part of it spent tracing, lowering and compiling (seconds; NaN for a unit computed
    before these records existed). A resumed sweep keeps the records of the units it did not
    recompute, so the table describes the runs that produced the results."""
    rows = []
    for phase in _units(cfg):
        for group in phase.values():
            for kind, arm, case, ctrl, name, key in group:
                rec = {}
                try:
                    rec = json.loads(_timing_path(store, name).read_text())
                except (OSError, ValueError):
                    pass
                ok = rec.get("key") == key
                rows.append({"unit": name, "kind": "build" if kind == "scen" else "simulation",
                             "arm": _arm_label(arm), "case": case, "controller": ctrl or "",
                             "wall_s": rec["wall_s"] if ok else float("nan"),
                             "compile_s": rec["compile_s"] if ok else float("nan")})
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=TIMING_COLUMNS)
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(Path(cfg.out) / "timing.csv", buf.getvalue())
    return rows


def timing_summary(rows: list[dict]) -> str:
    """Sums of :func:`write_timing`'s rows: builds (planning and IK validation) and simulations,
    each split into compilation and the rest. Unit times add up over the worker processes, so
    with ``jobs`` workers they exceed the wall time of the sweep."""
    def sums(kind):
        sel = [r for r in rows if r["kind"] == kind and np.isfinite(r["wall_s"])]
        return sum(r["wall_s"] for r in sel), sum(r["compile_s"] for r in sel), len(sel)

    lines = ["time in units (summed over workers):"]
    tw = tc = 0.0
    for kind, label in (("build", "builds (planning, IK)"), ("simulation", "simulations")):
        w, c, n = sums(kind)
        tw, tc = tw + w, tc + c
        lines.append(f"  {label:<22} {n:3d} units {w:8.1f} s, of which compiling {c:7.1f} s")
    share = f" ({100 * tc / tw:.0f} %)" if tw > 0 else ""
    lines.append(f"  {'total':<22}           {tw:8.1f} s, of which compiling {tc:7.1f} s{share}")
    return "\n".join(lines)


def write_table(out: Path, rows: list[dict]) -> None:
    """``runs.csv`` always; ``runs.parquet`` when pandas and pyarrow are installed (the io extra)."""
    cols = list(RUN_COLUMNS) + sorted({k for r in rows for k in r} - set(RUN_COLUMNS))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: _plain(r.get(k)) for k in cols})
    atomic_write_text(Path(out) / "runs.csv", buf.getvalue())
    parquet = Path(out) / "runs.parquet"
    try:
        import pandas as pd

        df = pd.DataFrame([{k: _plain(r.get(k)) for k in cols} for r in rows], columns=cols)
        pbuf = io.BytesIO()
        df.to_parquet(pbuf, index=False)
    except (ImportError, ValueError):
        parquet.unlink(missing_ok=True)  # never leave another sweep's table beside this runs.csv
        return
    atomic_write_bytes(parquet, pbuf.getvalue())


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray) and v.ndim == 0:
        return v.item()
    return v


def load_runs(out) -> list[dict]:
    """Read ``DIR/runs.csv`` back as a list of dicts with numbers parsed."""
    with open(Path(out) / "runs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        for k, v in r.items():
            if v in ("True", "False"):
                r[k] = v == "True"
            else:
                try:
                    r[k] = int(v) if v.lstrip("-").isdigit() else float(v)
                except (ValueError, AttributeError):
                    pass
    return rows
