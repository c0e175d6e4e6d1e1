"""Figures and the generated report of a study, side by side with the thesis (thesis 4 and 6; SPEC 10-11).

:func:`make_report` reads a results folder written by :func:`redman_jax._study.run_sweep`
(``DIR/runs.csv``, ``DIR/traces/<arm>_<case>_<controller>.npz``, ``DIR/config.json``) and writes

* ``DIR/figures/fig4_*.png``: the table- and trace-driven figures of thesis chapter 4 (one PNG each),
* ``DIR/figures/fig3_*.png`` and the field / dense-output figures through optional hooks into other
  modules (a missing hook is reported as "not generated (reason)", never raised),
* ``DIR/report.md``: the configuration, the headline table, and one section per quantitative
  statement of the thesis (SPEC section 11, R1-R8, and the hypothesis verdicts of chapter 6), each
  with the thesis's number or ordering, ours, and a verdict *computed from the data*.

Metrics follow SPEC section 10:

* **Position error** of a (case, arm, controller): the pooled mean over all valid samples of its
  successful runs, ``sum_i n_i e_i / sum_i n_i`` with ``e_i`` the run's mean per-sample error and
  ``n_i`` its number of samples (the thesis's "average per sample over all runs"). Gradient-guided
  runs have no reference trajectory and are excluded.
* **Orientation error** ``|e_o| = sin(phi/2)`` (E19) pooled over the ``rot = 1`` samples of the
  successful runs, from the traces (falling back to the mean of the runs' means without traces).
* **Failure**: collision or final error > 0.10 m; the cause is "collision" when the run collided
  (whatever the final error), "diverged" when the integration blew up or stopped (of these, column
  ``out_of_steps`` marks the runs whose solver used up its step budget), otherwise "not reached".
* **Total compute per test case** ``T = sum_c t_c * mean(N_samples)`` over the components ``c`` a
  controller needs (:data:`COST_COMPONENTS`): joint space = controller + IK + planning; operational
  space = controller + planning; gradient-guided = controller + local-minima estimator, times its
  own mean number of samples (it follows no planned trajectory).

The thesis timings are MATLAB wall times; only orderings and ratios are compared (SPEC section 10).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import functools
import json
import math
import platform
import re
import warnings
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

__all__ = [
    "make_report",
    "headline_table",
    "evaluate_claims",
    "Claim",
    "StudyData",
    "load_study",
    "FIGURES",
    "COST_COMPONENTS",
    "AGREES",
    "PARTLY",
    "DIFFERS",
    "NOT_EVALUATED",
]

AGREES, PARTLY, DIFFERS, NOT_EVALUATED = "agrees", "partly agrees", "differs", "not evaluated"

SUCCESS_RADIUS = 0.10  # [m] (thesis 3.5)
TRAJECTORY_CONTROLLERS = ("joint_space", "velocity", "acceleration")
OSC = ("velocity", "acceleration")
GUIDED = ("gradient",)
# Components of the total compute per test case (thesis 4.3): what each controller has to run.
COST_COMPONENTS: dict[str, tuple[str, ...]] = {
    "joint_space": ("controller", "ik", "planning"),
    "pid": ("controller", "ik", "planning"),
    "gradient": ("controller", "lme"),
}
DEFAULT_COST = ("controller", "planning")  # operational-space controllers
RRT_CASES = ("agriculture", "simple")

# Decision thresholds of the computed verdicts (stated in the report).
MOST = 0.5  # "in most cases": strictly more than half
ALMOST_ALL = 0.8  # "in almost all cases": at least 80 %
MODEL_SPREAD = 1.25  # "models do not differ": max / min over the arms <= 1.25
ROUGHLY_CONSTANT = 1.5  # "roughly constant across models": max / min over the arms <= 1.5
SIMILAR = 1.15  # "a ~ b": ratio within 15 %
APPROX_FACTOR = 2.0  # "about k times": within a factor 2 of k
ACC_LIMIT = 2.5  # [m/s^2] "accelerations stay <= about 2 m/s^2": the 99th percentile <= 2.5

# Thesis numbers (chapter 4, 6; SPEC section 11).
THESIS_CONTROLLER_TIME = {"joint_space": 0.0017, "velocity": 0.0022, "gradient": 0.0023, "acceleration": 0.0026}
THESIS_GRADIENT_SUCCESS = {"agriculture": (49, 60), "warehouse": (2, 60), "simple": (60, 60)}
THESIS_WAREHOUSE_PER_ARM = {7: (0, 20), 8: (2, 20), 9: (0, 20)}

CONTROLLER_LABELS = {
    "joint_space": "Joint space",
    "velocity": "Velocity OSC",
    "acceleration": "Acceleration OSC",
    "gradient": "Gradient-guided",
    "pid": "PID",
    "velocity_original": "Velocity OSC (orig.)",
    "impedance": "Impedance",
}
CONTROLLER_COLORS = {
    "joint_space": "#1f77b4",
    "velocity": "#ff7f0e",
    "acceleration": "#2ca02c",
    "gradient": "#d62728",
    "pid": "#9467bd",
    "velocity_original": "#8c564b",
    "impedance": "#e377c2",
}
COMPONENT_COLORS = {"ik": "#7f7f7f", "planning": "#bcbd22", "lme": "#17becf"}
CASE_LABELS = {"agriculture": "Agriculture", "warehouse": "Warehouse", "inspection": "Inspection",
               "welding": "Welding", "simple": "Simple obstacle"}
_STYLE = {
    "font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
    "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.spines.top": False, "axes.spines.right": False,
    "axes.grid": True, "axes.grid.axis": "y", "grid.alpha": 0.3, "grid.linewidth": 0.6,
    "axes.axisbelow": True, "legend.frameon": False, "savefig.dpi": 150, "savefig.bbox": "tight",
    "hatch.linewidth": 0.6,
}


def _clabel(c: str) -> str:
    return CONTROLLER_LABELS.get(c, c)


def _case_label(c: str) -> str:
    return CASE_LABELS.get(c, c)


# ------------------------------------------------------------------------------------------------
# data


def _num(v) -> float:
    """A table value as a float (NaN when missing or not a number)."""
    if isinstance(v, bool):
        return float(v)
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _flag(v) -> bool:
    if isinstance(v, str):
        return v.strip().lower() in ("true", "1", "yes")
    try:
        return bool(v) and not (isinstance(v, float) and math.isnan(v))
    except (TypeError, ValueError):
        return False


def _scenario_valid(r: dict) -> bool:
    """False for runs on scenarios that no IK retry validated (``scenario_valid``/``valid`` False);
    they are left out of every rate (the thesis counts validated scenarios only)."""
    for key in ("scenario_valid", "valid"):
        v = r.get(key)
        if v not in (None, "") and not (isinstance(v, float) and math.isnan(v)) and not _flag(v):
            return False
    return True


def _dof(arm: str) -> int | None:
    """DOF of a thesis arm label (``"7dof"`` -> 7); ``None`` for other arms."""
    m = re.fullmatch(r"(\d+)dof", str(arm))
    return int(m.group(1)) if m else None


def _ordered(values: Iterable[str], preferred: Iterable[str]) -> list[str]:
    values = list(dict.fromkeys(values))
    pref = [p for p in dict.fromkeys(preferred) if p in values]
    return pref + sorted(v for v in values if v not in pref)


def _mean(xs) -> float:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else math.nan


@dataclasses.dataclass
class Cell:
    """Aggregates of the runs of one (arm, case, controller)."""

    n: int = 0
    n_fail: int = 0
    n_collision: int = 0
    n_not_reached: int = 0
    n_diverged: int = 0
    pos_err: float = math.nan  # pooled over successful runs [m]
    ori_err: float = math.nan  # pooled over rot = 1 samples of successful runs [sin(phi/2)]
    t_controller: float = math.nan  # [s / sample]
    n_samples: float = math.nan  # mean over all runs
    final_errors: tuple = ()

    @property
    def failure_rate(self) -> float:
        return self.n_fail / self.n if self.n else math.nan


class StudyData:
    """The runs table of a results folder with its traces, and the aggregates the report needs.

    ``rows``: dicts as :func:`redman_jax._study.load_runs` returns them; ``out``: the results folder
    (for the traces; ``None`` when there are none).
    """

    def __init__(self, rows: list[dict], out: Path | None = None, config: dict | None = None):
        from ._scenario import CASES

        self.n_excluded = len(rows)
        rows = [r for r in rows if _scenario_valid(r)]
        self.n_excluded -= len(rows)
        self.rows = rows
        self.out = Path(out) if out is not None else None
        self.config = config or {}
        cfg_arms = [a if not str(a).isdigit() else f"{a}dof" for a in self.config.get("arms", ())]
        self.arms = _ordered((str(r["arm"]) for r in rows), cfg_arms + ["7dof", "8dof", "9dof"])
        self.cases = _ordered((str(r["case"]) for r in rows), CASES)
        self.controllers = _ordered((str(r["controller"]) for r in rows), CONTROLLER_LABELS)
        self._traces: dict = {}
        self.cells = {key: self._cell(key) for key in
                      dict.fromkeys((str(r["arm"]), str(r["case"]), str(r["controller"])) for r in rows)}

    # -- selection -------------------------------------------------------------------------------
    def select(self, arm=None, case=None, controller=None) -> list[dict]:
        def ok(v, want):
            return want is None or (str(v) in want if isinstance(want, (tuple, list, set)) else str(v) == want)

        return [r for r in self.rows if ok(r["arm"], arm) and ok(r["case"], case) and ok(r["controller"], controller)]

    def cell(self, arm, case, controller) -> Cell | None:
        return self.cells.get((arm, case, controller))

    @property
    def trajectory_controllers(self) -> list[str]:
        return [c for c in self.controllers if c not in GUIDED]

    # -- traces ------------------------------------------------------------------------------------
    def traces(self, arm, case, controller) -> dict | None:
        """The trace arrays of one (arm, case, controller), or ``None``."""
        key = (arm, case, controller)
        if key not in self._traces:
            data = None
            if self.out is not None:
                path = self.out / "traces" / f"{arm}_{case}_{controller}.npz"
                if path.is_file():
                    try:
                        with np.load(path, allow_pickle=False) as z:
                            data = {k: np.asarray(z[k]) for k in z.files}
                    except Exception as e:  # noqa: BLE001 -- damaged: BadZipFile, EOFError, zlib.error, ...
                        warnings.warn(f"{path}: unreadable traces ({type(e).__name__}: {e}); the figures "
                                      f"that need them are not generated", stacklevel=2)
                        data = None
            self._traces[key] = data
        return self._traces[key]

    # -- aggregates ---------------------------------------------------------------------------------
    def _cell(self, key) -> Cell:
        arm, case, ctrl = key
        runs = self.select(arm, case, ctrl)
        c = Cell(n=len(runs))
        ok_seeds = set()
        pos_num = pos_den = 0.0
        ori_means = []
        for r in runs:
            cause = run_cause(r)
            if cause == "success":
                ok_seeds.add(int(_num(r.get("seed"))) if math.isfinite(_num(r.get("seed"))) else None)
                e, n = _num(r.get("mean_pos_error")), _num(r.get("n_samples"))
                w = n if math.isfinite(n) and n > 0 else 1.0
                if math.isfinite(e):
                    pos_num += w * e
                    pos_den += w
                ori_means.append(_num(r.get("mean_ori_error")))
            else:
                c.n_fail += 1
                c.n_collision += cause == "collision"
                c.n_not_reached += cause == "not reached"
                c.n_diverged += cause == "diverged"
        if ctrl not in GUIDED and pos_den > 0:
            c.pos_err = pos_num / pos_den
        c.ori_err = self._pooled_orientation(arm, case, ctrl, ok_seeds)
        if not math.isfinite(c.ori_err) and ctrl not in GUIDED:
            c.ori_err = _mean(ori_means)
        c.t_controller = _mean(_num(r.get("t_controller_per_sample")) for r in runs)
        c.n_samples = _mean(_num(r.get("n_samples")) for r in runs)
        c.final_errors = tuple(_num(r.get("final_pos_error")) for r in runs)
        return c

    def _pooled_orientation(self, arm, case, ctrl, ok_seeds) -> float:
        if ctrl in GUIDED:
            return math.nan
        tr = self.traces(arm, case, ctrl)
        if not tr or "ori_err" not in tr or "rot" not in tr or "seed" not in tr:
            return math.nan
        err = np.asarray(tr["ori_err"], float)
        sel = np.asarray(tr["rot"]) > 0.5
        if "mask" in tr:
            sel &= np.asarray(tr["mask"], bool)
        run_ok = np.isin(np.asarray(tr["seed"]).astype(int), [s for s in ok_seeds if s is not None])
        sel &= run_ok[:, None] & np.isfinite(err)
        return float(err[sel].mean()) if sel.any() else math.nan

    def component_time(self, arm, case, component) -> float:
        """Mean per-sample time of ``ik``, ``planning`` or ``lme`` over the runs of (arm, case) that
        report one (finite and > 0), or of ``controller`` -- use :meth:`controller_time` for that."""
        col = f"t_{component}_per_sample"
        rows = self.select(arm, case, "gradient" if component == "lme" else None)
        return _mean(v for v in (_num(r.get(col)) for r in rows) if v > 0)

    def trajectory_samples(self, arm, case) -> float:
        """Mean N_samples of the planned trajectories of (arm, case) (over the non-guided runs)."""
        rows = [r for r in self.select(arm, case) if str(r["controller"]) not in GUIDED]
        return _mean(_num(r.get("n_samples")) for r in rows)

    def total_cost(self, arm, case, ctrl) -> float:
        """Total compute per test case ``sum_c t_c x mean N_samples`` (thesis Fig. 4.7)."""
        c = self.cell(arm, case, ctrl)
        if c is None:
            return math.nan
        comps = COST_COMPONENTS.get(ctrl, DEFAULT_COST)
        t = 0.0
        for comp in comps:
            v = c.t_controller if comp == "controller" else self.component_time(arm, case, comp)
            if not math.isfinite(v):
                return math.nan
            t += v
        n = c.n_samples if ctrl in GUIDED else self.trajectory_samples(arm, case)
        return t * n


def run_cause(r: dict) -> str:
    """``"success"``, ``"collision"``, ``"diverged"`` or ``"not reached"`` for one run row.

    ``success`` is taken from the table when present; a failed run is a "collision" when it
    collided (whatever its final error, thesis 4.4), otherwise "diverged" (the integration blew up
    or stopped, its step budget used up included: column ``out_of_steps``) or "not reached".
    """
    if "success" in r and r["success"] not in ("", None):
        ok = _flag(r["success"])
    else:
        ok = (not _flag(r.get("collided"))) and _num(r.get("final_pos_error")) < SUCCESS_RADIUS
    if ok:
        return "success"
    if _flag(r.get("collided")):
        return "collision"
    if _flag(r.get("diverged")):
        return "diverged"
    return "not reached"


def load_study(out) -> StudyData:
    """Read ``DIR/runs.csv`` (and ``DIR/config.json`` when present) into a :class:`StudyData`."""
    from ._study import load_runs

    out = Path(out)
    if not (out / "runs.csv").is_file():
        raise ValueError(f"out_dir: no runs.csv in {str(out)!r}; run a sweep first")
    config = {}
    if (out / "config.json").is_file():
        try:
            config = json.loads((out / "config.json").read_text())
        except (OSError, json.JSONDecodeError):
            config = {}
    rows = load_runs(out)
    missing = [c for c in _REQUIRED_COLUMNS if rows and c not in rows[0]]
    if missing:  # a KeyError deep in the report (in its worker process) otherwise
        raise ValueError(f"{str(out / 'runs.csv')!r}: not a runs table of a sweep, no column(s) {missing}")
    return StudyData(rows, out, config)


_REQUIRED_COLUMNS = ("arm", "case", "controller")  # indexed directly; the rest may be missing


# ------------------------------------------------------------------------------------------------
# headline table


def _fmt(x, spec=".1f", missing="–") -> str:
    return missing if x is None or not math.isfinite(x) else format(x, spec)


def headline_table(rows: list[dict] | StudyData) -> str:
    """Markdown table: failure rate and mean position error per case x controller (rows) and arm.

    ``rows``: the runs table (list of dicts, as :func:`redman_jax._study.load_runs` returns) or a
    :class:`StudyData`. Each arm gets a "failed" column (``failed/runs``) and an "error [mm]" column
    (pooled mean position error per sample over the successful runs; "–" for the gradient-guided
    controller, which follows no trajectory, and where no run succeeded).
    """
    data = rows if isinstance(rows, StudyData) else StudyData(list(rows))
    head = ["case", "controller"]
    for a in data.arms:
        head += [f"{a} failed", f"{a} error [mm]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|"]
    for case in data.cases:
        for ctrl in data.controllers:
            if not any(data.cell(a, case, ctrl) for a in data.arms):
                continue
            cols = [_case_label(case), _clabel(ctrl)]
            for a in data.arms:
                c = data.cell(a, case, ctrl)
                if c is None:
                    cols += ["", ""]
                else:
                    cols += [f"{c.n_fail}/{c.n} ({100 * c.failure_rate:.0f} %)", _fmt(1e3 * c.pos_err, ".2f")]
            lines.append("| " + " | ".join(cols) + " |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------
# claims


@dataclasses.dataclass(frozen=True)
class Claim:
    """One quantitative statement of the thesis with our number and the computed verdict."""

    id: str  # e.g. "R3.a"
    statement: str
    thesis: str
    ours: str
    verdict: str  # AGREES, PARTLY, DIFFERS or NOT_EVALUATED
    why: str = ""

    @property
    def section(self) -> str:
        return self.id.split(".")[0]


SECTIONS = {
    "R1": "R1 - Controller compute time per sample",
    "R2": "R2 - Gradient-guided success",
    "R3": "R3 - Failures",
    "R4": "R4 - Projected efficiency of the gradient-guided approach",
    "R5": "R5 - Compute-cost orderings",
    "R6": "R6 - Position tracking",
    "R7": "R7 - Orientation tracking",
    "R8": "R8 - Error within a sample",
    "H": "Hypothesis verdicts (thesis chapter 6)",
}


def _v(ok: bool | None) -> str:
    return NOT_EVALUATED if ok is None else (AGREES if ok else DIFFERS)


def _frac_verdict(n_ok: int, n: int, need: float) -> str:
    """AGREES when the fraction n_ok / n reaches ``need`` (>, for MOST), PARTLY when some hold."""
    if n == 0:
        return NOT_EVALUATED
    f = n_ok / n
    ok = f > need if need == MOST else f >= need
    return AGREES if ok else (PARTLY if n_ok > 0 else DIFFERS)


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k / n."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    # exact ends: rounding leaves e.g. 60/60 at 0.9999999999999999, which would exclude a 100 %
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def _not_eval(cid, statement, thesis, reason) -> Claim:
    return Claim(cid, statement, thesis, "–", NOT_EVALUATED, reason)


def _ratio_str(d: dict, base: str) -> str:
    b = d.get(base)
    if b is None or not math.isfinite(b) or b <= 0:
        return ""
    return ", ".join(f"{_clabel(k)} {v / b:.2f}x" for k, v in d.items() if math.isfinite(v))


def _claims_r1(d: StudyData) -> list[Claim]:
    out = []
    ctrls = [c for c in THESIS_CONTROLLER_TIME if c in d.controllers]
    t = {c: _mean(d.cells[k].t_controller for k in d.cells if k[2] == c) for c in ctrls}
    t = {c: v for c, v in t.items() if math.isfinite(v)}
    thesis_t = ", ".join(f"{_clabel(c)} {v * 1e3:.1f} ms" for c, v in THESIS_CONTROLLER_TIME.items())
    thesis_ratio = _ratio_str(THESIS_CONTROLLER_TIME, "joint_space")
    stmt = "Ordering JS < velocity ~ gradient < acceleration (per-sample controller time)"
    need = {"joint_space", "velocity", "acceleration"}
    if not need <= set(t):
        out.append(_not_eval("R1.a", stmt, thesis_t, "needs controller times of JS, velocity and acceleration"))
    else:
        js, vel, acc = t["joint_space"], t["velocity"], t["acceleration"]
        mids = [vel] + ([t["gradient"]] if "gradient" in t else [])
        checks = {"JS fastest": js < min(mids + [acc]), "acceleration slowest": acc > max(mids + [js])}
        if "gradient" in t:
            r = max(vel, t["gradient"]) / min(vel, t["gradient"])
            checks[f"velocity ~ gradient (within {SIMILAR:.2f}x)"] = r <= SIMILAR
        n_ok = sum(checks.values())
        verdict = AGREES if n_ok == len(checks) else (PARTLY if n_ok else DIFFERS)
        order = " < ".join(_clabel(c) for c in sorted(t, key=t.get))
        ours = ", ".join(f"{_clabel(c)} {v * 1e3:.3g} ms" for c, v in t.items())
        why = (f"measured ordering {order}; ratios to JS: ours {_ratio_str(t, 'joint_space')}, thesis "
               f"{thesis_ratio}. " + "; ".join(f"{k}: {'yes' if ok else 'no'}" for k, ok in checks.items())
               + ". Ours: the control law's compute per sample, one compiled loop over a run's samples "
               "(dispatch excluded, as IK and planning are timed); absolute times are JAX (jit, CPU) "
               "against MATLAB and are not comparable.")
        out.append(Claim("R1.a", stmt, thesis_t, ours, verdict, why))
    # models do not differ
    stmt = f"Controller time does not differ between models (max/min over arms <= {MODEL_SPREAD})"
    spreads = {}
    for c in ctrls:
        per_arm = [_mean(d.cells[k].t_controller for k in d.cells if k[0] == a and k[2] == c) for a in d.arms]
        per_arm = [v for v in per_arm if math.isfinite(v) and v > 0]
        if len(per_arm) >= 2:
            spreads[c] = max(per_arm) / min(per_arm)
    if not spreads:
        out.append(_not_eval("R1.b", stmt, "insignificant", "needs at least two arms with controller times"))
    else:
        worst = max(spreads.values())
        out.append(Claim("R1.b", stmt, "insignificant",
                         ", ".join(f"{_clabel(c)} {s:.2f}x" for c, s in spreads.items()),
                         _v(worst <= MODEL_SPREAD),
                         f"largest spread over the arms {worst:.2f}x"))
    return out


def _claims_r2(d: StudyData) -> list[Claim]:
    out = []
    grows = d.select(controller="gradient")
    if not grows:
        return [_not_eval("R2.a", "Gradient-guided success per case", "82 % / 2 of 60 / 100 %",
                          "no gradient-guided runs in this study")]
    for i, case in enumerate(("agriculture", "warehouse", "simple")):
        cid = f"R2.{'abc'[i]}"
        k_t, n_t = THESIS_GRADIENT_SUCCESS[case]
        thesis = f"{k_t}/{n_t} ({100 * k_t / n_t:.0f} %)"
        rows = d.select(case=case, controller="gradient")
        stmt = f"Gradient-guided success in {_case_label(case)}"
        if not rows:
            out.append(_not_eval(cid, stmt, thesis, f"no gradient-guided runs in {case}"))
            continue
        k = sum(run_cause(r) == "success" for r in rows)
        n = len(rows)
        lo, hi = wilson_interval(k, n)
        p_t = k_t / n_t
        per_arm = ", ".join(
            f"{a} {sum(run_cause(r) == 'success' for r in d.select(a, case, 'gradient'))}"
            f"/{len(d.select(a, case, 'gradient'))}" for a in d.arms if d.select(a, case, "gradient"))
        why = (f"thesis {100 * p_t:.0f} % {'inside' if lo <= p_t <= hi else 'outside'} our 95 % Wilson "
               f"interval [{100 * lo:.0f} %, {100 * hi:.0f} %]; per arm: {per_arm}")
        if case == "warehouse":
            why += " (thesis per arm: 7dof 0/20, 8dof 2/20, 9dof 0/20)"
        why += _field_shift_note(rows)
        if case == "agriculture":  # the study's field is always the default form (--gains sets scalars)
            why += ("; the guidance field in the continuous 'minus' form of 2.38 (SPEC E4); the literal "
                    "'plus' form of 3.8/3.9 is run by sweeps/ablation_obstacle_form.py")
        out.append(Claim(cid, stmt, thesis, f"{k}/{n} ({100 * k / n:.0f} %)", _v(lo <= p_t <= hi), why))
    fails = [r for r in grows if run_cause(r) != "success"]
    n_coll = sum(run_cause(r) == "collision" for r in fails)
    diverged = [r for r in fails if run_cause(r) == "diverged"]
    n_div = len(diverged)
    stmt = "Every gradient-guided failure is 'goal not reached'"
    if not fails:
        out.append(Claim("R2.d", stmt, "all failures not reached", "no failures", NOT_EVALUATED,
                         "no gradient-guided run failed"))
    else:
        far = [_num(r.get("final_pos_error")) for r in fails]
        far = [x for x in far if math.isfinite(x)]
        why = (f"{len(fails) - n_coll - n_div} not reached, {n_coll} collided, {n_div} diverged"
               + _out_of_steps_note(diverged)
               + (f"; final distance of the failures median {np.median(far):.3f} m, max {max(far):.3f} m"
                  if far else ""))
        out.append(Claim("R2.d", stmt, "all failures not reached",
                         f"{len(fails) - n_coll - n_div} of {len(fails)} not reached",
                         _v(n_coll == 0 and n_div == 0), why))
    return out


def _out_of_steps_note(diverged) -> str:
    """Of the ``diverged`` rows, those whose solver used up its step budget (column
    ``out_of_steps``): runs that may never have blown up, and those of them that ended within the
    success radius, a success the budget decided (absent from older tables: no note)."""
    spent = [r for r in diverged if _flag(r.get("out_of_steps"))]
    if not spent:
        return ""
    near = sum(_num(r.get("final_pos_error")) < SUCCESS_RADIUS for r in spent)
    return (f" ({len(spent)} of them out of the solver's step budget"
            + (f", {near} of those within {100 * SUCCESS_RADIUS:.0f} cm of the goal at their last "
               "sample" if near else "") + ")")


def _field_shift_note(rows) -> str:
    """How many scenes put the guidance field's minimum beyond the success radius (column
    ``goal_field_shift``, see ``_guidance.goal_field_minimum``): a bound no controller beats."""
    shifts = [_num(r.get("goal_field_shift")) for r in rows]
    pairs = [(x, r) for x, r in zip(shifts, rows) if math.isfinite(x)]
    if not pairs:
        return ""
    far = [r for x, r in pairs if x > 0.10]
    near = [r for x, r in pairs if x <= 0.10]
    ok_near = sum(run_cause(r) == "success" for r in near)
    return (f"; the field's minimum lies more than 0.10 m from the goal in {len(far)}/{len(pairs)} "
            f"scenes (unreachable for any controller that follows the field); success in the "
            f"other {len(near)}: {ok_near}")


def _fail_rate(d: StudyData, arms=None, cases=None, ctrls=None) -> tuple[int, int]:
    rows = d.select(arms, cases, ctrls)
    return sum(run_cause(r) != "success" for r in rows), len(rows)


def _claims_r3(d: StudyData) -> list[Claim]:
    out = []
    js = d.select(controller="joint_space")
    if not js:
        out.append(_not_eval("R3.a", "Joint space has 0 failures", "0", "no joint-space runs"))
    else:
        fails = [r for r in js if run_cause(r) != "success"]
        where = ", ".join(sorted({f"{r['arm']}/{r['case']}" for r in fails}))
        causes = ", ".join(f"{sum(run_cause(r) == c for r in fails)} {c}"
                           for c in ("collision", "not reached", "diverged") if any(run_cause(r) == c for r in fails))
        out.append(Claim("R3.a", "Joint space has 0 failures", "0 failures",
                         f"{len(fails)} of {len(js)} runs failed", _v(not fails),
                         f"failures in {where} ({causes})" if fails else "no joint-space run failed"))
    osc = d.select(controller=OSC)
    fails = [r for r in osc if run_cause(r) != "success"]
    stmt = "Every velocity/acceleration OSC failure is a collision"
    if not osc:
        out.append(_not_eval("R3.b", stmt, "all collisions", "no OSC runs"))
    elif not fails:
        out.append(Claim("R3.b", stmt, "all collisions", "no OSC failures", NOT_EVALUATED,
                         "no velocity/acceleration run failed, so the cause cannot be compared"))
    else:
        n_coll = sum(run_cause(r) == "collision" for r in fails)
        missed = sum(run_cause(r) == "collision" and _num(r.get("final_pos_error")) >= SUCCESS_RADIUS for r in fails)
        out.append(Claim("R3.b", stmt, "all collisions, some then miss the goal",
                         f"{n_coll} of {len(fails)} collisions ({missed} of them also miss the goal)",
                         _v(n_coll == len(fails)),
                         f"{len(fails) - n_coll} failures without a collision" if n_coll < len(fails) else ""))
    non_js = [c for c in d.controllers if c != "joint_space"]
    stmt = "Every case has some failure of a non-JS controller"
    if not non_js:
        out.append(_not_eval("R3.c", stmt, "yes", "only joint-space runs"))
    else:
        per_case = {case: _fail_rate(d, cases=case, ctrls=non_js)[0] for case in d.cases}
        none = [c for c, k in per_case.items() if k == 0]
        out.append(Claim("R3.c", stmt, f"all {len(d.cases)} cases" if len(d.cases) != 5 else "all 5 cases",
                         ", ".join(f"{c} {k}" for c, k in per_case.items()),
                         AGREES if not none else (PARTLY if len(none) < len(per_case) else DIFFERS),
                         f"cases without any non-JS failure: {', '.join(none)}" if none else ""))
    dofs = sorted((_dof(a), a) for a in d.arms if _dof(a) is not None)
    stmt = "Failures increase as the DOF decreases (velocity + acceleration OSC)"
    # an arm without OSC runs has no rate to order
    rates = [r for r in ((dof, *_fail_rate(d, arms=a, ctrls=OSC)) for dof, a in dofs) if r[2]] if osc else []
    if len(rates) < 2:
        out.append(_not_eval("R3.d", stmt, "7 > 8 > 9 DOF", "needs at least two thesis arms with OSC runs"))
    else:
        fr = [k / n for _, k, n in rates]
        mono = all(fr[i] >= fr[i + 1] for i in range(len(fr) - 1)) and fr[0] > fr[-1]
        out.append(Claim("R3.d", stmt, "7 > 8 > 9 DOF",
                         ", ".join(f"{dof}-DOF {k}/{n}" for dof, k, n in rates),
                         _v(mono), "" if mono else "the failure rate does not fall monotonically with the DOF"))
    return out


def _per_sample_cost(d: StudyData, arm, case, ctrl) -> float:
    c = d.cell(arm, case, ctrl)
    if c is None:
        return math.nan
    t = 0.0
    for comp in COST_COMPONENTS.get(ctrl, DEFAULT_COST):
        v = c.t_controller if comp == "controller" else d.component_time(arm, case, comp)
        t += v if math.isfinite(v) else math.nan
    return t


def _claims_r4(d: StudyData) -> list[Claim]:
    out = []
    cases = [c for c in RRT_CASES if c in d.cases]
    thesis = {"joint_space": 10.0, "osc": 3.0}
    ratios = {"joint_space": [], "osc": []}
    detail = []
    for a in d.arms:
        for case in cases:
            g = _per_sample_cost(d, a, case, "gradient")
            if not (math.isfinite(g) and g > 0):
                continue
            js = _per_sample_cost(d, a, case, "joint_space")
            osc = [_per_sample_cost(d, a, case, c) for c in OSC]
            osc = [x for x in osc if math.isfinite(x)]
            if math.isfinite(js):
                ratios["joint_space"].append(js / g)
            if osc:
                ratios["osc"].append(np.mean(osc) / g)
            detail.append(f"{a}/{case}: JS {js / g:.1f}x, OSC {np.mean(osc) / g if osc else math.nan:.1f}x")
    for key, cid, who in (("joint_space", "R4.a", "JS"), ("osc", "R4.b", "the OSC methods")):
        stmt = f"Gradient-guided up to ~{thesis[key]:.0f}x more efficient than {who} (per-sample cost, RRT cases)"
        if not ratios[key]:
            out.append(_not_eval(cid, stmt, f"~{thesis[key]:.0f}x", "needs gradient-guided and comparison timings "
                                 "in agriculture or simple"))
            continue
        best = max(ratios[key])
        ok = thesis[key] / APPROX_FACTOR <= best <= thesis[key] * APPROX_FACTOR
        out.append(Claim(cid, stmt, f"up to ~{thesis[key]:.0f}x", f"up to {best:.1f}x", _v(ok),
                         f"within a factor {APPROX_FACTOR:.0f} of the thesis: {'yes' if ok else 'no'}; "
                         f"per-sample cost (controller + IK/planning vs controller + LME) "
                         + "; ".join(detail)))
    return out


def _claims_r5(d: StudyData) -> list[Claim]:
    out = []
    # R5.a: IK dominates, then planning (RRT), controller small
    comp = {}
    for case in d.cases:
        comp[case] = {
            "ik": _mean(d.component_time(a, case, "ik") for a in d.arms),
            "planning": _mean(d.component_time(a, case, "planning") for a in d.arms),
            "controller": _mean(d.cells[k].t_controller for k in d.cells if k[1] == case),
        }
    stmt = "Cost is dominated by the IK, then RRT planning; the controller is small"
    if not all(math.isfinite(v) for c in comp.values() for v in (c["ik"], c["controller"])):
        out.append(_not_eval("R5.a", stmt, "IK > planning (RRT) > controller", "needs IK and controller timings"))
    else:
        ik_top = sum(c["ik"] >= max(c["planning"] if math.isfinite(c["planning"]) else 0, c["controller"])
                     for c in comp.values())
        rrt = [c for c in RRT_CASES if c in comp and math.isfinite(comp[c]["planning"])]
        plan_ok = sum(comp[c]["planning"] > comp[c]["controller"] for c in rrt)
        n_ok, n = ik_top + plan_ok, len(comp) + len(rrt)
        ours = "; ".join(f"{c}: IK {v['ik'] * 1e3:.3g}, planning {v['planning'] * 1e3:.3g}, controller "
                         f"{v['controller'] * 1e3:.3g} ms/sample" for c, v in comp.items())
        out.append(Claim("R5.a", stmt, "IK > planning (RRT cases) > controller", ours,
                         AGREES if n_ok == n else (PARTLY if n_ok else DIFFERS),
                         f"IK is the largest component in {ik_top} of {len(comp)} cases; planning exceeds the "
                         f"controller in {plan_ok} of {len(rrt)} RRT cases"))
    # R5.b: total ordering
    stmt = "Total per test case: JS > acceleration >~ velocity > gradient-guided"
    checks = []
    for a in d.arms:
        for case in d.cases:
            T = {c: d.total_cost(a, case, c) for c in ("joint_space", "acceleration", "velocity", "gradient")}
            if not all(math.isfinite(T[c]) for c in ("joint_space", "acceleration", "velocity")):
                continue
            ok = T["joint_space"] > T["acceleration"] and T["joint_space"] > T["velocity"]
            ok &= T["acceleration"] >= T["velocity"] / SIMILAR
            if math.isfinite(T["gradient"]):
                ok &= T["gradient"] < min(T["acceleration"], T["velocity"])
            checks.append(ok)
    means = {c: _mean(d.total_cost(a, case, c) for a in d.arms for case in d.cases)
             for c in ("joint_space", "acceleration", "velocity", "gradient")}
    if not checks:
        out.append(_not_eval("R5.b", stmt, "JS > acc >~ vel > gradient", "needs timings of JS, velocity, acceleration"))
    else:
        out.append(Claim("R5.b", stmt, "JS > acc >~ vel > gradient",
                         ", ".join(f"{_clabel(c)} {v:.3g} s" for c, v in means.items() if math.isfinite(v))
                         + " (mean over arms and cases)",
                         _frac_verdict(sum(checks), len(checks), ALMOST_ALL),
                         f"ordering holds in {sum(checks)} of {len(checks)} (arm, case) cells "
                         f"(acc >~ vel: acc >= vel / {SIMILAR}); ratios to JS: {_ratio_str(means, 'joint_space')}"))
    # R5.c: models do not differ
    stmt = f"Total cost does not differ between models (max/min over arms <= {MODEL_SPREAD})"
    spreads = []
    for case in d.cases:
        for c in d.controllers:
            v = [d.total_cost(a, case, c) for a in d.arms]
            v = [x for x in v if math.isfinite(x) and x > 0]
            if len(v) >= 2:
                spreads.append((max(v) / min(v), case, c))
    if not spreads:
        out.append(_not_eval("R5.c", stmt, "no significant difference", "needs at least two arms"))
    else:
        n_ok = sum(s <= MODEL_SPREAD for s, _, _ in spreads)
        worst = max(spreads)
        out.append(Claim("R5.c", stmt, "no significant difference",
                         f"{n_ok} of {len(spreads)} (case, controller) within {MODEL_SPREAD}x",
                         _frac_verdict(n_ok, len(spreads), ALMOST_ALL),
                         f"largest spread {worst[0]:.2f}x ({worst[2]}, {worst[1]})"))
    # R5.d: planning simple > agriculture; IK agriculture > simple; simple has more samples
    stmt = "Planning: simple > agriculture; IK: agriculture > simple; simple has more samples"
    if not {"agriculture", "simple"} <= set(d.cases):
        out.append(_not_eval("R5.d", stmt, "yes", "needs the agriculture and simple cases"))
    else:
        pa, ps = comp["agriculture"]["planning"], comp["simple"]["planning"]
        ia, is_ = comp["agriculture"]["ik"], comp["simple"]["ik"]
        na = _mean(d.trajectory_samples(a, "agriculture") for a in d.arms)
        ns = _mean(d.trajectory_samples(a, "simple") for a in d.arms)
        checks = {"planning simple > agriculture": ps > pa, "IK agriculture > simple": ia > is_,
                  "N simple > agriculture": ns > na}
        n_ok = sum(checks.values())
        out.append(Claim("R5.d", stmt, "all three",
                         f"planning {ps * 1e3:.3g} vs {pa * 1e3:.3g} ms, IK {ia * 1e3:.3g} vs {is_ * 1e3:.3g} ms"
                         f" per sample, N {ns:.0f} vs {na:.0f}",
                         AGREES if n_ok == 3 else (PARTLY if n_ok else DIFFERS),
                         "; ".join(f"{k}: {'yes' if v else 'no'}" for k, v in checks.items())))
    # R5.e: gradient clearly wins in RRT cases
    stmt = f"In the RRT cases the gradient approach clearly wins on compute (>= {APPROX_FACTOR:.0f}x cheaper)"
    wins = []
    for a in d.arms:
        for case in RRT_CASES:
            g = d.total_cost(a, case, "gradient")
            others = [d.total_cost(a, case, c) for c in TRAJECTORY_CONTROLLERS]
            others = [x for x in others if math.isfinite(x)]
            if math.isfinite(g) and others:
                wins.append((min(others) / g, a, case))
    if not wins:
        out.append(_not_eval("R5.e", stmt, "yes", "needs gradient-guided runs in agriculture or simple"))
    else:
        n_ok = sum(w >= APPROX_FACTOR for w, _, _ in wins)
        out.append(Claim("R5.e", stmt, "yes",
                         ", ".join(f"{a}/{c} {w:.1f}x" for w, a, c in wins),
                         _frac_verdict(n_ok, len(wins), ALMOST_ALL),
                         "cheapest non-gradient total divided by the gradient-guided total"))
    return out


def _best_worst(d: StudyData, arm, case, attr="pos_err") -> tuple[str | None, str | None, dict]:
    vals = {}
    for c in TRAJECTORY_CONTROLLERS:
        cell = d.cell(arm, case, c)
        if cell is not None and math.isfinite(getattr(cell, attr)):
            vals[c] = getattr(cell, attr)
    if len(vals) < 2:
        return None, None, vals
    return min(vals, key=vals.get), max(vals, key=vals.get), vals


def _switch_ratios(d: StudyData) -> dict:
    """Per controller: pooled position error on rot = 1 samples / on rot = 0 samples (traces of
    successful runs in cases where orientation switches)."""
    out = {}
    for c in TRAJECTORY_CONTROLLERS:
        on, off = [], []
        for a in d.arms:
            for case in d.cases:
                tr = d.traces(a, case, c)
                if not tr or not {"pos_err", "rot", "seed"} <= set(tr):
                    continue
                ok = {int(_num(r["seed"])) for r in d.select(a, case, c) if run_cause(r) == "success"}
                m = np.isin(np.asarray(tr["seed"]).astype(int), list(ok))[:, None]
                if "mask" in tr:
                    m = m & np.asarray(tr["mask"], bool)
                rot = np.asarray(tr["rot"]) > 0.5
                switching = (rot & m).any(1) & (~rot & m).any(1)
                m = m & switching[:, None]
                e = np.asarray(tr["pos_err"], float)
                on.append(e[m & rot])
                off.append(e[m & ~rot])
        on = np.concatenate(on) if on else np.zeros(0)
        off = np.concatenate(off) if off else np.zeros(0)
        if on.size and off.size:
            out[c] = float(np.nanmean(on) / np.nanmean(off))
    return out


def _reference_accelerations(d: StudyData) -> np.ndarray:
    """|p_d''| by second differences of the sampled references (non-guided traces, one controller
    per (arm, case) suffices since all share the trajectory)."""
    accs = []
    for a in d.arms:
        for case in d.cases:
            for c in d.trajectory_controllers:
                tr = d.traces(a, case, c)
                if not tr or not {"p_d", "t"} <= set(tr):
                    continue
                t = np.asarray(tr["t"], float)
                if t.size < 3:
                    continue
                ts = float(np.median(np.diff(t)))
                pd = np.asarray(tr["p_d"], float)
                acc = np.linalg.norm(pd[:, 2:] - 2 * pd[:, 1:-1] + pd[:, :-2], axis=-1) / ts**2
                if "mask" in tr:
                    m = np.asarray(tr["mask"], bool)
                    acc = acc[m[:, 2:] & m[:, :-2]]
                accs.append(acc.ravel())
                break
    return np.concatenate(accs) if accs else np.zeros(0)


def _claims_r6(d: StudyData) -> list[Claim]:
    out = []
    # R6.a: 8/9-DOF JS best in most cases
    stmt = "On 8- and 9-DOF, JS has the lowest position error in most cases (E21)"
    arms89 = [a for a in d.arms if _dof(a) in (8, 9)]
    res = {}
    for a in arms89:
        bests = [_best_worst(d, a, case)[0] for case in d.cases]
        bests = [b for b in bests if b is not None]
        if bests:
            res[a] = (sum(b == "joint_space" for b in bests), len(bests))
    if not res:
        out.append(_not_eval("R6.a", stmt, "JS best in most cases", "needs 8- or 9-DOF tracking results"))
    else:
        n_ok = sum(k / n > MOST for k, n in res.values())
        out.append(Claim("R6.a", stmt, "JS best in most cases",
                         ", ".join(f"{a}: JS best in {k}/{n}" for a, (k, n) in res.items()),
                         AGREES if n_ok == len(res) else (PARTLY if n_ok else DIFFERS)))
    # R6.b: 7-DOF pattern
    stmt = "On 7-DOF, JS is worst except in agriculture and simple, where it is best"
    arm7 = [a for a in d.arms if _dof(a) == 7]
    if not arm7:
        out.append(_not_eval("R6.b", stmt, "worst / best in agr. and simple", "no 7-DOF arm"))
    else:
        match, tot, parts = 0, 0, []
        for case in d.cases:
            best, worst, _ = _best_worst(d, arm7[0], case)
            if best is None:
                continue
            want = best if case in RRT_CASES else worst
            rank = "best" if best == "joint_space" else ("worst" if worst == "joint_space" else "middle")
            parts.append(f"{case}: JS {rank}")
            tot += 1
            match += want == "joint_space"
        if not tot:
            out.append(_not_eval("R6.b", stmt, "worst / best in agr. and simple", "no 7-DOF tracking results"))
        else:
            out.append(Claim("R6.b", stmt, "worst; best in agriculture and simple", "; ".join(parts),
                             AGREES if match == tot else (PARTLY if match else DIFFERS),
                             f"{match} of {tot} cases match the thesis's pattern"))
    # R6.c: 7-DOF errors higher
    stmt = "All 7-DOF position errors are higher than on 8 and 9 DOF"
    dofs = {_dof(a): a for a in d.arms if _dof(a) in (7, 8, 9)}
    if 7 not in dofs or len(dofs) < 2:
        out.append(_not_eval("R6.c", stmt, "higher", "needs the 7-DOF arm and another thesis arm"))
    else:
        checks, parts = [], []
        for c in TRAJECTORY_CONTROLLERS:
            m = {dof: _mean(d.cell(a, case, c).pos_err for case in d.cases if d.cell(a, case, c))
                 for dof, a in dofs.items()}
            others = [v for k, v in m.items() if k != 7 and math.isfinite(v)]
            if math.isfinite(m[7]) and others:
                checks.append(m[7] > max(others))
                parts.append(f"{_clabel(c)} " + " / ".join(f"{k}: {1e3 * v:.2f}" for k, v in sorted(m.items())))
        if not checks:
            out.append(_not_eval("R6.c", stmt, "higher", "no tracking errors"))
        else:
            out.append(Claim("R6.c", stmt, "higher", "mean over cases [mm]: " + "; ".join(parts),
                             AGREES if all(checks) else (PARTLY if any(checks) else DIFFERS),
                             f"7-DOF highest for {sum(checks)} of {len(checks)} controllers"))
    # R6.d: velocity roughly constant over models
    stmt = f"Velocity OSC error is roughly constant across models (max/min <= {ROUGHLY_CONSTANT})"
    spread = {}
    for c in TRAJECTORY_CONTROLLERS:
        per_arm = [_mean(d.cell(a, case, c).pos_err for case in d.cases if d.cell(a, case, c)) for a in d.arms]
        per_arm = [v for v in per_arm if math.isfinite(v) and v > 0]
        if len(per_arm) >= 2:
            spread[c] = max(per_arm) / min(per_arm)
    if "velocity" not in spread:
        out.append(_not_eval("R6.d", stmt, "roughly constant", "needs velocity OSC results on two arms"))
    else:
        out.append(Claim("R6.d", stmt, "roughly constant",
                         "spread " + ", ".join(f"{_clabel(c)} {s:.2f}x" for c, s in spread.items()),
                         _v(spread["velocity"] <= ROUGHLY_CONSTANT)))
    # R6.e: velocity beats acceleration
    stmt = "Velocity OSC beats acceleration OSC in almost all cases and models"
    cmp_ = []
    for a in d.arms:
        for case in d.cases:
            v, ac = d.cell(a, case, "velocity"), d.cell(a, case, "acceleration")
            if v and ac and math.isfinite(v.pos_err) and math.isfinite(ac.pos_err):
                cmp_.append(v.pos_err < ac.pos_err)
    if not cmp_:
        out.append(_not_eval("R6.e", stmt, "almost all", "needs velocity and acceleration results"))
    else:
        out.append(Claim("R6.e", stmt, "almost all", f"{sum(cmp_)} of {len(cmp_)} (arm, case) cells",
                         _frac_verdict(sum(cmp_), len(cmp_), ALMOST_ALL), f"threshold {ALMOST_ALL:.0%}"))
    # R6.f: acceleration error rises with orientation on
    stmt = "Acceleration OSC position error rises when orientation switches on (more than velocity OSC)"
    r = _switch_ratios(d)
    if "acceleration" not in r:
        out.append(_not_eval("R6.f", stmt, "rises (Fig. 4.2)", "needs traces of runs where orientation switches"))
    else:
        ok = r["acceleration"] > 1 and r["acceleration"] > r.get("velocity", -math.inf)
        out.append(Claim("R6.f", stmt, "rises; less so for velocity OSC",
                         "error ratio rot on / off: " + ", ".join(f"{_clabel(c)} {v:.2f}" for c, v in r.items()),
                         _v(ok), "pooled over the switching runs that succeeded"))
    # R6.g: trajectory accelerations
    stmt = "Trajectory accelerations stay <= ~2 m/s^2"
    acc = _reference_accelerations(d)
    if not acc.size:
        out.append(_not_eval("R6.g", stmt, "<= ~2 m/s^2", "needs the reference positions in the traces"))
    else:
        p99 = float(np.percentile(acc, 99))
        out.append(Claim("R6.g", stmt, "max ~2 m/s^2", f"99th percentile {p99:.2f}, max {acc.max():.2f} m/s^2",
                         _v(p99 <= ACC_LIMIT),
                         f"second differences of the sampled references; bound {ACC_LIMIT} m/s^2 on the 99th "
                         "percentile (the maximum includes the zero-order-hold steps at segment joins)"))
    return out


def _claims_r7(d: StudyData) -> list[Claim]:
    out = []
    bests = {}
    for a in d.arms:
        for case in d.cases:
            b, _, _ = _best_worst(d, a, case, "ori_err")
            if b is not None:
                bests[(a, case)] = b
    stmt = "Velocity OSC has the best orientation tracking overall"
    if not bests:
        return [_not_eval("R7.a", stmt, "velocity best", "no orientation errors")]
    counts = {c: sum(b == c for b in bests.values()) for c in TRAJECTORY_CONTROLLERS}
    top = max(counts.values())
    ok = counts.get("velocity", 0) == top and sum(v == top for v in counts.values()) == 1
    out.append(Claim("R7.a", stmt, "velocity best", "best in " + ", ".join(
        f"{_clabel(c)} {k}" for c, k in counts.items()) + f" of {len(bests)} cells", _v(ok)))
    stmt = "JS is not best, except in welding where it wins most of the time"
    other = [b for (a, case), b in bests.items() if case != "welding"]
    weld = [b for (a, case), b in bests.items() if case == "welding"]
    k_o = sum(b == "joint_space" for b in other)
    k_w = sum(b == "joint_space" for b in weld)
    checks = [k_o / len(other) <= MOST] if other else []
    checks += [k_w / len(weld) > MOST] if weld else []
    out.append(Claim("R7.b", stmt, "JS rarely best; best in welding",
                     f"JS best in {k_o}/{len(other)} non-welding and {k_w}/{len(weld)} welding cells",
                     AGREES if checks and all(checks) else (PARTLY if any(checks) else DIFFERS)))
    return out


def _claims_h(d: StudyData) -> list[Claim]:
    out = []
    cells = []
    for a in d.arms:
        for case in d.cases:
            T = {c: d.total_cost(a, case, c) for c in ("joint_space", "velocity", "acceleration")}
            if all(math.isfinite(v) for v in T.values()):
                cells.append(T["velocity"] < T["joint_space"] and T["acceleration"] < T["joint_space"])
    stmt = "OSC beats JS on compute (total per test case)"
    out.append(_not_eval("H.a", stmt, "true", "needs timings") if not cells else
               Claim("H.a", stmt, "true", f"true in {sum(cells)} of {len(cells)} (arm, case) cells",
                     _frac_verdict(sum(cells), len(cells), ALMOST_ALL)))
    for cid, attr, what, want in (("H.b", "pos_err", "position", {7: False, 8: True, 9: True}),
                                  ("H.c", "ori_err", "orientation", {7: False, 8: False, 9: False})):
        got = {}
        for a in d.arms:
            dof = _dof(a)
            if dof not in want:
                continue
            bs = [_best_worst(d, a, case, attr)[0] for case in d.cases]
            bs = [b for b in bs if b is not None]
            if bs:
                got[dof] = sum(b == "joint_space" for b in bs) / len(bs) > MOST
        thesis = ", ".join(f"{k}-DOF {'true' if v else 'false'}" for k, v in want.items())
        stmt = f"JS beats OSC on {what} tracking (JS best in most cases)"
        if not got:
            out.append(_not_eval(cid, stmt, thesis, "no tracking results on thesis arms"))
            continue
        n_ok = sum(got[k] == want[k] for k in got)
        out.append(Claim(cid, stmt, thesis, ", ".join(f"{k}-DOF {'true' if v else 'false'}" for k, v in got.items()),
                         AGREES if n_ok == len(got) else (PARTLY if n_ok else DIFFERS)))
    stmt = "OSC trades reliability for compute (OSC fails more, costs less than JS)"
    kj, nj = _fail_rate(d, ctrls="joint_space")
    ko, no = _fail_rate(d, ctrls=OSC)
    if not (nj and no and cells):
        out.append(_not_eval("H.d", stmt, "true", "needs JS and OSC runs with timings"))
    else:
        more = ko / no > kj / nj
        cheaper = sum(cells) / len(cells) >= ALMOST_ALL
        out.append(Claim("H.d", stmt, "true", f"failure rate OSC {ko}/{no} vs JS {kj}/{nj}; cheaper in "
                         f"{sum(cells)}/{len(cells)} cells", _v(more and cheaper)))
    return out


def evaluate_claims(data: StudyData, extra: dict | None = None) -> list[Claim]:
    """Every quantitative statement of the thesis (SPEC section 11) with our number and a verdict.

    The verdicts are computed from ``data`` with the thresholds of this module (:data:`MOST`,
    :data:`ALMOST_ALL`, :data:`MODEL_SPREAD`, ...); ``extra`` may carry results of optional hooks
    (``{"R8": (verdict, ours, why)}``).
    """
    claims = (_claims_r1(data) + _claims_r2(data) + _claims_r3(data) + _claims_r4(data) + _claims_r5(data)
              + _claims_r6(data) + _claims_r7(data))
    r8 = (extra or {}).get("R8")
    stmt = "The error within a sample is a saw-tooth (Fig. 4.3)"
    claims.append(Claim("R8.a", stmt, "saw-tooth", r8[1], r8[0], r8[2]) if r8 else
                  _not_eval("R8.a", stmt, "saw-tooth", "needs the dense-output simulation (Fig. 4.3 hook)"))
    return claims + _claims_h(data)


# ------------------------------------------------------------------------------------------------
# figures


def _new_figure(ncols=1, nrows=1, width=None, height=3.0, sharey=False):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width or max(4.5, 3.6 * ncols), height * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, sharey=sharey, squeeze=False)
    return fig, axes


def _save(fig, path: Path) -> Path:
    """Write the PNG atomically (a killed run never leaves half a file)."""
    import io

    from ._store import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())
    return path


def _bars(ax, groups, series, *, width=0.8, log=False):
    """Grouped bars: ``series`` = [(label, values(len(groups)), color, hatch)]; NaNs are skipped."""
    k = max(len(series), 1)
    w = width / k
    x = np.arange(len(groups))
    handles = []
    for i, (label, vals, color, hatch) in enumerate(series):
        vals = np.asarray(vals, float)
        ok = np.isfinite(vals) & ((vals > 0) if log else True)
        h = ax.bar(x[ok] + (i - (k - 1) / 2) * w, vals[ok], w * 0.92, color=color, label=label,
                   hatch=hatch, edgecolor="white" if not hatch else "black", linewidth=0.4)
        handles.append(h)
    ax.set_xticks(x, [_case_label(g) for g in groups], rotation=20, ha="right")
    if log:
        ax.set_yscale("log")
    return handles


def _fig_tracking(d: StudyData, path: Path, attr: str, ylabel: str, scale: float, title: str) -> Path:
    ctrls = d.trajectory_controllers
    if not ctrls:
        raise _NotGenerated("no trajectory-tracking controllers in the study")
    if not any(math.isfinite(getattr(d.cell(a, case, c), attr)) for a in d.arms for case in d.cases for c in ctrls
               if d.cell(a, case, c)):
        raise _NotGenerated(f"no {'orientation' if attr == 'ori_err' else 'position'} errors of successful runs")
    fig, axes = _new_figure(len(d.arms), sharey=True)
    for ax, a in zip(axes[0], d.arms):
        series = []
        for c in ctrls:
            vals = [scale * getattr(d.cell(a, case, c), attr) if d.cell(a, case, c) else math.nan for case in d.cases]
            series.append((_clabel(c), vals, CONTROLLER_COLORS.get(c), None))
        _bars(ax, d.cases, series)
        ax.set_title(a)
    axes[0, 0].set_ylabel(ylabel)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=len(ctrls), title=title)
    return _save(fig, path)


def fig_tracking_error(d, path):
    """Fig. 4.1: pooled mean position error per sample of the successful runs."""
    return _fig_tracking(d, path, "pos_err", "mean position error per sample [mm]", 1e3,
                         "Position tracking error (successful runs, pooled over samples)")


def fig_orientation_error(d, path):
    """Fig. 4.4: pooled mean orientation error |e_o| = sin(phi/2) over the rot = 1 samples."""
    return _fig_tracking(d, path, "ori_err", r"mean $|e_o| = \sin(\varphi/2)$", 1.0,
                         "Orientation tracking error (rot = 1 samples of successful runs)")


def _pick_example(d: StudyData, case: str):
    """(arm, seed, traces) of a run of ``case`` with orientation switching in its traces, preferring
    the 9-DOF arm and a seed that succeeded for every trajectory controller (then any seed)."""
    arms = sorted(d.arms, key=lambda a: (_dof(a) != 9, -(_dof(a) or 0)))
    for need_success in (True, False):
        for a in arms:
            trs = {c: d.traces(a, case, c) for c in d.trajectory_controllers}
            trs = {c: t for c, t in trs.items() if t and {"pos_err", "seed"} <= set(t)}
            if not trs:
                continue
            ok = None
            for c in trs:
                s = {int(_num(r["seed"])) for r in d.select(a, case, c)
                     if run_cause(r) == "success" or not need_success}
                ok = s if ok is None else ok & s
            first = next(iter(trs.values()))
            seeds = [int(x) for x in np.asarray(first["seed"]).astype(int)]
            rot_all = np.asarray(first["rot"]) > 0.5 if "rot" in first else None
            for i, seed in enumerate(seeds):
                if seed in (ok or set()) and rot_all is not None and rot_all[i].any() and (~rot_all[i]).any():
                    return a, seed, trs
            if ok and need_success:
                return a, int(sorted(ok)[0]), trs
            if not need_success and seeds:
                return a, seeds[0], trs
    return None


def fig_orientation_switch(d: StudyData, path: Path) -> Path:
    """Fig. 4.2: position and orientation error over time for one warehouse run (every trajectory
    controller on the same scenario), with the rot = 1 intervals shaded."""
    case = "warehouse" if "warehouse" in d.cases else None
    pick = _pick_example(d, case) if case else None
    if pick is None:
        for case in d.cases:
            pick = _pick_example(d, case)
            if pick:
                break
    if pick is None:
        raise _NotGenerated("no traces of a run that succeeded for every trajectory controller")
    arm, seed, trs = pick
    fig, axes = _new_figure(1, 2, width=7.0, height=2.4)
    axes[1, 0].sharex(axes[0, 0])
    shaded = False
    for c, tr in trs.items():
        idx = np.nonzero(np.asarray(tr["seed"]).astype(int) == seed)[0]
        if not idx.size:
            continue
        i = idx[0]
        n = np.asarray(tr["pos_err"]).shape[-1]
        t = np.asarray(tr.get("t", np.arange(n)), float)
        m = np.asarray(tr["mask"], bool)[i] if "mask" in tr else np.ones(n, bool)
        axes[0, 0].plot(t[m], 1e3 * np.asarray(tr["pos_err"], float)[i][m], color=CONTROLLER_COLORS.get(c),
                        label=_clabel(c), lw=1.0)
        if "ori_err" in tr:
            rot = np.asarray(tr.get("rot", np.ones(n)))[i] > 0.5
            e = np.where(rot & m, np.asarray(tr["ori_err"], float)[i], np.nan)
            axes[1, 0].plot(t, e, color=CONTROLLER_COLORS.get(c), lw=1.0)
        if not shaded and "rot" in tr:
            rot = (np.asarray(tr["rot"])[i] > 0.5) & m
            for ax in axes[:, 0]:
                _shade(ax, t, rot)
            shaded = True
    axes[0, 0].set_ylabel("position error [mm]")
    axes[1, 0].set_ylabel(r"$|e_o|$")
    axes[1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(ncols=3, loc="upper left")
    axes[0, 0].set_title(f"{_case_label(case)}, {arm}, seed {seed} (shaded: orientation control on)")
    return _save(fig, path)


def _shade(ax, t, on):
    on = np.asarray(on, bool)
    if not on.any():
        return
    edges = np.diff(np.concatenate([[0], on.astype(int), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    for s, e in zip(starts, ends):
        ax.axvspan(t[s] - dt, t[e - 1], color="0.85", lw=0, zorder=0)


def _timing_arm(d: StudyData) -> str:
    return next((a for a in d.arms if _dof(a) == 9), d.arms[-1])


def fig_compute_per_sample(d: StudyData, path: Path) -> Path:
    """Fig. 4.5: per-sample compute by component (each controller, IK, planning, LME) and case,
    9-DOF arm (log scale)."""
    arm = _timing_arm(d)
    series = []
    for c in d.controllers:
        vals = [d.cell(arm, case, c).t_controller if d.cell(arm, case, c) else math.nan for case in d.cases]
        series.append((f"{_clabel(c)} controller", vals, CONTROLLER_COLORS.get(c), None))
    for comp, label in (("ik", "IK"), ("planning", "Planning"), ("lme", "LME")):
        vals = [d.component_time(arm, case, comp) for case in d.cases]
        if any(math.isfinite(v) for v in vals):
            series.append((label, vals, COMPONENT_COLORS[comp], None))
    if not any(np.isfinite(np.asarray(s[1], float)).any() for s in series):
        raise _NotGenerated("no timings in runs.csv")
    fig, axes = _new_figure(1, width=7.0, height=3.2)
    ax = axes[0, 0]
    _bars(ax, d.cases, series, log=True)
    ax.set_ylabel("compute time per sample [s]")
    ax.set_title(f"Compute time per sample by component ({arm})")
    ax.legend(ncols=1, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _save(fig, path)


def fig_samples_per_case(d: StudyData, path: Path) -> Path:
    """Fig. 4.6: average N_samples per case (9-DOF): planned trajectories, and gradient-guided runs."""
    arm = _timing_arm(d)
    traj = [d.trajectory_samples(arm, case) for case in d.cases]
    grad = [d.cell(arm, case, "gradient").n_samples if d.cell(arm, case, "gradient") else math.nan
            for case in d.cases]
    series = [("Planned trajectory", traj, "#4c72b0", None)]
    if any(math.isfinite(g) for g in grad):
        series.append(("Gradient-guided run", grad, CONTROLLER_COLORS["gradient"], "//"))
    fig, axes = _new_figure(1, width=5.0, height=3.0)
    ax = axes[0, 0]
    _bars(ax, d.cases, series)
    ax.set_ylabel("average number of samples")
    ax.set_title(f"Samples per test case ({arm})")
    ax.legend()
    return _save(fig, path)


def fig_total_compute(d: StudyData, path: Path) -> Path:
    """Fig. 4.7: total compute per test case by controller (sum of per-sample times x mean
    N_samples), every arm (log scale)."""
    fig, axes = _new_figure(len(d.arms), sharey=True)
    any_ok = False
    for ax, a in zip(axes[0], d.arms):
        series = []
        for c in d.controllers:
            vals = [d.total_cost(a, case, c) for case in d.cases]
            any_ok |= any(math.isfinite(v) for v in vals)
            series.append((_clabel(c), vals, CONTROLLER_COLORS.get(c), None))
        _bars(ax, d.cases, series, log=True)
        ax.set_title(a)
    if not any_ok:
        raise _NotGenerated("no timings in runs.csv")
    axes[0, 0].set_ylabel("total compute per test case [s]")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=len(d.controllers))
    return _save(fig, path)


def fig_failure_rate(d: StudyData, path: Path) -> Path:
    """Fig. 4.8: failure rate by controller x case, every arm; solid = collision, hatched = not
    reached, dotted = diverged."""
    from matplotlib.patches import Patch

    fig, axes = _new_figure(len(d.arms), sharey=True)
    k = len(d.controllers)
    w = 0.8 / k
    x = np.arange(len(d.cases))
    for ax, a in zip(axes[0], d.arms):
        for i, c in enumerate(d.controllers):
            xs = x + (i - (k - 1) / 2) * w
            bottom = np.zeros(len(d.cases))
            for attr, hatch, alpha in (("n_collision", None, 1.0), ("n_not_reached", "///", 0.55),
                                       ("n_diverged", "..", 0.3)):
                v = np.array([100 * getattr(d.cell(a, case, c), attr) / d.cell(a, case, c).n
                              if d.cell(a, case, c) and d.cell(a, case, c).n else 0.0 for case in d.cases])
                if v.any():
                    ax.bar(xs, v, w * 0.92, bottom=bottom, color=CONTROLLER_COLORS.get(c), alpha=alpha,
                           hatch=hatch, edgecolor="black" if hatch else "white", linewidth=0.4)
                bottom += v
        ax.set_xticks(x, [_case_label(g) for g in d.cases], rotation=20, ha="right")
        ax.set_ylim(0, 105)
        ax.set_title(a)
    axes[0, 0].set_ylabel("failed runs [%]")
    handles = [Patch(color=CONTROLLER_COLORS.get(c), label=_clabel(c)) for c in d.controllers]
    handles += [Patch(facecolor="0.6", edgecolor="white", label="collision"),
                Patch(facecolor="0.6", alpha=0.55, hatch="///", edgecolor="black", label="not reached"),
                Patch(facecolor="0.6", alpha=0.3, hatch="..", edgecolor="black", label="diverged")]
    fig.legend(handles=handles, loc="outside upper center", ncols=min(len(handles), 7))
    return _save(fig, path)


def fig_gradient_success(d: StudyData, path: Path) -> Path:
    """Figs. 4.9-4.10 (numbers): gradient-guided success per case and arm, with the thesis's."""
    cases = [c for c in d.cases if d.select(case=c, controller="gradient")]
    if not cases:
        raise _NotGenerated("no gradient-guided runs")
    fig, axes = _new_figure(1, width=5.5, height=3.0)
    ax = axes[0, 0]
    arms = [a for a in d.arms if d.select(a, controller="gradient")]
    shades = ["#fcbba1", "#fb6a4a", "#a50f15", "#67000d"]
    series = []
    for j, a in enumerate(arms):
        vals = []
        for case in cases:
            c = d.cell(a, case, "gradient")
            vals.append(100 * (1 - c.failure_rate) if c and c.n else math.nan)
        series.append((a, vals, shades[j % len(shades)], None))
    _bars(ax, cases, series)
    k = max(len(series), 1)
    w = 0.8 / k
    for j, a in enumerate(arms):  # counts above the bars (a 0 % bar is invisible otherwise)
        for i, case in enumerate(cases):
            c = d.cell(a, case, "gradient")
            if c and c.n:
                ax.text(i + (j - (k - 1) / 2) * w, 2.0, f"{c.n - c.n_fail}/{c.n}", ha="center", va="bottom",
                        fontsize=7, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))
    first = True
    for i, case in enumerate(cases):
        if case not in THESIS_GRADIENT_SUCCESS:
            continue
        for j, a in enumerate(arms):
            kt, nt = THESIS_GRADIENT_SUCCESS[case]
            if case == "warehouse" and _dof(a) in THESIS_WAREHOUSE_PER_ARM:
                kt, nt = THESIS_WAREHOUSE_PER_ARM[_dof(a)]
            xc = i + (j - (k - 1) / 2) * w
            ax.plot([xc - w * 0.45, xc + w * 0.45], [100 * kt / nt] * 2, color="black", lw=1.5,
                    label="thesis" if first else None)
            first = False
    ax.set_ylim(0, 112)
    ax.set_ylabel("runs reaching the goal [%]")
    ax.set_title("Gradient-guided success (black: thesis)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _save(fig, path)


def fig_gradient_final_distance(d: StudyData, path: Path) -> Path:
    """Figs. 4.9-4.10 (distribution): final distance to the goal of the gradient-guided runs per
    case, with the 0.10 m success radius."""
    cases = [c for c in d.cases if d.select(case=c, controller="gradient")]
    if not cases:
        raise _NotGenerated("no gradient-guided runs")
    fig, axes = _new_figure(len(cases), height=2.8, sharey=True)
    arms = [a for a in d.arms if d.select(a, controller="gradient")]
    for ax, case in zip(axes[0], cases):
        data = [[_num(r.get("final_pos_error")) for r in d.select(a, case, "gradient")] for a in arms]
        data = [[x for x in v if math.isfinite(x)] for v in data]
        allv = [x for v in data for x in v]
        if not allv:
            ax.set_title(f"{_case_label(case)} (no data)")
            continue
        hi = max(max(allv), 2 * SUCCESS_RADIUS) * 1.05
        bins = np.linspace(0, hi, 21)
        ax.hist(data, bins=bins, stacked=True, label=arms,
                color=["#fcbba1", "#fb6a4a", "#a50f15", "#67000d"][: len(arms)])
        ax.axvline(SUCCESS_RADIUS, color="black", ls="--", lw=1)
        ax.set_title(_case_label(case))
        ax.set_xlabel("final distance to goal [m]")
    axes[0, 0].set_ylabel("runs")
    axes[0, 0].legend(title="dashed: 0.10 m")
    return _save(fig, path)


class _NotGenerated(Exception):
    """A figure that cannot be drawn from the data at hand (the reason goes into the report)."""


@dataclasses.dataclass(frozen=True)
class FigureSpec:
    file: str
    thesis: str  # thesis figure number(s)
    caption: str
    make: Callable  # (StudyData, Path) -> Path; with ``prefetch``: (StudyData, Path, data) -> Path
    # (StudyData) -> data: the figure's computation (JAX), which make_report starts in a background
    # thread before drawing the other figures, so that it runs beside them (XLA compiles and runs
    # without Python's lock); ``make`` draws it afterwards, in the calling thread
    prefetch: Callable | None = None


FIGURES: tuple[FigureSpec, ...] = (
    FigureSpec("fig4_1_tracking_error.png", "4.1", "Mean position error per sample by case, arm and controller",
               fig_tracking_error),
    FigureSpec("fig4_2_orientation_switch.png", "4.2", "Warehouse error time series around the orientation switch",
               fig_orientation_switch),
    FigureSpec("fig4_4_orientation_error.png", "4.4", "Mean orientation error by case, arm and controller",
               fig_orientation_error),
    FigureSpec("fig4_5_compute_per_sample.png", "4.5", "Compute time per sample by component and case (9-DOF)",
               fig_compute_per_sample),
    FigureSpec("fig4_6_samples_per_case.png", "4.6", "Average number of samples per case (9-DOF)",
               fig_samples_per_case),
    FigureSpec("fig4_7_total_compute.png", "4.7", "Total compute per test case by controller, all arms",
               fig_total_compute),
    FigureSpec("fig4_8_failure_rate.png", "4.8", "Failure rate by controller and case with cause, all arms",
               fig_failure_rate),
    FigureSpec("fig4_9_gradient_success.png", "4.9-4.10", "Gradient-guided success per case and arm vs thesis",
               fig_gradient_success),
    FigureSpec("fig4_10_gradient_final_distance.png", "4.9-4.10",
               "Final distance to the goal of the gradient-guided runs", fig_gradient_final_distance),
)


# ------------------------------------------------------------------------------------------------
# figures that need other modules (scenes, fields, dense re-simulation). Each rebuilds what it needs
# from the stored units (``DIR/units/scen_<arm>_<case>.pkl``) and the traces; a missing module, unit
# or function is reported as "not generated (reason)", never raised.


def _attr(module: str, name: str):
    import importlib

    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        raise _NotGenerated(f"{module} not available ({e})") from None
    fn = getattr(mod, name, None)
    if fn is None:
        raise _NotGenerated(f"{module}.{name} not available")
    return fn


def _arm_spec(d: StudyData, label: str) -> str:
    from ._study import _arm_label

    for spec in d.config.get("arms", ()):
        if _arm_label(str(spec)) == label:
            return str(spec)
    if _dof(label) is not None:
        return str(_dof(label))
    raise _NotGenerated(f"cannot rebuild arm {label!r} (not in config.json)")


def _stored_scenario(d: StudyData, label: str, case: str, seed: int | None = None):
    """(arm, scenario, ik, index) of one stored scenario of (label, case); ``seed`` picks it
    (default the first valid one). Only the scenes of the table's sweep: the stored unit's key
    must be the one ``config.json`` gives (a sweep with other seeds interrupted in the folder
    leaves its own scenes there, which the figures drew beside the old table), and an asked-for
    seed must be among them."""
    import jax

    from ._store import UnitStore
    from ._study import arm_from_spec, scenario_key

    if d.out is None:
        raise _NotGenerated("no results folder")
    store = UnitStore(d.out)
    name = f"scen_{label}_{case}"
    if not store.path(name).is_file():
        raise _NotGenerated(f"no stored scenarios units/{name}.pkl")
    spec, cfg = _arm_spec(d, label), d.config
    try:
        key = scenario_key(spec, case, cfg["seeds"], cfg["ts"], cfg["max_retries"],
                           cfg.get("precision", "float64"))
    except (KeyError, OSError, ValueError) as e:
        raise _NotGenerated(f"cannot tell which scenes made the table (config.json: {e!r})") from None
    if not store.has(name, key):
        raise _NotGenerated(f"units/{name}.pkl holds another sweep's scenes, not those of runs.csv")
    payload = store.load(name)
    scen = payload["scenarios"]
    seeds = np.asarray(scen.seed).astype(int).ravel()
    valid = np.asarray(getattr(scen, "valid", np.ones_like(seeds, bool))).astype(bool).ravel()
    if seed is not None:
        if seed not in seeds:
            raise _NotGenerated(f"seed {seed} is not among the stored scenes of units/{name}.pkl")
        i = int(np.nonzero(seeds == seed)[0][0])
    else:
        i = int(np.argmax(valid)) if valid.any() else 0
    take = lambda x: x[i]  # noqa: E731
    sc = jax.tree.map(take, scen)
    ik = jax.tree.map(take, payload["ik"]) if payload.get("ik") is not None else None
    return arm_from_spec(spec), sc, ik, i


def _hook_scenarios(d: StudyData, path: Path):
    """Fig. 3.2: one example scene per case (9-DOF arm at q0) with its reference."""
    from matplotlib.figure import Figure

    plot_scenario = _attr("redman_jax._plots", "plot_scenario")
    label = _timing_arm(d)
    fig = Figure(figsize=(3.4 * len(d.cases), 3.6), layout="constrained")
    drawn = 0
    for j, case in enumerate(d.cases):
        ax = fig.add_subplot(1, len(d.cases), j + 1, projection="3d")
        try:
            arm, sc, _, _ = _stored_scenario(d, label, case)
        except _NotGenerated as e:
            ax.set_title(f"{case}: {e}", fontsize=7)
            ax.set_axis_off()
            continue
        plot_scenario(sc, arm, ax=ax)
        drawn += 1
    if not drawn:
        raise _NotGenerated(f"no stored scenarios for {label}")
    return _save(fig, path)


def _hook_field_slice(case: str, prefer_failed_gradient: bool = False):
    def hook(d: StudyData, path: Path):
        """Figs. 3.4 / 4.9 / 4.10: slice of the guidance potential through the goal."""
        from matplotlib.figure import Figure

        plot_field_slice = _attr("redman_jax._plots", "plot_field_slice")
        label = _timing_arm(d)
        seed = None
        if prefer_failed_gradient:  # a run where the gradient-guided controller missed the goal
            failed = [r for r in d.select(label, case, "gradient") if run_cause(r) == "not reached"]
            seed = int(_num(failed[0]["seed"])) if failed else None
        _, sc, _, _ = _stored_scenario(d, label, case, seed)
        fig = Figure(figsize=(4.8, 4.0), layout="constrained")
        ax = fig.add_subplot(111)
        title = f"{_case_label(case)} potential through the goal ({label}, seed {int(np.asarray(sc.seed))})"
        plot_field_slice(sc, ax=ax, title=title)
        return _save(fig, path)

    return hook


def _step_responses(d: StudyData):
    """The data of Fig. 3.6: the 0.05 m step responses of the 9-DOF arm (SPEC U28) with the gains
    the study ran (thesis gains unless ``--gains`` overrode them); three simulations, each compiled
    (20 of the report's 35 s on one core, so :func:`make_report` starts them first, beside the
    other figures)."""
    fn = _attr("redman_jax._tuning", "step_responses")
    from ._robot import thesis_arm

    return fn(thesis_arm(9), d.config.get("gains") or None)


def _hook_step_responses(d: StudyData, path: Path, responses=None):
    """Fig. 3.6, drawn by the tuning module from :func:`_step_responses` (computed here if not
    given)."""
    fn = _attr("redman_jax._tuning", "step_response_figure")
    from ._robot import thesis_arm

    fn(thesis_arm(9), path, gains_by_controller=d.config.get("gains") or None,
       responses=_step_responses(d) if responses is None else responses)
    return path


def _hook_perfect_controller(d: StudyData, path: Path):
    """Fig. 3.7: the perfect-controller path (3.18) in a simple-obstacle scene, with the virtual
    obstacles active at the end (cyan) and the earlier estimates (grey)."""
    from matplotlib.figure import Figure

    plot_scenario = _attr("redman_jax._plots", "plot_scenario")
    perfect_controller = _attr("redman_jax._guidance", "perfect_controller")
    label = _timing_arm(d)
    _, sc, _, _ = _stored_scenario(d, label, "simple")
    res = perfect_controller(np.asarray(sc.reference.p)[0], np.asarray(sc.goal_p), sc.obstacles)
    n = int(np.asarray(res.termination.n_samples))
    x = np.asarray(res.x)[:n]
    est = np.asarray(res.estimates)[:n][np.asarray(res.estimate_valid)[:n]]
    buf = np.asarray(res.buffers)[n - 1][np.asarray(res.buffer_masks)[n - 1]]
    fig = Figure(figsize=(5.0, 4.6), layout="constrained")
    ax = fig.add_subplot(111, projection="3d")
    plot_scenario(sc, None, ax=ax, title=f"Perfect controller, simple case ({'reached' if bool(np.asarray(res.termination.success)) else 'not reached'})")
    ax.plot(x[:, 0], x[:, 1], x[:, 2], color="black", lw=1.6, zorder=10, label="guided path")
    if est.size:
        ax.scatter(est[:, 0], est[:, 1], est[:, 2], s=8, color="0.6", depthshade=False, zorder=10, label="estimates")
    if buf.size:
        ax.scatter(buf[:, 0], buf[:, 1], buf[:, 2], s=20, color="c", depthshade=False, zorder=11,
                   label="active virtual obstacles")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=3, fontsize=7)
    return _save(fig, path)


