"""Range-of-motion alignment view: how the target's blendshapes were personalised to the actor.

Shows the diagnostics of :func:`core.personalize.personalize` (Ribera et al. 2017 §4) from
the session snapshot:

* the contrast-enhanced similarity c̃_kf of every shape with every frame (eq. 8, Fig. 7) as an
  image, shapes × time; tapping a row selects that shape;
* the cumulative filtered similarity whose peaks are the key expressions (§4.2, Fig. 8),
  with the key frames marked and the selected shape's c̃_kf row on a second axis;
* the selected shape's RBF initial guess Δg_k (Seol 2012 §3.2) next to the personalised
  Δp_k, as segments from the actor's neutral markers (front view, x/y, magnified), the markers
  coloured by the local-support mask u_k (§4.3), the trust t_k (eq. 6) in the title;
* the alignment energies (eq. 4, 10, 11, 13) before and after.

When personalisation is off a short hint replaces the plots. Bokeh directly, as in
:mod:`dashboard.curves`. No numerics: only slicing, unit conversion and scaling for display.
"""

from __future__ import annotations

import html
import math

import numpy as np
import panel as pn
from bokeh.models import (BoxAnnotation, ColorBar, ColumnDataSource, CustomJSHover, FixedTicker, HoverTool,
                          LinearAxis, LinearColorMapper, Range1d, TapTool)
from bokeh.palettes import Viridis256
from bokeh.plotting import figure

from core.report import readable

HINT = (
    "**Range-of-motion alignment is off.** Tick **personalize** in the sidebar to fit actor-specific "
    "blendshapes (Ribera et al. 2017 §4): the target's marker blendshapes, warped into the actor's proportions "
    "by the RBF calibration, are aligned to the actor's own range of motion. The source take serves as the "
    "range-of-motion take unless **rom** names another capture of the same actor."
)
NO_RESULTS = "*No results yet: the pipeline has not produced a snapshot.*"

#: ~one readable shape label per this many pixels of the similarity image's height
LABEL_PX = 11
SIM_HEIGHT = 400
MARKER_HEIGHT = 430
#: u_k colours, low (grey-blue) to full support (dark red)
MASK_PALETTE = ("#c6dbef", "#9ecae1", "#6baed6", "#fdae6b", "#fd8d3c", "#e6550d", "#a63603")
MM = 1e3  # metres inside, millimetres on screen


def _default_shape(names, previous, similarity, key_frames):
    """Keep the user's choice; else the shape the key expressions resemble most (the one the
    alignment pulls hardest), the first on ties."""
    if previous in names:
        return previous
    if not names:
        return None
    kf = np.asarray(key_frames, dtype=int)
    S = np.asarray(similarity)
    return names[int(np.argmax(S[:, kf].max(axis=1)))] if len(kf) else names[0]


