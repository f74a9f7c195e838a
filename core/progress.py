"""Progress reporting for long runs: a callback type and a plain stderr bar.

Long stages accept ``progress: Callable[[float, str], None] | None`` and call it with the
fraction done (0..1) and a short message. The CLI passes :class:`StderrBar`; the dashboard
passes a function that sets its progress widget. Written by hand (a dozen lines) rather
than adding tqdm as a hard dependency.
"""

from __future__ import annotations

import sys
import time
import warnings
from typing import Callable, Optional

ProgressFn = Callable[[float, str], None]


#: the bar whose line is drawn and not ended yet (warnings clear it first, see _show_warning)
_OPEN: Optional["StderrBar"] = None
_SHOW = None  # warnings.showwarning as it was before the first bar drew


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """``warnings.showwarning`` while a bar is drawn: clear the bar's line, show the warning on a
    line of its own, draw the bar again under it (a warning no longer lands in the bar's line)."""
    bar = _OPEN
    if bar is not None and bar._line and (file is None or file is bar.stream):
        bar.stream.write("\r" + " " * len(bar._line) + "\r")
        bar.stream.flush()
    _SHOW(message, category, filename, lineno, file, line)
    if bar is not None and bar._line and _OPEN is bar:
        bar.stream.write(bar._line)
        bar.stream.flush()


class StderrBar:
    """``label [#########.........]  45%  message`` on stderr, redrawn at most 10x/s; a warning
    shown meanwhile gets a line of its own above the bar."""

    def __init__(self, label: str = "", stream=None, width: int = 30, min_interval: float = 0.1):
        self.label, self.width, self.min_interval = label, width, min_interval
        self.stream = stream or sys.stderr
        self._last = 0.0
        self._start = time.perf_counter()
        self._done = False
        self._line = ""  # the bar as last drawn (without its leading carriage return)

    def __call__(self, fraction: float, message: str = "") -> None:
        now = time.perf_counter()
        fraction = min(max(float(fraction), 0.0), 1.0)
        if fraction < 1.0 and now - self._last < self.min_interval:
            return
        self._last = now
        n = int(round(fraction * self.width))
        line = f"{self.label} [{'#' * n}{'.' * (self.width - n)}] {fraction * 100:3.0f}% {now - self._start:5.1f}s {message}"
        self._line = line[:159].ljust(79)
        self.stream.write("\r" + self._line)
        self._open()
        if fraction >= 1.0 and not self._done:
            self.stream.write("\n")
            self._done = True
            self._close()
        self.stream.flush()

    def _open(self) -> None:
        global _OPEN, _SHOW
        if warnings.showwarning is not _show_warning:
            _SHOW = warnings.showwarning
            warnings.showwarning = _show_warning
        _OPEN = self

    def _close(self) -> None:
        global _OPEN
        self._line = ""
        if _OPEN is self:
            _OPEN = None


class TimeLeft:
    """A :data:`ProgressFn` that adds one estimate of the time left for the whole run to each
    message: ``elapsed × (1 − f) / f`` at overall fraction ``f`` (from 5 % on, before that the
    estimate is noise). Wrap a run's callback once, at the top (:meth:`core.pipeline.Pipeline.run`):
    a stage that estimated its own time left said how long *it* had, not the run."""

    def __init__(self, progress: ProgressFn, clock: Callable[[], float] = time.perf_counter):
        self.progress, self.clock = progress, clock
        self._start = clock()

    def __call__(self, fraction: float, message: str = "") -> None:
        if 0.05 <= fraction < 1.0:
            left = (self.clock() - self._start) * (1.0 - fraction) / fraction
            message = f"{message} — about {left:.0f} s left in all"
        self.progress(fraction, message)


def report(progress: Optional[ProgressFn], fraction: float, message: str = "") -> None:
    """Call ``progress`` when given (stages use this so None means silent)."""
    if progress is not None:
        progress(fraction, message)
