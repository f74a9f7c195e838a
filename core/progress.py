"""Progress reporting for long runs: a callback type and a plain stderr bar.

Long stages accept ``progress: Callable[[float, str], None] | None`` and call it with the
fraction done (0..1) and a short message. The CLI passes :class:`StderrBar`; the dashboard
passes a function that sets its progress widget. Written by hand (a dozen lines) rather
than adding tqdm as a hard dependency.
"""

from __future__ import annotations

import sys
import time
from typing import Callable, Optional

ProgressFn = Callable[[float, str], None]


class StderrBar:
    """``label [#########.........]  45%  message`` on stderr, redrawn at most 10x/s."""

    def __init__(self, label: str = "", stream=None, width: int = 30, min_interval: float = 0.1):
        self.label, self.width, self.min_interval = label, width, min_interval
        self.stream = stream or sys.stderr
        self._last = 0.0
        self._start = time.perf_counter()
        self._done = False

    def __call__(self, fraction: float, message: str = "") -> None:
        now = time.perf_counter()
        fraction = min(max(float(fraction), 0.0), 1.0)
        if fraction < 1.0 and now - self._last < self.min_interval:
            return
        self._last = now
        n = int(round(fraction * self.width))
        line = f"\r{self.label} [{'#' * n}{'.' * (self.width - n)}] {fraction * 100:3.0f}% {now - self._start:5.1f}s {message}"
        self.stream.write(line[:160].ljust(80))
        if fraction >= 1.0 and not self._done:
            self.stream.write("\n")
            self._done = True
        self.stream.flush()


def report(progress: Optional[ProgressFn], fraction: float, message: str = "") -> None:
    """Call ``progress`` when given (stages use this so None means silent)."""
    if progress is not None:
        progress(fraction, message)
