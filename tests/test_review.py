"""Shared review without a browser: two pages (dashboard apps) of one shot on one review
server see each other's settings, edits, notes and frame; a stale write is rebased or refused,
never lost; a restart of the server (a new store on the same folder) keeps everything."""

import numpy as np
import pytest

from core.pipeline import StageCache


@pytest.fixture
def server(tmp_path):
    from dashboard import review

    srv = review.configure(tmp_path / "data")
    yield srv
    review.SERVER = None
    srv.store.close()


def page(server, sid, name):
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    hub = server.hub(sid)
    s = Session(cache=CACHE)
    s.open_shot(hub.shot, locate=server.store.locate)
    return DashboardApp(s, hub=hub, reviewer=name)


CACHE = StageCache()


@pytest.fixture
def shot_id(server):
    from dashboard.session import Session

    s = Session(cache=CACHE)
    s.pipeline.configure(last_frame=299)
    return server.create(s.shot(), title="test", author="lead")


def test_two_pages_see_each_others_changes(server, shot_id):
    a, b = page(server, shot_id, "ana"), page(server, shot_id, "bo")
    assert sorted(server.hub(shot_id).participants.values()) == ["ana", "bo"]
    # a setting
    a.pipe.configure(alpha=0.05)
    assert b.pipe.solve.alpha == 0.05
    np.testing.assert_array_equal(a.s.snapshot["weights"], b.s.snapshot["weights"])
    # an edit, and its undo
    a.playback.w_frame.value = 150
    a.edits.w_shape.value = "AK_25_JawOpen"
    a.edits.w_value.value = 0.6
    a.edits.add()
    assert b.pipe.edit.edits == a.pipe.edit.edits and len(b.pipe.edit.edits) == 1
    np.testing.assert_array_equal(a.s.snapshot["weights"], b.s.snapshot["weights"])
    b.edits.undo()
    assert a.pipe.edit.edits == [] and a.pipe.redo["spacetime"]
    # a note at a frame, resolved from the other page
    a.review.w_note.value = "jaw opens late"
    assert a.review.add_note()
    (note,) = b.pipe.notes
    assert note["text"] == "jaw opens late" and note["frame"] == 150 and note["author"] == "ana"
    b.mirror.set_note(note["id"], True)
    assert a.pipe.notes[0]["resolved"]
    # the notes list is one model whose rows are data: a resolved note leaves the shown rows
    # (unless asked for), its buttons come back as actions (reopen, jump to its frame)
    assert a.review.w_notes.notes == [] and b.review.w_notes.notes == []
    b.review.w_show_resolved.value = True
    (row,) = b.review.w_notes.notes
    assert row["text"] == "jaw opens late" and row["author"] == "ana" and row["frame"] == 150 and row["resolved"]
    b.review.w_notes.action = {"op": "reopen", "id": note["id"], "frame": 150, "n": 1}
    assert not a.pipe.notes[0]["resolved"] and [r["text"] for r in a.review.w_notes.notes] == ["jaw opens late"]
    b.playback.w_frame.value = 10
    b.review.w_notes.action = {"op": "jump", "id": note["id"], "frame": 150, "n": 2}
    assert b.playback.w_frame.value == 150
    # text is text: markup in a note reaches the other page as the characters typed
    a.review.w_note.value = "<img src=x onerror=alert(1)> **bold**"
    assert a.review.add_note()
    assert "<img src=x onerror=alert(1)> **bold**" in [r["text"] for r in b.review.w_notes.notes]
    # the presenter's frame: b follows a
    a.review.w_present.value = True
    a.playback.w_frame.value = 200
    a.review._on_own_frame()
    assert b.playback.w_frame.value == 200


def test_a_stale_change_is_rebased_or_refused_with_a_message(server, shot_id):
    a, b = page(server, shot_id, "ana"), page(server, shot_id, "bo")
    hub = server.hub(shot_id)
    seen = []
    b.mirror.notify = lambda kind, msg: seen.append(msg)
    v = b.mirror.version
    a.pipe.configure(alpha=0.07)
    # b writes on the version it saw before a's change: another setting rebases, the same one is refused
    b.mirror.version = v
    assert b.mirror._send({"kind": "settings", "values": {"solve": {"beta": 0.1}}})
    b.mirror.version = v
    assert not b.mirror._send({"kind": "settings", "values": {"solve": {"alpha": 0.2}}})
    assert seen and "alpha" in seen[-1] and "ana" in seen[-1]
    shot, _ = server.store.get(shot_id)
    assert shot.settings["solve"]["alpha"] == 0.07 and shot.settings["solve"]["beta"] == 0.1
    assert b.pipe.solve.alpha == 0.07  # the refused page shows the shot as it is


def test_everything_survives_a_restart(server, shot_id, tmp_path):
    from dashboard import review

    a = page(server, shot_id, "ana")
    a.pipe.configure(alpha=0.04)
    a.review.w_note.value = "keep me"
    a.review.add_note()
    a.pipe.add_edit("spacetime", {"frame": 100, "weights": {"AK_25_JawOpen": 0.5}, "window": [90, 110]})
    W = a.s.snapshot["weights"].copy()
    server.store.close()
    again = review.configure(server.data_dir)
    b = page(again, shot_id, "bo")
    assert b.pipe.solve.alpha == 0.04 and b.pipe.notes[0]["text"] == "keep me" and len(b.pipe.edit.edits) == 1
    np.testing.assert_array_equal(b.s.snapshot["weights"], W)
    again.store.close()