def _hook_gradient_path(d: StudyData, path: Path):
    """Fig. 4.11: the end-effector path of a gradient-guided run in a simple-obstacle scene (from the
    traces), with the local-minima estimates."""
    from matplotlib.figure import Figure

    plot_scenario = _attr("redman_jax._plots", "plot_scenario")
    label = _timing_arm(d)
    tr = d.traces(label, "simple", "gradient")
    if not tr or "p" not in tr or "seed" not in tr:
        raise _NotGenerated("no gradient-guided traces with positions in the simple case")
    rows = {int(_num(r["seed"])): r for r in d.select(label, "simple", "gradient")}
    seeds = np.asarray(tr["seed"]).astype(int)
    ok = [i for i, s in enumerate(seeds) if s in rows and run_cause(rows[s]) == "success"]
    i = ok[0] if ok else 0
    arm, sc, _, _ = _stored_scenario(d, label, "simple", int(seeds[i]))
    m = np.asarray(tr["mask"], bool)[i] if "mask" in tr else np.ones(np.asarray(tr["p"]).shape[1], bool)
    p = np.asarray(tr["p"], float)[i][m]
    fig = Figure(figsize=(5.0, 4.6), layout="constrained")
    ax = fig.add_subplot(111, projection="3d")
    plot_scenario(sc, arm, ax=ax, title=f"Gradient-guided run, simple case ({label}, seed {seeds[i]})")
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="black", lw=1.6, zorder=10, label="end effector")
    if "estimates" in tr and "estimate_valid" in tr:
        e = np.asarray(tr["estimates"], float)[i][m & np.asarray(tr["estimate_valid"], bool)[i]]
        if e.size:
            ax.scatter(e[:, 0], e[:, 1], e[:, 2], s=10, color="c", depthshade=False, zorder=11,
                       label="virtual obstacles")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncols=3, fontsize=7)
    return _save(fig, path)


