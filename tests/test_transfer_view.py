"""The dense-transfer editing view (dashboard/transfer_view.py), driven through its params and
widgets without a browser: a drag on the viewer (its ``dragged`` param, as the browser sets it)
becomes a point constraint, Apply appends a large-scale edit to the shot (the pipeline's
``transfer_edit`` stage runs core's editor), the viewer gets the new bases/weights; undo
restores them.

Fast tests use a same-topology transfer of the tiger through the pipeline (no registration,
tests/dense_case.py); the slow one runs the real ICT → Rocketbox transfer of a Live Link take.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.pipeline import StageCache
from core.transfer.edit import LargeScaleEditor, PointConstraint
from dense_case import T as FRAMES
from dense_case import tiger_files


def shown(result_neutral, D, W):
    """(T, V, 3) the frames of the shown rig: neutral + W @ D."""
    return result_neutral[None] + np.einsum("tk,kvc->tvc", W, D)


@pytest.fixture(scope="module")
def tiger_case(tmp_path_factory):
    return tiger_files(tmp_path_factory.mktemp("tiger"))


@pytest.fixture
def view(tiger_case):
    from dashboard.session import Session
    from dashboard.transfer_view import TransferView

    s = Session(cache=CACHE)
    s.use_files(**tiger_case)
    s.pipeline.configure(transfer_max_bases=8, transfer_last_frame=-1)
    v = TransferView(s)
    assert v.run(block=True), v.status
    assert v.result is not None, v.status
    return v


CACHE = StageCache()  # the tests share the transfer; each view starts with empty edit lists


@pytest.fixture
def tiger_transfer(view):
    return view.result


def moving_vertex(res, frame):
    """The vertex that moves most over the sequence, and the frame where it is farthest from
    its position at ``frame`` (a target the weights can reach)."""
    S = shown(res.neutral, res.deltas, res.weights)
    v = int(np.argmax(np.linalg.norm(S - S.mean(0), axis=2).max(0)))
    f2 = int(np.argmax(np.linalg.norm(S[:, v] - S[frame, v], axis=1)))
    return v, f2, S


def drag(viewer, vertex, frame, start, end, count=1):
    """What the browser sends at the end of a drag in pick mode."""
    viewer.dragged = {"vertex": int(vertex), "frame": int(frame), "start": [float(x) for x in start],
                      "end": [float(x) for x in end], "count": count}


def test_the_view_shows_the_pipelines_transfer(view, tiger_transfer):
    res = tiger_transfer
    assert len(res.weights) == FRAMES and view.viewer.n_shapes == res.n_bases and res.n_bases <= 8
    assert view.viewer.pick_mode == "vertex" and view.first_frame == 0
    # the registration and transfer are the pipeline's cached stages: running again computes nothing
    runs = dict(view.pipe.runs)
    assert view.run(block=True)
    assert dict(view.pipe.runs) == runs
    assert view.editor.consistency() < 1e-9


def test_drag_becomes_a_point_constraint_and_apply_edits_the_window(view, tiger_transfer):
    res = tiger_transfer
    T = len(res.weights)
    f = 20
    v, f2, S = moving_vertex(res, f)
    start, target = S[f, v], S[f2, v]
    assert np.linalg.norm(target - start) > 1e-3 * 0.25  # the test needs a real move (tiger ~0.25 m)
    view.w_lam_b.value = 0.0  # weights only: frames outside the window must not change at all
    view.w_half.value = 4
    drag(view.viewer, v, f, start, target)
    assert view.pending == [{"kind": "point", "frame": f, "vertex": v, "target": target.tolist(), "start": start.tolist()}]
    assert view.viewer.highlight == [v]
    assert view.window() == (16, 24)
    assert view.apply_edit(), view.status
    D1, W1 = view.state
    after = res.neutral[v] + W1[f] @ D1[:, v]
    miss0, miss1 = np.linalg.norm(start - target), np.linalg.norm(after - target)
    assert miss1 < 0.5 * miss0, f"vertex did not move towards the target: {miss0 * 1e3:.2f} -> {miss1 * 1e3:.2f} mm"
    outside = np.r_[0:16, 25:T]
    np.testing.assert_array_equal(W1[outside], res.weights[outside])
    np.testing.assert_array_equal(D1, res.deltas)
    S1 = shown(res.neutral, D1, W1)
    np.testing.assert_array_equal(S1[outside], S[outside])
    assert not np.allclose(S1[16:25], S[16:25])
    # the viewer plays the edited weights; constraints are consumed, the edit is listed
    np.testing.assert_allclose(view.viewer.track, W1.astype(np.float32))
    assert view.pending == [] and view.viewer.highlight == []
    (spec,) = view.pipe.transfer_edit.transfer_edits  # the edit is in the shot, as plain data
    assert spec == {"constraints": [{"kind": "point", "frame": f, "vertex": v, "target": target.tolist()}],
                    "window": [16, 24], "lam_b": 0.0, "lam_w": 1.0, "lam_e": 100.0}
    assert view.session.shot().edits["transfer"].done == [spec]
    # the same edit by core's editor directly (the view only glues): identical weights
    e = view.editor
    ed = LargeScaleEditor(e.transfer, np.asarray(res.neutral)[e.rep], np.asarray(res.deltas)[:, e.rep], res.weights)
    direct = ed.edit([PointConstraint(f, int(e.welded_index[v]), tuple(target))], 0.0, 1.0, 100.0, (16, 24))
    np.testing.assert_allclose(direct.weights, W1, rtol=0, atol=1e-12)

    # a second edit with λ_b > 0 edits the bases (every frame using them moves) but not the
    # weights outside the window; the viewer gets the new deltas
    view.w_lam_b.value = 1.0
    f = 30
    v2, f3, _ = moving_vertex(res, f)
    S1f = S1[f, v2]
    target2 = S1f + 0.5 * (S[f3, v2] - S1f)
    drag(view.viewer, v2, f, S1f, target2, count=2)
    assert view.apply_edit(), view.status
    D2, W2 = view.state
    after2 = res.neutral[v2] + W2[f] @ D2[:, v2]
    assert np.linalg.norm(after2 - target2) < 0.5 * np.linalg.norm(S1f - target2)
    assert not np.allclose(D2, D1)
    out2 = np.r_[0:26, 35:T]
    np.testing.assert_array_equal(W2[out2], W1[out2])
    np.testing.assert_allclose(view.viewer.deltas, D2.astype(np.float32))

    # undo twice: back to the transfer, in the viewer too; redo brings the first edit back
    assert view.undo()
    np.testing.assert_array_equal(view.state[1], W1)
    np.testing.assert_allclose(view.viewer.deltas, D1.astype(np.float32))
    assert view.undo() and not view.undo()
    np.testing.assert_allclose(view.viewer.track, res.weights.astype(np.float32))
    assert view.pipe.transfer_edit.transfer_edits == [] and len(view.pipe.redo["transfer"]) == 2
    assert view.redo()
    np.testing.assert_array_equal(view.state[1], W1)


def test_distance_and_fixed_constraints(view, tiger_transfer):
    res = tiger_transfer
    f = 12
    S = shown(res.neutral, res.deltas, res.weights)
    # two vertices across the mouth: the most moving vertex of the sequence and its farthest partner nearby
    v, _, _ = moving_vertex(res, f)
    near = np.argsort(np.linalg.norm(res.neutral - res.neutral[v], axis=1))[1:200]
    j = int(near[np.argmax(np.linalg.norm(S[:, near] - S[:, [v]], axis=2).std(0))])
    view.w_mode.value = "distance"
    view.viewer.picked = {"vertex": v, "frame": f, "position": S[f, v].tolist(), "count": 1}
    assert view.w_add_distance.disabled
    view.viewer.picked = {"vertex": j, "frame": f, "position": S[f, j].tolist(), "count": 2}
    d0 = np.linalg.norm(S[f, v] - S[f, j])
    assert view.w_distance.value == pytest.approx(d0 * 1000, abs=1e-3)
    assert not view.w_add_distance.disabled and sorted(view.viewer.highlight) == sorted([v, j])
    view.w_distance.value = round(d0 * 1000 * 1.3, 3)
    view.add_distance()
    # and a fixed vertex elsewhere (point mode, fixed on: a click pins it)
    view.w_mode.value = "point"
    view.w_fixed.value = True
    far = int(np.argmax(np.linalg.norm(res.neutral - res.neutral[v], axis=1)))
    view.viewer.picked = {"vertex": far, "frame": f, "position": S[f, far].tolist(), "count": 3}
    assert [p["kind"] for p in view.pending] == ["distance", "fixed"]
    view.w_lam_b.value = 1.0
    view.w_half.value = 0  # whole range
    assert view.window() is None
    assert view.apply_edit(), view.status
    D1, W1 = view.state
    S1 = shown(res.neutral, D1, W1)
    d1 = np.linalg.norm(S1[f, v] - S1[f, j])
    want = d0 * 1.3
    assert abs(d1 - want) < 0.5 * abs(d0 - want), f"distance {d0 * 1e3:.2f} -> {d1 * 1e3:.2f} mm, wanted {want * 1e3:.2f}"
    assert np.linalg.norm(S1[f, far] - S[f, far]) < 0.1 * abs(d1 - d0), "the fixed vertex moved"


def test_apply_without_constraints_and_update_without_results(view):
    assert not view.apply_edit()
    assert "nothing to apply" in view.status
    view.update({})  # no snapshot yet: nothing to do, no error


@pytest.mark.slow
def test_ict_to_rocketbox_run_then_drag_edit():
    """The real thing: Session on the Live Link take (ICT drives, Rocketbox target), the
    transfer of 30 frames (non-rigid ICP: tens of seconds), a drag at one frame."""
    from dashboard.session import Session
    from dashboard.transfer_view import TransferView

    session = Session()
    session.param.update(source="livelinkface_take_s07.csv", source_rig="ict_facekit.glb",
                         target_rig="rocketbox_female_adult_02.glb")
    assert session.recompute(), session.error
    view = TransferView(session)
    view.update(session.snapshot)
    assert view.w_range.value == (0, 299) and not view.w_run.disabled
    view.w_range.value = (600, 629)
    session.pipeline.configure(transfer_iterations=30)  # the settings card's widgets set these
    assert view.run(block=True), view.status
    assert view.result is not None, view.status
    res = view.result
    assert res.weights.shape[0] == 30 and res.n_bases >= 1
    assert res.registration is not None and res.registration.report["landmark_residual_mm_mean"] < 5
    assert view.editor.consistency() < 1e-8
    lines = session.pipeline.results(["deform"])["deform"]["feature_lines"]
    assert lines is not None and len(lines) == 3  # 2 eyes + mouth
    assert view.viewer.n_shapes == res.n_bases and view.viewer.pick_mode == "vertex"
    assert view.first_frame == 600 and "30 frames" in view.status

    f = 15
    v, f2, S = moving_vertex(res, f)
    start, target = S[f, v], S[f2, v]
    assert np.linalg.norm(target - start) > 0.5e-3, "ICT → Rocketbox: expected a vertex that moves > 0.5 mm"
    view.w_lam_b.value = 0.0
    view.w_half.value = 5
    drag(view.viewer, v, f, start, target)
    assert view.apply_edit(), view.status
    D1, W1 = view.state
    after = res.neutral[v] + W1[f] @ D1[:, v]
    assert np.linalg.norm(after - target) < 0.5 * np.linalg.norm(start - target)
    outside = np.r_[0:10, 21:30]
    np.testing.assert_array_equal(W1[outside], res.weights[outside])
    np.testing.assert_array_equal(D1, res.deltas)
    np.testing.assert_allclose(view.viewer.track, W1.astype(np.float32))
    # a second take of the same actor onto the same rig reuses the registration
    runs = session.pipeline.runs["register"]
    view.w_range.value = (700, 719)
    assert view.run(block=True) and session.pipeline.runs["register"] == runs


def busiest_vertex(view, frame):
    """The rig vertex with the largest detail coating at ``frame`` on a smooth part of the
    surface (the brush around it faces one way: not an eyelid rim or a lip edge)."""
    ed = view.details.current()
    N = ed.normals(frame)
    r = view.details.w_radius.value / 1000
    for v in np.argsort(-np.linalg.norm(ed.coating(frame), axis=1)):
        if (N[ed.select_paint([v], r, frame)] @ N[v]).min() > 0.8:
            return int(ed.rep[v])
    raise AssertionError("no smooth vertex with details")


def test_details_shown_on_the_paused_frame(view, tiger_transfer):
    res = tiger_transfer
    v = view.viewer
    assert res.details is not None and view.details.editor is not None
    np.testing.assert_array_equal(v.offsets, res.details[0].astype(np.float32))
    v.frame = 17
    np.testing.assert_array_equal(v.offsets, res.details[17].astype(np.float32))
    v.playing = True
    assert v.offsets is None  # the rig only while playing
    v.playing = False
    np.testing.assert_array_equal(v.offsets, res.details[17].astype(np.float32))
    view.details.w_show.value = False
    assert v.offsets is None


def test_detail_scale_edit_from_clicks_then_undo(view, tiger_transfer):
    res = tiger_transfer
    k = 20
    vtx = busiest_vertex(view, k)
    view.w_tool.value = "detail selection"
    view.viewer.picked = {"vertex": vtx, "frame": k, "position": [0.0, 0.0, 0.0], "count": 1}
    assert view.pending == [] and view.details.picks == [vtx] and view.details.key_frame == k
    assert view.viewer.colors is not None  # the selection is coloured
    n_sel = int((np.abs(view.viewer.colors - np.float32([1.0, 0.6, 0.02])).sum(1) < 1e-6).sum())
    assert n_sel > 1
    view.details.w_factor.value = 0.0
    view.details.w_lam_e.value = 100.0
    assert view.details.apply(), view.status
    new = view.current_details
    assert len(view.pipe.detail_edit.detail_edits) == 1 and "scale ×0" in view.status
    # the same edit by core directly: identical details
    ed = view.details.editor
    region = ed.select_paint(ed.to_editor([vtx]), view.details.w_radius.value / 1000, k)
    direct = ed.apply(ed.scale(region, k, 0.0), lam_e=100.0, propagation="per_frame")
    np.testing.assert_array_equal(new, direct.details)
    ts, te = direct.window
    assert ts <= k <= te
    changed = np.flatnonzero(np.abs(new - res.details).reshape(len(new), -1).max(1) > 0)
    assert changed.min() >= ts and changed.max() <= te and k in changed
    # the region's details at the key frame are mostly gone
    after = view.details.current()
    assert after.activity(region)[k] < 0.2 * ed.activity(region)[k]
    # shown: the viewer's offsets are the edited details of its frame; bases/weights unchanged
    view.viewer.frame = k
    np.testing.assert_array_equal(view.viewer.offsets, new[k])
    np.testing.assert_array_equal(view.state[0], res.deltas)
    assert view.undo("detail")
    np.testing.assert_array_equal(view.viewer.offsets, res.details[k].astype(np.float32))


def test_detail_copy_paste_and_reshape_from_clicks(view, tiger_transfer):
    res = tiger_transfer
    k = 20
    vtx = busiest_vertex(view, k)
    view.w_tool.value = "detail selection"
    view.details.w_op.value = "copy-paste"
    view.viewer.picked = {"vertex": vtx, "frame": k, "position": [0.0, 0.0, 0.0], "count": 1}
    assert not view.details.apply() and "paste anchor" in view.status
    # an anchor 2-5 cm away on a part of the face that faces the same way
    ed = view.details.current()
    N = ed.normals(k)[ed.wi]
    dist = np.linalg.norm(res.neutral - res.neutral[vtx], axis=1)
    far = int(np.flatnonzero((dist > 0.02) & (dist < 0.05) & (N @ N[vtx] > 0.95))[0])
    view.w_tool.value = "paste anchor"
    view.viewer.picked = {"vertex": far, "frame": k, "position": res.neutral[far].tolist(), "count": 2}
    assert far in view.viewer.highlight
    assert view.details.apply(), view.status
    pasted = view.current_details[k] - res.details[k]
    assert np.linalg.norm(pasted[far]) > 0 and "copy-paste" in view.status
    # reshape: the wrinkle as a curve through two vertices near the busiest one, a target beside it
    view.details.clear()
    view.details.w_op.value = "reshape wrinkle"
    view.details.w_select.value = "curve"
    view.w_tool.value = "detail selection"
    near = np.argsort(np.linalg.norm(res.neutral - res.neutral[vtx], axis=1))
    a, b = vtx, int(near[np.searchsorted(np.sort(np.linalg.norm(res.neutral - res.neutral[vtx], axis=1)), 0.01)])
    for n, x in enumerate((a, b)):
        view.viewer.picked = {"vertex": x, "frame": k, "position": res.neutral[x].tolist(), "count": 3 + n}
    assert not view.details.apply() and "wrinkle target" in view.status
    view.w_tool.value = "wrinkle target"
    shift = np.array([0.0, 0.004, 0.0])
    for n, x in enumerate((a, b)):
        view.viewer.picked = {"vertex": x, "frame": k, "position": (res.neutral[x] + shift).tolist(), "count": 5 + n}
    before = view.current_details
    assert view.details.apply(), view.status
    assert "reshape" in view.status and [e["op"] for e in view.pipe.detail_edit.detail_edits] == ["copy_paste", "reshape"]
    assert not np.array_equal(view.current_details, before)


def test_detail_paint_stroke_from_a_drag(view, tiger_transfer):
    res = tiger_transfer
    k = 20
    a = busiest_vertex(view, k)
    ed = view.details.current()
    X = ed.surface(k)[ed.wi]
    dist = np.linalg.norm(res.neutral - res.neutral[a], axis=1)
    b = int(np.flatnonzero((dist > 0.02) & (dist < 0.03))[0])
    view.w_tool.value = "detail selection"
    # the browser reports the drag's end in the view plane: a little off the surface
    view.viewer.dragged = {"vertex": a, "frame": k, "start": X[a].tolist(), "end": (X[b] + [0, 0, 0.001]).tolist(),
                           "count": 1}
    assert view.pending == [] and view.details.picks == [a, b] and view.details.strokes == [(a, b)]
    region = view.details.region(ed)
    r = view.details.w_radius.value / 1000
    along = ed.select_curve(ed.to_editor([a, b]), r, k)
    assert set(along) <= set(region) and len(region) > len(ed.select_paint(ed.to_editor([a, b]), r, k))
    # the large-scale tool still turns drags into point constraints
    view.w_tool.value = "large-scale constraint"
    view.viewer.dragged = {"vertex": a, "frame": k, "start": X[a].tolist(), "end": X[b].tolist(), "count": 2}
    assert len(view.pending) == 1 and view.pending[0]["kind"] == "point"


def test_details_play_along_as_morph_targets(view, tiger_transfer):
    res = tiger_transfer
    v = view.viewer
    K, T = res.n_bases, len(res.weights)
    view.details.w_play.value = True
    C, B, err = view.details.morphs()
    assert v.n_shapes == K + len(B) and v.track.shape == (T, K + len(B)) and v.offsets is None
    assert v.shape_names[K:] == [f"detail_{j:02d}" for j in range(len(B))]
    assert v.shape_names[:K] == list(res.to_rig().names)  # the bases keep the names the viewer opened with
    # what the browser blends, frame by frame, is the transfer with its details (to the stated error)
    shown = v.neutral[None] + np.einsum("tk,kvc->tvc", v.track, v.deltas)
    want = res.neutral[None] + np.einsum("tk,kvc->tvc", res.weights, res.deltas) + res.details
    miss = np.linalg.norm(shown - want, axis=2).max()
    top = np.linalg.norm(res.details, axis=2).max()
    assert 0 < err <= 0.05 * top and miss <= err + 1e-6
    assert "extra morph targets" in view.status
    # a detail edit re-factors; undo goes back; unticking restores the plain rig and offsets
    k = 20
    view.w_tool.value = "detail selection"
    view.viewer.picked = {"vertex": busiest_vertex(view, k), "frame": k, "position": [0.0, 0.0, 0.0], "count": 1}
    assert view.details.apply(), view.status
    shown = v.neutral[None] + np.einsum("tk,kvc->tvc", v.track, v.deltas)
    want = res.neutral[None] + np.einsum("tk,kvc->tvc", res.weights, res.deltas) + view.current_details
    assert np.linalg.norm(shown - want, axis=2).max() <= view.details.morphs()[2] + 1e-6
    view.details.w_play.value = False
    assert v.n_shapes == K and np.array_equal(v.track, res.weights.astype(np.float32))
    v.frame = k
    np.testing.assert_array_equal(v.offsets, view.current_details[k])
