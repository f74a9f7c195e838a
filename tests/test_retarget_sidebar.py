"""What the sidebar's setting cards show (dashboard.retarget_sidebar.visible_settings): no browser."""

from __future__ import annotations

import pytest

from core.pipeline import METHODS, Pipeline, StageCache
from core.stages.methods import METHODS as REGISTRY
from dashboard.retarget_sidebar import visible_settings
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
