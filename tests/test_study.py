"""The sweep driver: CLI validation, atomic resumable storage, resume after interruption, sharding.

The pipeline units (build a case, run a controller) are replaced by cheap deterministic fakes here,
so these tests check the driver's bookkeeping; the real units are exercised by the examples tests.
"""

import contextlib
import dataclasses
import json
import os
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import numpy as np
import pytest

import redman_jax._pipeline as pipe
from redman_jax._cli import main, parse_int_list
from redman_jax._store import UnitStore, atomic_write_text, json_ready
from redman_jax._scenario import CASES
from redman_jax._study import SweepConfig, load_runs, run_sweep


def test_parse_int_list():
    assert parse_int_list("1-3,7", "seeds") == (1, 2, 3, 7)
    assert parse_int_list("5", "seeds") == (5,)
    for bad in ("a-b", "3-1", ",", "1-"):
        with pytest.raises(ValueError, match="--seeds"):
            parse_int_list(bad, "seeds")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sweep", "--cases", "kitchen"], "--cases"),
        (["sweep", "--controllers", "magic"], "--controllers"),
        (["sweep", "--seeds", "x"], "--seeds"),
        (["sweep", "--arms", "11"], "arms"),
        (["sweep", "--ts", "-1"], "ts"),
        (["sweep", "--gains", "/nonexistent/gains.json"], "--gains"),
        (["sweep", "--solver", "euler"], "solver"),
        (["sweep", "--arms", "urdf:robot.urdf"], "urdf:PATH:TIP_LINK"),
        (["sweep", "--arms", "urdf:/nonexistent/robot.urdf:tool0"], "not found"),
        (["sweep", "--arms", ","], "arms: empty"),
        (["--seeds", "x"], "redman-jax study: error: --seeds"),
        (["--seeds", "1-20000000000"], "--seeds: range '1-20000000000' holds more than 1,000,000 values"),
        (["demo", "--seed", "99999999999999999999"], "demo: error: --seed: at most 2147483647"),
        (["demo", "--arm", "seven"], "demo: error: --arm: 'seven'"),  # its own option, not --arms
        (["demo", "--arm", "urdf:robot.urdf"], "demo: error: --arm: URDF arms are given as"),  # no subcommand: the study's options
    ],
)
def test_cli_rejects_bad_options(argv, message, capsys, tmp_path):
    code = main([*argv, "--out", str(tmp_path / "o")])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and "error" in err


def test_an_out_that_is_a_file_is_refused_by_every_subcommand(capsys, tmp_path):
    """``--out`` naming a file: a clear message and exit 2 (``demo`` and ``tune`` raised
    ``FileExistsError`` with a traceback)."""
    f = tmp_path / "a-file"
    f.write_text("")
    for argv in (["demo", "--no-animation"], ["tune"], ["sweep"]):
        assert main([*argv, "--out", str(f)]) == 2
        assert "is a file, not a folder" in capsys.readouterr().err


def test_sweep_configuration_is_checked_before_any_work(tmp_path):
    """Repeated arms on the command line are one arm (they doubled every row of the table);
    built directly, repeated or empty entries, gains that are not a mapping and unknown gain names
    are refused at construction, not after an hour of scenario builds."""
    from redman_jax._cli import build_parser

    args = build_parser().parse_args(["sweep", "--arms", "9,9, 9", "--out", str(tmp_path)])
    assert SweepConfig.from_args(args, study=False).arms == ("9",)
    for kw, message in [({"arms": ("9", "9")}, "arms: repeated"), ({"arms": ()}, "arms: empty"),
                        ({"cases": ("simple", "simple")}, "cases: repeated"),
                        ({"gains": [1, 2]}, "gains: expected"),
                        ({"gains": {"velocity": {"nope": 1.0}}}, "no field 'nope'"),
                        ({"gains": {"velocity": {"kp": [1.0, 2.0]}}}, "VelocityGains.kp: expected shape"),
                        # a value that is no number, or not finite (every run of it diverged)
                        ({"gains": {"velocity": {"kp": "abc"}}}, "VelocityGains.kp: expected a number"),
                        ({"gains": {"velocity": {"kp": None}}}, "VelocityGains.kp: expected a number"),
                        ({"gains": {"velocity": {"kp": float("nan")}}}, "VelocityGains.kp: expected finite"),
                        ({"gains": {"velocity": {"kp": True}}}, "VelocityGains.kp: expected a number"),
                        # a retry count no seed can use was reported as a (negative) bound on seeds
                        ({"max_retries": 3_000_000}, r"max_retries: must be 0 to 2147483"),
                        # a case none of the controllers runs on: its scenarios built for nothing
                        ({"cases": ("welding", "simple"), "controllers": ("gradient",)},
                         "cases: welding runs none of the controllers gradient"),
                        # seeds whose retries leave int32 (JAX PRNG keys without x64)
                        ({"seeds": (2**31 - 1000,)}, "seeds: at most"),
                        ({"out": str(tmp_path / "a-file")}, "is a file, not a folder")]:
        (tmp_path / "a-file").write_text("")
        with pytest.raises(ValueError, match=message):
            SweepConfig(out=str(tmp_path), **kw) if "out" not in kw else SweepConfig(**kw)
    assert SweepConfig(out=str(tmp_path), seeds=(2**31 - 1 - 20_000,)).seeds  # the largest with 20 retries


def test_urdf_arms_are_keyed_by_their_file_and_never_share_unit_files(tmp_path):
    """Two URDF files with the same stem and tip link would share unit files and table rows:
    refused. An edited URDF file is another arm: its scenario (and so run) keys change."""
    from redman_jax._study import _run_key, _scenario_key

    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "robot.urdf").write_text(f"<robot name='{d}'/>")
    a, b = (f"urdf:{tmp_path / d / 'robot.urdf'}:tool0" for d in ("a", "b"))
    with pytest.raises(ValueError, match="share the label 'robot-tool0'"):
        SweepConfig(out=str(tmp_path), arms=(a, b))
    cfg = SweepConfig(out=str(tmp_path), arms=(a,), cases=("simple",), controllers=("velocity",))
    before = _scenario_key(cfg, a, "simple"), _run_key(cfg, a, "simple", "velocity")
    assert before == (_scenario_key(cfg, a, "simple"), _run_key(cfg, a, "simple", "velocity"))
    (tmp_path / "a" / "robot.urdf").write_text("<robot name='a2'/>")
    after = _scenario_key(cfg, a, "simple"), _run_key(cfg, a, "simple", "velocity")
    assert before[0] != after[0] and before[1] != after[1]


