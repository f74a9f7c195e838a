"""How the generated setting cards draw a stage's settings (shared by the sidebar and the tabs),
and the small static pieces the pages share."""

from __future__ import annotations

import math

import panel as pn
import param
from bokeh.models import CustomJSTickFormatter

#: tiny relative weights read better typed than on a slider that shows 1e-5 as "0"
TYPED = {"ridge": pn.widgets.FloatInput, "rbf_smoothing": pn.widgets.FloatInput, "l1": pn.widgets.FloatInput,
         "name_weight": pn.widgets.FloatInput, "transfer_eps": pn.widgets.FloatInput,
         "transfer_alpha": pn.widgets.FloatInput, "transfer_iterations": pn.widgets.IntInput,
         "transfer_max_bases": pn.widgets.IntInput, "detail_tolerance": pn.widgets.FloatInput}


class LogSlider(pn.widgets.CompositeWidget):
    """A slider over log10 of a positive weight whose ``value`` is the weight itself: 1e-4 … 1 in
    steps of 10**0.05 (~12 %), with 0 (the term off) one step left of 1e-4. The label shows the
    weight, not its logarithm. A value set from Python (another page, the CLI's shot) is kept
    exactly; only a move of the handle rounds it to three significant digits."""

    value = param.Number(default=0.01, bounds=(0, None))
    label = param.String(default="")
    # named apart from a slider's start/end/step: pn.Param hands those the setting's linear bounds
    log_start = param.Number(default=-4.0, doc="log10 of the smallest positive weight")
    log_end = param.Number(default=0.0, doc="log10 of the largest weight")
    log_step = param.Number(default=0.05, doc="slider step in log10")

    _composite_type = pn.Row

    def __init__(self, **params):
        super().__init__(**params)
        off = self.log_start - self.log_step
        fmt = CustomJSTickFormatter(code=f"return tick <= {off + 1e-9} ? '0' : String(Number(Math.pow(10, tick).toPrecision(2)))")
        self._slider = pn.widgets.FloatSlider(label=self.label, start=off, end=self.log_end, step=self.log_step,
                                              value=self.position(self.value), format=fmt, sizing_mode="stretch_width")
        self._composite[:] = [self._slider]
        self._composite.margin = 0  # the slider keeps its own margin, in line with the other settings
        self._syncing = False
        self._slider.param.watch(self._moved, "value")
        self.param.watch(self._set, "value")

    def position(self, value: float) -> float:
        """The slider's position (log10) of weight ``value``; 0 sits one step left of ``start``."""
        if value <= 0:
            return self.log_start - self.log_step
        return min(max(math.log10(value), self.log_start), self.log_end)

    def weight(self, position: float) -> float:
        """The weight at slider ``position``, to three significant digits (0 left of ``start``)."""
        if position < self.log_start - self.log_step / 2:
            return 0.0
        return float(f"{10.0 ** position:.3g}")

    def _moved(self, event):
        if self._syncing:
            return
        self._syncing = True
        try:
            self.value = self.weight(event.new)
            if self.value != self.weight(event.new):
                # a watcher set the value back meanwhile (a shared shot refusing the change: the
                # page returns to the shot's value); the guard kept _set from moving the handle,
                # so it follows here — else the page shows the refused value until the next
                # change arrives (found by the review load test: a page kept its refused α)
                self._slider.value = self.position(self.value)
        finally:
            self._syncing = False

    def _set(self, event):
        if not self._syncing:
            self._syncing = True
            try:
                self._slider.value = self.position(event.new)
            finally:
                self._syncing = False


#: weights spread over decades: a slider over their logarithm (Seol's α: 1e-4 … 1, default 1e-2)
LOG = {"alpha": LogSlider}


def param_widgets(stage, names, extra=None) -> dict:
    """pn.Param widget choices for ``names`` of ``stage``: a Boolean setting is a toggle button
    (its whole label is clickable — a Bokeh checkbox toggles only from its box), tiny relative
    weights are typed, weights over decades are on a log slider; ``extra`` adds more."""
    out = {n: {"type": pn.widgets.Toggle, "button_type": "light"} for n in names if isinstance(stage.param[n], param.Boolean)}
    out.update({k: v for k, v in TYPED.items() if k in names})
    out.update({k: {"type": v} for k, v in LOG.items() if k in names})
    out.update({k: v for k, v in (extra or {}).items() if k in names})
    return out


#: a thin rule, as HTML: put in one pane with the heading under it (a Divider and a heading are two
#: Panel objects, and each costs every page ~25-35 KB of server memory)
RULE = "<hr style='border:none;border-top:1px solid #ddd;margin:4px 0 8px 0'>"


def ruled_heading(text: str, note: str = "") -> str:
    """HTML of a rule and a bold heading ``text`` (plain text) with an optional ``note`` after it."""
    import html

    return f"{RULE}<p><strong>{html.escape(text)}</strong>{(' ' + html.escape(note)) if note else ''}</p>"


class _TextUpdate:
    """A text pane whose new ``object`` reaches its model as the new text alone. Panel's own update
    of a text pane (``HTMLBasePane._update``) recomputes every property of the model — design,
    stylesheets, sizing — for each new text: ~1.3 ms a time, and a shared shot's change updates a
    page's status, summary and timings on every page of the shot. Only ``object`` (and the
    sanitising settings, folded into ``_transform_object``) re-render a text pane; every other
    parameter still takes Panel's normal path."""

    def _update(self, ref, model) -> None:
        model.update(text=self._transform_object(self.object)["object"])


class Markdown(_TextUpdate, pn.pane.Markdown):
    """``pn.pane.Markdown`` whose updates send only the new text (see :class:`_TextUpdate`)."""


class HTML(_TextUpdate, pn.pane.HTML):
    """``pn.pane.HTML`` whose updates send only the new text (see :class:`_TextUpdate`)."""
