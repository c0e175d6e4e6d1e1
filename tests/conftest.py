"""Test configuration: float64 (as the package enables), and a small helper set.

Each test module uses its own small problem sizes; heavy runs live in benchmarks/.
"""

import contextlib
import os

os.environ.setdefault("REDMAN_JAX_X64", "1")


def _default_xla_flag(flag: str) -> None:
    """Append ``--name=value`` to ``XLA_FLAGS`` unless the user already set ``name``."""
    name = flag.lstrip("-").split("=")[0]
    if name not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()


# The suite's time is mostly XLA compilation of programs it runs only briefly, and LLVM's
# optimisation passes are much of that. At backend level 0 four compile-bound tests took 84/77 s
# against 115/101 s at the default (two interleaved rounds, 2026-12-03); the whole `make test` took
# 887 s against 1,307 s an hour earlier (sum of test times 1,598 against 2,452 s). The HLO-level
# passes are the same; the machine code differs (instruction selection, fused multiply-adds), so
# results agree with the default level's to rounding only (9-DOF forward dynamics and its gradient
# at 64 random states: within 8e-13 of their largest entry), as between any two machines. The
# assertions are unchanged. Set before jax's backend starts, and inherited by the subprocesses the
# tests start (examples, study workers). A level the user chose is kept.
_default_xla_flag("--xla_backend_optimization_level=0")
# The same holds for XLA's CPU fusion emitters: the older (LLVM IR) loop emitters compile much faster
# than the default (MLIR) ones and run slower, which suits programs that run briefly. Measured
# (2026-12-03), six compile-bound tests (test_controllers' and test_sim's gradient tests, the guided
# batch/NaN test, the slot-layout test), the two settings side by side on one core each and then on
# swapped cores: 529 / 517 s default, 335 / 310 s with the older emitters; one reverse-mode simulator
# program compiles in 24 s against 37 s. Results agree to rounding, but the older emitters do not
# keep the bit identity of differently shaped programs (padded against unpadded obstacle sets: 1 ulp
# in 3 of the suite's assertions), so the tests that assert it run in a subprocess with the default
# emitters (test_nullspace's ``_default_emitters_only``). ``REDMAN_TEST_DEFAULT_EMITTERS=1`` keeps
# the default emitters.
LEGACY_EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters=false"
if os.environ.get("REDMAN_TEST_DEFAULT_EMITTERS") != "1":
    _default_xla_flag(LEGACY_EMITTERS_FLAG)
DEFAULT_EMITTERS = LEGACY_EMITTERS_FLAG not in os.environ.get("XLA_FLAGS", "").split()


def run_under_default_emitters(test_file, names, passed: int) -> None:
    """Run the tests ``names`` of ``test_file`` in a subprocess with XLA's default emitters (the
    bit identities of separately compiled programs that the older emitters do not keep) and
    assert that ``passed`` of them pass."""
    import subprocess
    import sys

    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f != LEGACY_EMITTERS_FLAG)
    env = dict(os.environ, XLA_FLAGS=flags, REDMAN_TEST_DEFAULT_EMITTERS="1")
    env.pop("PYTEST_XDIST_WORKER", None)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
         str(test_file), "-k", " or ".join(names)],
        env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert f"{passed} passed" in proc.stdout, proc.stdout[-2000:]


