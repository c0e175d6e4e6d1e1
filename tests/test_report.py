"""Figures and report of a study (issue 7, SPEC sections 10-11), on synthetic results folders.

A synthetic ``runs.csv`` + traces with known failures, errors and timings is written in the layout of
``redman_jax._study`` (``RUN_COLUMNS``, ``traces/<arm>_<case>_<controller>.npz``, ``config.json``);
the tests check that every figure is a non-empty PNG, the report has each R-section, and the computed
verdicts follow the data (a JS failure must turn R3 into "differs", swapped timings R1, ...).
"""

import json
import math
import os
import re
from typing import NamedTuple

import numpy as np
import pytest

import redman_jax._report as report_mod
from redman_jax._report import (
    AGREES, DIFFERS, FIGURES, HOOKS, NOT_EVALUATED, PARTLY, FigureSpec, StudyData, _render, evaluate_claims,
    headline_table, load_study, make_report, sawtooth_fraction, wilson_interval,
)
from redman_jax._study import GRADIENT_CASES, RUN_COLUMNS, load_runs, write_table

ARMS = ("7dof", "8dof", "9dof")
CASES = ("agriculture", "warehouse", "inspection", "welding", "simple")
CTRLS = ("joint_space", "velocity", "acceleration")
SEEDS = (1, 2, 3, 4)
N_CASE = {"agriculture": 60, "warehouse": 50, "inspection": 45, "welding": 40, "simple": 75}
T_CTRL = {"joint_space": 1.7e-4, "velocity": 2.2e-4, "gradient": 2.3e-4, "acceleration": 2.6e-4}
T_IK = {"agriculture": 5e-3, "simple": 3e-3}
T_PLAN = {"agriculture": 1e-3, "simple": 2e-3}
TS = 0.01


def _pos_level(arm, case, ctrl):
    """Mean position error [m] of the synthetic runs: JS best on 8/9-DOF, worst on 7-DOF except in
    agriculture and simple; velocity below acceleration; 7-DOF highest (the thesis's pattern)."""
    base = {"joint_space": 1.0e-3, "velocity": 1.5e-3, "acceleration": 2.0e-3}[ctrl]
    if arm == "7dof":
        base = {"joint_space": 10.0e-3 if case not in ("agriculture", "simple") else 1.2e-3,
                "velocity": 1.6e-3, "acceleration": 2.4e-3}[ctrl]
    return base


def _ori_level(case, ctrl):
    if case == "welding":
        return {"joint_space": 0.01, "velocity": 0.02, "acceleration": 0.03}[ctrl]
    return {"joint_space": 0.05, "velocity": 0.02, "acceleration": 0.04}[ctrl]