def sawtooth_fraction(k, err, n_samples) -> tuple[float, int]:
    """Fraction of the samples whose error falls within the sample (first fine point > last, the
    sample end), from a dense re-simulation: ``k`` (held sample of each fine point), ``err``."""
    k, err = np.asarray(k).astype(int), np.asarray(err, float)
    drops = []
    for s in range(1, int(n_samples)):  # sample 0 starts from rest at the reference
        e = err[k == s]
        if e.size >= 2 and np.all(np.isfinite(e)):
            drops.append(e[0] > e[-1])
    return (float(np.mean(drops)) if drops else math.nan), len(drops)


def _hook_within_sample(d: StudyData, path: Path):
    """Fig. 4.3 and R8: dense re-simulation of an agriculture run with velocity OSC; the error
    against the held sample over a window of samples, with the sample boundaries."""
    from matplotlib.figure import Figure

    simulate_dense = _attr("redman_jax._sim", "simulate_dense")
    controllers = _attr("redman_jax._controllers", "CONTROLLERS")
    from ._pipeline import make_gains

    label = _timing_arm(d)
    ok = [r for r in d.select(label, "agriculture", "velocity") if run_cause(r) == "success"]
    if not ok:
        raise _NotGenerated(f"no successful agriculture run with velocity OSC on {label}")
    arm, sc, _, _ = _stored_scenario(d, label, "agriculture", int(_num(ok[0]["seed"])))
    ctrl = controllers["velocity"]
    ctrl = ctrl() if isinstance(ctrl, type) else ctrl
    gains = make_gains(ctrl, (d.config.get("gains") or {}).get("velocity"))
    t, k, _, _, _, err, _ = simulate_dense(arm, sc, ctrl, gains, points_per_sample=20)
    t, k, err = np.asarray(t), np.asarray(k), np.asarray(err)
    n = int(np.asarray(sc.reference.n_samples))
    frac, count = sawtooth_fraction(k, err, n)
    mid = n // 2
    sel = (k >= mid) & (k < mid + 10)
    fig = Figure(figsize=(6.0, 2.6), layout="constrained")
    ax = fig.add_subplot(111)
    ax.plot(t[sel], 1e3 * err[sel], color=CONTROLLER_COLORS["velocity"], lw=1.0, label="within the sample")
    ends = sel & (np.r_[k[1:] != k[:-1], True])
    ax.plot(t[ends], 1e3 * err[ends], "o", ms=3, color="black", label="sample end (reported)")
    ts = float(np.asarray(sc.reference.ts))
    for j in range(mid, mid + 11):
        ax.axvline(j * ts, color="0.8", lw=0.6, zorder=0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [mm]")
    ax.set_title(f"Error between samples, agriculture, velocity OSC ({label}, seed {int(np.asarray(sc.seed))})")
    fig.legend(loc="outside lower center", ncols=2)
    _save(fig, path)
    ok_ = frac >= ALMOST_ALL if math.isfinite(frac) else None
    return {"R8": (_v(ok_), f"error falls within {100 * frac:.0f} % of {count} samples",
                   f"dense re-simulation with 20 points per sample; saw-tooth when the error at a sample's "
                   f"start exceeds its end in >= {ALMOST_ALL:.0%} of the samples")}


HOOKS: tuple[FigureSpec, ...] = (
    FigureSpec("fig3_2_cases.png", "3.2", "One example scene per case with its reference (9-DOF)", _hook_scenarios),
    FigureSpec("fig3_4_field_slice.png", "3.4", "Slice of the warehouse potential", _hook_field_slice("warehouse")),
    FigureSpec("fig3_6_step_responses.png", "3.6", "Step responses of the tuned controllers (9-DOF)",
               _hook_step_responses, prefetch=_step_responses),
    FigureSpec("fig3_7_perfect_controller.png", "3.7", "Perfect-controller path with virtual obstacles (simple case)",
               _hook_perfect_controller),
    FigureSpec("fig4_3_within_sample.png", "4.3", "Error within samples, agriculture, velocity OSC (dense output)",
               _hook_within_sample),
    FigureSpec("fig4_9_field_agriculture.png", "4.9", "Agriculture potential through the goal (a failed "
               "gradient-guided seed when there is one)", _hook_field_slice("agriculture", True)),
    FigureSpec("fig4_10_field_warehouse.png", "4.10", "Warehouse potential around the goal",
               _hook_field_slice("warehouse", True)),
    FigureSpec("fig4_11_gradient_path.png", "4.11", "Gradient-guided path in a simple-obstacle scene",
               _hook_gradient_path),
)


def _render(spec: FigureSpec, d: StudyData, fig_dir: Path) -> tuple[str, str, object]:
    """Run one figure maker; returns (status, reason, hook result). Never raises."""
    import matplotlib

    path = fig_dir / spec.file
    try:
        with matplotlib.rc_context(_STYLE):
            res = spec.make(d, path)
    except Exception as e:  # noqa: BLE001 - a broken figure must not lose the report
        path.unlink(missing_ok=True)  # never leave a stale figure from an earlier run beside the report
        return "missing", str(e) if isinstance(e, _NotGenerated) else f"{type(e).__name__}: {e}", None
    if not path.is_file() or path.stat().st_size == 0:
        return "missing", "the figure maker wrote no file", res
    return "ok", "", res


# ------------------------------------------------------------------------------------------------
# report


def _cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's model name (Linux: the first ``model name`` of ``cpuinfo``; elsewhere
    ``platform.processor()``), or ``"CPU model unknown"``: the report's timings depend on it."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, sep, value = line.partition(":")
                if sep and key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or "CPU model unknown"


