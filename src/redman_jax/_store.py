"""Atomic, resumable result storage for sweeps.

A sweep writes one file per unit of work (the scenarios and IK of one arm and case; the runs of one
arm, case and controller) under ``DIR/units/``. Every write goes to a temporary file in the same
folder and is moved into place with ``os.replace``, so a file either exists whole or not at all:
a sweep killed at any moment loses only the unit in flight, and a rerun computes only what is
missing. Each unit records the hash of the configuration that produced it; a unit whose hash does
not match the current configuration is recomputed.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import pickle
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_text", "config_hash", "UnitStore"]


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes it 0600; results are as readable as any file
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


@functools.lru_cache(maxsize=None)
def _umask() -> int:
    mask = os.umask(0)  # the only way to read it; set back at once (once per process)
    os.umask(mask)
    return mask


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def json_ready(obj: Any) -> Any:
    """``obj`` with NumPy scalars and arrays made plain Python and every non-finite float made
    ``None``, so that ``json.dumps(..., allow_nan=False)`` writes strict JSON (``null`` where Python's
    default would write the ``NaN`` and ``Infinity`` tokens that strict parsers reject)."""
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def config_hash(obj: Any) -> str:
    """Stable short hash of a JSON-serialisable configuration."""
    blob = json.dumps(obj, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _to_numpy(tree):
    import jax

    return jax.tree.map(lambda x: np.asarray(x) if hasattr(x, "shape") else x, tree)


class UnitStore:
    """Pickled units of work under ``root/units``, each tagged with a configuration hash."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.units = self.root / "units"
        self.units.mkdir(parents=True, exist_ok=True)

    def path(self, name: str) -> Path:
        return self.units / f"{name}.pkl"

    def has(self, name: str, key: str) -> bool:
        p = self.path(name)
        if not p.exists():
            return False
        try:
            with open(p, "rb") as f:
                return pickle.load(f)["key"] == key
        except Exception:  # a corrupt or foreign file: recompute it
            return False

    def save(self, name: str, key: str, payload: Any) -> None:
        blob = pickle.dumps({"key": key, "payload": _to_numpy(payload)}, protocol=pickle.HIGHEST_PROTOCOL)
        atomic_write_bytes(self.path(name), blob)

    def load(self, name: str) -> Any:
        with open(self.path(name), "rb") as f:
            return pickle.load(f)["payload"]
