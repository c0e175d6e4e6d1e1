"""Deterministic stand-ins for the two pipeline units (imported by test_study and by the worker
processes of the parallel sweep test)."""

import zlib

import numpy as np


def build_case(arm, case, seeds, ts=0.01, max_retries=20):
    return {"case": case, "seeds": list(seeds)}


def run_controller(arm, scen, ctrl, gains=None, **kw):
    import gc
    import os

    folder = os.environ.get("REDMAN_TEST_AFFINITY_DIR")
    if folder:  # the collector's thresholds where the units run
        with open(os.path.join(folder, f"{os.getpid()}.gc"), "w") as f:
            f.write(" ".join(map(str, gc.get_threshold())))
    rng = np.random.default_rng(zlib.crc32(f"{scen['case']}-{ctrl}".encode()))
    rows = [{"case": scen["case"], "seed": s, "seed_used": s, "controller": ctrl, "success": True,
             "mean_pos_error": float(rng.random()), "n_samples": 10} for s in scen["seeds"]]
    return {"rows": rows, "traces": {"seed": np.asarray(scen["seeds"]), "pos_err": rng.random((len(rows), 4))}}


def install():
    """Worker initializer: replace the real units in this process (and, if the test asks for it,
    record the cores this worker may run on)."""
    import os

    import redman_jax._pipeline as pipe

    folder = os.environ.get("REDMAN_TEST_AFFINITY_DIR")
    if folder and hasattr(os, "sched_getaffinity"):  # one line per thread of this process
        from redman_jax._study import _thread_affinities

        lines = [",".join(str(c) for c in sorted(cores)) for cores in _thread_affinities()]
        with open(os.path.join(folder, f"{os.getpid()}.txt"), "w") as f:
            f.write("\n".join(lines))
        # the width of XLA's CPU thread pool (threads named "tf_XLAEigen"), sized when jax started
        import jax.numpy as jnp

        jnp.ones(3).sum().block_until_ready()
        names = []
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/comm") as f:
                    names.append(f.read().strip())
            except OSError:
                continue
        with open(os.path.join(folder, f"{os.getpid()}.pool"), "w") as f:
            f.write(str(sum(n.endswith("XLAEigen") for n in names)))
        with open(os.path.join(folder, f"{os.getpid()}.flags"), "w") as f:
            f.write(os.environ.get("XLA_FLAGS", ""))

    pipe.build_case = build_case
    pipe.run_controller = run_controller


def report_probe(out):
    """Stand-in for ``make_report`` (``_study.render_report``): records the process it runs in and
    its ``XLA_FLAGS``, and fails where the folder says so."""
    import os
    from pathlib import Path

    out = Path(out)
    if (out / "fail").exists():
        raise RuntimeError("the report failed")
    (out / "probe.txt").write_text(f"{os.getpid()}\n{os.environ.get('XLA_FLAGS', '')}")


def install_slow():
    """Worker initializer: units that record this worker's pid in ``$REDMAN_TEST_PID_DIR`` and
    then hang (the test kills the sweep's main process meanwhile)."""
    import os
    import time

    import redman_jax._pipeline as pipe

    def hang(*args, **kwargs):
        with open(os.path.join(os.environ["REDMAN_TEST_PID_DIR"], f"{os.getpid()}.pid"), "w") as f:
            f.write(str(os.getppid()))
        time.sleep(120)
        raise RuntimeError("not killed")

    pipe.build_case = hang
    pipe.run_controller = hang