def _pin_xdist_worker():
    """Under pytest-xdist (``make test`` runs ``-n 2``) each worker process runs on a core of its
    own, as the study's workers do: two unpinned XLA processes contend for both cores
    (:func:`redman_jax._study._worker_start`). Called before jax's backend starts (at the first JAX
    computation; ``import redman_jax`` starts none since it stopped building arrays at import), so
    that XLA's CPU thread pool, sized then by the cores the process may run on, is one thread wide;
    pinned later, its two threads would share the one core. The logic of
    :func:`redman_jax._study._worker_cores` and ``_pin_threads``, inline, so that nothing runs before
    it."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if not worker.startswith("gw") or count < 2:
        return
    try:
        cores = sorted(os.sched_getaffinity(0))
        tids = os.listdir("/proc/self/task")
    except (AttributeError, OSError):
        return
    if len(cores) < count:
        return
    core = cores[:count][int(worker[2:]) % count]
    try:
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):  # the thread ended meanwhile
                os.sched_setaffinity(int(tid), {core})
    except OSError:
        return
    os.environ["REDMAN_TEST_PINNED_CORE"] = str(core)  # for the test that checks it


_pin_xdist_worker()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import redman_jax  # noqa: E402,F401  (enables x64)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(params=[7, 8, 9])
def thesis_arm_any(request):
    return redman_jax.thesis_arm(request.param)


def fd_jacobian(f, x, eps=1e-6, order=2):
    """Central finite-difference Jacobian of f: R^n -> R^m (NumPy, float64).

    ``order=2``: two-point stencil, truncation O(eps^2); ``order=4``: five-point stencil, O(eps^4),
    for functions whose rounding noise calls for a larger ``eps``."""
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x))
    out = np.zeros(f0.shape + x.shape)
    for i in range(x.size):
        e = np.zeros_like(x)
        e.flat[i] = eps
        d1 = np.asarray(f(x + e)) - np.asarray(f(x - e))
        if order == 2:
            out[..., i] = d1 / (2 * eps)
        else:
            d2 = np.asarray(f(x + 2 * e)) - np.asarray(f(x - 2 * e))
            out[..., i] = (8 * d1 - d2) / (12 * eps)
    return out



@contextlib.contextmanager
def backend_compiles():
    """The XLA compilations that finish inside the block: a list of their durations [s], filled as
    they happen (``jax.monitoring``; the listener is removed on exit)."""
    from jax import monitoring

    seen = []

    def on_duration(name, secs, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            seen.append(secs)

    monitoring.register_event_duration_secs_listener(on_duration)
    try:
        yield seen
    finally:
        monitoring.unregister_event_duration_listener(on_duration)

# Files in decreasing order of their run time under ``make test`` (seconds summed over the file's tests,
# measured 2026-12-07 with ``--durations=0``, the suite's flags above): test_sim 219, test_controllers
# 151, test_sim_guided 147, test_distributed 119, test_study 111, test_examples 84, test_nullspace 67,
# test_tuning 58, test_guidance 46, test_ik 45, test_dynamics 42, test_fields 29, test_qp 27,
# test_numpy_baseline 26, test_planning 24, test_report 19; the rest take under 15 s each.
_LONGEST_FIRST = ("test_sim.py", "test_controllers.py", "test_sim_guided.py", "test_distributed.py",
                  "test_study.py", "test_examples.py", "test_nullspace.py", "test_tuning.py",
                  "test_guidance.py", "test_ik.py", "test_dynamics.py", "test_fields.py", "test_qp.py",
                  "test_numpy_baseline.py", "test_planning.py", "test_report.py")


def pytest_collection_modifyitems(session, config, items):
    """Collect the longest test files first. ``make test`` runs ``-n 2 --dist loadfile
    --no-loadscope-reorder``: xdist hands out whole files in collection order, each worker taking the
    next file when it is done, so starting with the longest ones keeps the two workers' totals even.
    Without ``--no-loadscope-reorder`` (xdist 3.5 and later) this order is ignored and files go out
    by decreasing number of tests: test_sim_guided, 7 tests and about 170 s, ran near the end (a
    ``make test`` on 2026-12-03 took 900 s, its last 20 tests 3.5 min). Order within a file is
    unchanged."""
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda it: rank.get(it.path.name, len(rank)))  # stable: files keep their order


def pytest_collection_finish(session):
    """Python's cyclic garbage collector, tuned for a process that mostly traces JAX programs: the
    objects alive after collection (jax, numpy, the test modules) moved out of its reach
    (``gc.freeze``), and a young-generation collection every 100,000 net allocations instead of 700.
    Tracing a reverse-mode simulation builds millions of short-lived objects, and a ``perf`` profile
    of one compile-bound test (test_sim's finite-difference gradient test) found 7.5 % of its time in
    the collector (``gc_collect_main``, ``visit_decref``, ``visit_reachable``). Measured (2026-12-07,
    test_controllers.py and test_tuning.py without the slow tests, one core each, the two settings
    side by side and then on swapped cores): 185.8 / 196.0 s with the default thresholds, 171.0 /
    179.7 s with these. Cycles are still collected, later; the computations are unchanged. The
    sweep's workers do the same (:func:`redman_jax._study.tune_gc`)."""
    from redman_jax._study import tune_gc

    tune_gc()
