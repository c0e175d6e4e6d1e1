"""Gradient-guided runs: the one-loop stepper (``mode="horizon"``) against the scan of per-sample
solves (``mode="per_sample"``), side by side in one process on the same validated scenarios.

For each case: wall time cold (first call, with compilation) and warm (second call) of
``simulate_batch`` over the seeds; the loop iterations the batch pays under ``vmap`` (stepper:
``max_members(total steps)``; scan: ``sum_k max_members(steps in sample k)``, read from the
per-sample step counts); and the agreement of the two (success per seed, largest difference of
the final goal distance, largest joint difference over the first second).

Run: ``python benchmarks/bench_guided.py [--dof 9] [--cases simple] [--seeds 1-20] [--reps 2]``
"""

from __future__ import annotations

import argparse
import inspect
import os
import platform
import time

import jax
import numpy as np

import redman_jax as rj
from redman_jax import _sim
from redman_jax._cli import parse_int_list
from redman_jax._controllers import CONTROLLERS
from redman_jax._pipeline import build_case


def _per_sample_counts():
    """``_simulate_guided`` with the per-sample step counts kept (``n_steps`` becomes ``(N,)``)."""
    src = inspect.getsource(_sim._simulate_guided)
    # per_sample mode sums the scan's (N, 3) per-sample counts; keep them instead, so that
    # _guided_result's n_steps = steps[0] is (N,) (the horizon stepper's batch path is unchanged)
    if src.count("steps = stats.sum(0)") != 1:  # else the iteration counts below would be wrong
        raise RuntimeError("bench_guided: _sim._simulate_guided no longer sets steps = stats.sum(0)")
    src = src.replace("steps = stats.sum(0)", "steps = stats.T")
    ns = dict(_sim.__dict__)
    exec(src, ns)
    return ns["_simulate_guided"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--cases", default="simple")
    ap.add_argument("--seeds", default="1-20")
    ap.add_argument("--reps", type=int, default=2)
    args = ap.parse_args()
    print(f"machine: {platform.platform()}, {os.cpu_count()} cpus (shared); load {os.getloadavg()}; "
          f"jax {jax.__version__} {jax.devices()[0].platform}")
    arm = rj.thesis_arm(args.dof)
    seeds = parse_int_list(args.seeds, "seeds")
    ctrl = CONTROLLERS["gradient"]()
    gains = ctrl.default_gains()
    _sim._simulate_guided = _per_sample_counts()  # same maths; keeps the per-sample counts
    rows = []
    for case in args.cases.split(","):
        scen = build_case(arm, case, seeds)["scenarios"]
        res = {}
        for mode in ("per_sample", "horizon"):
            params = _sim.SimParams(mode=mode)
            walls = []
            for _ in range(args.reps):
                t0 = time.perf_counter()
                r = jax.block_until_ready(_sim.simulate_batch(arm, scen, ctrl, gains, params=params))
                walls.append(time.perf_counter() - t0)
            steps = np.asarray(r.n_steps)
            iters = int(steps.max(0).sum()) if steps.ndim == 2 else int(steps.max())
            total = steps.sum(1) if steps.ndim == 2 else steps
            res[mode] = r
            rows.append((case, mode, walls[0], min(walls[1:]) if len(walls) > 1 else float("nan"),
                         int(total.max()), iters, int(np.asarray(r.success).sum()), len(seeds)))
            print(f"  {case} {mode}: cold {walls[0]:.1f} s, warm {rows[-1][3]:.1f} s, iterations {iters}",
                  flush=True)
        a, b = res["per_sample"], res["horizon"]
        fe = np.abs(np.asarray(a.metrics.final_pos_err) - np.asarray(b.metrics.final_pos_err))
        dq = np.abs(np.asarray(a.q)[:, :100] - np.asarray(b.q)[:, :100]).max()
        same = int((np.asarray(a.success) == np.asarray(b.success)).sum())
        print(f"  {case}: success equal in {same}/{len(seeds)} seeds; max |final error difference| "
              f"{fe.max():.2e} m; max |q difference| over the first 100 samples {dq:.2e}")
    print(f"\n{'case':12s} {'mode':11s} {'cold s':>8s} {'warm s':>8s} {'max steps':>10s} {'loop iters':>11s} {'success':>8s}")
    for case, mode, cold, warm, mx, it, ok, n in rows:
        print(f"{case:12s} {mode:11s} {cold:8.1f} {warm:8.1f} {mx:10d} {it:11d} {ok:>5d}/{n}")
    for case in args.cases.split(","):
        ps = next(r for r in rows if r[0] == case and r[1] == "per_sample")
        hz = next(r for r in rows if r[0] == case and r[1] == "horizon")
        print(f"{case}: stepper / per-sample, warm speed-up {ps[3] / hz[3]:.2f}x, cold {ps[2] / hz[2]:.2f}x, "
              f"loop iterations {ps[5] / hz[5]:.2f}x fewer")


if __name__ == "__main__":
    main()