def _machine() -> str:
    """The report's machine row: platform, architecture, CPU model and the machine's logical CPUs
    (not this process's: :func:`redman_jax._study.render_report` pins the report to one core)."""
    import os

    return f"{platform.platform()}, {platform.machine()}, {_cpu_model()}, {os.cpu_count()} logical CPUs"


def _versions() -> str:
    import importlib.metadata as md

    parts = []
    for pkg in ("redman-jax", "jax", "jaxlib", "diffrax", "equinox", "numpy", "matplotlib"):
        try:
            parts.append(f"{pkg} {md.version(pkg)}")
        except md.PackageNotFoundError:
            pass
    parts.append(f"Python {platform.python_version()}")
    return ", ".join(parts)


def _ranges(xs) -> str:
    xs = sorted({int(x) for x in xs})
    if not xs:
        return "–"
    out, start, prev = [], xs[0], xs[0]
    for x in xs[1:] + [None]:
        if x is not None and x == prev + 1:
            prev = x
            continue
        out.append(f"{start}-{prev}" if prev > start else f"{start}")
        if x is not None:
            start = prev = x
    return ", ".join(out)


def _header(d: StudyData) -> list[str]:
    cfg = d.config
    seeds = cfg.get("seeds") or [r["seed"] for r in d.rows if math.isfinite(_num(r.get("seed")))]
    retried = sum(1 for r in d.rows if math.isfinite(_num(r.get("seed_used"))) and _num(r.get("seed_used"))
                  != _num(r.get("seed")))
    lines = [
        "# redman-jax study report",
        "",
        "Generated by `redman_jax._report.make_report` from `runs.csv` and `traces/`; every verdict below is",
        "computed from these data (thresholds in the Method section).",
        "",
        "| | |",
        "|---|---|",
        f"| date | {_dt.datetime.now(_dt.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')} |",
        f"| arms | {', '.join(d.arms)} |",
        f"| cases | {', '.join(d.cases)} |",
        f"| seeds | {_ranges(seeds)} ({len(set(int(s) for s in seeds))} per arm and case) |",
        f"| controllers | {', '.join(d.controllers)} |",
        f"| runs | {len(d.rows)} ({retried} on a reseeded scenario, seed + 1000 k; {d.n_excluded} left out: "
        f"scenario not validated) |",
    ]
    if "ts" in cfg:
        lines.append(f"| sample time | {cfg['ts']} s |")
    if cfg.get("gradient_cases"):
        lines.append(f"| gradient-guided cases | {', '.join(cfg['gradient_cases'])} |")
    if cfg.get("gains"):
        lines.append(f"| gain overrides | `{json.dumps(cfg['gains'])}` |")
    lines += [f"| versions | {_versions()} |", f"| machine | {_machine()} |", ""]
    return lines