def synthetic_study(out, *, js_failures=(), ctrl_time=None, gradient_success=None, traces=True,
                    drop_trace_keys=()):
    """Write a results folder; returns the rows. ``js_failures``: (arm, case, seed) that collide under
    JS; ``gradient_success``: {case: successes per arm} (default agriculture 3, warehouse 0, simple 4)."""
    rng = np.random.default_rng(0)
    ctrl_time = ctrl_time or T_CTRL
    gsucc = {"agriculture": 3, "warehouse": 0, "simple": 4}
    gsucc.update(gradient_success or {})
    rows = []
    for arm in ARMS:
        dof = int(arm[0])
        for case in CASES:
            n_nom = N_CASE[case]
            N = n_nom + 5
            t = TS * np.arange(1, N + 1)
            ctrls = CTRLS + (("gradient",) if case in GRADIENT_CASES else ())
            for ctrl in ctrls:
                tr = {k: [] for k in ("pos_err", "ori_err", "rot", "mask", "p", "p_d", "min_dist", "goal_err")}
                for i, seed in enumerate(SEEDS):
                    n = n_nom + (i % 3) * 2  # unequal lengths: pooled != mean of means
                    mask = np.arange(N) < n
                    rot = np.zeros(N)
                    if case == "welding":
                        rot[:] = 1
                    elif case in ("warehouse", "inspection"):
                        rot[n // 3: 2 * n // 3] = 1
                    row = dict(arm=arm, case=case, seed=seed, seed_used=seed + (1000 if i == 3 else 0),
                               controller=ctrl, joint_limit_hit=False, diverged=False, n_steps=3 * n,
                               min_distance=0.2, path_length=1.0, time_to_goal=float("nan"),
                               t_controller_per_sample=ctrl_time[ctrl],
                               t_ik_per_sample=T_IK.get(case, 2e-3), t_planning_per_sample=T_PLAN.get(case, 1e-5),
                               t_lme_per_sample=1e-4 if ctrl == "gradient" else float("nan"))
                    if ctrl == "gradient":
                        ok = i < gsucc[case]
                        n = 300 if ok else 600
                        mask = np.arange(N) < N
                        final = 0.05 if ok else 0.3 + 0.1 * i
                        pos = np.full(N, np.nan)
                        goal = np.linspace(0.8, final, N)
                        row.update(success=ok, collided=False, reached=ok, final_pos_error=final,
                                   mean_pos_error=float("nan"), mean_ori_error=0.1, n_samples=n)
                        tr["goal_err"].append(goal)
                    else:
                        lvl = _pos_level(arm, case, ctrl) * (1 + 0.1 * i)
                        pos = lvl * (1 + 0.2 * np.sin(np.arange(N)))
                        if ctrl == "acceleration":
                            pos = np.where(rot > 0.5, 2 * pos, pos)
                        collided = ctrl == "joint_space" and (arm, case, seed) in js_failures
                        # OSC failures: collisions, more on fewer DOF, one in every case
                        collided |= ctrl == "acceleration" and i < (3 - (dof - 7))
                        collided |= ctrl == "velocity" and dof == 7 and i == 0 and case in ("warehouse", "simple")
                        final = 0.15 if (collided and i == 0) else 0.01
                        ori = _ori_level(case, ctrl) * (1 + 0.05 * rng.standard_normal(N))
                        row.update(success=not collided, collided=collided, reached=final < 0.1,
                                   final_pos_error=final, mean_pos_error=float(pos[mask].mean()),
                                   mean_ori_error=float(ori[mask & (rot > 0.5)].mean()) if (rot > 0.5).any()
                                   else float("nan"), n_samples=n)
                        tr["ori_err"].append(ori)
                        tr["goal_err"].append(np.full(N, np.nan))
                    rows.append(row)
                    p_d = np.stack([0.3 * np.sin(0.5 * t), 0.2 * np.cos(0.5 * t), 0.5 + 0 * t], -1)
                    tr["pos_err"].append(pos)
                    tr["rot"].append(rot)
                    tr["mask"].append(mask)
                    tr["p_d"].append(p_d)
                    tr["p"].append(p_d + 1e-3)
                    tr["min_dist"].append(np.full(N, 0.2))
                    if not tr["ori_err"] or len(tr["ori_err"]) < len(tr["pos_err"]):
                        tr["ori_err"].append(np.zeros(N))
                if traces:
                    arrays = {k: np.stack(v) for k, v in tr.items() if v}
                    arrays["seed"] = np.asarray(SEEDS)
                    arrays["t"] = t
                    if ctrl != "gradient":
                        arrays.pop("goal_err")
                    for k in drop_trace_keys:
                        arrays.pop(k, None)
                    (out / "traces").mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(out / "traces" / f"{arm}_{case}_{ctrl}.npz", **arrays)
    write_table(out, rows)
    (out / "config.json").write_text(json.dumps({"arms": ["7", "8", "9"], "cases": list(CASES),
                                                 "seeds": list(SEEDS), "ts": TS,
                                                 "controllers": list(CTRLS) + ["gradient"],
                                                 "gradient_cases": list(GRADIENT_CASES)}))
    return rows


def _claims(out):
    return {c.id: c for c in evaluate_claims(load_study(out))}


def _is_png(path):
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_make_report_end_to_end(tmp_path, monkeypatch):
    synthetic_study(tmp_path)

    def good_hook(d, path):  # stands in for a scene / re-simulation figure that also judges R8
        from matplotlib.figure import Figure

        fig = Figure(figsize=(3, 2))
        fig.add_subplot(111).plot([0, 1], [1, 0])
        fig.savefig(path)
        return {"R8": (AGREES, "error falls within 97 % of 50 samples", "synthetic")}

    def bad_hook(d, path):
        raise RuntimeError("boom")

    hooks = (FigureSpec("fig4_3_within_sample.png", "4.3", "within", good_hook),
             FigureSpec("fig3_2_cases.png", "3.2", "cases", bad_hook))
    monkeypatch.setattr(report_mod, "HOOKS", hooks)
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "fig3_2_cases.png").write_bytes(b"stale")  # from an earlier run
    report = make_report(tmp_path)
    assert not (tmp_path / "figures" / "fig3_2_cases.png").exists()
    text = report.read_text()
    for spec in FIGURES + hooks[:1]:
        assert _is_png(tmp_path / "figures" / spec.file), spec.file
        assert f"figures/{spec.file}" in text
    assert "* Fig. 3.2 (fig3_2_cases.png): not generated (RuntimeError: boom)" in text
    assert "| R8.a | The error within a sample is a saw-tooth (Fig. 4.3) | saw-tooth | error falls within 97 % " \
           "of 50 samples | **agrees** |" in text
    for sec in ("R1", "R2", "R3", "R4", "R5", "R6", "R7", "R8"):
        assert f"## {sec} - " in text
    assert "## Hypothesis verdicts" in text
    assert "| R3.a | Joint space has 0 failures | 0 failures | 0 of 60 runs failed | **agrees** |" in text
    assert "| seeds | 1-4 (4 per arm and case) |" in text
    assert "MATLAB" in text
    assert len(list(tmp_path.glob("figures/.*"))) == 0  # no temporary files left behind