def test_guided_horizon_and_hold_are_six_and_one_seconds_at_any_sample_time():
    """SPEC section 9: a gradient-guided run ends after 6 s or 1 s held at the goal. The sweep
    passed ``SimParams``' sample counts (600, 100) whatever ``--ts``: 12 s and 2 s at 0.02."""
    from redman_jax._study import _sim_params

    for ts in (0.01, 0.02, 0.005, 0.004):
        p = _sim_params(SweepConfig(ts=ts))
        assert p.guidance_samples * ts == pytest.approx(6.0) and p.hold_samples * ts == pytest.approx(1.0)


def test_simulation_key_holds_the_shapes_the_case_is_padded_to():
    """The cases of a sweep share padded shapes (one compilation), so a case's shapes, and its
    results to rounding, depend on the other cases in the sweep: the key says which."""
    from redman_jax._study import _run_key

    alone = SweepConfig(cases=("simple",), controllers=("velocity",))
    shared = SweepConfig(cases=("simple", "inspection"), controllers=("velocity",))
    assert pipe.study_shapes(("simple",))["simple"] != pipe.study_shapes(("simple", "inspection"))["simple"]
    assert _run_key(alone, "9", "simple", "velocity") != _run_key(shared, "9", "simple", "velocity")
    # the joint-space controller's cases all share one shape, the warehouse's box slots included;
    # the others keep the warehouse's own whatever else runs: its key does not move
    every = pipe.study_shapes(CASES, every_case=True)
    assert len(set(every.values())) == 1 and every["inspection"][1][1] == every["warehouse"][1][1] >= 32
    j = SweepConfig(cases=("warehouse",), controllers=("joint_space",))
    j2 = SweepConfig(cases=("warehouse", "inspection"), controllers=("joint_space",))
    assert _run_key(j, "9", "warehouse", "joint_space") != _run_key(j2, "9", "warehouse", "joint_space")
    for ctrl in ("velocity", "gradient"):
        w = SweepConfig(cases=("warehouse",), controllers=(ctrl,))
        w2 = SweepConfig(cases=("warehouse", "simple"), controllers=(ctrl,))
        assert _run_key(w, "9", "warehouse", ctrl) == _run_key(w2, "9", "warehouse", ctrl)
    apart = pipe.study_shapes(("warehouse", "simple"))
    assert apart["warehouse"] != apart["simple"]


def test_only_a_controller_that_does_not_read_the_obstacles_shares_the_warehouses_shapes(monkeypatch):
    """Only a controller whose control law does not pass over the obstacles (``reads_obstacles``
    False: the joint-space controller, ``nullspace="none"``) shares the warehouse's shapes; one
    that does not say (a user's own, registered in ``CONTROLLERS``) keeps the warehouse apart, as
    every controller did before; a user's that says so shares them."""
    import redman_jax as rj
    from redman_jax._study import _sim_shapes

    class Own(rj.AbstractController):
        def default_gains(self):
            return ()

        def init_state(self, arm, q0, qd0):
            return ()

        def __call__(self, gains, arm, state, ref, env):  # pragma: no cover (never simulated)
            raise NotImplementedError

    class Blind(Own):
        @property
        def reads_obstacles(self):
            return False

    reads = {name: rj.CONTROLLERS[name]().reads_obstacles for name in rj.CONTROLLERS}
    assert [k for k, v in reads.items() if not v] == ["joint_space", "pid"], reads
    assert rj.CONTROLLERS["joint_space"](nullspace="actuator").reads_obstacles
    assert not rj.CONTROLLERS["velocity"](nullspace="none").reads_obstacles
    monkeypatch.setitem(rj.CONTROLLERS, "own", Own)
    monkeypatch.setitem(rj.CONTROLLERS, "blind", Blind)
    cfg = SweepConfig(cases=("warehouse", "inspection"), controllers=("own", "blind", "joint_space"))
    assert _sim_shapes(cfg, "warehouse", "own") != _sim_shapes(cfg, "inspection", "own")
    for ctrl in ("blind", "joint_space"):
        assert _sim_shapes(cfg, "warehouse", ctrl) == _sim_shapes(cfg, "inspection", ctrl)


def test_table_without_parquet_support_removes_an_old_parquet(monkeypatch, tmp_path):
    from redman_jax._study import write_table

    (tmp_path / "runs.parquet").write_bytes(b"another sweep's table")
    monkeypatch.setitem(sys.modules, "pandas", None)  # `import pandas` raises ImportError
    write_table(tmp_path, [{"arm": "9dof", "case": "simple", "seed": 1}])
    assert (tmp_path / "runs.csv").exists() and not (tmp_path / "runs.parquet").exists()


def test_atomic_writes_are_as_readable_as_any_new_file(tmp_path):
    """``mkstemp`` creates 0600 files; the results get the mode the umask gives a new file."""
    mask = os.umask(0)
    os.umask(mask)
    atomic_write_text(tmp_path / "t.txt", "x")
    assert (tmp_path / "t.txt").stat().st_mode & 0o777 == 0o666 & ~mask


