"""Evidence for the step-size controller's PID coefficients (``SimParams.pcoeff``, ``icoeff``).

For every case and controller of the study on one arm, the same validated scenarios are simulated
with each candidate ``(pcoeff, icoeff)`` at the default tolerances (one compilation per row: the
coefficients are arrays), and optionally at rtol 1e-9 / atol 1e-11 as a reference (``--reference``).
Printed per row and candidate: integration steps summed over the seeds (accepted + rejected), the
share rejected, the batch's largest member (what a ``vmap``-ed batch pays), the warm wall time of
one call, and with ``--reference`` the largest relative deviation of the study's metrics from the
reference (as ``bench_tolerance.py``) and whether the success / collision / joint-limit flags agree
seed by seed. The totals at the end sum the steps and walls over the rows.

The candidates are diffrax's own suggestions (``diffrax.PIDController``'s docstring): the I
controller (0, 1), diffrax's default, and the PI controllers it suggests for error estimates that
do not vary smoothly: (0.4, 0.3), (0.3, 0.3), (0.2, 0.4), (0.1, 0.3).

``--obs-d D`` runs every row with the null-space obstacle policy's range ``D`` [m] instead of the
gains' 0.75 m (options shared with ``bench_tolerance.py`` and ``bench_solvers.py``). The policy's
gradient jumps at ``D`` (SPEC E4), so each crossing of a point of interest through an obstacle's
``D`` shell is a jump of the closed loop that the solver locates with rejected steps; with a ``D``
larger than the scene none is crossed (another, weaker-at-range policy: evidence of the jumps'
share of the steps, not a proposal). ``--dof 8 --seeds 1-20 --cases warehouse --controllers velocity
--candidates 0,1`` (the study's PID): 32,430 steps, 34.9 % rejected, warm 12.79 s; with ``--obs-d
5``: 17,070 steps, 16.6 %, 10.29 s (the batch pays for its slowest member: 2,488 and 2,248 steps).

Run: ``python benchmarks/bench_stepsize.py [--dof 9] [--seeds 1-4] [--cases ...] [--controllers ...]
[--reference] [--obs-d 5]``
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench_tolerance import (REFERENCE, compare, reference_complete, reference_params, study_arguments,
                             study_closed_loops)

import redman_jax as rj
from redman_jax._cli import parse_int_list
from redman_jax._sim import SimParams, tolerances

CANDIDATES = ((0.0, 1.0), (0.4, 0.3), (0.3, 0.3), (0.2, 0.4), (0.1, 0.3))


def main():
    ap = study_arguments(argparse.ArgumentParser())
    ap.add_argument("--candidates", default=";".join(f"{p},{i}" for p, i in CANDIDATES),
                    help="pcoeff,icoeff pairs separated by ';' (default: %(default)s)")
    ap.add_argument("--reference", action="store_true",
                    help="also simulate at rtol 1e-9 / atol 1e-11 (Tsit5) and print the deviations")
    ap.add_argument("--ref-budget", type=int, default=256,
                    help="reference step budget per sample (max_steps = samples x this)")
    args = ap.parse_args()
    cands = [tuple(float(v) for v in c.split(",")) for c in args.candidates.split(";")]
    arm = rj.thesis_arm(args.dof)
    seeds = parse_int_list(args.seeds, "seeds")
    base = SimParams()
    base_tol = tolerances(base, jnp.result_type(float))  # None: by the states' precision
    print(f"jax {jax.__version__}, {args.dof}-DOF arm, seeds {args.seeds}, solver {base.solver}, "
          f"rtol/atol {float(base_tol[0]):.0e}/{float(base_tol[1]):.0e}"
          + (f", obstacle policy range D = {args.obs_d:g} m" if args.obs_d is not None else "")
          + (f"; reference tsit5 {REFERENCE[0]:.0e}/{REFERENCE[1]:.0e}" if args.reference else ""))
    print(f"{'case':12s} {'controller':13s} {'p,i':>8s} {'steps':>7s} {'rej %':>6s} {'max':>6s} "
          f"{'wall s':>7s}" + (f" {'mean_pos':>9s} {'mean_ori':>9s} {'final':>9s} flags" if args.reference else ""))
    tot_steps = {c: 0 for c in cands}
    tot_wall = {c: 0.0 for c in cands}
    worst = {c: 0.0 for c in cands}
    for case, name, ctrl, gains, scen, ikarg in study_closed_loops(
            arm, args.cases.split(","), args.controllers.split(","), seeds, obs_d=args.obs_d):
        ref = None
        if args.reference:
            ref = jax.block_until_ready(rj.simulate_batch(arm, scen, ctrl, gains, ik=ikarg,
                                                          params=reference_params(args.ref_budget))).metrics
            if not reference_complete(ref):
                print(f"{case:12s} {name:13s} reference incomplete (raise --ref-budget); no deviations")
                ref = None
        sim = lambda c: rj.simulate_batch(arm, scen, ctrl, gains, ik=ikarg,  # noqa: E731
                                          params=SimParams(pcoeff=c[0], icoeff=c[1]))
        jax.block_until_ready(sim(cands[0]))  # compiles (the coefficients are arrays: once per row)
        for c in cands:
            t0 = time.perf_counter()
            res = jax.block_until_ready(sim(c))
            wall = time.perf_counter() - t0
            steps, rej = np.asarray(res.n_steps), np.asarray(res.n_rejected)
            tot_steps[c] += int(steps.sum())
            tot_wall[c] += wall
            line = (f"{case:12s} {name:13s} {c[0]:.1f},{c[1]:.1f} {int(steps.sum()):7d} "
                    f"{100.0 * rej.sum() / max(1, steps.sum()):6.1f} {int(steps.max()):6d} {wall:7.2f}")
            if ref is not None:
                devs, same = compare(res.metrics, ref)
                worst[c] = max(worst[c], *devs)
                line += f" {devs[0]:9.1e} {devs[1]:9.1e} {devs[2]:9.1e} {'same' if same else 'DIFFER'}"
            print(line, flush=True)
    print("totals over the rows: steps (all seeds) | warm wall s"
          + (" | largest relative deviation from the reference" if args.reference else ""))
    for c in cands:
        print(f"  pcoeff {c[0]:.1f} icoeff {c[1]:.1f}: {tot_steps[c]:8d} ({tot_steps[c] / tot_steps[cands[0]]:.2f}x)"
              f" | {tot_wall[c]:7.2f} ({tot_wall[c] / tot_wall[cands[0]]:.2f}x)"
              + (f" | {worst[c]:.2e}" if args.reference else ""))


if __name__ == "__main__":
    main()
