"""IK cost per trajectory sample (SPEC section 10 "Compute time"; issue 5 speed target).

For each case: the 20 scenarios of one arm from ``redman_jax._cases.make_scenarios`` (unvalidated
first candidates, real lengths and obstacle capacities), the batched IK (one vmap over the 20
seeds) timed warm, and one single-scenario IK; beside them a controller-like cost per sample (one
Jacobian and one adaptive damped pseudo-inverse, vmapped over 20, jitted). The IK scan runs over
the padded capacity, so the time per *valid* sample is also reported.

``--rounds``: instead, the study's scenario validation per case (``validated_scenarios``: the
generator's retry rounds, each an IK batch of the pending seeds), with its candidates screened
(``screen=True``, the default: a candidate stops iterating its QPs at its first collision or limit
violation) and without, alternating (after a warm-up that compiles): rounds, the batch's QP
iterations (per sample the batch's largest, summed) and wall time, and whether both gave the same
seeds and trajectories.

    .venv/bin/python benchmarks/bench_ik.py [--dof 9] [--seeds 20] [--cases warehouse,welding] [--rounds]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import redman_jax
from redman_jax._cases import make_scenarios
from redman_jax._ik import IKParams, ik_trajectory, validated_scenarios
from redman_jax._kinematics import jacobian
from redman_jax._nullspace import damped_pinv
from redman_jax._report import _cpu_model  # the CPU's model name, as the study report's machine row gives it
from redman_jax._scenario import CASES


def timed(fn, *a, repeat=1):
    out = fn(*a)
    jax.block_until_ready(out)
    t = time.perf_counter()
    for _ in range(repeat):
        out = fn(*a)
        jax.block_until_ready(out)
    return (time.perf_counter() - t) / repeat, out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dof", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--rounds", action="store_true", help="time the validation's retry rounds, screened or not")
    args = ap.parse_args()
    print(f"jax {jax.__version__}, {jax.devices()[0]}, {_cpu_model()}, "
          f"x64={jax.config.jax_enable_x64}")
    arm = redman_jax.thesis_arm(args.dof)
    seeds = list(range(1, args.seeds + 1))
    params = IKParams()
    if args.rounds:
        return rounds(arm, seeds, args.cases.split(","))

    qs = jnp.tile(arm.q0, (args.seeds, 1)) + 0.1
    ctrl = jax.jit(jax.vmap(lambda q: damped_pinv(jacobian(arm, q), 0.1, 0.01)[0]))
    t_ctrl, _ = timed(ctrl, qs, repeat=200)
    print(f"controller-like (J + damped pinv), batch {args.seeds}: {t_ctrl / args.seeds * 1e6:.1f} us per sample")

    total_warm = 0.0
    for case in args.cases.split(","):
        t0 = time.perf_counter()
        scen = make_scenarios(case, seeds, arm)
        t_gen = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = ik_trajectory(arm, scen, params)
        jax.block_until_ready(res)
        t_first = time.perf_counter() - t0
        t_warm, res = timed(lambda s: ik_trajectory(arm, s, params), scen)
        one = jax.tree.map(lambda x: x[0], scen)
        t_one_first = time.perf_counter()
        jax.block_until_ready(ik_trajectory(arm, one, params))
        t_one_first = time.perf_counter() - t_one_first
        t_one, _ = timed(lambda s: ik_trajectory(arm, s, params), one)
        C = scen.reference.p.shape[1]
        n_valid = int(np.sum(np.asarray(res.n_samples)))
        total_warm += t_warm
        print(f"{case:12s} capacity {C:5d} valid samples {n_valid:6d} | generation {t_gen:6.1f} s | "
              f"batched IK first {t_first:6.1f} s warm {t_warm:6.2f} s = {t_warm / (args.seeds * C) * 1e6:7.1f} us "
              f"per padded sample, {t_warm / n_valid * 1e6:7.1f} us per valid sample | single warm {t_one:5.2f} s "
              f"= {t_one / C * 1e6:7.1f} us per sample (first {t_one_first:5.1f} s) | IK valid "
              f"{int(np.sum(np.asarray(res.valid)))}/{args.seeds}, QP not converged in "
              f"{int(np.sum(~np.asarray(res.qp_converged)))} samples")
    print(f"all cases, batched, warm: {total_warm:.1f} s (target < 30 s on 2 cores)")


def rounds(arm, seeds, cases):
    """validated_scenarios with and without screening, alternating: B A B A after a warm-up."""
    print(f"{arm.n_dof}-DOF, {len(seeds)} seeds; validation wall time includes generation and planning")
    print("| case | rounds | batch QP iterations, screened / not | wall [s], screened | wall [s], not | same |")
    print("|---|---:|---:|---:|---:|---|")
    tot = {True: 0.0, False: 0.0}
    for case in cases:
        validated_scenarios(case, seeds, arm)  # compiles
        stats, wall, out = {}, {True: [], False: []}, {}
        for screen in (False, True, False, True):
            st = {}
            t0 = time.perf_counter()
            scen, ik = validated_scenarios(case, seeds, arm, stats=st, screen=screen)
            jax.block_until_ready(ik)
            wall[screen].append(time.perf_counter() - t0)
            stats[screen], out[screen] = st, (np.asarray(scen.seed_used), np.asarray(ik.q))
        same = (np.array_equal(out[True][0], out[False][0]) and np.array_equal(out[True][1], out[False][1]))
        for s_ in (True, False):
            tot[s_] += min(wall[s_])
        print(f"| {case} | {stats[True]['ik_rounds']} | {stats[True]['ik_batch_qp_iterations']:,} / "
              f"{stats[False]['ik_batch_qp_iterations']:,} | {' / '.join(f'{w:.1f}' for w in wall[True])} | "
              f"{' / '.join(f'{w:.1f}' for w in wall[False])} | {'yes' if same else 'NO'} |")
    print(f"all cases, the lesser of each: screened {tot[True]:.1f} s, not {tot[False]:.1f} s")


if __name__ == "__main__":
    main()
