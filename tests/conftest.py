"""Test configuration: float64 (as the package enables), and a small helper set.

Each test module uses its own small problem sizes; heavy runs live in benchmarks/.
"""

import os

os.environ.setdefault("REDMAN_JAX_X64", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import redman_jax  # noqa: E402,F401  (enables x64)


def _pin_xdist_worker():
    """Under pytest-xdist (``make test`` runs ``-n 2``) each worker process runs on a core of its
    own, as the study's workers do: two unpinned XLA processes contend for both cores
    (:func:`redman_jax._study._worker_start`)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if not worker.startswith("gw") or count < 2:
        return
    from redman_jax._study import _pin_threads, _worker_cores

    cores = _worker_cores(count)
    if cores:
        core = cores[int(worker[2:]) % len(cores)]
        if _pin_threads(core):
            os.environ["REDMAN_TEST_PINNED_CORE"] = str(core)  # for the test that checks it


_pin_xdist_worker()


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
