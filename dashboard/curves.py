"""Weight-curve and diagnostics plots: Bokeh figures fed by ColumnDataSources.

Bokeh directly rather than hvplot (PANEL_NOTES: 50 curves x 2000 frames build in 0.17 s and
a cursor move is an 87-byte update). Views only turn arrays into glyphs: no numerics.
"""

from __future__ import annotations

import numpy as np
from bokeh.models import ColumnDataSource, HoverTool, Span, TapTool
from bokeh.palettes import Category10_10
from bokeh.plotting import figure
from panel.io.document import unlocked


def _page_safe(method):
    """Run a method that changes these raw Bokeh models under Panel's ``unlocked()``.

    Panel runs a widget's pending change (debounced 50 ms) inside a task *without* the document
    lock when a Bokeh event of the same page (a button click, a tap) arrives before it
    (``Syncable._server_event`` -> ``_event_coroutine``): Panel's own widgets cope, but a raw
    Bokeh model changed from such a watcher makes Bokeh raise "_pending_writes should be
    non-None ..." and the change is lost (found by the review load test: a scrub followed by a
    click on "Add note"). ``unlocked()`` holds the page's events and writes them itself, with or
    without the lock."""
    import functools

    @functools.wraps(method)
    def run(*args, **kwargs):
        with unlocked():
            return method(*args, **kwargs)

    return run


def _fig(title, y_label, height=260, x_range=None):
    # the wheel scrolls the page, not the plot (scrolling past the curves zoomed them): the wheel
    # zoom is in the toolbar, off until chosen
    kw = dict(height=height, sizing_mode="stretch_width", title=title, tools="xpan,xwheel_zoom,box_zoom,reset,tap",
              active_scroll=None, x_axis_label="time (s)", y_axis_label=y_label, toolbar_location="above")
    if x_range is not None:
        kw["x_range"] = x_range
    f = figure(**kw)
    f.title.text_font_size = "11pt"
    return f


def curve_columns(weights, valid=None) -> np.ndarray:
    """(T, K) weights as the curve plot draws them: (K, T) float rows, NaN (tracking loss) kept
    as gaps, ±inf made finite. ``valid`` (T,) bool: frames without data (False) become NaN too,
    so a curve breaks there instead of running straight across the filled-in gap (which looked
    like a face at rest)."""
    cols = np.nan_to_num(np.asarray(weights, dtype=float).T, nan=np.nan)
    if valid is not None:
        cols[:, ~np.asarray(valid, bool)] = np.nan
    return np.ascontiguousarray(cols)


class CurvePlot:
    """The target's weight curves over time with a time cursor; tapping seeks.

    ``on_seek(time_s)`` is called when the user taps the plot.
    """

    def __init__(self, on_seek=None, title="Target weight curves"):
        self.fig = _fig(title, "weight", height=300)
        self.source = ColumnDataSource(data=dict(xs=[], ys=[], name=[], color=[]))
        r = self.fig.multi_line("xs", "ys", source=self.source, line_color="color", line_width=1.6, alpha=0.9,
                                hover_line_width=3.5, hover_line_alpha=1.0)
        self.fig.add_tools(HoverTool(renderers=[r], tooltips=[("shape", "@name")], line_policy="nearest"))
        self.cursor = Span(location=0, dimension="height", line_color="#d62728", line_width=2)
        self.fig.add_layout(self.cursor)
        # review notes: marks at their frames on the time axis
        self.notes = ColumnDataSource(data=dict(t=[], y=[], text=[]))
        nr = self.fig.scatter("t", "y", source=self.notes, marker="inverted_triangle", size=13, color="#9467bd",
                              line_color="white")
        self.fig.add_tools(HoverTool(renderers=[nr], tooltips=[("note", "@text")]))
        self._on_seek = on_seek
        self.fig.on_event("tap", self._tap)
        self.fig.select_one(TapTool).behavior = "inspect"

    def _tap(self, event):
        if self._on_seek is not None and event.x is not None:
            self._on_seek(float(event.x))

    @_page_safe
    def update(self, times, weights, names, selected, columns=None):
        """Show the curves of ``selected`` shape names (all when empty: the 10 most active).
        ``columns``: the weights as (K, T) C-contiguous rows, NaN kept and ±inf made finite, if
        the caller keeps them (shared by the pages of a shot: a shown curve is then a view of
        its row, not a copy per page); made from ``weights`` otherwise."""
        W = np.asarray(weights)
        if not selected:
            act = np.nan_to_num(np.nanmax(W, axis=0) - np.nanmin(W, axis=0))
            selected = [names[i] for i in np.argsort(-act)[:8]]
        idx = [names.index(n) for n in selected if n in names]
        t = np.asarray(times, dtype=float)
        cols = columns if columns is not None else curve_columns(W)
        self.source.data = dict(
            xs=[t] * len(idx),
            ys=[cols[i] for i in idx],
            name=[names[i] for i in idx],
            color=[Category10_10[j % 10] for j in range(len(idx))],
        )
        return [names[i] for i in idx]

    @_page_safe
    def set_time(self, t: float):
        self.cursor.location = float(t)

    @_page_safe
    def set_notes(self, times, texts) -> None:
        """Mark the review notes at their times (just above the curves' zero line)."""
        self.notes.data = dict(t=[float(t) for t in times], y=[0.0] * len(times), text=list(texts))


class DiagnosticsPlot:
    """Per-frame marker error (mm) and velocity error, sharing the curve plot's time axis."""

    def __init__(self, x_range=None):
        self.fig = _fig("Per-frame error", "marker RMS error (mm)", height=220, x_range=x_range)
        self.source = ColumnDataSource(data=dict(t=[], err=[], vel=[]))
        self.fig.line("t", "err", source=self.source, color="#1f77b4", legend_label="marker error (mm)", line_width=1.5)
        self.fig.line("t", "vel", source=self.source, color="#ff7f0e", legend_label="velocity error (mm/frame)", line_width=1.2)
        self.fig.legend.location = "top_left"
        self.fig.legend.label_text_font_size = "9pt"
        self.cursor = Span(location=0, dimension="height", line_color="#d62728", line_width=2)
        self.fig.add_layout(self.cursor)

    @_page_safe
    def update(self, times, marker_error_mm, velocity_error_mm_per_frame):
        self.source.data = dict(t=np.asarray(times, float), err=np.asarray(marker_error_mm, float), vel=np.asarray(velocity_error_mm_per_frame, float))

    @_page_safe
    def set_time(self, t: float):
        self.cursor.location = float(t)
