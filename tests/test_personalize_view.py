"""The range-of-motion alignment view (dashboard/personalize_view.py), no browser.

A real session (Live Link Face ROM take on ICT -> Rocketbox, geometric method, personalize on)
is recomputed once; the view's Bokeh data sources are checked against the snapshot's
diagnostics (core.personalize.Personalization, Ribera 2017 §4).
"""

from __future__ import annotations

import numpy as np
import pytest
from bokeh.events import Tap

from core.pipeline import StageCache
from dashboard.personalize_view import HINT, NO_RESULTS, PersonalizeView
from dashboard.session import Session

MM = 1e3


@pytest.fixture(scope="module")
def session():
    s = Session(cache=StageCache())
    s.source, s.source_rig, s.target_rig = "livelinkface_rom.csv", "ict_facekit.glb", "rocketbox_female_adult_02.glb"
    s.pipeline.configure(method="geometric", personalize=True, last_frame=599)
    assert s.recompute(), s.error
    return s


@pytest.fixture(scope="module")
def snap(session):
    snap = session.snapshot
    assert snap["personalize"]["personalized"]
    return snap


def shape_names(snap):
    """Names of the (K, M, 3) deltas: the solver's shapes (marker-invisible ones dropped)."""
    names = snap["solver_names"]
    assert snap["personalize"]["deltas"].shape[0] == snap["calibrated_deltas"].shape[0] == len(names)
    return names


@pytest.fixture
def view(snap):
    v = PersonalizeView()
    v.update(snap)
    return v


def test_similarity_image_and_key_frames(view, snap):
    diag = snap["personalize"]["diagnostics"]
    names = shape_names(snap)
    K, T = len(names), len(snap["times"])
    assert view.body.visible and not view.hint.visible
    img = view.sim_source.data["image"][0]
    assert img.shape == (K, T) == diag.blended_similarity.shape
    np.testing.assert_allclose(img, diag.blended_similarity, rtol=1e-6, atol=1e-7)  # float32 for transport
    # the image covers the take's time span, one row per shape
    x0, dw = view.sim_source.data["x"][0], view.sim_source.data["dw"][0]
    assert x0 <= snap["times"][0] and x0 + dw >= snap["times"][-1]
    assert view.sim_source.data["dh"][0] == K
    # y axis labels are shape names, the selected shape always among them
    labels = view.sim_fig.yaxis.major_label_overrides
    assert labels and all(names[i] == n for i, n in labels.items())
    assert view.w_shape.value in labels.values()
    # Fig. 8: cumulative curve and its peaks
    kf = diag.key_frames
    assert len(view.key_source.data["frame"]) == len(kf) > 0
    np.testing.assert_array_equal(view.key_source.data["frame"], kf)
    np.testing.assert_allclose(view.key_source.data["t"], snap["times"][kf])
    np.testing.assert_allclose(view.key_source.data["c"], diag.cumulative[kf])
    assert len(view.cum_source.data["c"]) == T
    assert f"{len(kf)} key frames" in view.cum_fig.title.text


def test_shape_selection_changes_the_deltas(view, snap):
    diag = snap["personalize"]["diagnostics"]
    names = shape_names(snap)
    P, G = snap["personalize"]["deltas"], snap["calibrated_deltas"]
    # two shapes whose personalised deltas differ
    norms = np.linalg.norm(P.reshape(len(P), -1), axis=1)
    a, b = np.argsort(-norms)[:2]
    shown = {}
    for k in (a, b):
        view.w_shape.value = names[k]
        d = view.personal_source.data
        shown[k] = np.column_stack([d["dx"], d["dy"], d["dz"]])
        np.testing.assert_allclose(shown[k], P[k] * MM)
        g = view.initial_source.data
        np.testing.assert_allclose(np.column_stack([g["dx"], g["dy"], g["dz"]]), G[k] * MM)
        np.testing.assert_allclose(d["mask"], diag.masks[k])
        np.testing.assert_allclose(view.row_source.data["c"], diag.blended_similarity[k])
        assert f"{diag.trust[k]:.2f}" in view.shape_info.object
        assert names[k] in view.shape_info.object
    assert not np.allclose(shown[a], shown[b])
    # the initial guess and the personalised shape are different arrows from the same neutral
    assert not np.allclose(view.initial_source.data["x1"], view.personal_source.data["x1"])
    np.testing.assert_array_equal(view.initial_source.data["x0"], view.personal_source.data["x0"])


