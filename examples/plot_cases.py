"""Write one figure per case (thesis Figure 3.2 A-E, 9-DOF arm) and a potential-field slice of
the warehouse case (Figure 3.4) as PNG files.

Usage: ``python examples/plot_cases.py [OUT_DIR] [--seed N] [--dof 9]`` (default ``./out``).
The RRT cases (agriculture, simple) compile the planner once each, which dominates the cost.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import redman_jax  # noqa: E402
from redman_jax._cases import make_scenario  # noqa: E402
from redman_jax._plots import plot_field_slice, plot_scenario  # noqa: E402
from redman_jax._scenario import CASES  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--dof", type=int, default=9, choices=(7, 8, 9))
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    arm = redman_jax.thesis_arm(args.dof)
    scenes = {}
    for case in args.cases:
        t0 = time.perf_counter()
        sc = make_scenario(case, args.seed, arm)
        scenes[case] = sc
        ax = plot_scenario(sc, arm)
        ax.legend(loc="upper right", fontsize=6, frameon=False)
        path = out / f"case_{case}_seed{args.seed}_{args.dof}dof.png"
        ax.figure.savefig(path, dpi=150, bbox_inches="tight")
        plt.close(ax.figure)
        print(f"{path}  ({time.perf_counter() - t0:.1f} s, {int(sc.reference.n_samples)} samples, "
              f"seed used {int(sc.seed_used)})")
    if "warehouse" in scenes:
        ax = plot_field_slice(scenes["warehouse"], normal="z")
        path = out / f"field_warehouse_seed{args.seed}.png"
        ax.figure.savefig(path, dpi=150, bbox_inches="tight")
        plt.close(ax.figure)
        print(path)


if __name__ == "__main__":
    main()
