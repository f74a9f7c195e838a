"""The weight-curve plot of the Retarget tab (dashboard/curves_view.py), without a browser."""

import numpy as np


def test_frames_without_data_break_the_curves():
    """Issue 33.6: across a tracking loss the played weights are filled in (linear), and the
    curves were drawn straight across it, like a face at rest; now they break there (NaN)."""
    from types import SimpleNamespace

    from dashboard.curves_view import CurvesView

    T = 10
    t = np.arange(T) / 30.0
    W = np.linspace(0, 1, T)[:, None] * np.array([[1.0, 0.5]])  # the filled-in curves (no NaN)
    valid = np.ones(T, bool)
    valid[4:7] = False
    snap = {"times": t, "weights": W, "valid": valid, "target_names": ["a", "b"], "derived": {},
            "evaluate": {"marker_error_mm": np.zeros(T), "velocity_error_mm_per_frame": np.zeros(T)}}
    view = CurvesView(SimpleNamespace(snapshot=snap), on_seek=lambda s: None, time_of=lambda f: t[f], frame=lambda: 0)
    view.draw(snap)
    ys = view.curves.source.data["ys"]
    assert len(ys) == 2
    for y in ys:
        assert np.isnan(y[4:7]).all() and np.isfinite(y[:4]).all() and np.isfinite(y[7:]).all()


def test_frames_without_data_are_marked_in_the_views(tmp_path):
    """Issue 33.6: a take with tracking loss (frames 100-109 blank): the 3D views are told the
    gap (their label says "no tracking data" there) and the curves break over it."""
    from core.pipeline import StageCache
    from dashboard.app import DashboardApp
    from dashboard.session import Session
    from datapaths import PERFORMANCES

    lines = (PERFORMANCES / "livelinkface_take_s07.csv").read_text().splitlines()
    for i in range(101, 111):  # data lines 100..109 (line 0 is the header)
        cells = lines[i].split(",")
        lines[i] = ",".join(cells[:2] + [""] * (len(cells) - 2))
    s = Session(cache=StageCache())
    s.add_upload("lost.csv", ("\n".join(lines) + "\n").encode())
    app = DashboardApp(s)
    assert app.playback.source_viewer.gaps == [[100, 109]]
    assert app.playback.target_viewer.gaps == [[100, 109]]
    ys = app.curves.curves.source.data["ys"]
    assert all(np.isnan(y[100:110]).all() and np.isfinite(y[90:100]).all() for y in ys)


def test_both_cursors_follow_a_take_switch_and_the_wheel_does_not_zoom_the_plots():
    """Issue 33.7: after a take switch the error plot's cursor stayed at the previous take's
    time of the frame (its frame rate); and scrolling over the curve plot zoomed it."""
    from types import SimpleNamespace

    from dashboard.curves_view import CurvesView

    def snap(T, fps):
        return {"times": np.arange(T) / fps, "weights": np.zeros((T, 1)), "valid": np.ones(T, bool),
                "target_names": ["a"], "derived": {},
                "evaluate": {"marker_error_mm": np.zeros(T), "velocity_error_mm_per_frame": np.zeros(T)}}

    session = SimpleNamespace(snapshot=snap(100, 30.0))
    view = CurvesView(session, on_seek=lambda s: None, time_of=lambda f: session.snapshot["times"][f], frame=lambda: 60)
    view.draw(session.snapshot)
    assert view.curves.cursor.location == view.diag.cursor.location == 2.0
    session.snapshot = snap(100, 60.0)  # the other take, at 60 fps
    view.draw(session.snapshot)
    assert view.curves.cursor.location == view.diag.cursor.location == 1.0
    for fig in (view.curves.fig, view.diag.fig):
        assert fig.toolbar.active_scroll is None


def test_the_error_map_has_a_legend_in_millimetres():
    """Issue 33 item 8: the error map coloured the target with no legend and no units; with the
    map on, a legend says what the colours mean, from 0 mm to the largest error in mm."""
    from core.evaluate import marker_error_field
    from core.pipeline import StageCache
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    pb = app.playback
    assert not pb.w_legend.visible
    pb.w_heat.value = "error map"
    snap = app.s.snapshot
    top = np.nanmax(marker_error_field(snap["target_rig"], snap["target_layout"],
                                       snap["evaluate"]["marker_error_per_marker_mm"]))
    assert pb.w_legend.visible and "0 mm" in pb.w_legend.object and f"{top:.1f} mm" in pb.w_legend.object
    pb.w_heat.value = "plain"
    assert not pb.w_legend.visible