def test_magnification_scales_the_arrows_only(view):
    d0 = dict(view.personal_source.data)
    for gain in (2.0, 10.0):
        view.w_gain.value = gain
        d = view.personal_source.data
        np.testing.assert_allclose(np.asarray(d["x1"]) - d["x0"], gain * np.asarray(d["dx"]))
        np.testing.assert_allclose(np.asarray(d["y1"]) - d["y0"], gain * np.asarray(d["dy"]))
        np.testing.assert_array_equal(d["dx"], d0["dx"])
        np.testing.assert_array_equal(d["x0"], d0["x0"])


def test_neutral_markers(view, snap):
    X = snap["source_markers"]
    # the session's snapshot carries the stabilisation's neutral: the view draws from it
    np.testing.assert_allclose(view.personal_source.data["x0"], snap["source_neutral"][:, 0] * MM)
    # without it the view falls back to the take's first complete frame
    assert np.isfinite(X[0]).all()
    v0 = PersonalizeView()
    v0.update({k: v for k, v in snap.items() if k != "source_neutral"})
    np.testing.assert_allclose(v0.personal_source.data["x0"], X[0, :, 0] * MM)
    # a snapshot that carries the neutral explicitly wins over the first frame
    shifted = dict(snap, source_neutral=X[0] + np.array([0.01, 0.0, 0.0]))
    v = PersonalizeView()
    v.update(shifted)
    np.testing.assert_allclose(v.personal_source.data["x0"], (X[0, :, 0] + 0.01) * MM)


def test_tap_on_a_row_selects_the_shape(view, snap):
    names = shape_names(snap)
    k = 7 if view.w_shape.value != names[7] else 8
    view.sim_fig._trigger_event(Tap(view.sim_fig, x=1.0, y=k + 0.3))
    assert view.w_shape.value == names[k]
    np.testing.assert_allclose(view.personal_source.data["dx"], snap["personalize"]["deltas"][k, :, 0] * MM)
    band = view.shape_band
    assert min(band.top, band.bottom) < k < max(band.top, band.bottom)


def test_selection_survives_a_new_snapshot(session, view, snap):
    names = shape_names(snap)
    view.w_shape.value = names[3]
    session.pipeline.configure(align_gamma=0.2)
    try:
        assert session.recompute(), session.error
        new = session.snapshot
        view.update(new)
        assert view.w_shape.value == names[3]
        np.testing.assert_allclose(view.personal_source.data["dx"], new["personalize"]["deltas"][3, :, 0] * MM)
        assert not np.allclose(new["personalize"]["deltas"], snap["personalize"]["deltas"])
    finally:
        session.pipeline.configure(align_gamma=0.1)
        assert session.recompute(), session.error


def test_off_state_shows_the_hint(session):
    v = PersonalizeView()
    v.update({})
    assert v.hint.visible and not v.body.visible and v.hint.object == NO_RESULTS
    session.pipeline.configure(personalize=False)
    try:
        assert session.recompute(), session.error
        off = session.snapshot
        assert off["personalize"]["personalized"] is False
        v.update(off)
        assert v.hint.visible and not v.body.visible
        assert v.hint.object == HINT and "personalize" in HINT and "rom" in HINT
        assert len(v.sim_source.data["image"]) == 0  # nothing drawn behind the hint
    finally:
        session.pipeline.configure(personalize=True)
        assert session.recompute(), session.error
    v.update(session.snapshot)
    assert v.body.visible and not v.hint.visible
    assert v.sim_source.data["image"][0].shape == session.snapshot["personalize"]["diagnostics"].blended_similarity.shape


def test_layout_is_panel(view):
    import panel as pn

    assert isinstance(view.__panel__(), pn.Column)
    assert view.__panel__().objects == [view.hint, view.body]
