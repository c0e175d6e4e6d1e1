"""XLA flags a benchmark asks for on its command line, set before JAX's backend starts."""

from __future__ import annotations

import os


def start_with_xla_flags(extra, option: str) -> str:
    """Add ``extra`` to ``$XLA_FLAGS`` (each unless ``$XLA_FLAGS`` names it already, as the study's
    workers do: :func:`redman_jax._study._with_flags`) and return the flags. XLA reads them when
    JAX's backend starts, so this must run first; exits naming ``option`` if the backend has
    started or this jaxlib does not start with the flags."""
    from jax._src import xla_bridge

    from redman_jax._study import _with_flags, _xla_accepts

    if xla_bridge.backends_are_initialized():
        raise SystemExit(f"{option}: JAX's backend is already started; XLA reads its flags at the start")
    flags = _with_flags(os.environ.get("XLA_FLAGS", ""), extra)
    if not _xla_accepts(flags):
        raise SystemExit(f"{option}: this jaxlib does not start with XLA_FLAGS={flags!r}")
    os.environ["XLA_FLAGS"] = flags
    return flags


def start_with_host_devices(count: int, extra=(), option: str = "--devices") -> str:
    """:func:`start_with_xla_flags` with the CPU split into ``count`` XLA devices
    (``--xla_force_host_platform_device_count``) besides ``extra``; exits naming ``option`` if the
    count is not positive or JAX starts with another one (``$XLA_FLAGS`` named it)."""
    if count < 1:
        raise SystemExit(f"{option}: expected a positive count, got {count}")
    flags = start_with_xla_flags((*extra, f"--xla_force_host_platform_device_count={count}"), option)
    import jax

    if len(jax.devices()) != count:
        raise SystemExit(f"{option} {count}: JAX started with {len(jax.devices())} devices "
                         f"(XLA_FLAGS={flags!r})")
    return flags