def test_hooks_and_figures_can_be_disabled(tmp_path):
    synthetic_study(tmp_path)
    text = make_report(tmp_path, figures=False).read_text()
    assert not (tmp_path / "figures").exists() or not list((tmp_path / "figures").iterdir())
    for spec in FIGURES + HOOKS:
        assert f"({spec.file}): not generated (figures disabled)" in text


def test_the_report_names_the_cpu_its_timings_ran_on(tmp_path, monkeypatch):
    """The machine row carries the CPU model (the report compares timings) and the machine's CPUs."""
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: Test CPU 9000 @ 3.1GHz\n"
                    "processor\t: 1\nmodel name\t: Test CPU 9000 @ 3.1GHz\n")
    assert report_mod._cpu_model(str(info)) == "Test CPU 9000 @ 3.1GHz"
    info.write_text("processor\t: 0\nmodel name\t:\n")  # no name: platform's word, or unknown
    assert report_mod._cpu_model(str(info)) == (report_mod.platform.processor() or "CPU model unknown")
    assert report_mod._cpu_model(str(tmp_path / "absent")) == (report_mod.platform.processor() or "CPU model unknown")
    monkeypatch.setattr(report_mod, "_cpu_model", lambda: "Test CPU 9000")
    synthetic_study(tmp_path / "study")
    text = make_report(tmp_path / "study", figures=False).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| machine |"))
    assert "Test CPU 9000" in row and f"{os.cpu_count()} logical CPUs" in row, row


def test_verdicts_follow_the_data(tmp_path):
    synthetic_study(tmp_path)
    c = _claims(tmp_path)
    assert c["R3.a"].verdict == AGREES
    assert c["R3.b"].verdict == AGREES  # every OSC failure collided
    assert c["R3.c"].verdict == AGREES  # acceleration fails in every case
    assert c["R3.d"].verdict == AGREES  # 7 > 8 > 9 DOF by construction
    assert c["R1.a"].verdict == AGREES and c["R1.b"].verdict == AGREES
    # gradient: agriculture 9/12 (thesis 82 % inside the Wilson interval), warehouse 0/12, simple 12/12
    assert c["R2.a"].ours.startswith("9/12") and c["R2.a"].verdict == AGREES
    assert c["R2.b"].ours.startswith("0/12") and c["R2.b"].verdict == AGREES
    assert c["R2.c"].verdict == AGREES and c["R2.d"].verdict == AGREES
    assert c["R6.a"].verdict == AGREES and c["R6.b"].verdict == AGREES and c["R6.c"].verdict == AGREES
    assert c["R6.e"].verdict == AGREES  # velocity below acceleration everywhere
    assert c["R6.f"].verdict == AGREES  # acceleration error doubles with rot on, velocity's does not
    assert c["R6.g"].verdict == AGREES  # |p_d''| = 0.25 * 0.3 m/s^2
    assert c["R7.a"].verdict == AGREES and c["R7.b"].verdict == AGREES
    assert c["R5.d"].verdict == AGREES  # planning simple > agri, IK agri > simple, N simple > agri
    assert c["H.b"].verdict == AGREES and c["H.c"].verdict == AGREES
    assert c["R8.a"].verdict == NOT_EVALUATED


