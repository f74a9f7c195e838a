"""``kill -9`` of a review server in the middle of a burst of edits and notes from a page: after a
restart on the same data directory every edit and note the page had been shown (acknowledged) is
in the shot, the database passes ``PRAGMA integrity_check``, and a new page shows them.

Localhost only, one page, bounded (at most 40 actions, a minute in all).
"""

from __future__ import annotations

import asyncio
import json
import re

import pytest

import review_client as rc


@pytest.mark.slow
def test_kill_minus_9_during_a_burst_keeps_every_acknowledged_change(tmp_path):
    from core.store import Store

    rc.register_models()
    data = tmp_path / "data"
    sid = rc.sample_shot(data, "crash")
    acked: dict = {}   # what the page was shown: note text / edit text -> time
    sent: list = []

    srv = rc.Server("--data-dir", str(data), "--warm-pages", "0")  # the burst, not warm-page builds, on the loop
    try:
        async def burst():
            def on_patch(page, changes, t):
                blob = json.dumps([c[2] for c in changes], default=str)
                for what in sent:
                    if what not in acked and what in blob:
                        acked[what] = t

            (page,), _ = await rc.open_pages(srv.base, sid, 1, on_patch=on_patch)
            note_box = page.one("TextAreaInput", placeholder=re.compile("a note at this frame"))
            note_button = page.one("Button", label=re.compile("^Add note"))
            frame = page.one("Slider", title="Frame")
            value = page.one("Slider", title="Weight at this frame")
            pose = page.one("Button", label="Set pose at this frame")
            for k in range(40):
                if k % 2 == 0:
                    text = f"burst note {k}"
                    sent.append(text)
                    page.set(note_box, value=text)
                    await asyncio.sleep(0.06)
                    page.click(note_button)
                else:
                    f, v = 20 + 6 * k, round(0.3 + 0.01 * k, 2)
                    # the edit row starts so (its Markdown arrives rendered: no backtick); the
                    # frame is checked below
                    sent.append(f"frame {f}: ")
                    page.set(frame, value=f, value_throttled=f)
                    page.set(value, value=v, value_throttled=v)
                    await asyncio.sleep(0.06)
                    page.click(pose)
                await asyncio.sleep(0.15)
                if len(acked) >= 12:
                    break
            srv.proc.kill()  # SIGKILL: no shutdown, no flush, mid-burst
            srv.proc.wait(timeout=10)
            await page.close()

        rc.run(burst())
    finally:
        srv.stop()
    assert len(acked) >= 12, f"only {len(acked)} of {len(sent)} changes were shown before the kill"

    store = Store(data)
    try:
        assert store.integrity_check() == "ok"
        shot, version = store.get(sid)
        notes = {n["text"] for n in shot.notes}
        edit_frames = {int(e["frame"]) for e in shot.edits["spacetime"].done}
    finally:
        store.close()
    for what in acked:
        if what.startswith("burst note"):
            assert what in notes, f"acknowledged note {what!r} lost by the kill"
        else:
            f = int(what.split()[1].rstrip(":"))
            assert f in edit_frames, f"acknowledged edit at frame {f} lost by the kill"
    print(f"sent {len(sent)}, acknowledged {len(acked)}, stored {len(notes)} notes and {len(edit_frames)} edits "
          f"(version {version})")

    # a restarted server shows them to a new page
    with rc.Server("--data-dir", str(data)) as srv2:
        async def look():
            (page,), _ = await rc.open_pages(srv2.base, sid, 1)
            await asyncio.sleep(1.0)
            # the notes list's rows are data (review_view.NotesList), the rest text
            texts = " ".join(str(getattr(m, "text", "")) + str(getattr(m, "notes", "")) for m in page.doc.models) + json.dumps(
                list(page.values.values()), default=str)
            await page.close()
            return texts

        texts = rc.run(look())
    for what in acked:
        if what.startswith("burst note"):
            assert what in texts, f"{what!r} not on the restarted server's page"