_METHOD = f"""## Method

* Position error: pooled mean per sample over the successful runs of each (case, arm, controller),
  `|p(t_(k+1)) - p_d[k]|` at the sample end; gradient-guided runs excluded (no trajectory).
* Orientation error: `|e_o| = sin(phi/2)` (E19: a 45 deg error is 0.383, not 0.7071) over the
  `rot = 1` samples of the successful runs.
* Failure: collision, or final error > {SUCCESS_RADIUS} m (gradient-guided: the goal held for 1 s or
  reached at the 6 s stop). Cause "collision" whenever the run collided.
* Total compute per test case = sum of the per-sample times of what the controller needs (JS:
  controller + IK + planning; OSC: controller + planning; gradient-guided: controller + LME) x the
  mean number of samples (the gradient-guided runs' own).
* Thesis timings are MATLAB wall times; ours are JAX (jit, CPU). Only orderings and ratios compare.
  Ours are per-sample times of one compiled call over many samples (IK and planning: a case's
  batch; controller and LME: a run's samples one after another), measured in the study's
  workers while other work runs beside them. On a shared machine a cell's time moves between
  runs of the same code (two fresh runs of the default study on 2 cores: controllers up to 1.6x,
  IK and planning up to 2.0x and 2.7x, the medians within 8 %), so a timing verdict whose number
  lies that close to its threshold can change from run to run (there: R1.b, R4.a; in three fresh
  runs of one day: R1.b, R5.d).
* Verdict thresholds: "most" > {MOST:.0%}; "almost all" >= {ALMOST_ALL:.0%}; "models do not differ"
  max/min over arms <= {MODEL_SPREAD}; "roughly constant" <= {ROUGHLY_CONSTANT}; "a ~ b" within
  {SIMILAR}x; "about k times" within a factor {APPROX_FACTOR:.0f}; success rates agree when the thesis's
  proportion is inside our 95 % Wilson interval. "partly agrees" = some but not all parts hold.
"""


