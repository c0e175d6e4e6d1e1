"""One scenario end to end: generate it, validate it with the trajectory IK, simulate the velocity-
based operational-space controller and the joint-space controller on it, print their metrics and
save a figure (thesis 3.2-3.5; SPEC sections 4, 8, 10).

Steps:

1. :func:`redman_jax.validated_scenarios` draws the scene of ``--seed`` for the arm, plans its
   reference and runs the IK; a seed whose IK trajectory fails validation (collision, joint limit,
   goal not reached) moves on to ``seed + 1000`` (thesis 3.4), at most ``--max-retries`` times.
2. :func:`redman_jax.validate_ik` re-checks the accepted IK trajectory independently (from its
   joint path only).
3. :func:`redman_jax.simulate` runs the closed loop (adaptive Dopri5, reference held per sample)
   with ``VelocityOSC`` (operational space, needs no IK) and ``JointSpaceID`` (tracks the IK's
   joint trajectory ``q, qd, qdd``).
4. The metrics are printed as a table, written to ``DIR/metrics.json``, and ``DIR/single_scenario.png``
   shows the scene with both end-effector paths and the position / orientation error per sample.

Run (full size: 9-DOF arm, welding, about 1200 samples; a few minutes on 2 cores)::

    .venv/bin/python examples/single_scenario.py --out single_scenario

Small (7-DOF arm, inspection, about a minute)::

    .venv/bin/python examples/single_scenario.py --small --out /tmp/single
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

CASES = ("agriculture", "warehouse", "inspection", "welding", "simple")
FULL = {"arm": "9", "case": "welding", "max_retries": 20}
SMALL = {"arm": "7", "case": "inspection", "max_retries": 5}


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--small", action="store_true",
                    help=f"small run: defaults {SMALL} instead of {FULL} (explicit options still win)")
    ap.add_argument("--arm", default=None, help="thesis arm DOF (7, 8, 9) or urdf:PATH:TIP_LINK")
    ap.add_argument("--case", default=None, choices=CASES, help="case (full default welding)")
    ap.add_argument("--seed", type=int, default=1, help="seed (default 1)")
    ap.add_argument("--max-retries", type=int, default=None, help="IK-validation retries (seed + 1000 k)")
    ap.add_argument("--out", default="single_scenario", help="output folder (default single_scenario)")
    args = ap.parse_args(argv)
    base = SMALL if args.small else FULL
    for key, value in base.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def _row(name, res, wall):
    m = res.metrics
    return {
        "controller": name,
        "success": bool(m.success),
        "collided": bool(m.collided),
        "joint_limit_hit": bool(m.joint_limit),
        "diverged": bool(res.diverged),
        "final_pos_error_mm": 1e3 * float(m.final_pos_err),
        "mean_pos_error_mm": 1e3 * float(m.mean_pos_err),
        "mean_ori_error": float(m.mean_ori_err),
        "min_distance_m": _masked_min(res),
        "n_steps": int(res.n_steps),
        "wall_s": wall,  # includes the compilation of this controller's closed loop
    }


def _masked_min(res):
    import numpy as np

    d = np.where(np.asarray(res.mask), np.asarray(res.min_dist), np.inf)
    return float(d.min())


def _print_table(rows):
    cols = ["controller", "success", "collided", "joint_limit_hit", "final_pos_error_mm",
            "mean_pos_error_mm", "mean_ori_error", "min_distance_m", "n_steps", "wall_s"]
    fmt = {float: "{:.4g}", bool: "{}", int: "{}", str: "{}"}
    table = [cols] + [[fmt[type(r[c])].format(r[c]) for c in cols] for r in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(cols))]
    for line in table:
        print("  ".join(s.rjust(w) for s, w in zip(line, widths)))


def _figure(path, arm, scen, results, case, seed_used):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from redman_jax import plot_scenario

    n = int(scen.reference.n_samples)
    ts = float(scen.reference.ts)
    fig = plt.figure(figsize=(11.5, 4.6))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    name0, res0 = results[0]
    plot_scenario(scen, arm=arm, q=np.asarray(res0.q)[n - 1], ax=ax3,
                  title=f"{case}, seed {seed_used}, {arm.name}")
    colors = {"velocity": "crimson", "joint_space": "darkorange"}
    for name, res in results:
        p = np.asarray(res.p)[:n]
        ax3.plot(p[:, 0], p[:, 1], p[:, 2], color=colors.get(name, "k"), lw=1.3, label=f"{name} (actual)",
                 zorder=10)
    ax3.legend(loc="upper left", fontsize=6)
    ax_p = fig.add_subplot(2, 2, 2)
    ax_o = fig.add_subplot(2, 2, 4, sharex=ax_p)
    t = ts * np.arange(1, n + 1)
    rot = np.asarray(scen.reference.rot)[:n] > 0.5
    for name, res in results:
        ax_p.semilogy(t, np.maximum(1e3 * np.asarray(res.pos_err)[:n], 1e-6), color=colors.get(name, "k"),
                      label=name)
        ax_o.plot(t, np.where(rot, np.asarray(res.ori_err)[:n], np.nan), color=colors.get(name, "k"))
    ax_p.set_ylabel("|e_p| [mm]")
    ax_o.set_ylabel("|e_o| (rot on)")
    ax_o.set_xlabel("t [s]")
    ax_p.legend(fontsize=7)
    for a in (ax_p, ax_o):
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    import jax
    import numpy as np

    import redman_jax as rj
    from redman_jax._study import arm_from_spec

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    arm = arm_from_spec(args.arm)
    print(f"arm {arm.name} ({arm.n_dof} DOF), case {args.case}, seed {args.seed}")

    # 1. scenario + IK, reseeded until the IK trajectory validates
    t0 = time.perf_counter()
    scen_b, ik_b = rj.validated_scenarios(args.case, [args.seed], arm, max_retries=args.max_retries)
    scen = jax.tree.map(lambda x: x[0], scen_b)
    ik = jax.tree.map(lambda x: x[0], ik_b)
    t_build = time.perf_counter() - t0
    n = int(scen.reference.n_samples)
    print(f"scenario: seed_used {int(scen.seed_used)}, valid {bool(scen.valid)}, {n} samples "
          f"({n * float(scen.reference.ts):.2f} s), generated + planned + IK in {t_build:.1f} s")

    # 2. independent re-check of the IK trajectory
    recheck = bool(rj.validate_ik(arm, scen, ik))
    print(f"IK: valid {bool(ik.valid)} (re-check {recheck}), final error {1e3 * float(ik.final_error):.2f} mm, "
          f"min clearance {float(np.min(np.where(np.asarray(ik.mask), np.asarray(ik.clearance), np.inf))):.3f} m")
    if not (bool(scen.valid) and recheck):
        print(f"no valid scenario for seed {args.seed} within {args.max_retries} retries: "
              "nothing to simulate", file=sys.stderr)
        return 1

    # 3. closed-loop simulation of both controllers
    runs = [("velocity", rj.VelocityOSC(), None), ("joint_space", rj.JointSpaceID(), ik)]
    results, rows = [], []
    for name, ctrl, ref_ik in runs:
        t0 = time.perf_counter()
        res = jax.block_until_ready(rj.simulate(arm, scen, ctrl, ctrl.default_gains(), ik=ref_ik))
        wall = time.perf_counter() - t0
        results.append((name, res))
        rows.append(_row(name, res, wall))

    # 4. report
    print()
    _print_table(rows)
    (out / "metrics.json").write_text(json.dumps({
        "arm": arm.name, "case": args.case, "seed": args.seed, "seed_used": int(scen.seed_used),
        "n_samples": n, "ik_valid": recheck, "runs": rows}, indent=2))
    _figure(out / "single_scenario.png", arm, scen, results, args.case, int(scen.seed_used))
    print(f"\nwrote {out / 'metrics.json'} and {out / 'single_scenario.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
