"""The examples and sweep scripts, run end to end at small size.

Each example runs as a user would run it: a subprocess of the venv's Python with ``--small`` and a
temporary output folder; the test checks the exit code, the files it promises and that their
numbers are sane (finite, in physical ranges, and consistent with what the example claims).
The sweep scripts (full-scale work, hours) get a ``--help`` smoke test only.

Cost: the four small runs (``@pytest.mark.slow``) take about 2.7 min of CPU on a 2-core machine
(measured: 3 min wall for the whole file on an idle machine), nearly all of it XLA compilation. They share one JAX persistent compilation cache (a module-scoped temporary folder),
so the scenario build of ``single_scenario`` (7-DOF, inspection, seed 1) is a cache hit for
``custom_controller``, which runs the same case through ``run_sweep``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV_PY = ROOT / ".venv" / "bin" / "python"
PY = str(VENV_PY) if VENV_PY.exists() else sys.executable
TIMEOUT = 900  # s per script: generous for a loaded 2-core machine (each takes ~1 min alone)


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    e = dict(os.environ)
    e.update(
        JAX_COMPILATION_CACHE_DIR=str(tmp_path_factory.mktemp("jax_cache")),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
        REDMAN_JAX_X64="1",
        MPLBACKEND="Agg",
    )
    return e


def run(script: str, *args: str, env=None, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([PY, str(ROOT / script), *args], capture_output=True, text=True, env=env,
                          timeout=TIMEOUT, cwd=str(ROOT))
    if check:
        assert proc.returncode == 0, (f"{script} {' '.join(args)} exited {proc.returncode}\n"
                                      f"stdout:\n{proc.stdout[-4000:]}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def num(v) -> float:
    return float(v)


def is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 1000 and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------------------------------------
# examples at small size


@pytest.mark.slow
def test_single_scenario(tmp_path, env):
    out = tmp_path / "single"
    proc = run("examples/single_scenario.py", "--small", "--out", str(out), env=env)
    m = json.loads((out / "metrics.json").read_text())
    assert m["case"] == "inspection" and m["arm"] == "thesis7"
    assert m["ik_valid"] is True  # the script stops with exit 1 otherwise
    assert m["n_samples"] > 50 and m["seed_used"] % 1000 == m["seed"] % 1000  # seed + 1000 k
    runs = {r["controller"]: r for r in m["runs"]}
    assert set(runs) == {"velocity", "joint_space"}
    for name, r in runs.items():
        assert name in proc.stdout
        for key in ("final_pos_error_mm", "mean_pos_error_mm", "mean_ori_error", "min_distance_m"):
            assert math.isfinite(r[key]), (name, key, r[key])
        assert 0.0 <= r["mean_pos_error_mm"] < 100.0  # below the 0.10 m success radius
        assert 0.0 <= r["mean_ori_error"] <= 1.0  # sin(phi/2)
        assert r["min_distance_m"] > 0.0  # never inside an obstacle
        assert r["n_steps"] >= m["n_samples"]  # the solver restarts at every sample boundary
        assert not r["diverged"]
    # joint space tracks the validated (collision-free, within-limits) IK trajectory with mm errors
    js = runs["joint_space"]
    assert js["success"] and not js["collided"] and js["final_pos_error_mm"] < 100.0
    assert is_png(out / "single_scenario.png")


@pytest.mark.slow
def test_custom_controller(tmp_path, env):
    out = tmp_path / "custom"
    proc = run("examples/custom_controller.py", "--small", "--out", str(out), env=env)
    rows = read_rows(out / "runs.csv")
    assert len(rows) == 1
    r = rows[0]
    assert (r["arm"], r["case"], r["controller"], r["seed"]) == ("7dof", "inspection", "os_pd", "1")
    assert r["scenario_valid"] == "True"
    assert "os_pd" in proc.stdout and "1 runs in" in proc.stdout
    for key in ("final_pos_error", "mean_pos_error", "mean_ori_error", "min_distance", "t_controller_per_sample"):
        assert math.isfinite(num(r[key])), (key, r[key])
    # a PD law without feed-forward lags a moving reference but stays well inside the success radius
    assert 0.0 < num(r["mean_pos_error"]) < 0.05
    assert r["success"] == "True" and r["diverged"] == "False" and r["out_of_steps"] == "False"
    assert int(r["n_steps"]) >= int(r["n_samples"]) > 50
    assert 0.0 < num(r["t_controller_per_sample"]) < 0.1  # the control law per sample, seconds
    assert (out / "config.json").is_file() and (out / "traces" / "7dof_inspection_os_pd.npz").is_file()


def test_custom_controller_law_at_rest():
    """The example's controller against an independent reference: at rest on the reference with
    orientation control off, ``tau = g(q)`` (no task force, no null-space damping); with a position
    error ``e`` and orientation off, ``tau - g = J_v^T k_p e``."""
    import numpy as np

    import redman_jax as rj

    sys.path.insert(0, str(ROOT / "examples"))
    try:
        from custom_controller import OSPD
    finally:
        sys.path.pop(0)
    arm = rj.thesis_arm(7)
    ctrl = OSPD()
    gains = ctrl.default_gains()
    q = arm.q0 + 0.1
    n = arm.n_dof
    p, quat = rj.end_effector_pose(arm, q)
    zq, z3 = np.zeros(n), np.zeros(3)
    env = rj.make_environment(rj.empty_obstacles(), p, quat)
    g = np.asarray(rj.gravity_forces(arm, q))
    Jv = np.asarray(rj.jacobian(arm, q))[:3]
    e = np.array([0.01, -0.02, 0.005])
    for offset in (z3, e):
        ref = rj.RefSample(p=p + offset, v=z3, a=z3, quat=quat, omega=z3, omega_dot=z3, rot=np.asarray(0.0),
                           q=zq, qd=zq, qdd=zq)
        out = ctrl(gains, arm, rj.ControlState(t=np.asarray(0.0), q=q, qd=zq, z=()), ref, env)
        np.testing.assert_allclose(np.asarray(out.tau), g + Jv.T @ (float(gains.kp) * offset), rtol=1e-10,
                                   atol=1e-9)


@pytest.mark.slow
def test_own_jit(tmp_path, env):
    out = tmp_path / "own"
    proc = run("examples/own_jit.py", "--small", "--out", str(out), env=env)
    s = json.loads((out / "own_jit.json").read_text())
    assert s["batch"] == 3 and s["samples"] == 100 and "jax.grad" in proc.stdout
    assert math.isfinite(s["loss"]) and s["loss"] > 0.0
    # reverse mode through the scan vs a central difference of the same compiled loss (step 1e-3 kp):
    # truncation ~ (1e-3)^2 relative, rounding ~ 1e-16 L / (2e-2) ~ 1e-14; measured 1.3e-5
    assert math.isfinite(s["grad_kp"]) and s["grad_rel_diff"] < 1e-3
    assert s["grad_kp"] < 0.0  # stiffer position feedback, less lag on the moving reference
    # every member converges to the reference (initial offsets up to ~0.1 m): final error < 10 mm
    assert max(s["final_err_m"]) < 0.010
    assert all(0.0 < e < 0.05 for e in s["mean_err_m"])


@pytest.mark.slow
def test_panda_study(tmp_path, env):
    out = tmp_path / "panda"
    proc = run("examples/panda_study.py", "--small", "--out", str(out), env=env)
    rows = read_rows(out / "runs.csv")
    assert len(rows) == 1
    r = rows[0]
    assert r["arm"] == "panda-panda_hand" and r["case"] == "warehouse" and r["controller"] == "velocity"
    assert int(r["n_samples"]) >= 1 and int(r["seed_used"]) % 1000 == 1
    if r["scenario_valid"] == "False":  # expected with the thesis-sized generators: said, not hidden
        assert "NOTE:" in proc.stdout and "scenario_valid=False" in proc.stdout
    else:
        assert math.isfinite(num(r["final_pos_error"])) and "runs on validated scenarios" in proc.stdout


def test_perfect_controller_example(tmp_path, env, monkeypatch):
    """Fig. 3.7 example (seconds): the point reaches the goal of the simple scene of seed 2 before the
    6 s horizon, by a path no shorter than the straight line from start to goal, the estimator
    placed virtual obstacles on the way, and the figure is written."""
    import re

    import numpy as np

    out = tmp_path / "fig3_7.png"
    proc = run("examples/perfect_controller.py", "--seed", "2", "--out", str(out), env=env)
    assert is_png(out)
    m = re.search(r"success (\w+), samples (\d+), path ([\d.]+) m, (\d+) valid estimates", proc.stdout)
    assert m, proc.stdout
    assert m.group(1) == "True" and 0 < int(m.group(2)) < 600 and int(m.group(4)) > 0
    monkeypatch.syspath_prepend(str(ROOT / "examples"))
    from perfect_controller import simple_scene

    _, xs, xg, _ = simple_scene(2)
    straight = float(np.linalg.norm(np.asarray(xg) - np.asarray(xs)))
    assert straight - 0.1 <= float(m.group(3)) < 4 * straight  # within the 10 cm goal radius of a straight line at best


def test_plot_cases_example(tmp_path, env):
    """Fig. 3.2 / 3.4 example (seconds): one PNG per case and the warehouse field slice."""
    from redman_jax._scenario import CASES

    proc = run("examples/plot_cases.py", str(tmp_path), "--seed", "1", env=env)
    for case in CASES:
        assert is_png(tmp_path / f"case_{case}_seed1_9dof.png"), proc.stdout
    assert is_png(tmp_path / "field_warehouse_seed1.png")
    assert len(proc.stdout.strip().splitlines()) == len(CASES) + 1


# ------------------------------------------------------------------------------------------------
# command lines


@pytest.mark.parametrize("script", [
    "sweeps/thesis_study.py", "sweeps/ablation_obstacle_form.py", "sweeps/ablation_jac_scaling.py",
    "examples/single_scenario.py", "examples/own_jit.py", "examples/panda_study.py",
    "examples/custom_controller.py", "examples/perfect_controller.py",
])
def test_help(script):
    proc = run(script, "--help")
    assert "--out" in proc.stdout and "usage" in proc.stdout.lower()
    bad = run(script, "--no-such-option", check=False)
    assert bad.returncode == 2 and "unrecognized arguments" in bad.stderr


@pytest.mark.parametrize("script", ["ablation_obstacle_form", "ablation_jac_scaling"])
def test_ablation_tables_from_a_finished_sweep(script, monkeypatch, tmp_path, capsys):
    """The ablations' tables after the sweep (the sweep itself stubbed out: its units are what the
    study's tests cover): the obstacle-form table read an undefined name after the whole sweep.
    The sweep gets worker processes (``--jobs auto``) and the script's ``register``, which puts
    its controller variants in each worker's registry."""
    import importlib

    import redman_jax._study as study

    monkeypatch.syspath_prepend(str(ROOT / "sweeps"))
    mod = importlib.import_module(script)
    rows = [dict(arm=arm, case="simple", seed=1, controller=ctrl, success=True, collided=False, diverged=False,
                 mean_pos_error=0.01, mean_ori_error=0.0, final_pos_error=0.05, time_to_goal=2.0,
                 scenario_valid=True)
            for arm in ("7dof", "8dof", "9dof") for ctrl in mod.VARIANTS]
    calls = []
    monkeypatch.setattr(study, "run_sweep", lambda cfg, **kw: calls.append((cfg, kw)) or tmp_path)
    monkeypatch.setattr(study, "load_runs", lambda out: rows)
    assert mod.main(["--cases", "simple", "--seeds", "1", "--quiet", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    (cfg, kw), = calls
    assert cfg.jobs == study._jobs("auto") and kw == {"_worker_init": mod.register}
    # one table row per variant: 3 successes of 3 runs (the jac table counts failures, 0/3)
    cell = "| 0/3 |" if script == "ablation_jac_scaling" else "| 3/3 |"
    assert sum(line.startswith("| simple |") and cell in line for line in out.splitlines()) == len(mod.VARIANTS)
    if script == "ablation_obstacle_form":  # diverged runs, and of them those out of the step budget
        # the out_of_steps column where a row has one, else n_steps at the budget (older tables)
        rows[0].update(success=False, diverged=True, n_steps=mod.out_of_steps_budget())
        rows[2].update(success=False, diverged=True, n_steps=mod.out_of_steps_budget(), out_of_steps=False)
        rows[1].update(success=False, diverged=True, n_steps=10, out_of_steps=True)
        rows[3].update(success=False, diverged=True, n_steps=10)
        assert mod.main(["--cases", "simple", "--seeds", "1", "--quiet", "--out", str(tmp_path)]) == 0
        lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| simple |")]
        assert [ln.split(" | ")[4] for ln in lines] == ["2 (1)", "2 (1)"]


def test_thesis_study_script_is_the_study_command(monkeypatch, tmp_path, capsys):
    """sweeps/thesis_study.py builds the configuration `redman-jax study` builds, worker processes
    included (it used to run in one process while documented as the same command); the sweep itself
    is stubbed out."""
    import importlib

    import redman_jax._study as study
    from redman_jax._cli import build_parser

    monkeypatch.syspath_prepend(str(ROOT / "sweeps"))
    mod = importlib.import_module("thesis_study")
    seen = []
    monkeypatch.setattr(study, "run_sweep", lambda cfg: seen.append(cfg) or tmp_path)
    monkeypatch.setattr(study, "load_runs", lambda out: [])
    for extra in ([], ["--jobs", "1"]):
        argv = ["--out", str(tmp_path), "--seeds", "1-2", "--quiet", *extra]
        assert mod.main(argv) == 0
        want = study.SweepConfig.from_args(build_parser().parse_args(["study", *argv]), study=True)
        assert seen[-1] == want
    assert seen[0].jobs == study._jobs("auto") and seen[1].jobs == 1
    capsys.readouterr()


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "benchmarks").glob("bench_*.py")))
def test_benchmark_help(script):
    """Every benchmark imports (its names still exist in the package) and parses its options."""
    proc = run(f"benchmarks/{script}", "--help")
    assert "usage" in proc.stdout.lower()


def test_bench_guided_patch_applies(monkeypatch):
    """bench_guided keeps the per-sample step counts by patching one line of the simulator's
    source; when that line moved, the benchmark stopped before any timing."""
    import importlib

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    fn = importlib.import_module("bench_guided")._per_sample_counts()
    assert callable(fn) and fn.__name__ == "_simulate_guided"


@pytest.mark.slow
def test_readme_python_example_runs(tmp_path, env):
    """The README's "From Python" block, as a user would paste it into a file: it runs (the names it
    uses still exist and take those arguments) and prints the run's success and a finite mean
    position error in metres (40 s on 2 cores)."""
    import re

    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) == 1, "the README's Python blocks changed: run each of them here"
    script = tmp_path / "readme_example.py"
    script.write_text(blocks[0])
    proc = subprocess.run([PY, str(script)], capture_output=True, text=True, env=env, timeout=TIMEOUT,
                          cwd=str(tmp_path))
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    success, err = proc.stdout.split()[-2:]
    assert success in ("True", "False")
    assert math.isfinite(float(err)) and 0.0 <= float(err) < 1.0
