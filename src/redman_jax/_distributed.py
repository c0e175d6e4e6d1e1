"""Several processes (nodes) in one sweep, through ``jax.distributed``.

Every process runs the same command (``redman-jax sweep --distributed ...``, one process per node,
which uses all of its node's devices). JAX then sees the devices of all processes as one list:
each simulation's batch is sharded over all of them (:func:`~redman_jax._pipeline.shard_batch`)
and gathered back to every process (:func:`to_host`). The sweep keeps the processes in step:
process 0 decides which units are missing and hands every process the scenarios it has stored
(:func:`broadcast_object`); it alone writes the results folder. A scenario build runs in every
process (it is not sharded) and process 0's is the one kept, so nodes that round differently
still simulate the same scenes.

On CPU the processes exchange data with gloo (``jax_cpu_collectives_implementation``), which is
how the tests run two processes on one machine.
"""

from __future__ import annotations

import os
import pickle

import numpy as np

__all__ = ["initialize", "is_multiprocess", "is_leader", "broadcast_object", "to_host", "barrier"]


def _int_or_env(value, env: str, name: str):
    if value is None:
        value = os.environ.get(env)
        if value is None:
            return None
        name = f"{name} (from ${env})"
    try:
        out = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected an integer, got {value!r}") from None
    return out


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> None:
    """Join a multi-process JAX run (``jax.distributed.initialize``); call it before any other JAX
    work in the process (``import redman_jax`` starts none).

    ``coordinator`` (``HOST:PORT`` of process 0; else ``$JAX_COORDINATOR_ADDRESS``),
    ``num_processes`` (else ``$JAX_NUM_PROCESSES``) and ``process_id`` (else ``$JAX_PROCESS_ID``);
    all three None on a cluster JAX detects by itself (SLURM, Open MPI, Kubernetes, TPU pods).

    **Raises** ``ValueError`` naming the option for a malformed or inconsistent value, or when JAX
    has already started its backend in this process.
    """
    import jax
    from jax._src import xla_bridge

    n = _int_or_env(num_processes, "JAX_NUM_PROCESSES", "num_processes")
    i = _int_or_env(process_id, "JAX_PROCESS_ID", "process_id")
    if n is not None and n < 1:
        raise ValueError(f"num_processes: expected a positive integer, got {n}")
    if i is not None and (i < 0 or (n is not None and i >= n)):
        raise ValueError(f"process_id: expected 0 <= process_id < num_processes ({n}), got {i}")
    if (n is None) != (i is None):
        raise ValueError("num_processes and process_id: give both or neither (neither: detected "
                         "from the cluster's environment)")
    if coordinator is not None and (":" not in coordinator or not coordinator.rsplit(":", 1)[1].isdigit()):
        raise ValueError(f"coordinator: expected HOST:PORT, got {coordinator!r}")
    if xla_bridge.backends_are_initialized():
        raise ValueError("distributed: JAX has already started its backend in this process; join the "
                         "multi-process run before any JAX computation")
    # CPU devices of several processes talk through gloo (no effect on GPU and TPU backends)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=n, process_id=i)


def is_multiprocess() -> bool:
    import jax

    return jax.process_count() > 1


def is_leader() -> bool:
    """Process 0 (the only one in a single-process run): the one that writes results."""
    import jax

    return jax.process_index() == 0


def broadcast_object(obj):
    """Process 0's ``obj`` (any picklable object) in every process; ``obj`` is ignored elsewhere.
    A single process gets ``obj`` back unchanged."""
    if not is_multiprocess():
        return obj
    from jax.experimental import multihost_utils as mu

    data = np.frombuffer(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL), np.uint8) if is_leader() \
        else np.zeros(0, np.uint8)
    size = int(mu.broadcast_one_to_all(np.int32(data.size)))
    buf = data if is_leader() else np.zeros(size, np.uint8)
    return pickle.loads(np.asarray(mu.broadcast_one_to_all(buf)).tobytes())


def to_host(tree):
    """NumPy copies of a pytree's arrays; arrays sharded over several processes are gathered whole
    into every process (a collective: every process must call it)."""
    import jax

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils as mu

            return np.asarray(mu.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree.map(one, tree)


def barrier(name: str) -> None:
    """Wait until every process reaches ``name`` (nothing in a single process)."""
    if is_multiprocess():
        from jax.experimental import multihost_utils as mu

        mu.sync_global_devices(name)
