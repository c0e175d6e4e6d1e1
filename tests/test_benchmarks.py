"""Every benchmark script runs to the end of its table at a tiny size.

``test_examples.py::test_benchmark_help`` only imports each script and parses its options. That let
``bench_sim.py`` and ``bench_stepsize.py`` break unseen: they called ``float()`` on
``SimParams().rtol``, which became None (resolved by the states' precision) in 1372374, and crashed
before their first row. Here each runs once, as a user would, on one arm, one case, one seed or the
smallest batch its options allow, and must exit 0 and print the line that ends its output. The
numbers themselves are the full-size runs' business (``make bench``).

Cost (``slow``): about 5.5 min on an idle 2-core machine with the twelve runs one after another (4 to
70 s each, nearly all of it compilation), 2 min with ``pytest -n 2``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV_PY = ROOT / ".venv" / "bin" / "python"
PY = str(VENV_PY) if VENV_PY.exists() else sys.executable

# script: (its smallest run, a line its output ends with)
SMALL_RUNS = {
    "bench_cases.py": (["--dof", "7", "--seeds", "1"], "all five"),
    "bench_controllers.py": (["--dof", "7", "--batches", "1", "--controllers", "joint_space", "--calls", "1",
                              "--devices", "2", "--study-flags", "--scene", "boxes"],
                             "acceleration_naive   batch     1:"),
    "bench_dynamics.py": (["--quick"], "paired rounds at batch 1024"),
    "bench_guided.py": (["--dof", "7", "--seeds", "1", "--reps", "2"], "simple: stepper / per-sample, warm speed-up"),
    "bench_ik.py": (["--dof", "7", "--seeds", "1", "--cases", "welding"], "all cases, batched, warm"),
    "bench_lapack_pool.py": (["--batches", "20", "--gfm-batches", "20", "--reps", "2"], "rows that hung: 0 of 5"),
    "bench_planning.py": (["--seeds", "1", "--repeat", "1"], "batch vmap"),
    "bench_sim.py": (["--dof", "7", "--seeds", "2", "--cases", "welding", "--controllers", "joint_space",
                      "--scipy-samples", "2"], "target >= 100x met in"),
    "bench_sharded.py": (["--dof", "7", "--seeds", "1", "--case", "welding", "--controllers", "joint_space",
                          "--repeats", "1"], "(warm: best of the repeats"),
    "bench_solvers.py": (["--dof", "7", "--seeds", "1", "--cases", "welding", "--controllers", "joint_space",
                          "--solvers", "tsit5,dopri5"], "all rows: total steps"),
    "bench_stepsize.py": (["--dof", "7", "--seeds", "1", "--cases", "welding", "--controllers", "joint_space",
                           "--candidates", "0.7,0.3"], "totals over the rows"),
    "bench_tolerance.py": (["--dof", "7", "--seeds", "1", "--cases", "welding", "--controllers", "joint_space",
                            "--candidates", "1e-5/1e-7"], "largest relative deviation from the reference"),
    "bench_tuning.py": (["--arm", "7", "--controllers", "velocity", "--steps", "1"], "total wall time"),
    "bench_vector_field.py": (["--batches", "1", "--controllers", "joint_space"],
                              "closed-loop vector field joint_space"),
}
# the other modes of a script: "script --mode" -> (its smallest run, a line its output ends with)
MODE_RUNS = {
    "bench_ik.py --rounds": (["--dof", "7", "--seeds", "2", "--cases", "welding", "--rounds"],
                             "all cases, the lesser of each"),
}


def test_every_benchmark_has_a_small_run():
    """A new benchmark gets its small run here (or this fails)."""
    assert set(SMALL_RUNS) == {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}


@pytest.mark.slow
@pytest.mark.parametrize("run", sorted(SMALL_RUNS) + sorted(MODE_RUNS))
def test_benchmark_runs_small(run):
    args, last = SMALL_RUNS[run] if run in SMALL_RUNS else MODE_RUNS[run]
    script = run.split()[0]
    env = dict(os.environ, JAX_PLATFORMS="cpu", MPLBACKEND="Agg", REDMAN_JAX_X64="1")
    proc = subprocess.run([PY, str(ROOT / "benchmarks" / script), *args], capture_output=True, text=True,
                          env=env, timeout=900, cwd=str(ROOT))
    assert proc.returncode == 0, (f"{script} {' '.join(args)} exited {proc.returncode}\n"
                                  f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}")
    assert last in proc.stdout, f"{script}: {last!r} not printed\n{proc.stdout[-3000:]}"


def test_obs_d_sets_the_obstacle_policys_range_only(monkeypatch):
    """``--obs-d`` of the step and tolerance benchmarks (``bench_tolerance.with_policy_range``) sets
    the null-space obstacle policy's range ``D`` in the gains and nothing else; no ``--obs-d``
    leaves them as they are."""
    import jax
    import numpy as np

    from redman_jax._controllers import CONTROLLERS

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from bench_tolerance import study_arguments, with_policy_range

    assert study_arguments(__import__("argparse").ArgumentParser()).parse_args(
        ["--obs-d", "5"]).obs_d == 5.0
    for name in ("velocity", "acceleration", "gradient", "joint_space"):
        g = CONTROLLERS[name]().default_gains()
        h = with_policy_range(g, 5.0)
        assert float(g.policy.obs_D) == 0.75 and float(h.policy.obs_D) == 5.0
        diff = [not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(h))]
        assert sum(diff) == 1, name
        assert with_policy_range(g, None) is g


def test_controller_benchmark_scenes(monkeypatch):
    """``bench_controllers.scene``: 40 obstacles, the issue's mix (12 spheres, 16 boxes, 12
    cylinders) or 40 of one shape, every slot active, each size in its own range."""
    import numpy as np

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from bench_controllers import SCENES, scene

    # per family, each size's range: sphere (r,), box (bx, by, bz), cylinder (r, h)
    ranges = ([(0.05, 0.1)], [(0.05, 0.15)] * 3, [(0.03, 0.08), (0.1, 0.3)])
    for kind, counts in SCENES.items():
        obs = scene(np.random.default_rng(0), kind)
        fams = (obs.spheres, obs.boxes, obs.cylinders)
        assert tuple(int(np.sum(f.mask)) for f in fams) == counts and sum(counts) == 40, kind
        for f, rng_ in zip(fams, ranges):
            dims = np.asarray(f.dims)[np.asarray(f.mask)]
            for j, (lo, hi) in enumerate(rng_):
                assert dims.size == 0 or (dims[:, j].min() >= lo and dims[:, j].max() <= hi), (kind, j)
            p = np.asarray(f.p)[np.asarray(f.mask)]
            assert p.size == 0 or np.hypot(p[:, 0], p[:, 1]).min() > 0.45, kind


def test_tolerance_table_metrics_are_the_headline_tables(monkeypatch):
    """``bench_tolerance.table_metrics``: a cell's failed runs and its mean position error over the
    successful runs only, as the study's headline table reports them; ``table_deviation`` compares
    them with the reference's (a run that fails under one tolerance only changes the count)."""
    import numpy as np
    from types import SimpleNamespace as NS

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from bench_tolerance import table_deviation, table_metrics

    ref = NS(success=np.array([True, True, False]), mean_pos_err=np.array([0.02, 0.04, 9.0]))
    assert table_metrics(ref) == (1, 0.03)
    near = NS(success=ref.success, mean_pos_err=np.array([0.0201, 0.0401, 1.0]))
    same, dev = table_deviation(near, ref)
    assert same and abs(dev - 0.0001 / 0.03) < 1e-12  # the failed run's error is not in the table
    flipped = NS(success=np.array([True, False, False]), mean_pos_err=ref.mean_pos_err)
    same, dev = table_deviation(flipped, ref)
    assert not same and abs(dev - 1 / 3) < 1e-12
    none = NS(success=np.zeros(3, bool), mean_pos_err=ref.mean_pos_err)
    assert table_metrics(none)[0] == 3 and np.isnan(table_metrics(none)[1])
    assert table_deviation(none, none) == (True, 0.0)
