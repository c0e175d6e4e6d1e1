"""Small helpers shared by the sweep scripts: the ablations' sweep configuration, the ``--jobs``
option, grouping runs and a markdown table."""

from __future__ import annotations

import math


def ablation_config(args, controllers, allowed_cases):
    """The ``SweepConfig`` of an ablation script from its ``--out --arms --cases --seeds
    --max-retries --jobs --quiet`` arguments (figures off: the script prints its own table).
    Call it before any JAX work: it gives this process the command line's setup for a sweep
    (``prepare_sweep_process``), so the table is the same for any ``--jobs``."""
    from redman_jax._cli import parse_int_list, parse_name_list
    from redman_jax._study import SweepConfig, _jobs, prepare_sweep_process

    prepare_sweep_process(args.jobs)
    arms = tuple(a.strip() for a in args.arms.split(",") if a.strip())
    return SweepConfig(out=args.out, arms=arms, cases=parse_name_list(args.cases, "cases", allowed_cases),
                       seeds=parse_int_list(args.seeds, "seeds"), controllers=tuple(controllers),
                       max_retries=args.max_retries, figures=False, progress=not args.quiet,
                       jobs=_jobs(args.jobs))


def run_main(main, argv=None) -> int:
    """``main(argv)`` with a bad option or configuration reported as ``redman-jax sweep`` reports
    it (one ``error:`` line, exit status 2) instead of a traceback."""
    import os
    import sys

    from redman_jax._cli import CLIError

    try:
        return main(argv)
    except (CLIError, ValueError) as e:
        print(f"{os.path.basename(sys.argv[0])}: error: {e}", file=sys.stderr)
        return 2


def add_jobs_option(ap) -> None:
    """``--jobs`` as in ``redman-jax sweep``. An ablation passes its ``register`` to the workers
    (``run_sweep(cfg, _worker_init=register)``), so they know its controller variants."""
    ap.add_argument("--jobs", default="auto",
                    help="worker processes (default auto: 2 on a CPU machine with 2 or more cores, 1 with "
                         "an accelerator), as `redman-jax sweep --jobs`")


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _flag(v) -> bool:
    return v is True or str(v) == "True"


def valid_runs(rows):
    """Runs on validated scenarios (an invalid scenario is no controller result)."""
    return [r for r in rows if not (r.get("scenario_valid") is False or str(r.get("scenario_valid")) == "False")]


def summarise(rows, key):
    """``{key(r): stats}`` with runs, successes, collisions, mean errors over the successful runs."""
    groups: dict = {}
    for r in valid_runs(rows):
        groups.setdefault(key(r), []).append(r)
    out = {}
    for k, rs in groups.items():
        ok = [r for r in rs if _flag(r["success"])]

        def mean(col, runs=ok):
            xs = [_num(r[col]) for r in runs if math.isfinite(_num(r[col]))]
            return sum(xs) / len(xs) if xs else float("nan")

        out[k] = {
            "runs": len(rs),
            "success": len(ok),
            "collided": sum(_flag(r["collided"]) for r in rs),
            "diverged": sum(_flag(r.get("diverged")) for r in rs),
            "mean_pos_error_mm": 1e3 * mean("mean_pos_error"),
            "mean_ori_error": mean("mean_ori_error"),
            "final_pos_error_mm": 1e3 * mean("final_pos_error", rs),
            "time_to_goal_s": mean("time_to_goal"),
        }
    return out


def markdown(header, lines):
    def fmt(x):
        if isinstance(x, float):
            return "–" if not math.isfinite(x) else f"{x:.3g}"
        return str(x)

    rows = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    rows += ["| " + " | ".join(fmt(x) for x in line) + " |" for line in lines]
    return "\n".join(rows)
