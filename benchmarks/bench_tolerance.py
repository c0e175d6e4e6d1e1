"""Evidence for the simulator's default tolerances (issue 6: "the study's metrics must agree within
1 % with a reference run at rtol 1e-9").

For every case and controller of the study on one arm, the same validated scenarios are simulated
at rtol 1e-9 / atol 1e-11 (reference) and at candidate tolerances; printed per row: integration
steps (the batch maximum), wall time and the largest relative deviation over the seeds of
each metric the study reports (mean position error, mean orientation error, final position error),
plus the relative deviation of the seed means, whether success / collision / joint-limit flags
agree seed by seed, and what the study's headline table reports of the cell: its failed runs (the
count) and the relative deviation of the mean position error over the successful runs. Wall times
are of one call each (the reference's and the first candidate's include their compilations).

``--solver`` picks the candidates' solver (default the simulator's ``auto``); the reference is always
Tsit5 at rtol 1e-9 / atol 1e-11, so a candidate solver is checked against another method.
``--float32`` runs the candidates in single precision (the arm, scenarios, IK, gains and parameters
cast to float32; the reference stays in float64), ``--candidates`` sets their tolerances
(``rtol/atol`` pairs).

Run: ``python benchmarks/bench_tolerance.py [--dof 9] [--seeds 1-4] [--cases ...] [--controllers ...]
[--solver dopri5] [--float32] [--candidates 1e-5/1e-7,1e-4/1e-6]``
"""

from __future__ import annotations

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import redman_jax as rj
from redman_jax._cli import parse_int_list
from redman_jax._controllers import CONTROLLERS
from redman_jax._pipeline import build_case
from redman_jax._sim import SimParams
from redman_jax._study import GRADIENT_CASES

CANDIDATES = ((1e-5, 1e-7), (1e-4, 1e-6))
REFERENCE = (1e-9, 1e-11)
METRICS = ("mean_pos_err", "mean_ori_err", "final_pos_err")  # compared as relative deviations
FLAGS = ("success", "collided", "joint_limit")  # compared seed by seed


def parse_candidates(text: str) -> tuple:
    """``"1e-5/1e-7,1e-4/1e-6"`` -> ``((1e-5, 1e-7), (1e-4, 1e-6))``."""
    return tuple(tuple(float(v) for v in pair.split("/")) for pair in text.split(","))


def max_rel_dev(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-9)))


def with_policy_range(gains, obs_d=None):
    """``gains`` with the null-space obstacle policy's range ``D`` [m] set to ``obs_d`` (gains
    without a ``policy``, and ``obs_d`` None: unchanged)."""
    if obs_d is None or not hasattr(gains, "policy"):
        return gains
    return eqx.tree_at(lambda g: g.policy.obs_D, gains, jnp.asarray(obs_d, jnp.result_type(float)))


def study_closed_loops(arm, cases, controllers, seeds, obs_d=None):
    """``(case, name, controller, gains, scenarios, ik)`` for every case and controller of the study
    (``gradient`` on its cases only), the scenarios and IK from the study's ``build_case``
    (``ik`` None for controllers that need no joint reference); JAX's caches are cleared after
    each case: each compiles its own programs, and keeping them all ran out of code mappings.
    ``obs_d``: the obstacle policy's range ``D`` instead of the gains' (:func:`with_policy_range`)."""
    for case in cases:
        built = build_case(arm, case, seeds)
        for name in controllers:
            if name == "gradient" and case not in GRADIENT_CASES:
                continue
            ctrl = CONTROLLERS[name]()
            ik = built["ik"] if ctrl.needs_joint_reference else None
            yield case, name, ctrl, with_policy_range(ctrl.default_gains(), obs_d), built["scenarios"], ik
        jax.clear_caches()


def reference_params(budget: int) -> SimParams:
    """The reference run's parameters: Tsit5 at ``REFERENCE`` tolerances, ``budget`` steps per sample."""
    return SimParams(rtol=REFERENCE[0], atol=REFERENCE[1], solver="tsit5", max_steps_per_sample=budget)


def reference_complete(ref) -> bool:
    """Whether every seed of the reference's metrics finished (not out of its step budget, not
    diverged); an incomplete reference is no evidence."""
    return bool(np.all(np.isfinite(np.asarray(ref.final_pos_err))))


def compare(m, ref) -> tuple[tuple[float, ...], bool]:
    """``(devs, same)``: the largest relative deviation over the seeds of each of ``METRICS`` from
    the reference, and whether the ``FLAGS`` agree seed by seed."""
    devs = tuple(max_rel_dev(getattr(m, f), getattr(ref, f)) for f in METRICS)
    same = all(np.array_equal(np.asarray(getattr(m, f)), np.asarray(getattr(ref, f))) for f in FLAGS)
    return devs, same


def _rel_mean(a, b):
    return max_rel_dev(np.mean(np.asarray(a, float)), np.mean(np.asarray(b, float)))


def table_metrics(m) -> tuple[int, float]:
    """What the study's headline table reports of a cell: ``(failed runs, mean position error over
    the successful runs)`` (NaN where none succeeded)."""
    ok = np.asarray(m.success, bool)
    err = np.asarray(m.mean_pos_err, float)
    return int(np.sum(~ok)), float(np.mean(err[ok])) if ok.any() else float("nan")


