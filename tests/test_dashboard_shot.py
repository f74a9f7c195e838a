"""The dashboard's whole state is the shot: set widgets as a user would (no browser), download
the shot, and the CLI reproduces the page's weights to the last bit; uploading the shot into
another page brings the same state back."""

import csv

import numpy as np
import panel as pn
import pytest

from core.cli import main
from core.pipeline import StageCache


def widget(app, label, stage=None):
    """The page's widget of a stage parameter (``label`` a param name of ``stage``), or labelled ``label``."""
    if stage is not None:
        label = getattr(app.pipe, stage).param[label].label
    for card in app.layout.select(pn.Card):  # open the collapsed cards, as a user would (their widgets are made then)
        card.collapsed = False
    found = [w for w in app.layout.select(pn.widgets.Widget) if getattr(w, "name", None) == label]
    assert found, f"no widget labelled {label!r}"
    return found[0]


@pytest.fixture(scope="module")
def app():
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    return DashboardApp(Session(cache=StageCache()))


@pytest.mark.slow
def test_widgets_to_shot_to_cli_bit_identical(app, tmp_path):
    widget(app, "last_frame", "frames").value = 299
    widget(app, "method", "solve").value = "bounded"  # not the page default
    widget(app, "upper", "solve").value = 0.8
    widget(app, "ridge", "solve").value = 1e-4
    assert app.s.snapshot["method"] == "bounded" and len(app.s.snapshot["times"]) == 300
    # a spacetime edit from the Edit card
    app.playback.w_frame.value = 150
    app.edits.w_shape.value = "AK_25_JawOpen"
    app.edits.w_value.value = 0.7
    app.edits.w_window.value = 10
    app.edits.add()
    assert app.pipe.edit.edits == [{"frame": 150, "weights": {"AK_25_JawOpen": 0.7}, "window": [140, 160]}]
    W_page = np.asarray(app.s.snapshot["weights"])
    shot = tmp_path / "shot.json"
    shot.write_bytes(app.sidebar.w_shot.callback().read())  # what "Download shot" sends
    out = tmp_path / "w.csv"
    assert main(["retarget", "--shot", str(shot), "--weights-csv", str(out), "--csv-precision", "full", "--quiet"]) == 0
    rows = list(csv.reader(open(out)))
    names = rows[0][3:]
    W_cli = np.array([[float(c) for c in r[3:]] for r in rows[1:]])
    assert names == app.s.snapshot["target_names"]
    assert W_cli.shape == W_page.shape and np.array_equal(W_cli, W_page)  # to the last bit


@pytest.mark.slow
def test_uploading_the_shot_restores_the_page(app, tmp_path):
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    data = app.sidebar.w_shot.callback().read()
    other = DashboardApp(Session(cache=StageCache()))
    assert other.pipe.solve.method != "bounded"
    other.sidebar.w_upload.filename = "review.json"
    other.sidebar.w_upload.value = data  # what the upload box does
    other.refresh()
    assert other.pipe.solve.method == "bounded" and other.pipe.solve.upper == 0.8
    assert other.pipe.edit.edits == app.pipe.edit.edits and other.pipe.frame == 150
    assert np.array_equal(other.s.snapshot["weights"], app.s.snapshot["weights"])


def test_collapsed_cards_fill_when_opened_and_the_shape_table_is_current():
    """The collapsed cards reach the browser only when opened (dashboard/lazy.py); the shape
    table, not kept up to date while collapsed, shows the current frame's weights when opened."""
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    assert app.shape_controls.card.collapsed and len(app.shape_controls.card.objects) == 0
    assert app.shape_controls.w_table is None  # not even made while nobody looks at it
    assert not app.layout.select(pn.widgets.Tabulator)
    app.playback.w_frame.value = 437
    app.shape_controls.card.collapsed = False
    assert app.shape_controls.w_table in app.shape_controls.card.select(pn.widgets.Tabulator)
    W = app.s.snapshot["weights"]
    assert np.allclose(app.shape_controls.w_table.value["now"].to_numpy(), np.round(np.nan_to_num(W[437]), 3))
    assert np.abs(W[437]).max() > 0.01  # a frame where the face moves: the check means something


@pytest.mark.slow
def test_a_settings_card_makes_its_widgets_when_opened_with_the_current_values():
    """A collapsed settings card makes its widgets only when first opened (dashboard/lazy.py
    ``build``); a setting changed before (by code, or another page of a shot) shows in them, and
    from then on they follow the pipeline both ways."""
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    card = next(c for c, _ in app.sidebar.setting_cards if c.title == "Source & calibration")
    assert card.collapsed and len(card.objects) == 0
    assert not [p for st, p in app.sidebar.setting_panes if st.stage_name == "calibrate"]  # not made yet
    app.pipe.configure(rbf_smoothing=0.03, calibrate=False)
    assert card.visible  # its stages have settings to show
    card.collapsed = False
    panes = [p for st, p in app.sidebar.setting_panes if st.stage_name == "calibrate"]
    assert len(panes) == 1 and panes[0] in card.objects
    w = panes[0]._widgets
    assert w["rbf_smoothing"].value == 0.03 and w["calibrate"].value is False
    w["rbf_smoothing"].value = 0.05  # the widget drives the setting
    assert app.pipe.calibrate.rbf_smoothing == 0.05
    app.pipe.configure(rbf_smoothing=0.01)  # and follows it
    assert w["rbf_smoothing"].value == 0.01
    card.collapsed, card.collapsed = True, False  # made once
    assert len([p for st, p in app.sidebar.setting_panes if st.stage_name == "calibrate"]) == 1


def test_use_as_example_pose_is_in_the_shot_and_auto_learns_from_it(app):
    """The Edit card's *Use as example pose*: the result at this frame with the slider's weight
    becomes a pose of the shot (a take frame), auto plays it there and says so; *Suggest frames
    to pose* shows a frame not posed yet; *Clear poses* empties them."""
    pipe = app.pipe
    pipe.configure(method="auto", controls={}, edits=[])  # the defaults (the module's other tests change them)
    app.refresh()
    assert "auto:" in app.s.snapshot["solve_info"]["auto"]
    f = len(app.s.snapshot["times"]) // 2  # the module's other tests may have shortened the range
    app.playback.w_frame.value = f
    app.edits.w_shape.value = "AK_25_JawOpen"
    app.edits.w_value.value = 0.8
    app.edits.use_as_pose()
    frame = f + app.s.snapshot["first_frame"]
    assert [p["frame"] for p in pipe.solve.example_poses] == [frame]
    assert app.s.shot().settings["solve"]["example_poses"] == pipe.solve.example_poses
    snap = app.s.snapshot
    jaw = snap["target_names"].index("AK_25_JawOpen")
    assert abs(snap["weights"][f, jaw] - 0.8) < 1e-3 and "learned from 1 example pose" in snap["solve_info"]["auto"]
    assert "Example poses at frames" in app.edits.w_poses.object
    app.edits.suggest()
    assert app.playback.w_frame.value != f
    app.edits.clear_poses()
    assert pipe.solve.example_poses == [] and "learned" not in app.s.snapshot["solve_info"]["auto"]


def test_downloads_are_named_after_the_take_the_rig_and_the_method(app):
    """Ten downloads are not ten result.glb: the files carry the take, the rig and the method."""
    app.refresh()
    method = app.s.snapshot["method"]
    stem = f"livelinkface_take_s07_on_rocketbox_female_adult_02_{method}"
    assert app.summary.w_glb.filename == f"{stem}.glb" and app.summary.w_csv.filename == f"{stem}.csv"
