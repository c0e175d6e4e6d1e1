"""Several processes in one sweep (``--distributed``, ``jax.distributed``): two CPU processes on this
machine, talking through gloo, against the same sweep in one process."""

import csv
import os
import shutil
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from redman_jax._cli import main
from redman_jax._store import UnitStore

SWEEP = ["sweep", "--arms", "7", "--cases", "simple", "--seeds", "1-3", "--controllers",
         "joint_space,gradient", "--no-figures", "--quiet"]
TIMING = {"t_controller_per_sample", "t_ik_per_sample", "t_planning_per_sample", "t_lme_per_sample",
          "sim_wall_s"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env():
    # one CPU device per process; a process pinned to one core by the suite keeps it
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split()
                     if "xla_force_host_platform_device_count" not in f)
    return dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")


def _sweep(args, out, **kw):
    return subprocess.Popen([sys.executable, "-m", "redman_jax", *SWEEP, *args, "--out", str(out)],
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _same_runs(got, ref):
    """The same runs: identical integers, flags and names; floats to 1e-9 relative (the two
    processes' programs are compiled for 2 members each, the single one for 3, so they round
    differently; the adaptive steps over 6 s then move the metrics by about 1e-11)."""
    assert len(got) == len(ref) == 6
    for a, b in zip(got, ref):
        assert a.keys() == b.keys()
        for k in a:
            if k in TIMING:
                continue
            what = (k, a["controller"], a["seed"], a[k], b[k])
            try:
                exact = b[k].lstrip("-").isdigit()  # integers: seeds, samples, steps, causes
                expected = float(b[k])
            except ValueError:  # names and flags
                exact = True
            if exact:
                assert a[k] == b[k], what
            else:
                np.testing.assert_allclose(float(a[k]), expected, rtol=1e-9, atol=1e-15, err_msg=str(what))


def test_two_processes_give_the_single_process_table(tmp_path):
    """A sweep run by two processes (one CPU device each) with --distributed: the simulations' batches
    (3 seeds, padded to 4) are sharded over both processes' devices and gathered back, the
    gradient-guided batch runs as one program (no host-driven straggler compaction across
    processes); process 0 writes the table, which is the one-process table; process 1 writes no
    results. The scenario build comes from process 0's folder (copied there from the one-process
    run: the resume path), handed to process 1 by broadcast."""
    ref = tmp_path / "ref"
    one = _sweep(["--jobs", "1"], ref)
    out, err = one.communicate(timeout=600)
    assert one.returncode == 0, err[-3000:]
    ref_rows = _rows(ref / "runs.csv")

    leader, other = tmp_path / "p0", tmp_path / "p1"
    (leader / "units").mkdir(parents=True)
    for f in (ref / "units").glob("scen_*"):
        shutil.copy(f, leader / "units" / f.name)
    port = _free_port()
    procs = [_sweep(["--distributed", "--coordinator", f"localhost:{port}", "--num-processes", "2",
                     "--process-id", str(i)], d) for i, d in enumerate((leader, other))]
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]

    _same_runs(_rows(leader / "runs.csv"), ref_rows)
    for ctrl in ("joint_space", "gradient"):
        timings = UnitStore(leader).load(f"run_7dof_simple_{ctrl}")["timings"]
        assert (timings["devices"], timings["processes"]) == (2, 2)  # sharded over both processes
        assert UnitStore(ref).load(f"run_7dof_simple_{ctrl}")["timings"]["processes"] == 1
    assert sorted(p.name for p in (leader / "units").iterdir()) == sorted(p.name for p in (ref / "units").iterdir())
    assert not [p for p in other.rglob("*") if p.is_file()]  # process 1 wrote nothing
    assert "distributed" not in (leader / "config.json").read_text()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["sweep", "--coordinator", "localhost:1234"], "--coordinator: only with --distributed"),
        (["sweep", "--process-id", "0"], "--process-id: only with --distributed"),
        (["sweep", "--distributed", "--jobs", "2"], "--jobs: a --distributed sweep runs one process"),
        (["sweep", "--distributed", "--num-processes", "2"], "give both or neither"),
        (["sweep", "--distributed", "--num-processes", "2", "--process-id", "2"], "process_id: expected 0 <="),
        (["sweep", "--distributed", "--num-processes", "two", "--process-id", "0"], "num_processes: expected an integer"),
        (["sweep", "--distributed", "--coordinator", "localhost", "--num-processes", "1", "--process-id", "0"],
         "coordinator: expected HOST:PORT"),
    ],
)
def test_distributed_options_are_checked_before_joining(argv, message, capsys, tmp_path):
    code = main([*argv, "--out", str(tmp_path / "o")])
    assert code == 2
    assert message in capsys.readouterr().err


def test_joining_after_jax_started_is_a_clear_error():
    script = textwrap.dedent(
        """
        import jax.numpy as jnp
        from redman_jax._distributed import initialize
        jnp.zeros(1).block_until_ready()
        try:
            initialize("localhost:1", 2, 0)
        except ValueError as e:
            print(e)
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], env=_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "already started its backend" in proc.stdout