def test_js_failure_gives_differs(tmp_path):
    synthetic_study(tmp_path, js_failures={("8dof", "welding", 2)})
    c = _claims(tmp_path)
    assert c["R3.a"].verdict == DIFFERS
    assert c["R3.a"].ours == "1 of 60 runs failed"
    assert "8dof/welding" in c["R3.a"].why
    text = make_report(tmp_path, figures=False).read_text()
    assert "| R3.a | Joint space has 0 failures | 0 failures | 1 of 60 runs failed | **differs** |" in text


def test_swapped_controller_times_differ(tmp_path):
    times = dict(T_CTRL, joint_space=3e-4)  # JS now the slowest
    synthetic_study(tmp_path, ctrl_time=times)
    c = _claims(tmp_path)
    assert c["R1.a"].verdict in (PARTLY, DIFFERS)
    assert "JS fastest: no" in c["R1.a"].why
    # velocity 0.22 vs gradient 0.23 ms are within 15 %; push gradient out of it
    synthetic_study(tmp_path, ctrl_time=dict(T_CTRL, gradient=2.55e-4))
    assert "velocity ~ gradient (within 1.15x): no" in _claims(tmp_path)["R1.a"].why


def test_gradient_success_against_thesis(tmp_path):
    synthetic_study(tmp_path, gradient_success={"simple": 2, "warehouse": 4})
    c = _claims(tmp_path)
    assert c["R2.c"].ours.startswith("6/12") and c["R2.c"].verdict == DIFFERS  # thesis 100 %
    assert c["R2.b"].ours.startswith("12/12") and c["R2.b"].verdict == DIFFERS  # thesis 2/60


def test_wilson_interval_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    z = float(stats.norm.ppf(0.975))  # SciPy's z for 95 %; ours defaults to the rounded 1.96
    for k, n in ((0, 12), (9, 12), (12, 12), (49, 60), (2, 60)):
        ref = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        lo, hi = wilson_interval(k, n, z=z)
        assert lo == pytest.approx(ref.low, abs=1e-12) and hi == pytest.approx(ref.high, abs=1e-12)
        lo, hi = wilson_interval(k, n)  # z = 1.96 moves the ends by less than 1e-5
        assert lo == pytest.approx(ref.low, abs=1e-5) and hi == pytest.approx(ref.high, abs=1e-5)


