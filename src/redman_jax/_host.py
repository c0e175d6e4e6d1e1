"""Moving concrete arrays between the host and the device without compiling.

Outside ``jit`` every ``jax.numpy`` operation is dispatched as a small XLA program of its own,
compiled once per shape and dtype: ``x[i]``, ``jnp.concatenate`` and, since jax 0.10, even
``jnp.asarray`` of a NumPy array (the ``stage`` primitive). Each such compilation costs some 15 ms;
the default study's pipeline (slicing stored scenarios, splitting a batch over threads, padding
cases) made 3,694 of them, about 50 s of its workers' time. These helpers do the same data
movement in NumPy and place the result with :func:`jax.device_put`, which compiles nothing.

They are for concrete arrays on one device of this host. Under a trace, for an array sharded over
several devices or one that is weakly typed (its promotion rules would change), they fall back on
the ``jax.numpy`` operation, so their results are the same either way.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["put", "to_device", "host_array", "take", "concatenate"]


def put(x):
    """``jnp.asarray(x)`` for a concrete ``x``, without a compilation: a ``jax.Array`` is returned
    as it is, a Python scalar stays weakly typed, anything else goes through ``np.asarray``."""
    if isinstance(x, jax.Array):
        return x
    if isinstance(x, (bool, int, float, complex)):
        return jax.device_put(x)
    return jax.device_put(np.asarray(x))


def to_device(tree):
    """:func:`put` on every leaf of ``tree``."""
    return jax.tree.map(put, tree)


def host_array(x):
    """NumPy view of ``x`` if it is a concrete, strongly typed array on one device of this process
    (or already NumPy), else None. An array sharded over several devices keeps its layout through
    the ``jax.numpy`` operation instead."""
    if isinstance(x, np.ndarray):
        return x
    if (isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and not x.weak_type
            and x.is_fully_addressable and len(x.sharding.device_set) == 1):
        return np.asarray(x)
    return None


def take(x, idx):
    """``x[idx]`` (an integer, a slice or an index array on the leading axis)."""
    h = host_array(x)
    return x[idx] if h is None else jax.device_put(h[idx])


def concatenate(xs, axis: int = 0):
    """``jnp.concatenate(xs, axis)``."""
    hs = [host_array(x) for x in xs]
    if any(h is None for h in hs):
        return jnp.concatenate(xs, axis=axis)
    return jax.device_put(np.concatenate(hs, axis=axis))
