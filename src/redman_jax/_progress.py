"""A small progress bar for long work: units done, units left and time left (stderr, no dependency)."""

from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


def _fmt(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else (f"{m}m{s:02d}s" if m else f"{s}s")


class Progress:
    """``Progress(total, label)``; call ``advance(weight, note)`` after each unit of work.

    Time left is extrapolated from the work done in this process (resumed units count as done but
    not as time spent). ``enabled=False`` prints nothing.
    """

    def __init__(self, total: float, label: str = "runs", enabled: bool = True, stream=None):
        self.total = float(total)
        self.done = 0.0
        self.done_here = 0.0
        self.label = label
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()

    def skip(self, weight: float = 1.0) -> None:
        """Count a unit that was already done (resumed) without timing it."""
        self.done += weight
        self._print("resumed")

    def advance(self, weight: float = 1.0, note: str = "") -> None:
        self.done += weight
        self.done_here += weight
        self._print(note)

    def _print(self, note: str) -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.t0
        left = self.total - self.done
        eta = elapsed / self.done_here * left if self.done_here > 0 else float("nan")
        width = 28
        frac = 0.0 if self.total <= 0 else min(1.0, self.done / self.total)
        bar = "#" * int(round(frac * width)) + "-" * (width - int(round(frac * width)))
        eta_s = _fmt(eta) if eta == eta else "?"
        self.stream.write(
            f"[{bar}] {self.done:g}/{self.total:g} {self.label} done, {left:g} left, "
            f"elapsed {_fmt(elapsed)}, ~{eta_s} left  {note}\n"
        )
        self.stream.flush()