def test_cli_help_exits_cleanly():
    proc = subprocess.run([sys.executable, "-m", "redman_jax", "sweep", "--help"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0
    for opt in ("--arms", "--cases", "--seeds", "--controllers", "--gains", "--ts", "--solver", "--out"):
        assert opt in proc.stdout


def strict_json_loads(text: str):
    """``json.loads`` that fails on the NaN / Infinity tokens strict JSON parsers reject."""

    def refuse(token):
        raise AssertionError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_json_ready_writes_strict_json():
    """Rows hold NaN (a time a controller does not have) and inf (no time to goal): strict JSON
    has neither, so they become null; NumPy scalars and arrays become plain numbers and lists."""
    row = {"t_ik_per_sample": float("nan"), "time_to_goal": np.float64(np.inf), "n_steps": np.int64(7),
           "success": np.bool_(True), "seed": 3, "case": "simple", "p": np.array([1.0, -np.inf]),
           "nested": {"x": (np.float32(0.5), -np.inf)}}
    back = strict_json_loads(json.dumps(json_ready(row), allow_nan=False))
    assert back == {"t_ik_per_sample": None, "time_to_goal": None, "n_steps": 7, "success": True,
                    "seed": 3, "case": "simple", "p": [1.0, None], "nested": {"x": [0.5, None]}}
    with pytest.raises(ValueError):  # what the demo wrote before: Python's NaN token
        json.dumps(row["t_ik_per_sample"], allow_nan=False)


def test_atomic_store_roundtrip_and_key(tmp_path):
    store = UnitStore(tmp_path)
    store.save("u", "k1", {"x": np.arange(3)})
    assert store.has("u", "k1") and not store.has("u", "k2") and not store.has("v", "k1")
    np.testing.assert_array_equal(store.load("u")["x"], np.arange(3))
    store.path("w").write_bytes(b"truncated garbage")  # a torn foreign file is recomputed, not trusted
    assert not store.has("w", "k1")
    atomic_write_text(tmp_path / "a.txt", "hello")
    assert (tmp_path / "a.txt").read_text() == "hello"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


class _Interrupt(BaseException):
    pass


def _fake_pipeline(monkeypatch, calls, interrupt_after=None, solvers=None):
    """Deterministic stand-ins for the two pipeline units, counting calls (and recording the
    ``SimParams.solver`` each simulation unit is given in ``solvers``)."""
    solvers = [] if solvers is None else solvers

    def build_case(arm, case, seeds, ts=0.01, max_retries=20):
        calls.append(("scen", case))
        return {"case": case, "seeds": list(seeds)}

    def run_controller(arm, scen, ctrl, gains=None, **kw):
        calls.append(("run", scen["case"], ctrl))
        solvers.append(kw["sim_params"].solver)
        if interrupt_after is not None and len([c for c in calls if c[0] == "run"]) > interrupt_after:
            raise _Interrupt()
        rng = np.random.default_rng(zlib.crc32(f"{scen['case']}-{ctrl}".encode()))
        rows = [{"case": scen["case"], "seed": s, "seed_used": s, "controller": ctrl, "success": True,
                 "mean_pos_error": float(rng.random()), "n_samples": 10} for s in scen["seeds"]]
        return {"rows": rows, "traces": {"seed": np.asarray(scen["seeds"]), "pos_err": rng.random((len(rows), 4))}}

    monkeypatch.setattr(pipe, "build_case", build_case)
    monkeypatch.setattr(pipe, "run_controller", run_controller)


def _config(out):
    return SweepConfig(out=str(out), arms=("9",), cases=("welding", "simple"), seeds=(1, 2),
                       controllers=("velocity", "gradient"), figures=False, progress=False)


def test_report_renders_in_a_process_with_the_report_flags(monkeypatch, tmp_path):
    """``render_report`` (the sweep's figures and report, ``redman-jax plot``): on a CPU backend in
    a spawned process whose ``XLA_FLAGS`` add the report's flags (the workers' emitter flags, LLVM's
    level 0) to this process's as they were before it adopted the workers' (``study``), so without
    the workers' loop hoisting; this process's are unchanged; an error there is raised here."""
    import _fake_units

    from redman_jax import _study
    from redman_jax._study import LOOP_XLA_FLAGS, REPORT_XLA_FLAGS, _with_flags, _xla_accepts, render_report

    tests_dir = os.path.dirname(os.path.abspath(__file__))
    monkeypatch.setenv("PYTHONPATH", tests_dir + os.pathsep + os.environ.get("PYTHONPATH", ""))
    before = os.environ.get("XLA_FLAGS", "")
    want = _with_flags(before, REPORT_XLA_FLAGS)
    assert "--xla_backend_optimization_level=0" in want.split() or "--xla_backend_optimization_level" in before
    accepted = _xla_accepts(want)

    def probe():
        render_report(tmp_path, make=_fake_units.report_probe)
        pid, flags = (tmp_path / "probe.txt").read_text().split("\n")
        assert int(pid) != os.getpid()
        return flags

    # redman-jax plot: the process never adopted the workers' flags (a test before may have made
    # this one adopt them: a command line run in this process before its backend started)
    monkeypatch.setattr(_study, "_FLAGS_BEFORE_ADOPTION", None)
    flags = probe()
    assert os.environ.get("XLA_FLAGS", "") == before
    assert flags == (want if accepted else before)
    assert not any(f in flags.split() for f in LOOP_XLA_FLAGS if f not in before.split())
    # redman-jax study: the command line gave this process the workers' flags first; the report
    # starts from the flags it had before, not from the workers'
    adopted = _with_flags(before, _study.WORKER_XLA_FLAGS)
    monkeypatch.setattr(_study, "_FLAGS_BEFORE_ADOPTION", before)
    monkeypatch.setenv("XLA_FLAGS", adopted)
    flags = probe()
    assert os.environ["XLA_FLAGS"] == adopted
    assert flags == (want if accepted else adopted)
    (tmp_path / "fail").touch()
    with pytest.raises(RuntimeError, match="the report failed"):
        render_report(tmp_path, make=_fake_units.report_probe)


def test_resume_after_interruption_equals_uninterrupted(monkeypatch, tmp_path):
    calls = []
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path / "clean"))
    clean = load_runs(tmp_path / "clean")
    # welding: velocity only (gradient runs on point-to-point cases); simple: velocity and gradient
    assert [c for c in calls if c[0] == "run"] == [("run", "welding", "velocity"), ("run", "simple", "velocity"),
                                                  ("run", "simple", "gradient")]

    calls.clear()
    _fake_pipeline(monkeypatch, calls, interrupt_after=1)
    with pytest.raises(_Interrupt):
        run_sweep(_config(tmp_path / "resumed"))
    assert not (tmp_path / "resumed" / "runs.csv").exists()
    calls.clear()
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path / "resumed"))
    # only the units that were missing are computed again
    assert calls == [("run", "simple", "velocity"), ("run", "simple", "gradient")]
    resumed = load_runs(tmp_path / "resumed")
    assert resumed == clean
    assert (tmp_path / "resumed" / "traces" / "9dof_simple_gradient.npz").exists()

    calls.clear()
    run_sweep(_config(tmp_path / "resumed"))  # everything done: nothing recomputed
    assert calls == []
    cfg = json.loads((tmp_path / "resumed" / "config.json").read_text())
    assert cfg["seeds"] == [1, 2]


def test_an_interrupted_sweep_leaves_the_folders_table_and_configuration_a_pair(monkeypatch, tmp_path):
    """``config.json`` is written with ``runs.csv``, at the end: a sweep with other seeds
    interrupted in the folder of a finished one leaves that one's table and configuration (written
    at the start, the new configuration was paired with the old table in the report)."""
    calls = []
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path))
    table = (tmp_path / "runs.csv").read_bytes()
    other = dataclasses.replace(_config(tmp_path), seeds=(3, 4))
    calls.clear()
    _fake_pipeline(monkeypatch, calls, interrupt_after=1)
    with pytest.raises(_Interrupt):
        run_sweep(other)
    assert len([c for c in calls if c[0] == "run"]) == 2  # one unit of the new sweep was finished
    assert (tmp_path / "runs.csv").read_bytes() == table
    assert json.loads((tmp_path / "config.json").read_text())["seeds"] == [1, 2]
    calls.clear()
    _fake_pipeline(monkeypatch, calls)
    run_sweep(other)
    assert json.loads((tmp_path / "config.json").read_text())["seeds"] == [3, 4]
    assert {r["seed"] for r in load_runs(tmp_path)} == {3, 4}