def table_deviation(m, ref) -> tuple[bool, float]:
    """``(same failure count, relative deviation of the mean error over successes)`` from ``ref``."""
    (f, e), (fr, er) = table_metrics(m), table_metrics(ref)
    dev = 0.0 if np.isnan(e) and np.isnan(er) else max_rel_dev(e, er)
    return f == fr, dev


def study_arguments(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options that pick the runs of :func:`study_closed_loops`: arm, seeds, cases, controllers."""
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--seeds", default="1-4")
    ap.add_argument("--cases", default=",".join(rj.CASES))
    ap.add_argument("--controllers", default="joint_space,velocity,acceleration,gradient")
    ap.add_argument("--obs-d", type=float, default=None,
                    help="the null-space obstacle policy's range D [m] instead of the gains' 0.75: "
                         "its gradient jumps at D (SPEC E4), and each crossing costs rejected steps; "
                         "a D beyond the scene is never crossed (another policy, not the study's)")
    return ap


def main():
    ap = study_arguments(argparse.ArgumentParser())
    ap.add_argument("--solver", default=SimParams().solver, help="the candidates' solver")
    ap.add_argument("--ref-budget", type=int, default=256,
                    help="reference step budget per sample (max_steps = samples x this)")
    ap.add_argument("--float32", action="store_true", help="run the candidates in float32")
    ap.add_argument("--candidates", default=",".join(f"{r:g}/{a:g}" for r, a in CANDIDATES),
                    help="the candidates' tolerances, rtol/atol pairs")
    args = ap.parse_args()
    candidates = parse_candidates(args.candidates)
    cast = (lambda tree: rj.cast_floating(tree, np.float32)) if args.float32 else (lambda tree: tree)
    arm = rj.thesis_arm(args.dof)
    seeds = parse_int_list(args.seeds, "seeds")
    print(f"jax {jax.__version__}, {args.dof}-DOF arm, seeds {args.seeds}; candidates {args.solver}"
          f"{' in float32' if args.float32 else ''}; "
          f"reference tsit5 rtol/atol {REFERENCE[0]:.0e}/{REFERENCE[1]:.0e}")
    print(f"{'case':12s} {'controller':13s} {'rtol/atol':>11s} {'steps':>7s} {'wall s':>7s} "
          f"{'mean_pos':>9s} {'mean_ori':>9s} {'final':>9s} | seed means: {'pos':>8s} {'ori':>8s} {'final':>8s} flags"
          f" | table: {'failed':>6s} {'error':>8s}")
    worst = {c: 0.0 for c in candidates}
    worst_mean = {c: 0.0 for c in candidates}
    worst_table = {c: 0.0 for c in candidates}
    counts_equal = {c: True for c in candidates}
    for case, name, ctrl, gains, scen, ikarg in study_closed_loops(
            arm, args.cases.split(","), args.controllers.split(","), seeds, obs_d=args.obs_d):
        runs = {}
        for i, (rtol, atol) in enumerate((REFERENCE,) + candidates):
            if i == 0:
                p, c = reference_params(args.ref_budget), (lambda tree: tree)
            else:
                p, c = SimParams(rtol=rtol, atol=atol, solver=args.solver), cast
            t0 = time.perf_counter()
            res = jax.block_until_ready(rj.simulate_batch(c(arm), c(scen), ctrl, c(gains), ik=c(ikarg),
                                                          params=c(p)))
            runs[(rtol, atol) if i else "ref"] = (res, time.perf_counter() - t0)
        ref = runs["ref"][0].metrics
        ref_ok = reference_complete(ref)
        if not ref_ok:  # the reference ran out of its step budget (or diverged): no evidence
            print(f"{case:12s} {name:13s} reference incomplete for seeds "
                  f"{[s for s, f in zip(seeds, np.asarray(ref.final_pos_err)) if not np.isfinite(f)]} "
                  f"(step budget {args.ref_budget}/sample; raise --ref-budget); row left out of the summary")
        for key, (res, wall) in runs.items():
            m = res.metrics
            devs, flags = compare(m, ref)
            mdevs = tuple(_rel_mean(getattr(m, f), getattr(ref, f)) for f in METRICS)
            same_count, tdev = table_deviation(m, ref)
            if key in worst and ref_ok:
                worst[key] = max(worst[key], *devs)
                worst_mean[key] = max(worst_mean[key], *mdevs)
                worst_table[key] = max(worst_table[key], tdev)
                counts_equal[key] &= same_count
            tol = "reference" if key == "ref" else f"{key[0]:.0e}/{key[1]:.0e}"
            print(f"{case:12s} {name:13s} {tol:>11s} {int(np.max(res.n_steps)):7d} "
                  f"{wall:7.2f} {devs[0]:9.1e} {devs[1]:9.1e} {devs[2]:9.1e} | {mdevs[0]:20.1e} {mdevs[1]:8.1e} "
                  f"{mdevs[2]:8.1e} {'same' if flags else 'DIFFER'} | {table_metrics(m)[0]:>6d} {tdev:8.1e}",
                  flush=True)
    print("largest relative deviation from the reference, any metric: per seed | of the seed means"
          " | of the table's mean error over successes, and whether every failure count is the reference's")
    for (rtol, atol), w in worst.items():
        c = (rtol, atol)
        print(f"  rtol {rtol:.0e} atol {atol:.0e}: {w:.2e} | {worst_mean[c]:.2e} | {worst_table[c]:.2e}, "
              f"failure counts {'equal' if counts_equal[c] else 'DIFFER'}")


if __name__ == "__main__":
    main()
