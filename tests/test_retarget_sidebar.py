"""What the sidebar's setting cards show (dashboard.retarget_sidebar.visible_settings): no browser."""

from __future__ import annotations

import panel as pn
import pytest

from core.pipeline import METHODS, Pipeline, StageCache
from core.stages.methods import METHODS as REGISTRY
from dashboard.retarget_sidebar import visible_settings
from dashboard.widgets import param_widgets
from datapaths import PERFORMANCES, RIGS


@pytest.fixture(scope="module")
def pipe():
    return Pipeline(cache=StageCache(), source=str(PERFORMANCES / "livelinkface_take_s07.csv"),
                    source_rig=str(RIGS / "ict_facekit.glb"), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))


@pytest.mark.parametrize("method", [m for m in METHODS if not REGISTRY[m].dense])
def test_weight_bounds_show_only_for_methods_that_honour_them(pipe, method):
    """Issue 33 item 7: Lowest/Highest weight were shown for lsq, range_pf and prior_pf, which do
    not solve within them; they stay in the solve's key either way (the controls' table)."""
    pipe.configure(method=method)
    cfg = pipe.config()
    shown = visible_settings(pipe.solve, cfg)
    honours = "bounds" in REGISTRY[method].honours
    assert ("lower" in shown) == honours and ("upper" in shown) == honours, (method, shown)
    assert {"lower", "upper"} <= set(pipe.solve.declared(cfg))


def _alpha_slider(pipe):
    """The sidebar's α widget as pn.Param makes it, and the slider the browser shows."""
    pane = pn.Param(pipe.solve, parameters=["alpha"], widgets=param_widgets(pipe.solve, ["alpha"]), show_name=False)
    w = pane._widgets["alpha"]
    return w, getattr(w, "_slider", w)


def test_alpha_is_on_a_log_scale(pipe):
    """Issue 33 item 7: α was a linear 0..1 slider (the default 0.01 a step or ten from 0 and the
    decades below it out of reach); on a log scale each decade takes the same length of slider,
    and the setting stays α itself both ways."""
    pipe.configure(method="spacetime", alpha=0.01)
    w, slider = _alpha_slider(pipe)
    where = {}
    for a in (1e-3, 1e-2, 1e-1, 1.0):
        pipe.solve.alpha = a
        where[a] = slider.value
    assert where[1e-2] - where[1e-3] == pytest.approx(where[1.0] - where[1e-1]), where
    assert (where[1e-2] - slider.start) / slider.step >= 20  # 0.01 is far from the slider's end
    # a value set from elsewhere (another page, the CLI) is kept exactly
    pipe.solve.alpha = 0.01234
    assert pipe.solve.alpha == 0.01234 and w.value == 0.01234
    # moving the handle sets α, not its logarithm; the left end is 0 (the prior off)
    slider.value = slider.start
    assert pipe.solve.alpha == 0.0
    slider.value = slider.end
    assert pipe.solve.alpha == pytest.approx(slider.end if slider is w else 1.0)
    slider.value = slider.end - 10 * slider.step if slider is not w else 0.5
    assert 0 < pipe.solve.alpha < 1
    pipe.solve.alpha = 0.01


def test_alpha_handle_follows_a_change_set_back_while_it_moved(pipe):
    """A shared shot that refuses a page's α sets the setting back inside the handle's own change
    (dashboard.review.Mirror._send on a Conflict); the handle must return with it, not keep showing
    the refused value (the review load test caught a page left on its refused α)."""
    pipe.configure(method="spacetime", alpha=0.01)
    w, slider = _alpha_slider(pipe)
    assert slider is not w  # the sidebar's α is a LogSlider (its handle is over log10 α)
    refused = []

    def refuse(event):  # what the Mirror does on a Conflict: the shot's value again
        if event.new != 0.01:
            refused.append(event.new)
            pipe.solve.alpha = 0.01

    watcher = pipe.solve.param.watch(refuse, "alpha")
    try:
        slider.value = slider.value + 4 * slider.step
    finally:
        pipe.solve.param.unwatch(watcher)
    assert refused and refused[0] > 0.01  # the move did reach the setting, and was set back
    assert pipe.solve.alpha == 0.01 and w.value == 0.01
    assert slider.value == pytest.approx(w.position(0.01))  # the handle is back at the shot's value