def _claims_markdown(claims: list[Claim]) -> list[str]:
    lines = []
    for sec, title in SECTIONS.items():
        cs = [c for c in claims if c.section == sec]
        if not cs:
            continue
        lines += [f"## {title}", "", "| | statement | thesis | ours | verdict |", "|---|---|---|---|---|"]
        for c in cs:
            lines.append(f"| {c.id} | {c.statement} | {c.thesis} | {c.ours} | **{c.verdict}** |")
        lines.append("")
        for c in cs:
            if c.why:
                lines.append(f"* {c.id} ({c.verdict}): {c.why.rstrip('.')}.")
        lines.append("")
    return lines


def _gradient_table(d: StudyData) -> list[str]:
    rows = d.select(controller="gradient")
    if not rows:
        return []
    lines = ["## Gradient-guided runs", "",
             "| case | arm | reached | not reached | collided | median final distance [m] | mean samples | "
             "orientation error to goal |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for case in d.cases:
        for a in d.arms:
            c = d.cell(a, case, "gradient")
            if c is None:
                continue
            rs = d.select(a, case, "gradient")
            fe = [x for x in c.final_errors if math.isfinite(x)]
            ori = _mean(_num(r.get("mean_ori_error")) for r in rs)
            lines.append(f"| {_case_label(case)} | {a} | {c.n - c.n_fail}/{c.n} | {c.n_not_reached} | "
                         f"{c.n_collision} | {_fmt(float(np.median(fe)) if fe else math.nan, '.3f')} | "
                         f"{_fmt(c.n_samples, '.0f')} | {_fmt(ori, '.3f')} |")
    return lines + [""]


def _timing_table(d: StudyData) -> list[str]:
    lines = ["## Compute time per sample", "",
             "Mean over arms [ms per sample]; totals per test case in Fig. 4.7.", "",
             "| case | " + " | ".join(f"{_clabel(c)} controller" for c in d.controllers) + " | IK | planning | LME |",
             "|---|" + "---:|" * (len(d.controllers) + 3)]
    for case in d.cases:
        cols = [_fmt(1e3 * _mean(d.cell(a, case, c).t_controller for a in d.arms if d.cell(a, case, c)), ".3g")
                for c in d.controllers]
        cols += [_fmt(1e3 * _mean(d.component_time(a, case, k) for a in d.arms), ".3g")
                 for k in ("ik", "planning", "lme")]
        lines.append(f"| {_case_label(case)} | " + " | ".join(cols) + " |")
    return lines + [""]


def _with_data(make, future, d, path):
    return make(d, path, future.result())  # the background computation's error, if any, raises here


def _study_with_runs(out: Path) -> StudyData:
    d = load_study(out)
    if not d.rows:
        raise ValueError(f"out_dir: runs.csv in {str(out)!r} has no runs")
    return d


def draw_figures(out_dir, *, only=None, exclude=()) -> dict:
    """Draw the figures of :data:`FIGURES` and :data:`HOOKS` named in ``only`` (default: all) but
    not in ``exclude`` into ``DIR/figures``, one after the other (a ``prefetch`` computes inline);
    returns ``{file: (status, reason, hook result)}``, what :func:`make_report` takes as ``drawn``.
    :func:`redman_jax._study.render_report` draws the figures in two processes this way."""
    out = Path(out_dir)
    d = _study_with_runs(out)
    drawn = {}
    for spec in FIGURES + HOOKS:
        if (only is not None and spec.file not in only) or spec.file in exclude:
            continue
        if spec.prefetch is not None:
            make, prefetch = spec.make, spec.prefetch
            spec = dataclasses.replace(spec, make=lambda d, path, make=make, prefetch=prefetch:
                                       make(d, path, prefetch(d)))
        drawn[spec.file] = _render(spec, d, out / "figures")
    return drawn


def make_report(out_dir, *, figures: bool = True, hooks: bool = True, drawn: dict | None = None) -> Path:
    """Write ``DIR/figures/*.png`` and ``DIR/report.md`` for a results folder; returns the report path.

    **Arguments:** ``out_dir``: a folder holding ``runs.csv`` (and, optionally, ``traces/*.npz`` and
    ``config.json``) as written by :func:`redman_jax._study.run_sweep`; ``figures=False`` writes only
    the report (its figure list then says "not generated (figures disabled)"); ``hooks=False`` skips
    the figures that rebuild scenes or re-simulate (:data:`HOOKS`; they compile JAX code); ``drawn``:
    figures drawn already (:func:`draw_figures`' result), not drawn again. A figure
    with a ``prefetch`` (Fig. 3.6's step responses) computes in a background thread while the
    others are drawn (the default study's results folder on an idle 2-core machine, two runs each,
    alternating: 29.1 and 28.8 s one after the other, 23.8 and 24.0 s so; the same figures and
    report; at 70f63c3). At a6c7301, with more figures, it takes 44.2 and 47.8 s in a process with
    JAX's own XLA flags and 34.2 and 37.0 s in the one :func:`redman_jax._study.render_report`
    starts.

    **Returns:** the path of ``report.md``.

    **Raises:** ``ValueError`` when ``runs.csv`` is missing or empty. A figure that cannot be drawn
    (missing traces, missing optional module) is listed as "not generated (reason)" in the report.
    """
    from ._store import atomic_write_text

    out = Path(out_dir)
    d = _study_with_runs(out)
    fig_dir = out / "figures"
    specs = FIGURES + HOOKS
    drawn = dict(drawn or {})
    for spec in specs:
        if spec.file in drawn:
            continue
        if not figures:
            drawn[spec.file] = ("missing", "figures disabled", None)
        elif spec in HOOKS and not hooks:
            drawn[spec.file] = ("missing", "scene and simulation figures disabled", None)
    todo = [spec for spec in specs if spec.file not in drawn]
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="redman-report") as pool:
        data = {spec.file: pool.submit(spec.prefetch, d) for spec in todo if spec.prefetch is not None}
        for spec in sorted(todo, key=lambda s: s.file in data):  # those computing in the background last
            if spec.file in data:
                spec = dataclasses.replace(spec, make=functools.partial(_with_data, spec.make, data[spec.file]))
            drawn[spec.file] = _render(spec, d, fig_dir)
    status = []
    extra = {}
    for spec in specs:
        st, reason, res = drawn[spec.file]
        status.append((spec, st, reason))
        if st == "ok" and isinstance(res, dict):
            extra.update(res)
    claims = evaluate_claims(d, extra)

    lines = _header(d)
    lines += ["## Headline", "",
              "Failed runs and pooled mean position error per sample (successful runs) for every "
              "controller, case and arm.", "", headline_table(d)]
    counts = {v: sum(c.verdict == v for c in claims) for v in (AGREES, PARTLY, DIFFERS, NOT_EVALUATED)}
    lines += ["Verdicts: " + ", ".join(f"{k} {v}" for k, v in counts.items()) + ".", ""]
    lines += _METHOD.splitlines() + [""]
    lines += _claims_markdown(claims)
    lines += _timing_table(d)
    lines += _gradient_table(d)
    lines += ["## Figures", ""]
    for spec, st, reason in status:
        if st == "ok":
            lines += [f"**Fig. {spec.thesis}** {spec.caption}", "", f"![Fig. {spec.thesis}](figures/{spec.file})", ""]
    missing = [(spec, reason) for spec, st, reason in status if st != "ok"]
    if missing:
        lines += ["### Not generated", ""]
        lines += [f"* Fig. {spec.thesis} ({spec.file}): not generated ({reason})" for spec, reason in missing]
    lines.append("")
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines))
    return report