def test_union_seconds_counts_nested_spans_once():
    from redman_jax._study import union_seconds

    assert union_seconds([]) == 0.0
    # an inner trace (2-3) inside an outer one (1-5), a disjoint compile (7-8), touching spans
    assert union_seconds([(7.0, 8.0), (1.0, 5.0), (2.0, 3.0)]) == pytest.approx(5.0)
    assert union_seconds([(0.0, 1.0), (1.0, 2.5), (2.0, 3.0)]) == pytest.approx(3.0)


def test_timing_table_has_every_unit_and_its_compile_time(monkeypatch, tmp_path):
    """``DIR/timing.csv`` lists every unit of the sweep with its wall time and the part spent
    compiling (each fake unit jits a new function, so it compiles); a resumed sweep keeps the
    records of the units it does not recompute, and the summary adds them up."""
    import csv

    import jax

    from redman_jax._study import _units, timing_summary

    calls = []
    _fake_pipeline(monkeypatch, calls)
    build, run = pipe.build_case, pipe.run_controller
    compiling = lambda f: lambda *a, **k: (jax.jit(lambda x: x + 1)(np.float64(len(calls))), f(*a, **k))[1]
    monkeypatch.setattr(pipe, "build_case", compiling(build))
    monkeypatch.setattr(pipe, "run_controller", compiling(run))
    cfg = _config(tmp_path)
    run_sweep(cfg)
    rows = list(csv.DictReader(open(tmp_path / "timing.csv")))
    assert [r["unit"] for r in rows] == [u[4] for ph in _units(cfg) for g in ph.values() for u in g]
    assert [r["kind"] for r in rows] == ["build", "build", "simulation", "simulation", "simulation"]
    for r in rows:
        assert 0 < float(r["compile_s"]) <= float(r["wall_s"]), r
    first = {r["unit"]: r["wall_s"] for r in rows}
    os.remove(tmp_path / "units" / f"{rows[-1]['unit']}.pkl")  # one unit lost: recomputed alone
    calls.clear()
    run_sweep(cfg)
    assert len(calls) == 1
    again = list(csv.DictReader(open(tmp_path / "timing.csv")))
    assert [r["wall_s"] for r in again[:-1]] == [first[r["unit"]] for r in again[:-1]]
    total = sum(float(r["wall_s"]) for r in again)
    assert f"{total:8.1f} s" in timing_summary([dict(r, wall_s=float(r["wall_s"]),
                                                     compile_s=float(r["compile_s"])) for r in again])


def test_changed_configuration_recomputes(monkeypatch, tmp_path):
    calls = []
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path))
    calls.clear()
    cfg = SweepConfig(out=str(tmp_path), arms=("9",), cases=("welding", "simple"), seeds=(1, 2),
                      controllers=("velocity", "gradient"), gains={"velocity": {"kp": 12.0}},
                      figures=False, progress=False)
    run_sweep(cfg)
    assert calls == [("run", "welding", "velocity"), ("run", "simple", "velocity")]


def test_a_float32_sweep_recomputes_a_float64_folder(monkeypatch, tmp_path):
    """Precision is part of the units' keys and of ``config.json``: a float32 sweep
    (``REDMAN_JAX_X64=0``) resumed in a float64 folder reused its scenes and runs (other scenes,
    other tolerances) and wrote them as its own table."""
    from redman_jax import _study

    calls = []
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path))
    assert json.loads((tmp_path / "config.json").read_text())["precision"] == "float64"
    calls.clear()
    monkeypatch.setattr(_study, "_precision", lambda: "float32")
    run_sweep(_config(tmp_path))
    assert [c for c in calls if c[0] == "scen"] == [("scen", "welding"), ("scen", "simple")]
    assert len([c for c in calls if c[0] == "run"]) == 3
    assert json.loads((tmp_path / "config.json").read_text())["precision"] == "float32"


def test_solver_choice_reaches_the_runs_and_keys_them_by_the_solver_used(monkeypatch, tmp_path):
    """``--solver``: each simulation unit gets ``SimParams(solver=...)``; the unit's key holds the
    solver it resolves to, so a folder computed with another solver recomputes exactly the runs
    whose solver changed (``auto`` is Dopri5 for the velocity OSC, Tsit5 for guided runs) and keeps
    the scenario builds."""
    calls, solvers = [], []
    _fake_pipeline(monkeypatch, calls, solvers=solvers)
    run_sweep(_config(tmp_path))
    assert solvers == ["auto"] * 3
    velocity = [("run", "welding", "velocity"), ("run", "simple", "velocity")]
    for solver, recomputed in [("tsit5", velocity),  # the guided unit was Tsit5 already
                               ("auto", velocity),
                               ("dopri5", [("run", "simple", "gradient")]),  # auto's for velocity
                               ("dopri5", [])]:
        calls.clear()
        solvers.clear()
        run_sweep(dataclasses.replace(_config(tmp_path), solver=solver))
        assert calls == recomputed, solver
        assert solvers == [solver] * len(recomputed)
    assert json.loads((tmp_path / "config.json").read_text())["solver"] == "dopri5"
    with pytest.raises(ValueError, match="solver"):
        SweepConfig(solver="euler")


def test_cli_solver_help_names_the_simulators_choices():
    from redman_jax._cli import build_parser
    from redman_jax._sim import SOLVER_CHOICES

    sweep = build_parser()._subparsers._group_actions[0].choices["sweep"]
    (action,) = [a for a in sweep._actions if a.dest == "solver"]
    assert action.default == "auto"
    assert all(name in action.help for name in SOLVER_CHOICES)