class PersonalizeView(pn.viewable.Viewer):
    """The range-of-motion alignment diagnostics of one session (see the module docstring).

    ``update(snapshot)`` takes the session's snapshot (the pipeline's snapshot stage, :mod:`core.stages.snapshot`);
    ``__panel__()`` returns the layout. Widgets: ``w_shape`` (shape shown in the marker
    plots) and ``w_gain`` (magnification of the deltas). Data sources (for tests):
    ``sim_source`` (image), ``cum_source``/``key_source``/``row_source`` (Fig. 8 plot),
    ``initial_source``/``personal_source`` (markers: neutral x0/y0, displaced x1/y1 in mm,
    ``dx``/``dy``/``dz`` the unmagnified delta in mm, ``mask`` u_k).
    """

    def __init__(self, **params):
        super().__init__(**params)
        self._snap_ref = None  # the snapshot objects drawn last (held so identity checks are safe)
        self.names: list = []
        self._initial = self._personal = self._neutral = self._diag = None
        self.hint = pn.pane.Markdown(HINT, sizing_mode="stretch_width", visible=True)
        self.header = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.energies = pn.pane.HTML("", sizing_mode="stretch_width")
        self.shape_info = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.w_shape = pn.widgets.Select(label="Shape (or tap a row of the similarity image)", options=[], width=300)
        self.w_gain = pn.widgets.FloatSlider(label="Magnification of the deltas", start=1.0, end=20.0, step=0.5, value=3.0,
                                             width=260)
        self.w_shape.param.watch(lambda e: self._draw_shape(), "value")
        self.w_gain.param.watch(lambda e: self._draw_shape(), "value")
        self._build_similarity()
        self._build_cumulative()
        self._build_markers()
        self.body = pn.Column(
            self.header,
            pn.pane.Bokeh(self.sim_fig, sizing_mode="stretch_width"),
            pn.pane.Bokeh(self.cum_fig, sizing_mode="stretch_width"),
            pn.Row(self.w_shape, self.w_gain, self.shape_info, sizing_mode="stretch_width"),
            pn.Row(pn.pane.Bokeh(self.initial_fig, sizing_mode="stretch_width"),
                   pn.pane.Bokeh(self.personal_fig, sizing_mode="stretch_width"), sizing_mode="stretch_width"),
            self.energies,
            sizing_mode="stretch_width", visible=False,
        )
        self.layout = pn.Column(self.hint, self.body, sizing_mode="stretch_width")

    # -- figures ------------------------------------------------------------------------------
    def _build_similarity(self):
        """c̃_kf as an image (Ribera 2017 eq. 8, Fig. 7): row k = shape, column = frame."""
        self.sim_mapper = LinearColorMapper(palette=Viridis256, low=0.0, high=1.0)
        # y runs top-down so the shape list reads like the selector
        f = figure(height=SIM_HEIGHT, sizing_mode="stretch_width", title="Similarity c̃ of every shape with every frame "
                   "(Ribera 2017 eq. 8, Fig. 7)", x_axis_label="time (s)", y_axis_label="target shape",
                   tools="xpan,xwheel_zoom,box_zoom,reset,tap", active_scroll="xwheel_zoom", toolbar_location="above",
                   x_range=Range1d(0, 1), y_range=Range1d(1, 0))
        f.title.text_font_size = "11pt"
        f.grid.visible = False
        self.sim_source = ColumnDataSource(data=dict(image=[], x=[], y=[], dw=[], dh=[]))
        r = f.image(image="image", x="x", y="y", dw="dw", dh="dh", source=self.sim_source, color_mapper=self.sim_mapper)
        f.add_layout(ColorBar(color_mapper=self.sim_mapper, width=10, title="c̃", title_text_font_size="9pt",
                              label_standoff=4, padding=4), "right")
        self.sim_ticker = FixedTicker(ticks=[])
        f.yaxis.ticker = self.sim_ticker
        f.yaxis.major_label_text_font_size = "8pt"
        self.shape_band = BoxAnnotation(top=0, bottom=0, fill_alpha=0.0, line_color="#ff3b30", line_width=1.5)
        f.add_layout(self.shape_band)
        self._shape_formatter = CustomJSHover(args=dict(names=[]), code=(
            "const k = Math.round(value); return (k >= 0 && k < names.length) ? names[k] : '';"))
        f.add_tools(HoverTool(renderers=[r], tooltips=[("shape", "$y{custom}"), ("time", "$x{0.00} s"), ("c̃", "@image{0.00}")],
                              formatters={"$y": self._shape_formatter}))
        f.select_one(TapTool).behavior = "inspect"
        f.on_event("tap", self._tap)
        self.sim_fig = f

    def _build_cumulative(self):
        """Σ_k of the filtered c̃_kf over time with its peaks, the key frames (§4.2, Fig. 8)."""
        f = figure(height=230, sizing_mode="stretch_width", title="Key expressions", x_axis_label="time (s)",
                   y_axis_label="Σ_k filtered c̃", tools="xpan,xwheel_zoom,box_zoom,reset",
                   active_scroll="xwheel_zoom", toolbar_location="above", x_range=self.sim_fig.x_range)
        f.title.text_font_size = "11pt"
        self.cum_source = ColumnDataSource(data=dict(t=[], c=[]))
        self.key_source = ColumnDataSource(data=dict(t=[], c=[], frame=[]))
        self.row_source = ColumnDataSource(data=dict(t=[], c=[]))
        f.extra_y_ranges = {"row": Range1d(0, 1.05)}
        self.row_axis = LinearAxis(y_range_name="row", axis_label="c̃ of the shape")
        f.add_layout(self.row_axis, "right")
        f.line("t", "c", source=self.row_source, y_range_name="row", color="#ff7f0e", alpha=0.7, line_width=1.2,
               legend_label="c̃ of the selected shape (right axis)")
        f.line("t", "c", source=self.cum_source, color="#1f77b4", line_width=1.6, legend_label="cumulative filtered similarity")
        k = f.scatter("t", "c", source=self.key_source, size=8, color="#d62728", marker="circle",
                      legend_label="key frames (local maxima)")
        f.add_tools(HoverTool(renderers=[k], tooltips=[("key frame", "@frame"), ("time", "@t{0.00} s")]))
        f.legend.location = "bottom_right"
        f.legend.label_text_font_size = "8pt"
        f.legend.background_fill_alpha = 0.6
        self.cum_fig = f

    def _build_markers(self):
        """Δg_k and Δp_k as segments from the neutral markers, front view, same axes."""
        self.mask_mapper = LinearColorMapper(palette=list(MASK_PALETTE), low=0.0, high=1.0)
        x_range, y_range = Range1d(-1, 1), Range1d(-1, 1)
        self.wire_source = ColumnDataSource(data=dict(xs=[], ys=[]))
        self.initial_source = self._marker_source()
        self.personal_source = self._marker_source()
        self.initial_fig = self._marker_fig("RBF initial guess Δg", self.initial_source, x_range, y_range)
        self.personal_fig = self._marker_fig("Personalised Δp", self.personal_source, x_range, y_range)
        self.personal_fig.add_layout(ColorBar(color_mapper=self.mask_mapper, width=10, title="mask u", padding=4,
                                              title_text_font_size="9pt"), "right")

    @staticmethod
    def _marker_source():
        return ColumnDataSource(data=dict(name=[], x0=[], y0=[], x1=[], y1=[], dx=[], dy=[], dz=[], mask=[]))

    def _marker_fig(self, title, source, x_range, y_range):
        f = figure(height=MARKER_HEIGHT, sizing_mode="stretch_width", title=title, x_axis_label="x (mm)", y_axis_label="y (mm)",
                   tools="pan,wheel_zoom,box_zoom,reset", active_scroll="wheel_zoom", toolbar_location="above",
                   match_aspect=True, x_range=x_range, y_range=y_range)
        f.title.text_font_size = "11pt"
        f.multi_line("xs", "ys", source=self.wire_source, line_color="#cccccc", line_width=1)
        f.scatter("x0", "y0", source=source, size=4, color="#888888")
        # segments, not Arrow annotations: a zero delta would still draw an arrowhead at every marker;
        # the direction reads from the small grey neutral dot to the coloured displaced marker
        f.segment("x0", "y0", "x1", "y1", source=source, line_color="#444444", line_width=1.5)
        r = f.scatter("x1", "y1", source=source, size=9, line_color="#333333",
                      fill_color={"field": "mask", "transform": self.mask_mapper})
        f.add_tools(HoverTool(renderers=[r], tooltips=[("marker", "@name"), ("Δ (mm)", "@dx{0.00}, @dy{0.00}, @dz{0.00}"),
                                                       ("mask u", "@mask{0.00}")]))
        return f

    # -- events -------------------------------------------------------------------------------
    def _tap(self, event):
        if event.y is None or not self.names:
            return
        k = int(round(event.y))
        if 0 <= k < len(self.names):
            self.w_shape.value = self.names[k]

    # -- drawing ------------------------------------------------------------------------------
    def update(self, snapshot: dict) -> None:
        """Draw the personalisation of ``snapshot``; a hint when personalisation is off."""
        pers = (snapshot or {}).get("personalize")
        if not pers or not pers.get("personalized") or pers.get("diagnostics") is None:
            self.hint.object = HINT if snapshot else NO_RESULTS
            self.hint.visible, self.body.visible = True, False
            return
        self.hint.visible, self.body.visible = False, True
        diag = pers["diagnostics"]
        refs = (diag, pers["deltas"], snapshot["calibrated_deltas"], snapshot["source_markers"], snapshot.get("source_neutral"))
        if self._snap_ref is not None and all(a is b for a, b in zip(refs, self._snap_ref)):
            return  # same cached results: nothing to redraw
        self._snap_ref = refs
        self._diag = diag
        # the shapes of the (K, M, 3) deltas: the solver's subset of the rig when the snapshot says so
        self.names = list(snapshot.get("solver_names") or snapshot["target_names"])
        self.marker_names = list(snapshot["marker_names"])
        self._initial = np.asarray(snapshot["calibrated_deltas"])
        self._personal = np.asarray(pers["deltas"])
        self._neutral = self._neutral_markers(snapshot)
        times = np.asarray(snapshot["times"], dtype=float)
        self.times = times
        self._draw_similarity(diag, times)
        self._draw_cumulative(diag, times)
        self._draw_wire(diag)
        self._draw_energies(diag)
        T, K, F = len(times), len(self.names), len(diag.key_frames)
        left_out = len(snapshot["target_names"]) - K
        self.header.object = (
            f"**Range-of-motion alignment** (Ribera et al. 2017 §4) of {K} target shapes"
            f"{f' ({left_out} move no marker and are left out)' if left_out > 0 else ''} on {len(self.marker_names)} markers "
            f"over {T} frames ({times[-1] - times[0]:.1f} s): {F} key expressions; the **{html.escape(str(snapshot.get('method', '')))}** "
            f"solve uses the personalised shapes.")
        shape = _default_shape(self.names, self.w_shape.value, diag.blended_similarity, diag.key_frames)
        self.w_shape.options = self.names
        if self.w_shape.value != shape:
            self.w_shape.value = shape  # draws the shape
        else:
            self._draw_shape()

    @staticmethod
    def _neutral_markers(snapshot):
        """The actor's neutral markers (M, 3): ``source_neutral`` when the snapshot has it,
        else the first source frame with every marker (the stabilisation's default neutral frame)."""
        if snapshot.get("source_neutral") is not None:
            return np.asarray(snapshot["source_neutral"], dtype=float)
        X = np.asarray(snapshot["source_markers"], dtype=float)
        full = np.flatnonzero(np.isfinite(X).all(axis=(1, 2)))
        return X[full[0] if len(full) else 0]

    def _draw_similarity(self, diag, times):
        S = np.asarray(diag.blended_similarity, dtype=np.float32)  # (K, T)
        K, T = S.shape
        dt = (times[-1] - times[0]) / (T - 1) if T > 1 else 1.0
        x0, x1 = times[0] - dt / 2, times[-1] + dt / 2
        self.sim_source.data = dict(image=[S], x=[x0], y=[-0.5], dw=[x1 - x0], dh=[K])
        self.sim_fig.x_range.update(start=x0, end=x1)
        self.sim_fig.y_range.update(start=K - 0.5, end=-0.5)
        self._shape_formatter.args = dict(names=self.names)

    def _label_ticks(self, selected):
        """Every n-th shape name on the y axis (all when they fit) plus the selected one."""
        K = len(self.names)
        step = max(1, math.ceil(K * LABEL_PX / (SIM_HEIGHT - 60)))
        # drop the regular labels that would collide with the selected shape's
        near = set(range(selected - step + 1, selected + step))
        ticks = sorted((set(range(0, K, step)) - near) | {selected})
        self.sim_ticker.ticks = ticks
        self.sim_fig.yaxis.major_label_overrides = {i: self.names[i] for i in ticks}

    def _draw_cumulative(self, diag, times):
        cum = np.asarray(diag.cumulative, dtype=float)
        kf = np.asarray(diag.key_frames, dtype=int)
        self.cum_source.data = dict(t=times, c=cum)
        self.key_source.data = dict(t=times[kf], c=cum[kf], frame=kf)
        self.cum_fig.title.text = (f"Key expressions: {len(kf)} key frames, the local maxima of the cumulative filtered "
                                   "similarity (Ribera 2017 §4.2, Fig. 8)")

    def _draw_wire(self, diag):
        """The marker triangulation of E_Mesh (§4.4) on the neutral, for orientation."""
        P = self._neutral[:, :2] * MM
        faces = np.asarray(diag.faces, dtype=int)
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]], np.asarray(diag.contacts, dtype=int).reshape(-1, 2)])
        self.wire_source.data = dict(xs=[P[e, 0] for e in edges], ys=[P[e, 1] for e in edges])
        lo, hi = np.nanmin(P, axis=0), np.nanmax(P, axis=0)
        pad = 0.12 * float(np.max(hi - lo))
        self.initial_fig.x_range.update(start=lo[0] - pad, end=hi[0] + pad)
        self.initial_fig.y_range.update(start=lo[1] - pad, end=hi[1] + pad)

    def _draw_energies(self, diag):
        e = diag.energies
        rows = "".join(
            f"<tr><td>{label}</td><td style='text-align:right'>{readable(e['initial'][k] * 1e6)}</td>"
            f"<td style='text-align:right'>{readable(e['aligned'][k] * 1e6)}</td></tr>"
            for k, label in (("match", "E_Match (eq. 10)"), ("mesh", "E_Mesh (eq. 11)"), ("ceg", "E_CEG (eq. 13)"),
                             ("total", "E_Align (eq. 4)")) if k in e.get("initial", {}) and k in e.get("aligned", {}))
        self.energies.object = ("<table style='font-size:0.85em'><tr><th>energy (mm²)</th><th>initial Δg</th>"
                                f"<th>aligned Δp</th></tr>{rows}</table>") if rows else ""

    def _draw_shape(self):
        if self._diag is None or self.w_shape.value not in self.names:
            return
        k = self.names.index(self.w_shape.value)
        gain = float(self.w_gain.value)
        mask = np.asarray(self._diag.masks[k], dtype=float)
        for src, D in ((self.initial_source, self._initial[k]), (self.personal_source, self._personal[k])):
            P, Dmm = self._neutral * MM, np.asarray(D, dtype=float) * MM
            src.data = dict(name=self.marker_names, x0=P[:, 0], y0=P[:, 1], x1=P[:, 0] + gain * Dmm[:, 0],
                            y1=P[:, 1] + gain * Dmm[:, 1], dx=Dmm[:, 0], dy=Dmm[:, 1], dz=Dmm[:, 2], mask=mask)
        t_k = float(self._diag.trust[k])
        name = self.names[k]
        self.initial_fig.title.text = f"RBF initial guess Δg (Seol 2012 §3.2) ×{gain:g}"
        self.personal_fig.title.text = f"Personalised Δp (Ribera 2017 §4) ×{gain:g}"
        self.row_source.data = dict(t=self.times, c=np.asarray(self._diag.blended_similarity[k], dtype=float))
        self.row_axis.axis_label = f"c̃ of {name}"
        self.shape_band.update(top=k - 0.5, bottom=k + 0.5, fill_alpha=0.0)
        self._label_ticks(k)
        self.shape_info.object = (f"**{html.escape(name)}**: trust t = {t_k:.2f} (eq. 6) · segments from the actor's "
                                  f"neutral markers, front view, ×{gain:g} · marker colour: mask u (§4.3)")

    def __panel__(self):
        return self.layout
