"""The default study of the thesis: 3 arms (7, 8, 9 DOF) x 5 cases x 20 validated seeds; the
joint-space, velocity-based and acceleration-based controllers on every case and the
gradient-guided one on the three point-to-point cases (thesis 3.4, 4; SPEC sections 10-11).

The same as ``redman-jax study`` (``python -m redman_jax study``, the same ``--jobs`` default:
two worker processes on a CPU machine with 2 or more cores), with the headline table printed at
the end. Resumable: rerun the same command after an interruption and only the missing units are
computed (``DIR/units/``); ``DIR/runs.csv`` / ``runs.parquet`` hold one row per run,
``DIR/traces/`` the per-sample traces, ``DIR/report.md`` and ``DIR/figures/`` the comparison with
the thesis.

    .venv/bin/python sweeps/thesis_study.py --out results
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description="The thesis study (3 arms x 5 cases x 20 seeds, all four "
                                             "controllers); resumable; prints the headline table.")
    ap.add_argument("--out", default="results", help="results folder (resumable; default results)")
    ap.add_argument("--seeds", default="1-20", help="seeds, e.g. 1-20 or 1,3 (default 1-20)")
    ap.add_argument("--max-retries", type=int, default=20,
                    help="IK-validation retries per seed (seed + 1000 k; default 20)")
    ap.add_argument("--no-figures", action="store_true", help="skip the figures and report.md")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    from _table import add_jobs_option

    add_jobs_option(ap)
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    from redman_jax._report import headline_table
    from redman_jax._study import SweepConfig, load_runs, prepare_sweep_process, run_sweep

    prepare_sweep_process(args.jobs)  # as the command line: the same table for any --jobs

    cfg = SweepConfig.from_args(args, study=True)  # what `redman-jax study` builds from the same options
    out = run_sweep(cfg)
    rows = load_runs(out)
    print(headline_table(rows))
    print(f"{len(rows)} runs in {Path(out) / 'runs.csv'}"
          + ("" if args.no_figures else f"; report in {Path(out) / 'report.md'}"))
    return 0


if __name__ == "__main__":
    from _table import run_main

    sys.exit(run_main(main))
