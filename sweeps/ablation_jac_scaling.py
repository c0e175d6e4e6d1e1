"""Ablation E7 / U27: the scaled task Jacobian with the literal "rows_only" references vs the
"consistent" ones, for the velocity- and acceleration-based operational-space controllers.

The task Jacobian of 3.13 scales the rotational rows by ``S_r = 0.2``; 3.14 leaves the reference
unscaled ("rows_only", the literal thesis and our default), so with an exact inverse the achieved
angular velocity is ``1/S_r = 5`` times the rotational reference: the rotational gains and the
feed-forward ``w_d`` act x5 (SPEC E7). "consistent" scales the reference by the same ``S``, which
leaves the rotational gains as stated. SPEC U27 asks for this ablation.

Registers ``velocity_consistent`` and ``acceleration_consistent`` (``jac_scaling="consistent"``;
everything else identical) and runs them beside ``velocity`` and ``acceleration`` on every case x
arm x seed through the study machinery (resumable). Prints, per controller and scaling, failures,
collisions and the mean (over the successful runs) of each run's mean position and orientation
error, per case and overall.

    .venv/bin/python sweeps/ablation_jac_scaling.py --out results_ablation_jac
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

CASES = ("agriculture", "warehouse", "inspection", "welding", "simple")
VARIANTS = {  # registry name -> (controller, jac_scaling)
    "velocity": ("velocity", "rows_only"),
    "velocity_consistent": ("velocity", "consistent"),
    "acceleration": ("acceleration", "rows_only"),
    "acceleration_consistent": ("acceleration", "consistent"),
}


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description="E7/U27 ablation: velocity and acceleration OSC with "
                                             "jac_scaling 'rows_only' vs 'consistent' (resumable).")
    ap.add_argument("--out", default="results_ablation_jac", help="results folder (default results_ablation_jac)")
    ap.add_argument("--arms", default="7,8,9", help="arms: 7,8,9 and/or urdf:PATH:TIP (default 7,8,9)")
    ap.add_argument("--cases", default=",".join(CASES), help="cases (default all five)")
    ap.add_argument("--seeds", default="1-20", help="seeds (default 1-20)")
    ap.add_argument("--max-retries", type=int, default=20, help="IK-validation retries per seed (default 20)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    from _table import add_jobs_option

    add_jobs_option(ap)
    return ap.parse_args(argv)


def register() -> None:
    """Add the ``*_consistent`` variants to the controller registry."""
    import equinox as eqx

    import redman_jax as rj

    class VelocityOSCConsistent(rj.VelocityOSC):
        """Velocity OSC with the reference scaled like the Jacobian rows (E7)."""

        jac_scaling: str = eqx.field(static=True, default="consistent")

    class AccelerationOSCConsistent(rj.AccelerationOSC):
        """Acceleration OSC with the reference scaled like the Jacobian rows (E7)."""

        jac_scaling: str = eqx.field(static=True, default="consistent")

    rj.CONTROLLERS["velocity_consistent"] = VelocityOSCConsistent
    rj.CONTROLLERS["acceleration_consistent"] = AccelerationOSCConsistent


def main(argv=None) -> int:
    args = parse_args(argv)
    from redman_jax._study import load_runs, run_sweep

    from _table import ablation_config, markdown, summarise

    register()
    cfg = ablation_config(args, VARIANTS, CASES)
    cases = cfg.cases
    out = run_sweep(cfg, _worker_init=register)
    rows = load_runs(out)

    header = ["case", "controller", "jac_scaling", "failed", "collided", "pos error [mm]", "ori error"]

    def table(stats, label):
        lines = []
        for group in label:
            for name, (ctrl, scaling) in VARIANTS.items():
                s = stats.get((group, name))
                if s is not None:
                    lines.append([group, ctrl, scaling, f"{s['runs'] - s['success']}/{s['runs']}", s["collided"],
                                  s["mean_pos_error_mm"], s["mean_ori_error"]])
        return lines

    per_case = summarise(rows, lambda r: (r["case"], r["controller"]))
    overall = summarise(rows, lambda r: ("all", r["controller"]))
    print(markdown(header, table(per_case, cases) + table(overall, ("all",))))
    print("\nErrors: mean over the successful runs of each run's mean error per sample (orientation: "
          "sin(phi/2) over the samples with orientation control on).")
    print(f"{len(rows)} runs in {Path(out) / 'runs.csv'} (runs on scenarios that did not validate are left "
          "out of the tables)")
    return 0


if __name__ == "__main__":
    from _table import run_main

    sys.exit(run_main(main))
