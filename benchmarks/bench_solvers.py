"""Which explicit Runge-Kutta solver the simulator should default to (issues 6 and 7): integration
steps and warm wall time of the study's closed loops under each solver, same tolerances.

For every case and controller of the study on one arm, the same validated scenarios (the study's
``build_case``, seeds ``--seeds``) are simulated with ``simulate_batch`` under each solver of
``--solvers`` at the default tolerances (float64: rtol 1e-5, atol 1e-7). Printed per row: integration steps
per member (accepted + rejected; batch maximum and mean), warm wall time of the batch (second call),
its ratio to the first solver's, the largest relative difference of the study's metrics (mean
position error, mean orientation error, final position error) from the first solver's run, and
whether the success / collision / joint-limit flags agree seed by seed. Accuracy against a
tight reference is ``bench_tolerance.py --solver NAME``'s job.

All solvers compared are FSAL with the same number of vector-field evaluations per step (Tsit5,
Dopri5: 6, plus one after each sample jump), so steps compare cost directly; Bosh3 (3 per step)
and Dopri8 (12) can be given too.

Run: ``python benchmarks/bench_solvers.py [--dof 9] [--seeds 1-4] [--cases ...] [--controllers ...]
[--solvers tsit5,dopri5]``
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import redman_jax as rj
from redman_jax._cli import parse_int_list
from redman_jax._sim import SimParams, tolerances

from bench_tolerance import FLAGS, METRICS, max_rel_dev, study_arguments, study_closed_loops


def main():
    ap = study_arguments(argparse.ArgumentParser())
    ap.add_argument("--solvers", default="tsit5,dopri5")
    args = ap.parse_args()
    arm = rj.thesis_arm(args.dof)
    seeds = parse_int_list(args.seeds, "seeds")
    solvers = args.solvers.split(",")
    rtol, atol = tolerances(SimParams(), jnp.result_type(float))  # None: by the states' precision
    print(f"jax {jax.__version__}, {args.dof}-DOF arm, seeds {args.seeds}, rtol/atol {float(rtol):.0e}/{float(atol):.0e}")
    print(f"{'case':12s} {'controller':13s} {'solver':7s} {'steps max':>9s} {'mean':>7s} {'warm s':>7s} "
          f"{'time ratio':>10s} {'metrics vs ' + solvers[0]:>17s} flags")
    totals = {s: [0, 0.0] for s in solvers}
    for case, name, ctrl, gains, scen, ikarg in study_closed_loops(
            arm, args.cases.split(","), args.controllers.split(","), seeds, obs_d=args.obs_d):
        first = None
        for solver in solvers:
            p = SimParams(solver=solver)
            jax.block_until_ready(rj.simulate_batch(arm, scen, ctrl, gains, ik=ikarg, params=p))
            t0 = time.perf_counter()
            res = jax.block_until_ready(rj.simulate_batch(arm, scen, ctrl, gains, ik=ikarg, params=p))
            wall = time.perf_counter() - t0
            m = res.metrics
            if first is None:
                first = (m, wall)
            dev = max(max_rel_dev(getattr(m, f), getattr(first[0], f)) for f in METRICS)
            flags = all(np.array_equal(np.asarray(getattr(m, f)), np.asarray(getattr(first[0], f)))
                        for f in FLAGS)
            steps = np.asarray(res.n_steps)
            totals[solver][0] += int(np.sum(steps))
            totals[solver][1] += wall
            print(f"{case:12s} {name:13s} {solver:7s} {int(steps.max()):9d} {float(steps.mean()):7.0f} "
                  f"{wall:7.2f} {wall / first[1]:10.2f} {dev:17.1e} {'same' if flags else 'DIFFER'}",
                  flush=True)
    print("all rows: total steps (summed over members) and warm wall time")
    for s, (n, w) in totals.items():
        print(f"  {s:7s} {n:10d} steps  {w:8.2f} s  (ratio to {solvers[0]}: steps "
              f"{n / totals[solvers[0]][0]:.2f}, time {w / totals[solvers[0]][1]:.2f})")


if __name__ == "__main__":
    main()