def test_parallel_workers_give_the_serial_table(monkeypatch, tmp_path):
    """``jobs=2``: the groups of both phases run in the same two spawned worker processes, each
    pinned to a core of its own where the machine has two; every unit is computed once, the table
    equals the one-process sweep, and a rerun computes nothing."""
    import _fake_units

    from redman_jax._study import _with_flags, _worker_cores, _worker_flags, _xla_accepts

    WORKER_XLA_FLAGS = _worker_flags()

    calls = []
    _fake_pipeline(monkeypatch, calls)
    run_sweep(_config(tmp_path / "serial"))
    tests_dir = os.path.dirname(os.path.abspath(__file__))
    monkeypatch.setenv("PYTHONPATH", tests_dir + os.pathsep + os.environ.get("PYTHONPATH", ""))
    affinity = tmp_path / "affinity"
    affinity.mkdir()
    monkeypatch.setenv("REDMAN_TEST_AFFINITY_DIR", str(affinity))
    cfg = dataclasses.replace(_config(tmp_path / "parallel"), jobs=2)
    flags_before = os.environ.get("XLA_FLAGS", "")
    # under `make test` this process is an xdist worker pinned to one core (conftest); the sweep's
    # workers inherit the affinity of this thread, so let it have every core while they start
    own = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    try:
        if own is not None:
            try:
                os.sched_setaffinity(0, range(os.cpu_count() or 1))
            except OSError:
                pass
        pins, allowed = _worker_cores(2), (os.sched_getaffinity(0) if own is not None else None)
        run_sweep(cfg, _worker_init=_fake_units.install)
    finally:
        if own is not None:
            os.sched_setaffinity(0, own)
    assert load_runs(tmp_path / "parallel") == load_runs(tmp_path / "serial")
    if hasattr(os, "sched_getaffinity"):
        seen = [[set(map(int, line.split(","))) for line in p.read_text().splitlines()]
                for p in affinity.glob("*.txt")]  # per worker, per thread
        pools = [int(p.read_text()) for p in affinity.glob("*.pool")]
        flags = [p.read_text().split() for p in affinity.glob("*.flags")]
        from redman_jax._study import GC_THRESHOLDS

        gcs = {p.read_text() for p in affinity.glob("*.gc")}  # the workers that ran simulations
        assert gcs == {" ".join(map(str, GC_THRESHOLDS))}, gcs
        assert len(flags) == len(seen) and os.environ.get("XLA_FLAGS", "") == flags_before
        if _xla_accepts(_with_flags(flags_before, WORKER_XLA_FLAGS)):  # the workers' XLA flags
            want = set(_with_flags(flags_before, WORKER_XLA_FLAGS).split())  # the user's own kept
            assert all(want <= set(f) for f in flags), flags
        else:
            assert all(f == flags_before.split() for f in flags), flags
        # two workers for both phases: the builds' workers run the simulations too (a pool per
        # phase started four)
        assert len(seen) == 2 and len(pools) == len(seen)
        if pins:  # every thread of a worker on the worker's one core; both cores used
            assert all(len(w[0]) == 1 and w[0] <= set(pins) and all(t == w[0] for t in w) for w in seen)
            assert set().union(*(w[0] for w in seen)) == set(pins)
            # and jax started on that one core: XLA's CPU thread pool is one thread wide (started
            # with two cores, it is two threads wide, and both then share the one core)
            assert pools == [1] * len(seen), pools
        else:  # a platform that cannot pin: nothing pinned
            assert all(t == allowed for w in seen for t in w)
        cores = sorted(os.sched_getaffinity(0))  # every worker on one core, a lone one too
        assert _worker_cores(1) == cores[:1] and _worker_cores(len(cores) + 1) == cores + cores[:1]
    names = sorted(p.name for p in (tmp_path / "parallel").iterdir())
    assert sorted(p.name for p in (tmp_path / "serial").iterdir()) == names
    calls.clear()
    run_sweep(dataclasses.replace(cfg, jobs=1))  # resumes: everything is there
    assert calls == []
    with pytest.raises(ValueError, match="jobs"):
        SweepConfig(jobs=0)


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux's /proc")
def test_workers_leave_when_the_sweep_is_killed(tmp_path):
    """A sweep's main process killed alone (``kill -9``, as the OOM killer or a scheduler does)
    left its two workers computing and then idling for ever (beside the queues' manager it had
    then); every process it started now leaves with it."""
    import signal
    import subprocess
    import sys
    import time

    pids = tmp_path / "pids"
    pids.mkdir()
    tests_dir = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, REDMAN_TEST_PID_DIR=str(pids),
               PYTHONPATH=tests_dir + os.pathsep + os.environ.get("PYTHONPATH", ""))
    script = ("import _fake_units; from redman_jax._study import SweepConfig, run_sweep; "
              f"run_sweep(SweepConfig(out={str(tmp_path / 'o')!r}, arms=('7',), cases=('welding', 'simple'), "
              "seeds=(1,), controllers=('velocity',), figures=False, progress=False, jobs=2), "
              "_worker_init=_fake_units.install_slow)")
    main = subprocess.Popen([sys.executable, "-c", script], env=env)

    def children(pid):
        out = []
        for d in os.listdir("/proc"):
            try:
                with open(f"/proc/{d}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if d.isdigit() and int(fields[1]) == pid:
                out.append(int(d))
        return out

    try:
        deadline = time.monotonic() + 180
        while len(list(pids.glob("*.pid"))) < 2:  # both workers inside a unit
            assert main.poll() is None and time.monotonic() < deadline, "the workers did not start"
            time.sleep(0.2)
        started = children(main.pid)
        workers = [int(p.stem) for p in pids.glob("*.pid")]
        assert set(workers) <= set(started) and len(started) >= 2  # two workers (and mp's resource tracker)
        main.send_signal(signal.SIGKILL)
        main.wait()
        deadline = time.monotonic() + 30
        alive = started
        while alive and time.monotonic() < deadline:
            time.sleep(0.2)
            alive = [p for p in started if os.path.exists(f"/proc/{p}") and _not_zombie(p)]
        assert not alive, f"still running after the sweep was killed: {alive}"
    finally:
        if main.poll() is None:
            main.kill()
        for pid in locals().get("started", []):  # never leave them behind, even when failing
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


def _not_zombie(pid) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_xdist_workers_run_on_a_core_of_their_own():
    """Under ``pytest -n 2`` (``make test``) conftest pins each worker's threads to one core, before
    jax starts."""
    core = os.environ.get("REDMAN_TEST_PINNED_CORE")
    if core is None:
        pytest.skip("not an xdist worker on a machine with a core per worker")
    import jax.numpy as jnp

    from redman_jax._study import _thread_affinities

    jnp.ones(3).sum().block_until_ready()
    assert all(cores == {int(core)} for cores in _thread_affinities())
    # pinned before jax's backend started: XLA's CPU thread pool is one thread wide
    names = []
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):
            names.append(Path(f"/proc/self/task/{tid}/comm").read_text().strip())
    assert sum(n.endswith("XLAEigen") for n in names) == 1, names


