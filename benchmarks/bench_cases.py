"""Generating and planning all seeds of every case for one arm, cold and warm (issue 3).

Times ``make_scenarios(case, seeds, arm)`` (host geometry + batched RRT planning for agriculture and
simple + geometric trajectories) twice per case: the first call includes compilation, the second is
warm. Prints per case the wall time, the mean number of samples and the time per trajectory sample
(the thesis's planning measure), and the total over the five cases.

    .venv/bin/python benchmarks/bench_cases.py --dof 9 --seeds 20
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import numpy as np

import redman_jax  # noqa: F401  (x64)
from redman_jax._cases import make_scenarios
from redman_jax._robot import thesis_arm
from redman_jax._scenario import CASES


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=20)
    args = ap.parse_args(argv)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cpus, "
          f"python {platform.python_version()}, x64={jax.config.jax_enable_x64}")
    arm = thesis_arm(args.dof)
    seeds = list(range(1, args.seeds + 1))
    print(f"{'case':<12} {'cold s':>8} {'warm s':>8} {'mean N':>8} {'warm us/sample':>15} {'seeds moved':>12}")
    tot_cold = tot_warm = 0.0
    for case in CASES:
        t0 = time.perf_counter()
        sc = jax.block_until_ready(make_scenarios(case, seeds, arm))
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        sc = jax.block_until_ready(make_scenarios(case, seeds, arm))
        warm = time.perf_counter() - t0
        n = np.asarray(sc.reference.n_samples)
        moved = int(np.sum(np.asarray(sc.seed_used) != np.asarray(sc.seed)))
        tot_cold += cold
        tot_warm += warm
        print(f"{case:<12} {cold:8.2f} {warm:8.2f} {n.mean():8.0f} {1e6 * warm / n.sum():15.1f} {moved:12d}")
    print(f"{'all five':<12} {tot_cold:8.2f} {tot_warm:8.2f}   (target: warm < 10 s on 2 cores)")


if __name__ == "__main__":
    main()