def test_the_review_downloads_as_one_file_and_opens_on_another_server(server, shot_id, tmp_path):
    """Download the review (.zip) from a page; a landing page of another server imports it."""
    from dashboard import review
    from dashboard.review_view import landing

    a = page(server, shot_id, "ana")
    a.review.w_note.value = "check the blink"
    assert a.review.add_note()
    data = a.review._export_bytes().read()
    other = review.ReviewServer(tmp_path / "other")
    try:
        ui = landing(other, lambda: None)
        upload = [w for w in ui.select(__import__("panel").widgets.FileInput)][0]
        upload.param.update(filename="review.zip", value=data)
        (sid,) = [r["id"] for r in other.store.recent(5)]
        shot, _ = other.store.get(sid)
        assert [n["text"] for n in shot.notes] == ["check the blink"]
        assert shot.content_hash() == server.store.get(shot_id)[0].content_hash()
        # a file that is not an export: a message on the landing page, nothing imported
        upload.param.update(filename="notes.zip", value=b"PK not really")
        status = [p for p in ui.select(__import__("panel").pane.Markdown) if "Error" in str(p.object)]
        assert status and "notes.zip" in status[0].object
        assert len(other.store.recent(5)) == 1
    finally:
        other.store.close()


def test_the_participants_line_counts_pages_that_share_a_name():
    from dashboard.review_view import people_text

    assert people_text(["bo", "ana"]) == "Here now: ana, bo"
    assert people_text(["someone", "someone", "ana"], "ana") == "Here now: ana, someone ×2 · presenting: **ana**"
    assert people_text([]) == "Here now: just you"
    assert people_text(["<b>x</b>"]) == "Here now: &lt;b&gt;x&lt;/b&gt;"


def test_recent_shots_say_when_in_words():
    """Issue 33 item 8: the recent shots showed the store's raw timestamp (1796...)."""
    import time

    from dashboard.review_view import when_text

    now = time.mktime((2026, 12, 4, 15, 0, 0, 0, 0, -1))
    assert when_text(time.mktime((2026, 12, 4, 14, 3, 0, 0, 0, -1)), now) == "today 14:03"
    assert when_text(time.mktime((2026, 12, 3, 9, 12, 0, 0, 0, -1)), now) == "yesterday 09:12"
    assert when_text(time.mktime((2026, 11, 28, 8, 5, 0, 0, 0, -1)), now) == "28 Nov 2026 08:05"
    assert when_text(None) == ""


def test_the_recent_shots_list_shows_the_time_in_words():
    import time
    from types import SimpleNamespace

    from dashboard.review_view import _start

    t = time.time()
    server = SimpleNamespace(store=SimpleNamespace(recent=lambda n: [{"id": "abc", "title": "take one", "updated": t}]))
    recent = _start(server, make_shot=lambda: None, label="New")[-1].object
    assert f"today {time.strftime('%H:%M', time.localtime(t))}" in recent and str(t) not in recent, recent


def test_a_page_of_its_own_becomes_the_shared_shot_in_place_and_takes_a_review_zip(server, shot_id):
    """The sidebar's Shared review card (collapsed until used) makes a shot of what the page
    shows and the page joins it without a reload (issue 32 item 3); a review .zip dropped into
    the page's one upload box is imported and opened on the page (item 1)."""
    import panel as pn

    from dashboard.app import DashboardApp
    from dashboard.lazy import fill
    from dashboard.review_view import review_start
    from dashboard.session import Session

    app = DashboardApp(Session(cache=CACHE))
    card = review_start(server, app.s.shot, on_open=app.open_shared)
    app.sidebar.review_slot[:] = [card]
    assert card.collapsed and not card.objects, "the review card is collapsed and empty until used"
    assert not fill(card).select(pn.widgets.FileInput), "one upload box on the page: the card has none of its own"
    app.s.pipeline.configure(last_frame=199)
    (new,) = [b for b in card.select(pn.widgets.Button) if b.name.startswith("New shared shot")]
    new.clicks += 1
    assert app.mirror is not None and app.review is not None
    sid = app.review.hub.shot_id
    assert sid != shot_id and server.store.get(sid)[0].settings["frames"]["last_frame"] == 199
    assert app.sidebar.review_slot.objects == [app.review.card]
    # a change on this page now reaches the shot
    app.s.pipeline.configure(last_frame=149)
    assert server.hub(sid).shot.settings["frames"]["last_frame"] == 149

    # a review .zip through the one upload box: imported and opened on a page of its own
    data = page(server, shot_id, "ana").review._export_bytes().read()
    other = DashboardApp(Session(cache=CACHE))
    other.sidebar.w_upload.param.update(filename="review.zip", value=data)
    assert other.mirror is not None and other.review.hub.shot_id not in (shot_id, sid)
    assert other.s.pipeline.shot().content_hash() == server.store.get(shot_id)[0].content_hash()
    assert "review.zip opened" in other.w_alert.object
    # not an export: a message naming it, nothing opened
    third = DashboardApp(Session(cache=CACHE))
    third.sidebar.w_upload.param.update(filename="notes.zip", value=b"PK not really")
    assert third.mirror is None and "notes.zip" in third.w_alert.object and "Error" in third.w_alert.object
