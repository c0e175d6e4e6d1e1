"""_host: host-side data movement gives what the jax.numpy operation gives, and compiles nothing."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import backend_compiles

import redman_jax  # noqa: F401  (float64)
from redman_jax import _host


def _same(a, b):
    assert isinstance(a, jax.Array)
    assert a.shape == b.shape and a.dtype == b.dtype and a.weak_type == b.weak_type
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# shapes no other test uses, so that the jax.numpy references below would compile
_SHAPES = [(13, 7, 3), (11, 5), (17,)]


@pytest.mark.parametrize("shape", _SHAPES)
def test_put_take_concatenate_equal_jax_numpy(shape):
    rng = np.random.default_rng(0)
    x = rng.normal(size=shape)
    xj = jnp.asarray(x)
    idx = np.array([3, 0, 3, 1])
    cases = [
        (lambda: _host.put(x), lambda: jnp.asarray(x)),
        (lambda: _host.put(x.astype(np.float32)), lambda: jnp.asarray(x.astype(np.float32))),
        (lambda: _host.put(x > 0), lambda: jnp.asarray(x > 0)),
        (lambda: _host.put(2.5), lambda: jnp.asarray(2.5)),  # weakly typed, both
        (lambda: _host.put(np.float64(2.5)), lambda: jnp.asarray(np.float64(2.5))),
        (lambda: _host.take(xj, idx), lambda: xj[idx]),
        (lambda: _host.take(x, 2), lambda: xj[2]),
        (lambda: _host.take(xj, slice(1, 4)), lambda: xj[1:4]),
        (lambda: _host.concatenate([xj, x[:2]]), lambda: jnp.concatenate([xj, x[:2]])),
    ]
    for ours, ref in cases:
        _same(ours(), ref())
    assert _host.put(xj) is xj


def test_no_compilation_for_new_shapes():
    x = np.arange(2 * 19 * 3, dtype=np.float64).reshape(2, 19, 3)
    with backend_compiles() as compiles:
        y = _host.put(x)
        _host.take(y, np.array([1, 0]))
        _host.take(y, 1)
        _host.concatenate([y, y], axis=1)
        _host.to_device({"a": x[0], "b": [x[1], 3.0]})
    assert compiles == []
    with backend_compiles() as compiles:  # the jax.numpy equivalent does compile (jax >= 0.10)
        jnp.concatenate([y, y], axis=1)
    assert len(compiles) >= 1


def test_traced_and_weak_inputs_fall_back_on_jax_numpy():
    x = jnp.arange(12.0).reshape(4, 3)

    @jax.jit
    def f(x):
        return _host.take(x, jnp.array([2, 0])) + _host.concatenate([x, x])[:2]

    np.testing.assert_array_equal(np.asarray(f(x)), np.asarray(x[jnp.array([2, 0])] + x[:2]))
    weak = jnp.broadcast_to(jnp.asarray(2.0), (3, 2))  # weakly typed: jax.numpy keeps its rules
    assert weak.weak_type and _host.host_array(weak) is None
    _same(_host.take(weak, 1), weak[1])
    _same(_host.concatenate([weak, weak]), jnp.concatenate([weak, weak]))


def test_an_array_sharded_over_devices_keeps_the_jax_numpy_path():
    """Two CPU devices (a subprocess): a batch sharded over both is not gathered to one device."""
    script = textwrap.dedent(
        """
        import jax, numpy as np
        from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
        import redman_jax
        from redman_jax import _host
        assert len(jax.devices()) == 2
        mesh = Mesh(np.array(jax.devices()), ("batch",))
        x = jax.device_put(np.arange(24.0).reshape(8, 3), NamedSharding(mesh, P("batch", None)))
        assert _host.host_array(x) is None
        y = _host.take(x, np.array([5, 1]))
        np.testing.assert_array_equal(np.asarray(y), np.asarray(x)[[5, 1]])
        one = jax.device_put(np.arange(3.0), jax.devices()[1])
        assert _host.host_array(one) is not None
        print("ok")
        """
    )
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split()
                     if "xla_force_host_platform_device_count" not in f)
    env = dict(os.environ, XLA_FLAGS=flags + " --xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


def _as_float_jnp(x):
    """as_float as it was before host values skipped jax.numpy (the reference): ``jnp.asarray``
    first, then its jax-array path."""
    from redman_jax._math import as_float

    return as_float(jnp.asarray(x))


def test_as_float_of_host_values_equals_jax_numpy_and_compiles_nothing():
    from redman_jax._math import as_float

    values = [2.5, 3, True, np.float64(0.25), np.float32(0.5), np.int64(4), np.bool_(False),
              np.arange(3, dtype=np.float32).reshape(1, 3) + 0.5, np.arange(5, dtype=np.int32),
              np.linspace(0.1, 0.7, 7), np.full((2, 9), 1.5, np.float16)]
    with backend_compiles() as compiles:  # first: the jax.numpy path would compile these shapes
        ours = [as_float(v) for v in values]
    assert compiles == []
    refs = [_as_float_jnp(v) for v in values]
    for a, b in zip(ours, refs):
        _same(a, b)
    # jax arrays (weak and strong) and tracers go through jax.numpy as before
    for v in (jnp.asarray(2.0), jnp.arange(3), jnp.ones(2, jnp.float32)):
        _same(as_float(v), _as_float_jnp(v))
    np.testing.assert_allclose(np.asarray(jax.jit(as_float)(jnp.arange(3))), [0.0, 1.0, 2.0])
    # a list (which may hold tracers) too
    _same(as_float([0.5, 1.5]), _as_float_jnp([0.5, 1.5]))
    np.testing.assert_allclose(np.asarray(jax.jit(lambda k: as_float([k, 2 * k]))(1.5)), [1.5, 3.0])
