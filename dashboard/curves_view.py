"""The Retarget tab's plots: the target's weight curves (the shapes picked, or the 8 most active)
and the per-frame marker and velocity errors under them, sharing the time axis, with the
current frame's cursor; a tap on a curve seeks there. The figures are
:class:`dashboard.curves.CurvePlot` and :class:`dashboard.curves.DiagnosticsPlot`.
"""

from __future__ import annotations

from typing import Callable

import panel as pn

from dashboard.curves import CurvePlot, DiagnosticsPlot, curve_columns
from dashboard.session import derived


class CurvesView(pn.viewable.Viewer):
    """The shape picker, the weight curves and the error plot.

    ``on_seek(time_s)``: a tap on the plot; ``time_of(frame)``: a frame's time in seconds;
    ``frame()``: the page's current frame."""

    def __init__(self, session, on_seek: Callable[[float], None], time_of: Callable[[int], float],
                 frame: Callable[[], int], **params):
        super().__init__(**params)
        self.s = session
        self._time_of, self._frame = time_of, frame
        self.w_shapes = pn.widgets.MultiChoice(name="Curves shown (empty: the 8 most active)", options=[], sizing_mode="stretch_width")
        self.w_shapes.param.watch(lambda e: self.draw_curves(), "value")
        self.curves = CurvePlot(on_seek=on_seek)
        self.diag = DiagnosticsPlot(x_range=self.curves.fig.x_range)
        self.layout = pn.Column(self.w_shapes, pn.pane.Bokeh(self.curves.fig, sizing_mode="stretch_width"),
                                pn.pane.Bokeh(self.diag.fig, sizing_mode="stretch_width"), sizing_mode="stretch_width")

    def __panel__(self):
        return self.layout

    def draw(self, snap: dict) -> None:
        """The snapshot's shapes as the picker's options, its curves and its errors."""
        names = snap["target_names"]
        if self.w_shapes.options != names:
            self.w_shapes.param.update(options=names, value=[v for v in self.w_shapes.value if v in names])
        self.draw_curves()
        ev = snap["evaluate"]
        self.diag.update(snap["times"], ev["marker_error_mm"], ev["velocity_error_mm_per_frame"])

    def draw_curves(self) -> None:
        snap = self.s.snapshot
        if snap:
            self.curves.update(snap["times"], snap["weights"], snap["target_names"], list(self.w_shapes.value),
                               columns=derived(snap, "curve_columns", lambda: curve_columns(snap["weights"], snap.get("valid"))))
            # both cursors at this snapshot's time of the frame (the error plot's kept the
            # previous take's frame rate after a switch)
            self.set_time(self._time_of(self._frame()))

    def set_time(self, time_s: float) -> None:
        """Move both plots' cursor to ``time_s``."""
        self.curves.set_time(time_s)
        self.diag.set_time(time_s)

    def set_notes(self, times, texts) -> None:
        """Mark a shared shot's notes on the curves (at ``times``, with ``texts``)."""
        self.curves.set_notes(times, texts)