def test_wilson_interval_ends_are_exact():
    # every success (or none) must keep 100 % (0 %) inside: rounding gave 60/60 an upper bound of
    # 0.9999999999999999, and the report called the thesis's 100 % (R2.c) "differs"
    for n in range(1, 400):
        assert wilson_interval(n, n)[1] == 1.0 and wilson_interval(0, n)[0] == 0.0, n
        lo, hi = wilson_interval(max(1, n // 2), n) if n > 1 else (0.5, 0.5)
        assert 0.0 < lo <= hi < 1.0


def test_dof_ordering_skips_an_arm_without_osc_runs(tmp_path):
    rows = synthetic_study(tmp_path)
    keep = [r for r in rows if not (r["arm"] == "8dof" and r["controller"] in ("velocity", "acceleration"))]
    write_table(tmp_path, keep)
    c = _claims(tmp_path)["R3.d"]
    assert c.verdict == AGREES, c  # 7-DOF fails more than 9-DOF; the 8-DOF arm has no rate
    assert "8-DOF" not in c.ours
    only_7 = [r for r in keep if not (r["arm"] == "9dof" and r["controller"] in ("velocity", "acceleration"))]
    write_table(tmp_path, only_7)
    assert _claims(tmp_path)["R3.d"].verdict == NOT_EVALUATED


def test_pooled_errors_and_headline_table(tmp_path):
    rows = synthetic_study(tmp_path)
    d = load_study(tmp_path)
    # pooled position error = all valid samples of the successful runs, recomputed from the traces
    for arm, case, ctrl in (("7dof", "warehouse", "velocity"), ("9dof", "inspection", "acceleration")):
        tr = np.load(tmp_path / "traces" / f"{arm}_{case}_{ctrl}.npz")
        ok = [r["seed"] for r in rows if (r["arm"], r["case"], r["controller"]) == (arm, case, ctrl) and r["success"]]
        sel = tr["mask"] & np.isin(tr["seed"], ok)[:, None]
        assert d.cell(arm, case, ctrl).pos_err == pytest.approx(tr["pos_err"][sel].mean(), rel=1e-12)
        sel_o = sel & (tr["rot"] > 0.5)
        assert d.cell(arm, case, ctrl).ori_err == pytest.approx(tr["ori_err"][sel_o].mean(), rel=1e-12)
        # unequal run lengths: the pooled mean is not the mean of the run means
        means = [r["mean_pos_error"] for r in rows if (r["arm"], r["case"], r["controller"]) == (arm, case, ctrl)
                 and r["success"]]
        assert abs(np.mean(means) - d.cell(arm, case, ctrl).pos_err) > 1e-9
    table = headline_table(load_runs(tmp_path))
    line = next(ln for ln in table.splitlines() if ln.startswith("| Agriculture | Acceleration OSC |"))
    cols = [s.strip() for s in line.strip("|").split("|")]
    assert cols[2] == "3/4 (75 %)" and cols[4] == "2/4 (50 %)" and cols[6] == "1/4 (25 %)"
    assert float(cols[3]) == pytest.approx(1e3 * d.cell("7dof", "agriculture", "acceleration").pos_err, abs=0.006)
    grad = next(ln for ln in table.splitlines() if ln.startswith("| Warehouse | Gradient-guided |"))
    assert grad.count("4/4 (100 %)") == 3 and "–" in grad
    # total compute per test case: JS = (controller + IK + planning) x mean trajectory samples
    n_mean = np.mean([r["n_samples"] for r in rows if r["arm"] == "9dof" and r["case"] == "agriculture"
                      and r["controller"] != "gradient"])
    assert d.total_cost("9dof", "agriculture", "joint_space") == pytest.approx(
        (T_CTRL["joint_space"] + T_IK["agriculture"] + T_PLAN["agriculture"]) * n_mean, rel=1e-12)
    assert d.total_cost("9dof", "agriculture", "gradient") == pytest.approx(
        (T_CTRL["gradient"] + 1e-4) * np.mean([300, 300, 300, 600]), rel=1e-12)


def test_a_table_without_the_runs_columns_is_refused_by_name(tmp_path):
    """A runs.csv that is not a sweep's (no arm / case / controller column) stopped ``plot`` with a
    KeyError from the report's process."""
    (tmp_path / "runs.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"not a runs table of a sweep, no column\(s\) \['arm', 'case'"):
        load_study(tmp_path)


def test_missing_traces_and_columns_do_not_crash(tmp_path):
    synthetic_study(tmp_path, traces=False)
    text = make_report(tmp_path, hooks=False).read_text()
    assert "fig4_2_orientation_switch.png): not generated (" in text
    for spec in FIGURES:
        if spec.file != "fig4_2_orientation_switch.png":
            assert _is_png(tmp_path / "figures" / spec.file), spec.file
    assert "| R6.f |" in text and "| R6.g |" in text
    c = _claims(tmp_path)
    assert c["R6.f"].verdict == NOT_EVALUATED and c["R6.g"].verdict == NOT_EVALUATED
    assert c["R3.a"].verdict == AGREES  # the table alone decides the failures
    # traces without some keys, and a table without timing columns
    sub = tmp_path / "sub"
    sub.mkdir()
    rows = synthetic_study(sub, drop_trace_keys=("rot", "p_d", "mask"))
    for r in rows:
        for k in ("t_ik_per_sample", "t_planning_per_sample", "t_lme_per_sample", "t_controller_per_sample"):
            r.pop(k)
    write_table(sub, rows)
    make_report(sub, figures=False)
    d = load_study(sub)
    spec = next(f for f in FIGURES if f.file == "fig4_5_compute_per_sample.png")
    assert _render(spec, d, sub / "figures") == ("missing", "no timings in runs.csv", None)
    spec = next(f for f in FIGURES if f.file == "fig4_2_orientation_switch.png")
    assert _render(spec, d, sub / "figures")[0] == "ok"  # drawn without rot and mask
    assert _claims(sub)["R1.a"].verdict == NOT_EVALUATED
    assert set(RUN_COLUMNS) <= set(load_runs(sub)[0])


def test_damaged_traces_read_as_missing_with_a_warning(tmp_path):
    """A truncated or empty traces file (a full disk, a copy cut short) raised ``BadZipFile`` or
    ``EOFError`` while the report's data were read, so ``plot`` stopped with a traceback; it is
    a missing file now, named in a warning."""
    synthetic_study(tmp_path)
    files = sorted((tmp_path / "traces").glob("*.npz"))
    cut, empty = files[0], files[1]
    cut.write_bytes(cut.read_bytes()[:300])
    empty.write_bytes(b"")
    with pytest.warns(UserWarning, match="unreadable traces") as seen:
        d = load_study(tmp_path)
        for path in (cut, empty):
            assert d.traces(*_trace_key(path, d)) is None
    assert {p.name for p in (cut, empty)} <= {f.name for f in (tmp_path / "traces").iterdir()}
    assert any(cut.name in str(w.message) for w in seen) and any(empty.name in str(w.message) for w in seen)
    with pytest.warns(UserWarning, match="unreadable traces"):
        make_report(tmp_path, hooks=False)  # no traceback


def _trace_key(path, d):
    for arm, case, ctrl in {(r["arm"], r["case"], r["controller"]) for r in d.rows}:
        if path.name == f"{arm}_{case}_{ctrl}.npz":
            return arm, case, ctrl
    raise AssertionError(path)


def test_unvalidated_scenarios_are_left_out(tmp_path):
    rows = synthetic_study(tmp_path, js_failures={("9dof", "welding", 1)})
    for r in rows:
        r["scenario_valid"] = not (r["arm"] == "9dof" and r["case"] == "welding" and r["seed"] == 1)
    write_table(tmp_path, rows)
    d = load_study(tmp_path)
    assert d.n_excluded == 3 and d.cell("9dof", "welding", "joint_space").n == 3
    assert _claims(tmp_path)["R3.a"].verdict == AGREES  # the failing JS run was on an invalid scene


def test_sawtooth_fraction():
    m, n = 10, 30
    k = np.repeat(np.arange(n), m)
    frac = np.tile(np.arange(1, m + 1) / m, n)
    saw = 1e-3 * (1.5 - frac)  # falls within every sample
    assert sawtooth_fraction(k, saw, n) == (1.0, n - 1)
    rising = 1e-3 * (0.5 + frac)
    assert sawtooth_fraction(k, rising, n) == (0.0, n - 1)


def test_empty_or_absent_table_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="runs.csv"):
        make_report(tmp_path)
    write_table(tmp_path, [])
    with pytest.raises(ValueError, match="no runs"):
        make_report(tmp_path)


def test_studydata_from_rows_only():
    rows = [dict(arm="9dof", case="simple", seed=s, controller="joint_space", success=s != 2, collided=s == 2,
                 final_pos_error=0.01, mean_pos_error=1e-3 * s, n_samples=10 * s) for s in (1, 2, 3)]
    d = StudyData(rows)
    c = d.cell("9dof", "simple", "joint_space")
    assert (c.n, c.n_fail, c.n_collision) == (3, 1, 1)
    assert c.pos_err == pytest.approx((1e-3 * 10 + 3e-3 * 30) / 40)
    assert math.isnan(c.ori_err)


def test_gradient_claims_count_scenes_with_a_displaced_field_minimum(tmp_path):
    rows = synthetic_study(tmp_path)
    grad = [r for r in rows if r["controller"] == "gradient" and r["case"] == "agriculture"]
    for i, r in enumerate(grad):  # every failure and one success have the minimum off the goal
        r["goal_field_shift"] = 0.15 if (not r["success"] or i == 0) else 0.05
    write_table(tmp_path, rows)
    why = _claims(tmp_path)["R2.a"].why
    n_far = sum(not r["success"] for r in grad) + (1 if grad[0]["success"] else 0)
    n_ok_near = sum(r["success"] for r in grad) - (1 if grad[0]["success"] else 0)
    assert f"more than 0.10 m from the goal in {n_far}/{len(grad)} scenes" in why
    assert f"success in the other {len(grad) - n_far}: {n_ok_near}" in why
    assert "0.10 m from the goal" not in _claims(tmp_path)["R2.b"].why  # no column there: no note


def test_a_figure_with_prefetch_computes_in_a_background_thread(tmp_path, monkeypatch):
    """make_report starts a figure's ``prefetch`` (Fig. 3.6's step responses) in a thread of its own
    before drawing the other figures and hands its result to ``make``; an error in the background
    computation is that figure's reason for not being generated, and the others are drawn."""
    import threading

    synthetic_study(tmp_path)
    ran = {}

    def compute(d):
        ran["thread"] = threading.current_thread().name
        return [0.0, 1.0, 0.5]

    def draw(d, path, data):
        from matplotlib.figure import Figure

        ran["data"] = data
        ran["drawn_in"] = threading.current_thread().name
        fig = Figure(figsize=(3, 2))
        fig.add_subplot(111).plot(data)
        fig.savefig(path)
        return path

    def broken(d):
        raise RuntimeError("no step")

    hooks = (FigureSpec("fig3_6_step_responses.png", "3.6", "steps", draw, prefetch=compute),
             FigureSpec("fig3_7_perfect_controller.png", "3.7", "perfect", draw, prefetch=broken))
    monkeypatch.setattr(report_mod, "HOOKS", hooks)
    text = make_report(tmp_path).read_text()
    assert ran["thread"].startswith("redman-report") and ran["drawn_in"] == threading.current_thread().name
    assert ran["data"] == [0.0, 1.0, 0.5]
    assert _is_png(tmp_path / "figures" / "fig3_6_step_responses.png")
    assert "* Fig. 3.7 (fig3_7_perfect_controller.png): not generated (RuntimeError: no step)" in text
    for spec in FIGURES:
        assert _is_png(tmp_path / "figures" / spec.file), spec.file
    # the step-response figure of the study is one with a prefetch
    assert [s.file for s in HOOKS if s.prefetch] == ["fig3_6_step_responses.png"]  # (imported before the patch)


def test_figures_drawn_in_parts_give_the_same_report(tmp_path, monkeypatch):
    """``draw_figures`` in two parts (as ``render_report``'s two processes: the figures with a
    ``prefetch``, computed inline, and the rest), then ``make_report(drawn=...)``, which draws
    nothing again: the same figures, byte for byte, and the same report as ``make_report`` alone,
    a hook's result (R8's verdict) included."""
    from redman_jax._report import draw_figures

    calls = []

    def compute(d):
        calls.append("prefetch")
        return [0.0, 1.0, 0.5]

    def steps(d, path, data):
        from matplotlib.figure import Figure

        fig = Figure(figsize=(3, 2))
        fig.add_subplot(111).plot(data)
        report_mod._save(fig, path)
        return path

    def within(d, path):
        calls.append("within")
        steps(d, path, [1.0, 0.0])
        return {"R8": (AGREES, "error falls within 97 % of 50 samples", "synthetic")}

    hooks = (FigureSpec("fig3_6_step_responses.png", "3.6", "steps", steps, prefetch=compute),
             FigureSpec("fig4_3_within_sample.png", "4.3", "within", within))
    monkeypatch.setattr(report_mod, "HOOKS", hooks)
    one, two = tmp_path / "one", tmp_path / "two"
    synthetic_study(one)
    synthetic_study(two)
    text_one = make_report(one).read_text()
    assert calls == ["within", "prefetch"] or calls == ["prefetch", "within"]
    calls.clear()
    apart = ("fig3_6_step_responses.png",)
    drawn = draw_figures(two, exclude=apart)
    assert set(drawn) == {s.file for s in FIGURES} | {"fig4_3_within_sample.png"}
    drawn.update(draw_figures(two, only=apart))
    assert sorted(calls) == ["prefetch", "within"]
    text_two = make_report(two, drawn=drawn).read_text()
    assert sorted(calls) == ["prefetch", "within"]  # nothing drawn again
    date = re.compile(r"^\| date \|.*$", re.M)
    assert date.sub("", text_one) == date.sub("", text_two)
    assert "error falls within 97 % of 50 samples | **agrees** |" in text_two
    for spec in FIGURES + hooks:
        assert (one / "figures" / spec.file).read_bytes() == (two / "figures" / spec.file).read_bytes(), spec.file


class _StoredScenes(NamedTuple):
    """A stand-in for a stored Scenario batch: only what ``_stored_scenario`` reads."""

    seed: np.ndarray
    valid: np.ndarray


def test_figures_use_only_the_scenes_of_the_tables_sweep(tmp_path):
    """A sweep with other seeds interrupted in a finished folder rewrites ``units/scen_*.pkl``
    while ``runs.csv`` and ``config.json`` stay: the scene figures drew that other sweep's scene
    (seed 5) for seeds 1, 2 or none. Only the unit whose key ``config.json`` gives is used, and a
    seed it lacks is not replaced by another one."""
    from redman_jax._report import _NotGenerated, _stored_scenario
    from redman_jax._store import UnitStore
    from redman_jax._study import scenario_key

    synthetic_study(tmp_path)
    cfg = json.loads((tmp_path / "config.json").read_text())
    cfg["max_retries"] = 20
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    store = UnitStore(tmp_path)
    scenes = lambda seeds: {"scenarios": _StoredScenes(np.asarray(seeds), np.ones(len(seeds), bool)), "ik": None}
    store.save("scen_9dof_simple", scenario_key("9", "simple", SEEDS, TS, 20), scenes(SEEDS))
    d = load_study(tmp_path)
    assert int(_stored_scenario(d, "9dof", "simple", 3)[1].seed) == 3
    assert int(_stored_scenario(d, "9dof", "simple")[1].seed) == SEEDS[0]
    with pytest.raises(_NotGenerated, match="seed 7 is not among"):
        _stored_scenario(d, "9dof", "simple", 7)
    store.save("scen_9dof_simple", scenario_key("9", "simple", (5,), TS, 20), scenes([5]))  # the other sweep
    for seed in (None, 1):
        with pytest.raises(_NotGenerated, match="another sweep's scenes"):
            _stored_scenario(d, "9dof", "simple", seed)


def test_diverged_gradient_failures_say_which_ran_out_of_steps(tmp_path):
    """R2.d counts the diverged gradient-guided failures and says how many of them only used up
    the solver's step budget (column ``out_of_steps``), and how many of those sat within the success
    radius (a success the budget took away); a table without the column gets no such note."""
    rows = synthetic_study(tmp_path)
    assert "step budget" not in _claims(tmp_path)["R2.d"].why
    fails = [r for r in rows if r["controller"] == "gradient" and not r["success"]]
    for r in fails[:3]:
        r["diverged"] = True
    fails[1]["out_of_steps"] = True
    fails[2]["out_of_steps"] = True
    fails[2]["final_pos_error"] = 0.08  # within the success radius when the budget ran out
    write_table(tmp_path, rows)
    c = _claims(tmp_path)["R2.d"]
    assert c.verdict == DIFFERS
    assert (f"{len(fails) - 3} not reached, 0 collided, 3 diverged (2 of them out of the solver's "
            "step budget, 1 of those within 10 cm of the goal at their last sample)") in c.why
    assert load_runs(tmp_path)[0]["out_of_steps"] == ""  # written as empty where a row has none
