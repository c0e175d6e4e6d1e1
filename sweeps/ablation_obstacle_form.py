"""Ablation E4: the gradient-guided controller under the two obstacle-potential forms.

SPEC E4: the thesis's 2.38 uses ``V = a (1/r - 1/D) / r^2`` ("minus", continuous at the range
``D``; our default) while 3.8/3.9 use ``+1/D`` ("plus", what the MATLAB code probably ran: a jump
of ``2a/D^3`` at ``D``, 1.2-1.7x stronger at 0.1-0.3 m, shifting the goal minimum more). SPEC asks
to report the gradient-guided results under both. The form is a static option of
:class:`redman_jax.FieldParams`, reached through the gradient controller's gains
(``GradientGains.field``); the simulator's local-minima estimator uses the same field (it takes
``gains.field`` when ``SimParams.field`` is None), so potential, guidance and estimator agree.

Two controllers are registered: ``gradient`` (the default, form "minus") and ``gradient_plus``
(``GradientGains(field=FieldParams(form="plus"))``; everything else identical, including the
null-space obstacle policy of 3.34, which keeps its own default form). Both run on the three
point-to-point cases (agriculture, warehouse, simple) x arms x seeds through the study machinery
(resumable), and the script prints successes, collisions, diverged runs (and of them those that
used up the step budget, whose outcome the budget decided), mean time to goal and final distance
per case and form beside the thesis's successes.

    .venv/bin/python sweeps/ablation_obstacle_form.py --out results_ablation_form
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

GRADIENT_CASES = ("agriculture", "warehouse", "simple")
VARIANTS = {"gradient": "minus", "gradient_plus": "plus"}


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description="E4 ablation: gradient-guided success under the 'minus' and "
                                             "'plus' obstacle-potential forms (resumable).")
    ap.add_argument("--out", default="results_ablation_form", help="results folder (default results_ablation_form)")
    ap.add_argument("--arms", default="7,8,9", help="arms: 7,8,9 and/or urdf:PATH:TIP (default 7,8,9)")
    ap.add_argument("--cases", default=",".join(GRADIENT_CASES),
                    help="point-to-point cases (default agriculture,warehouse,simple)")
    ap.add_argument("--seeds", default="1-20", help="seeds (default 1-20)")
    ap.add_argument("--max-retries", type=int, default=20, help="IK-validation retries per seed (default 20)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    from _table import add_jobs_option

    add_jobs_option(ap)
    return ap.parse_args(argv)


def register() -> None:
    """Add ``gradient_plus`` to the controller registry (``gradient`` is the "minus" default)."""
    import redman_jax as rj

    class GradientPlus(rj.GradientGuided):
        """Gradient-guided controller whose guidance field uses the "plus" form (3.8/3.9, E4)."""

        def default_gains(self):
            return rj.GradientGains(field=rj.FieldParams(form="plus"))

    rj.CONTROLLERS["gradient_plus"] = GradientPlus


def out_of_steps_budget() -> int:
    """The step budget of a gradient-guided run (``SimParams``' steps per sample times its horizon in
    samples): a run that takes this many steps ran out of it."""
    from redman_jax._sim import SimParams

    p = SimParams()
    return p.max_steps_per_sample * p.guidance_samples


def ran_out_of_steps(r: dict, budget: int) -> bool:
    """A run that used up its solver's step budget: the table's ``out_of_steps`` column, or in a
    table written before that column (empty there) ``n_steps`` at ``budget``."""
    from _table import _flag, _num

    if r.get("out_of_steps") not in (None, ""):
        return _flag(r["out_of_steps"])
    return _num(r.get("n_steps")) >= budget


def main(argv=None) -> int:
    args = parse_args(argv)
    from redman_jax._report import THESIS_GRADIENT_SUCCESS
    from redman_jax._study import load_runs, run_sweep

    from _table import ablation_config, markdown, summarise, valid_runs

    register()
    cfg = ablation_config(args, VARIANTS, GRADIENT_CASES)
    cases = cfg.cases
    out = run_sweep(cfg, _worker_init=register)
    rows = load_runs(out)

    stats = summarise(rows, lambda r: (r["case"], r["controller"]))
    budget = out_of_steps_budget()
    spent = {}  # runs that used up the step budget (flagged diverged: the budget decided them)
    for r in valid_runs(rows):
        if ran_out_of_steps(r, budget):
            spent[(r["case"], r["controller"])] = spent.get((r["case"], r["controller"]), 0) + 1
    lines = []
    for case in cases:
        for ctrl, form in VARIANTS.items():
            s = stats.get((case, ctrl))
            if s is None:
                continue
            thesis = THESIS_GRADIENT_SUCCESS.get(case)
            lines.append([case, form, f"{s['success']}/{s['runs']}", s["collided"],
                          f"{s['diverged']} ({spent.get((case, ctrl), 0)})",
                          s["time_to_goal_s"], s["final_pos_error_mm"],
                          f"{thesis[0]}/{thesis[1]}" if thesis and len(cfg.arms) == 3 else "–"])
    print(markdown(["case", "form", "success", "collided", f"diverged (of them out of the {budget:,}-step budget)",
                    "time to goal [s] (successes)",
                    "final distance [mm] (all)", "thesis success (3 arms)"], lines))
    per_arm = summarise(rows, lambda r: (r["arm"], r["controller"]))
    print()
    print(markdown(["arm", "form", "success", "collided"],
                   [[arm, VARIANTS[c], f"{s['success']}/{s['runs']}", s["collided"]]
                    for (arm, c), s in sorted(per_arm.items())]))
    print(f"\n{len(rows)} runs in {Path(out) / 'runs.csv'} (runs on scenarios that did not validate are "
          "left out of the tables)")
    return 0


if __name__ == "__main__":
    from _table import run_main

    sys.exit(run_main(main))
