"""The sidebar's marker card (dashboard.marker_layout_view): moving a marker by two clicks on the
target view, without a browser (the page's host is a stand-in; the session is real)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from core.pipeline import StageCache
from dashboard.marker_layout_view import MarkerLayoutView
from dashboard.session import Session


class _Viewer:
    def __init__(self):
        self.pick_mode, self.highlight = "off", []

    def set_highlight(self, ids):
        self.highlight = list(ids)


@pytest.fixture
def card(tmp_path):
    s = Session(cache=StageCache())
    s._upload_dir = tmp_path
    s.snapshot = dict(s.pipeline.results(["target_face"])["target_face"])
    viewer = _Viewer()
    host = SimpleNamespace(s=s, refresh=lambda: s.snapshot.update(s.pipeline.results(["target_face"])["target_face"]),
                           playback=SimpleNamespace(target_viewer=viewer, forget_target=lambda: None),
                           notify=lambda *a: None)
    view = MarkerLayoutView(host)
    view._widgets()
    return view, s, viewer


def _click(view, vertex):
    view.on_target_pick(SimpleNamespace(new={"vertex": int(vertex)}))


def test_one_move_then_move_mode_is_off_and_undo_puts_it_back(card):
    """Issue 33 item 8: after a move, move mode stayed on (a later stray click picked and moved
    another marker) and a move could not be undone."""
    view, s, viewer = card
    layout0 = s.snapshot["target_layout"]
    rig = s.snapshot["target_rig"]
    name = layout0.names[0]
    at = int(layout0.vertices[0, 0])
    other = int(np.argmax(np.linalg.norm(rig.neutral - rig.neutral[at], axis=1)))  # the vertex farthest from it
    view.w_move.value = True
    assert viewer.pick_mode == "vertex"
    _click(view, at)
    _click(view, other)
    moved = s.snapshot["target_layout"]
    assert moved.vertices[0].tolist() == [other] * 3
    assert not view.w_move.value and viewer.pick_mode == "off"  # move mode is off after one move
    _click(view, int(layout0.vertices[1, 0]))  # a later click moves nothing
    assert view._pick is None
    assert not view.w_undo.disabled
    view.w_undo.clicks += 1  # the Undo button
    back = s.snapshot["target_layout"]
    np.testing.assert_array_equal(back.vertices, layout0.vertices)
    np.testing.assert_allclose(back.weights, layout0.weights, atol=1e-12)
    assert view.w_undo.disabled