SHARD_SCRIPT = textwrap.dedent(
    """
    import sys, numpy as np, jax, jax.numpy as jnp
    import redman_jax as rj
    from redman_jax._pipeline import _pad_batch, shard_batch
    from redman_jax._sim import _batch_mesh, simulate_batch
    sys.path.insert(0, sys.argv[2])
    from test_sim_guided import CTRL, GAINS, guided_scenario
    arm = rj.thesis_arm(7)
    n = len(jax.devices())
    rng = np.random.default_rng(0)
    q = jnp.asarray(rng.normal(size=(5, 7))); qd = jnp.asarray(rng.normal(size=(5, 7)))
    (qp, qdp), R = _pad_batch((q, qd), n)
    qp, qdp = shard_batch((qp, qdp))
    f = jax.jit(jax.vmap(lambda a, b: rj.forward_dynamics(arm, a, b, jnp.zeros(7))))
    out = np.asarray(f(qp, qdp))[:R]
    # the simulator on the sweep's path: 3 gradient-guided runs (stepped from the host), padded to
    # a multiple of the devices and sharded
    scen = rj.stack_scenarios([guided_scenario(o, seed=i) for i, o in
                               enumerate(((0.0, 0.35, -0.1), (0.1, -0.3, 0.0), (-0.2, 0.2, 0.1)))])
    scen, R = _pad_batch(scen, n)
    scen = shard_batch(scen)
    params = rj.SimParams(guidance_samples=60, hold_samples=10)
    res = simulate_batch(arm, scen, CTRL, GAINS, params=params)
    np.savez(sys.argv[1], fd=out, q=np.asarray(res.q)[:R], steps=np.asarray(res.n_steps)[:R],
             diverged=np.asarray(res.diverged)[:R])
    print(n, len(qp.sharding.device_set), len(scen.reference.p.sharding.device_set),
          _batch_mesh(scen) is not None)
    if n > 1:  # a sharded batch is one program by default (no host chunks), and threads > 1 refused
        from redman_jax._sim import _chunks
        print(_chunks(None, 16 * n, shard_batch(jnp.zeros((16 * n, 3)))))
        try:
            simulate_batch(arm, scen, CTRL, GAINS, params=params, threads=2)
            print("ran")
        except ValueError as e:
            print("threads=2" in str(e) and "sharded over several" in str(e))
    """
)


def test_sharded_batch_equals_single_device(tmp_path):
    """The sweep's data-parallel path (pad to a multiple of the device count, shard the leading axis
    over a 1-D mesh) gives the same numbers on 2 (forced host) devices as on one: forward dynamics
    under ``jit``'s partitioning, and a batch of gradient-guided runs, which ``simulate_batch`` steps
    with ``shard_map`` (each device steps its own members; ``_sim._batch_mesh``), also with the
    default ``threads`` (a sharded batch is not split into host threads; ``threads=2`` is refused).
    The other controllers' one-program path is ``test_distributed``'s."""
    script = tmp_path / "shard.py"
    script.write_text(SHARD_SCRIPT)
    outs = {}
    for n in (1, 2):
        flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={n}".strip()
        env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
        path = tmp_path / f"out{n}.npz"
        proc = subprocess.run([sys.executable, str(script), str(path), str(Path(__file__).parent)],
                              env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        extra = ["1", "True"] if n == 2 else []  # one chunk by default, threads=2 refused
        assert proc.stdout.split() == [str(n), str(n), str(n), str(n == 2)] + extra
        outs[n] = dict(np.load(path))
    assert outs[1]["fd"].shape == (5, 7) and outs[1]["q"].shape == (3, 60, 7)
    assert not outs[1]["diverged"].any()
    np.testing.assert_allclose(outs[2]["fd"], outs[1]["fd"], rtol=1e-12, atol=1e-12)
    # each member takes the steps of the one-device batch, to rounding (programs for 3 and 2 rows)
    np.testing.assert_array_equal(outs[2]["steps"], outs[1]["steps"])
    np.testing.assert_array_equal(outs[2]["diverged"], outs[1]["diverged"])
    np.testing.assert_allclose(outs[2]["q"], outs[1]["q"], rtol=0, atol=1e-12)


def test_gain_overrides_from_a_tuned_gains_file(tmp_path):
    """`--gains` takes the `{controller: {gain: value}}` file `redman-jax tune` writes; the
    overrides land in the gains pytree as strongly typed arrays and bad names are refused."""
    import jax

    from redman_jax._controllers import CONTROLLERS
    from redman_jax._tuning import gains_to_dict, write_gains_json

    ctrl = CONTROLLERS["acceleration"]()
    tuned = pipe.make_gains(ctrl, {"kp": 444.5, "kd": 36.38})
    path = tmp_path / "tuned_gains.json"
    write_gains_json(path, {"acceleration": gains_to_dict(tuned, ("kp", "kd"))})
    overrides = json.loads(path.read_text())["acceleration"]
    gains = pipe.make_gains(ctrl, overrides)
    assert float(gains.kp) == 444.5 and float(gains.kd) == 36.38
    assert float(gains.kpr) == float(ctrl.default_gains().kpr)
    # same structure, dtypes and weak types as the defaults: one compilation serves both
    assert jax.tree.structure(gains) == jax.tree.structure(ctrl.default_gains())
    for a, b in zip(jax.tree.leaves(gains), jax.tree.leaves(ctrl.default_gains())):
        assert a.dtype == b.dtype and a.weak_type == b.weak_type
    with pytest.raises(ValueError, match="no field 'kq'"):
        pipe.make_gains(ctrl, {"kq": 1.0})
    cfg = SweepConfig(out=str(tmp_path), gains={"acceleration": overrides}, figures=False, progress=False)
    assert cfg.gains["acceleration"]["kp"] == 444.5


def test_compiled_programs_are_dropped_after_each_group(monkeypatch, tmp_path):
    """A worker that kept every compiled program ran out of memory mappings (vm.max_map_count)
    part-way through the full study. _run_group drops them after each group: each scenario build,
    and each (arm, controller) group of simulations, whose cases share one compilation."""
    import jax

    calls, cleared = [], []
    _fake_pipeline(monkeypatch, calls)
    real_clear = jax.clear_caches
    monkeypatch.setattr(jax, "clear_caches", lambda: (cleared.append(len(calls)), real_clear()))
    run_sweep(_config(tmp_path))
    # builds: welding, simple; then the groups (9, velocity): welding, simple and (9, gradient): simple
    assert [c for c in calls] == [("scen", "welding"), ("scen", "simple"), ("run", "welding", "velocity"),
                                  ("run", "simple", "velocity"), ("run", "simple", "gradient")]
    assert cleared == [1, 2, 4, 5]


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs Linux /proc")
def test_clear_caches_returns_memory_mappings():
    """The mechanism the sweep relies on: a compiled program's memory mappings go with clear_caches."""
    import gc

    import jax
    import jax.numpy as jnp

    def maps():
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)

    jax.clear_caches()
    gc.collect()
    base = maps()
    for k in range(20):  # 20 distinct programs
        jax.block_until_ready(jax.jit(lambda x, k=k: jnp.sin(x) * k + jnp.cumsum(x) ** 2)(jnp.ones(8 + k)))
    grown = maps()
    jax.clear_caches()
    gc.collect()
    assert grown - base >= 20  # each executable holds mappings of its own
    assert maps() - base < (grown - base) / 4


