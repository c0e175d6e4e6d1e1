"""The study on the Franka Emika Panda, loaded from its URDF.

The Panda's URDF ships with the ``example-robot-data`` package; :func:`redman_jax.from_urdf`
turns the chain ``panda_link0 -> panda_hand`` into an :class:`redman_jax.Arm` (7 revolute joints,
the fingers lumped into the hand, 4 points of interest per segment, 0.10 m link width), and the
study takes it as the arm spec ``urdf:PATH:panda_hand`` wherever it takes ``7``, ``8`` or ``9``:

    SweepConfig(arms=("urdf:/.../panda.urdf:panda_hand",), cases=..., seeds=..., controllers=...)

or on the command line ``redman-jax sweep --arms urdf:/.../panda.urdf:panda_hand ...``.

**Caveat.** The case generators are sized for the thesis arms (reach ~1.3 m, goals up to 1.6 m
high); the Panda reaches ~0.85 m from a base on the floor. Measured (seeds 1-3, 20 retries): the
inspection and welding generators find no scene within the Panda's reach at all (reach and
start-protection rules), and the warehouse scenes generate but their IK trajectories do not
validate (collisions, goals not reached). ``from_urdf``'s default start pose is zeros clipped
into the limits and kept 5 % of each range away from them (joint 4 of the Panda starts at
-0.22 rad, its upper limit -0.07 rad), and the null-space joint-limit policy (3.35) is capped at
the value the thesis gives it beyond the limits, so a start near a limit no longer makes the OSC controllers diverge in
their first sample (as it did when the start pose sat on the limit). Runs without a validated
scenario stay in the table with ``scenario_valid = False``; this script says so rather than
reporting them as controller results.

Run (full: all five cases, seeds 1-20, the thesis's four controllers)::

    .venv/bin/python examples/panda_study.py --out panda_study

Small (warehouse, one seed, the velocity OSC; about a minute)::

    .venv/bin/python examples/panda_study.py --small --out /tmp/panda
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

URDF = "panda_description/urdf/panda.urdf"
TIP = "panda_hand"
CASES = ("agriculture", "warehouse", "inspection", "welding", "simple")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description="The study on the Franka Panda from URDF.")
    ap.add_argument("--small", action="store_true",
                    help="warehouse, seed 1, velocity OSC, 2 retries (explicit options win)")
    ap.add_argument("--cases", default=None, help="cases, comma-separated (full default: all five)")
    ap.add_argument("--seeds", default=None, help="seeds, e.g. 1-20 or 1,2 (full default 1-20)")
    ap.add_argument("--controllers", default=None,
                    help="controllers, comma-separated (full default joint_space,velocity,acceleration,gradient)")
    ap.add_argument("--max-retries", type=int, default=None, help="IK-validation retries (full default 20)")
    ap.add_argument("--urdf", default=None, help=f"URDF file (default: example-robot-data's {URDF})")
    ap.add_argument("--tip", default=TIP, help=f"tip link (default {TIP})")
    ap.add_argument("--out", default="panda_study", help="results folder (resumable; default panda_study)")
    ap.add_argument("--figures", action="store_true", help="also write the study figures and report.md")
    args = ap.parse_args(argv)
    full = {"cases": ",".join(CASES), "seeds": "1-20",
            "controllers": "joint_space,velocity,acceleration,gradient", "max_retries": 20}
    small = {"cases": "warehouse", "seeds": "1", "controllers": "velocity", "max_retries": 2}
    for key, value in (small if args.small else full).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    from redman_jax._cli import parse_int_list, parse_name_list
    from redman_jax._controllers import CONTROLLERS
    from redman_jax._study import SweepConfig, arm_from_spec, load_runs, run_sweep
    from redman_jax._urdf import example_robot_data_file

    path = args.urdf
    if path is None:
        try:
            path = example_robot_data_file(URDF)
        except FileNotFoundError as e:
            print(f"panda_study: {e}", file=sys.stderr)
            return 2
    spec = f"urdf:{path}:{args.tip}"
    arm = arm_from_spec(spec)
    print(f"arm {arm.name}: {arm.n_dof} joints {', '.join(arm.joint_names)}; tip {args.tip}")

    cfg = SweepConfig(out=args.out, arms=(spec,), cases=parse_name_list(args.cases, "cases", CASES),
                      seeds=parse_int_list(args.seeds, "seeds"),
                      controllers=parse_name_list(args.controllers, "controllers", tuple(sorted(CONTROLLERS))),
                      max_retries=args.max_retries, figures=args.figures)
    out = run_sweep(cfg)
    rows = load_runs(out)

    cols = ["arm", "case", "seed", "seed_used", "scenario_valid", "controller", "success", "collided",
            "joint_limit_hit", "diverged", "final_pos_error", "mean_pos_error", "mean_ori_error", "n_samples"]
    print(",".join(cols))
    for r in rows:
        print(",".join(f"{r.get(c):.6g}" if isinstance(r.get(c), float) else str(r.get(c)) for c in cols))

    invalid = sorted({(r["case"], r["seed"]) for r in rows if r.get("scenario_valid") is False})
    valid_rows = [r for r in rows if r.get("scenario_valid") is not False]
    if invalid:
        print(f"\nNOTE: {len(invalid)} (case, seed) pair(s) had no scenario whose IK trajectory validates "
              f"on the Panda within {cfg.max_retries} retries: {invalid}. The case generators are sized "
              "for the thesis arms (reach ~1.3 m); the Panda reaches ~0.85 m. Those runs are in the "
              "table with scenario_valid=False and are not controller failures.")
    if valid_rows:
        n_ok = sum(bool(r["success"]) for r in valid_rows)
        print(f"\n{n_ok}/{len(valid_rows)} runs on validated scenarios succeeded.")
    else:
        print("\nNo validated scenario: nothing to compare on the Panda with these settings "
              "(try more --max-retries or another case).")
    print(f"{len(rows)} runs in {Path(out) / 'runs.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