def test_worker_xla_flags_keep_what_the_user_set(monkeypatch):
    from redman_jax import _study

    extra = ("--xla_a=1", "--xla_b=")
    assert _study._with_flags("", extra) == "--xla_a=1 --xla_b="
    assert _study._with_flags("--xla_a=0 --other", extra) == "--xla_a=0 --other --xla_b="
    monkeypatch.setattr(_study, "_xla_accepts", lambda flags: True)
    monkeypatch.setenv("XLA_FLAGS", "--xla_b=x")
    with _study._worker_xla_flags(extra):
        assert os.environ["XLA_FLAGS"] == "--xla_b=x --xla_a=1"
    assert os.environ["XLA_FLAGS"] == "--xla_b=x"
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setattr(_study, "_xla_accepts", lambda flags: False)  # a jaxlib that lacks them
    with _study._worker_xla_flags(extra):
        assert "XLA_FLAGS" not in os.environ
    assert "XLA_FLAGS" not in os.environ


@pytest.mark.slow
def test_demo_writes_its_figures_and_a_strict_json_summary(tmp_path):
    """``redman-jax demo`` end to end (about 30 s on 2 cores): the figures, and a summary that
    strict JSON parsers read (a joint-space run has no LME time and no time to goal: null)."""
    from redman_jax._demo import run_demo

    summary = run_demo("7", "inspection", 1, "joint_space", tmp_path, animation=False)
    for name in ("scene.png", "errors.png", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0, name

    back = strict_json_loads((tmp_path / "summary.json").read_text())
    assert back == summary
    assert back["controller"] == "joint_space" and back["t_lme_per_sample"] is None
    assert back["n_samples"] > 0 and np.isfinite(back["mean_pos_error"])


def test_demo_draws_a_diverged_run_up_to_its_last_finite_sample(monkeypatch, tmp_path):
    """A run whose state turned inf after sample ``k`` (7-DOF simple PID does) stopped ``demo``
    with matplotlib's "Axis limits cannot be NaN or Inf" and no summary; it is drawn up to its last
    finite sample and every file is written. Fakes for the units (a real scene, no simulation)."""
    import jax

    from redman_jax import _demo
    from redman_jax._cases import make_scenario
    from redman_jax._study import arm_from_spec

    arm = arm_from_spec("7")
    scen = make_scenario("simple", 1, arm)
    N, n, k = scen.reference.p.shape[0], int(scen.reference.n_samples), 40
    assert n > k + 1
    diverged = lambda x: np.where((np.arange(N) >= k).reshape((N,) + (1,) * (x.ndim - 1)), np.inf, x)
    p = diverged(np.asarray(scen.reference.p))
    traces = {"p": p[None], "pos_err": diverged(np.full(N, 1e-3))[None],
              "ori_err": diverged(np.full(N, 1e-2))[None], "rot": np.asarray(scen.reference.rot)[None]}
    row = {"case": "simple", "seed": 1, "seed_used": 1, "controller": "pid", "success": False,
           "n_samples": n, "mean_pos_error": float("inf")}
    monkeypatch.setattr(pipe, "build_case", lambda *a, **kw: {
        "scenarios": jax.tree.map(lambda x: np.asarray(x)[None], scen), "ik": None})
    monkeypatch.setattr(pipe, "run_controller", lambda *a, **kw: {"rows": [row], "traces": traces})
    q = diverged(np.tile(np.asarray(arm.q0), (N, 1)))
    monkeypatch.setattr(_demo, "_joint_path", lambda *a: q)
    summary = _demo.run_demo("7", "simple", 1, "pid", tmp_path, animation=True)
    for name in ("scene.png", "errors.png", "animation.gif", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert strict_json_loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["mean_pos_error"] is None  # inf: not a JSON number


@pytest.mark.slow
def test_the_table_does_not_depend_on_jobs_or_on_a_resume(tmp_path):
    """Real units (7-DOF simple case, one seed, joint space and velocity OSC; about 40 s per sweep
    on 2 cores): ``--jobs 1`` (units in the command's own process), ``--jobs 2`` (in workers),
    and a ``--jobs 2`` sweep resumed with one group left give the same table, value for value.
    Before, the last phase's single group ran in the main process under XLA's default flags, and
    a process with both cores split its batches in two: 10 and 17 values differed to rounding."""
    import csv
    import shutil

    def sweep(out, jobs):
        cmd = [sys.executable, "-m", "redman_jax", "sweep", "--arms", "7", "--cases", "simple", "--seeds", "1",
               "--controllers", "joint_space,velocity", "--no-figures", "--quiet", "--jobs", str(jobs),
               "--out", str(out)]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stderr[-3000:]
        with open(out / "runs.csv") as f:
            return [{k: v for k, v in r.items() if not k.startswith("t_") and k != "sim_wall_s"}
                    for r in csv.DictReader(f)]

    one, two = sweep(tmp_path / "one", 1), sweep(tmp_path / "two", 2)
    assert len(one) == 2 and one == two
    units = tmp_path / "two" / "units"
    (victim,) = [p for p in units.iterdir() if p.name.startswith("run_7dof_simple_velocity")]
    victim.unlink()  # as if killed before its last unit: one group left
    shutil.rmtree(tmp_path / "two" / "traces")
    assert sweep(tmp_path / "two", 2) == one


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="needs core affinity (Linux)")
def test_a_sweep_process_is_prepared_as_a_worker_before_jax_starts():
    """``prepare_sweep_process`` (the command line and the sweep scripts call it first): the
    workers' XLA flags, and for ``--jobs 1`` one core, so that the units this process computes
    round as a worker's (and the garbage collector's thresholds, :func:`tune_gc`); where JAX's
    backend already runs it changes neither flags nor cores."""
    from redman_jax._study import _with_flags, _worker_flags, _xla_accepts, prepare_sweep_process

    WORKER_XLA_FLAGS = _worker_flags()

    code = ("import os, sys; from redman_jax import _study; from redman_jax._study import prepare_sweep_process; "
            "prepare_sweep_process(sys.argv[1]); import jax.numpy as j; j.zeros(1).block_until_ready(); "
            "print(repr(_study._FLAGS_BEFORE_ADOPTION)); import gc; print(gc.get_threshold() == _study.GC_THRESHOLDS); "
            "print(len(os.sched_getaffinity(0))); print(os.environ.get('XLA_FLAGS', ''))")
    env = dict(os.environ)
    cores = len(os.sched_getaffinity(0))
    for jobs, want in (("1", 1), ("2", cores)):
        done = subprocess.run([sys.executable, "-c", code, jobs], capture_output=True, text=True, env=env,
                              timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        kept, gc_tuned, n, flags = done.stdout.splitlines()[-4:]
        assert int(n) == want and gc_tuned == "True"
        if _xla_accepts(_with_flags(env.get("XLA_FLAGS", ""), WORKER_XLA_FLAGS)):
            assert set(_with_flags(env.get("XLA_FLAGS", ""), WORKER_XLA_FLAGS).split()) <= set(flags.split())
        # the flags before, from which the report's process starts (render_report)
        assert kept == (repr(env.get("XLA_FLAGS", "")) if flags != env.get("XLA_FLAGS", "") else "None")
    import jax.numpy as jnp

    jnp.zeros(1).block_until_ready()  # this process's backend runs: nothing changes
    before = (os.sched_getaffinity(0), os.environ.get("XLA_FLAGS"))
    prepare_sweep_process("1")
    assert (os.sched_getaffinity(0), os.environ.get("XLA_FLAGS")) == before


@pytest.mark.parametrize("script, args, message", [
    ("thesis_study.py", ["--seeds", "x"], "--seeds: cannot parse 'x'"),
    ("ablation_jac_scaling.py", ["--cases", "kitchen"], "--cases: unknown value(s) ['kitchen']"),
    ("ablation_obstacle_form.py", ["--cases", "welding"], "--cases: unknown value(s) ['welding']")])
def test_sweep_scripts_report_bad_options_in_one_line(script, args, message, tmp_path):
    """As ``redman-jax sweep``: an ``error:`` line and exit status 2 (they printed a traceback)."""
    path = Path(__file__).resolve().parents[1] / "sweeps" / script
    done = subprocess.run([sys.executable, str(path), *args, "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"{script}: error: {message}" in done.stderr and "Traceback" not in done.stderr


def _last_word_with_flags(code: str, flags) -> str:
    """The last word ``python -c code`` prints in a fresh CPU process whose ``XLA_FLAGS`` are
    ``flags`` alone, as a worker starts (a failed process fails the test with its stderr)."""
    from redman_jax._study import _with_flags

    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=_with_flags("", flags))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.split()[-1]


def test_the_workers_loop_flags_hoist_a_simulation_sized_loop():
    """``LOOP_XLA_FLAGS`` take effect in this jaxlib: a while loop whose body (a dot among
    element-wise work) reads more than XLA's default 1 kB threshold is compiled as one hoisted call
    (``xla_cpu_small_call``) with the workers' flags and not with their emitter flags alone (a
    jaxlib that drops or renames the option fails here, not silently in the study's speed). Each in
    a fresh process, as a worker starts."""
    from redman_jax._study import EMITTER_XLA_FLAGS, WORKER_XLA_FLAGS, _with_flags, _xla_accepts

    if not _xla_accepts(_with_flags("", WORKER_XLA_FLAGS)):
        pytest.skip("this jaxlib does not accept the workers' flags (the workers then start without them)")
    code = ("import jax, jax.numpy as jnp\n"
            "f = jax.jit(lambda x: jax.lax.while_loop(lambda c: c[1] < 100, "
            "lambda c: (jnp.sin(c[0]) @ c[0] * 0.5, c[1] + 1), (x, 0))[0])\n"
            "print('xla_cpu_small_call' in f.lower(jnp.ones((20, 20))).compile().as_text())\n")
    seen = [_last_word_with_flags(code, extra) for extra in (EMITTER_XLA_FLAGS, WORKER_XLA_FLAGS)]
    assert seen == ["False", "True"]


@pytest.mark.parametrize("option", ["-forget-scev-loop-unroll=true", "-inline-threshold=-20000"])
def test_the_workers_llvm_options_leave_the_results_alone(option):
    """Each LLVM option in ``LOOP_XLA_FLAGS`` reaches LLVM (an unknown LLVM option aborts the
    process) and leaves the arithmetic alone: a hoisted loop of small fused loops and dots (9 x 9
    and 9 x 3 matrix-vector products from several places, XLA's kernels that the inline threshold
    keeps as calls; element-wise work; the shapes of a step) returns the same bits with and
    without it, each in a fresh process as a worker starts. ``-forget-scev-loop-unroll`` changes
    what LLVM caches, ``-inline-threshold`` which calls it copies into the loop."""
    from redman_jax._study import LOOP_XLA_FLAGS, WORKER_XLA_FLAGS, _with_flags, _xla_accepts

    assert any(option in f for f in LOOP_XLA_FLAGS)
    if not _xla_accepts(_with_flags("", WORKER_XLA_FLAGS)):
        pytest.skip("this jaxlib does not accept the workers' flags (the workers then start without them)")
    code = ("import jax, jax.numpy as jnp, numpy as np\n"
            "jax.config.update('jax_enable_x64', True)\n"
            "r = np.random.default_rng(0)\n"
            "A, B = (jnp.asarray(r.normal(size=s) / 3) for s in ((9, 9), (9, 3)))\n"
            "def body(c):\n"
            "    x, v, k = c\n"
            "    v = jnp.tanh(A @ x) - 0.1 * jnp.sin(x[::-1]) * v + jnp.cos(A.T @ v) / (1 + x * x)\n"
            "    v = v + B @ jnp.tanh(B.T @ v) - 0.01 * (A @ (B @ (B.T @ x)))\n"
            "    return x + 0.01 * v, v, k + 1\n"
            "f = jax.jit(lambda x: jax.lax.while_loop(lambda c: c[2] < 500, body, (x, x, 0))[:2])\n"
            "x, v = f(jnp.linspace(-1, 1, 9))\n"
            "print(np.asarray(x).tobytes().hex() + np.asarray(v).tobytes().hex())\n")
    without = tuple(f.replace("," + option, "") for f in WORKER_XLA_FLAGS)
    assert option not in _with_flags("", without)
    seen = [_last_word_with_flags(code, flags) for flags in (without, WORKER_XLA_FLAGS)]
    assert seen[0] == seen[1]


def test_the_loop_flags_are_for_a_cpu_backend_only(monkeypatch):
    """The workers' loop flags (LLVM's level is an accelerator backend's too) only where JAX will
    run on the CPU: ``JAX_PLATFORMS``' first entry if set, else no accelerator plugin installed."""
    import importlib.util

    from redman_jax import _study

    monkeypatch.setenv("JAX_PLATFORMS", "cuda,cpu")
    assert _study._worker_flags() == _study.EMITTER_XLA_FLAGS
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert _study._worker_flags() == _study.WORKER_XLA_FLAGS
    monkeypatch.delenv("JAX_PLATFORMS")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name in _study._ACCELERATOR_PLUGINS
                        else real(name, *a))
    assert _study._cpu_backend_expected()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: object() if name == "jax_cuda12_plugin"
                        else None)
    assert not _study._cpu_backend_expected()
    monkeypatch.setattr(_study, "_xla_accepts", lambda flags: True)
    monkeypatch.setenv("XLA_FLAGS", "")
    with _study._worker_xla_flags():  # what spawned workers inherit
        assert os.environ["XLA_FLAGS"] == _study._with_flags("", _study.EMITTER_XLA_FLAGS)
