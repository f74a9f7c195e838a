"""A corpus of bad files sent through the page's upload widget of a running review server (as a
browser sends them: base64 over the websocket), while a second page of the same shot keeps
scrubbing: each file gets a readable message in the uploading page (its name, what is wrong, no
traceback, no server path), the second page is answered throughout, the server logs no error and
the shot is unchanged. Timings: tests/artifacts/review_bad_input.json.

Localhost only; the server is started with ``--max-upload-mb 8`` so that the file over the limit
is small enough to send quickly.
"""

from __future__ import annotations

import asyncio
import base64
import html
import json
import re
import struct
import time
from pathlib import Path

import numpy as np
import pytest

import review_client as rc
from datapaths import PERFORMANCES, RIGS

ART = Path(__file__).resolve().parent / "artifacts"
LIMIT_MB = 8
#: bad files that are still takes (their bad cells masked as invalid, as issue 13 wants): a note
TAKEN = ("text_in_numbers.csv", "nan_inf.csv")


def _glb_parts(data: bytes):
    """(JSON dict, BIN bytes) of a GLB."""
    (n,) = struct.unpack_from("<I", data, 12)
    doc = json.loads(data[20:20 + n])
    rest = data[20 + n:]
    (m,) = struct.unpack_from("<I", rest, 0)
    return doc, rest[8:8 + m]


def _glb(doc: dict, bin_: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    bin_ += b"\0" * (-len(bin_) % 4)
    body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(bin_), b"BIN\0") + bin_
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def corpus(tmp_path) -> list:
    """``(file name, bytes, what the message must say)``: every kind of bad input the issue lists."""
    tiger = (RIGS / "jeeliz_tiger.glb").read_bytes()
    doc, bin_ = _glb_parts(tiger)
    bad = json.loads(json.dumps(doc))
    bad["accessors"][0]["count"] = 10**9  # reads far past its buffer
    take = (PERFORMANCES / "livelinkface_take_s07.csv").read_text().splitlines()
    header, row = take[0], take[1].split(",")
    text_row = list(row)
    text_row[5] = "abc"
    nan_row = list(row)
    nan_row[4], nan_row[6] = "nan", "inf"
    rest = "\n".join(take[2:6]) + "\n"

    from core.io.gltf import read_rig, write_rig
    from core.model import Rig

    r = read_rig(RIGS / "jeeliz_tiger.glb")
    write_rig(tmp_path / "plain.glb", Rig(r.neutral, r.faces, np.zeros((0,) + r.neutral.shape), [], None, "m", "plain"))
    wide = ("Timecode,BlendShapeCount," + ",".join(f"c{i}" for i in range(10**6)) + "\n").encode()
    over = (header + "\n" + "\n".join(take[1:]) + "\n").encode()
    over = over * (LIMIT_MB * 2**20 // len(over) + 2)
    return [
        ("truncated.glb", tiger[:len(tiger) // 3], "truncated.glb"),
        ("garbage.glb", b"glTF" + bytes(range(256)) * 40, "garbage.glb"),
        ("out_of_range.glb", _glb(bad, bin_), "out_of_range.glb"),
        # a real take's bad cells are masked, not fatal (issue 13): taken, and the note says which
        ("text_in_numbers.csv", (header + "\n" + ",".join(text_row) + "\n" + rest).encode(), "1 non-numeric cells at lines 2"),
        ("nan_inf.csv", (header + "\n" + ",".join(nan_row) + "\n" + rest).encode(), "2 nan/inf cells at lines 2"),
        ("million_columns.csv", wide, "million_columns.csv has a first line of more than 4 MB"),
        ("empty.csv", b"", "empty.csv is empty"),
        ("utf16.csv", (header + "\n" + take[1] + "\n" + rest).encode("utf-16"), "utf16.csv is UTF-16 text"),
        ("latin1.csv", ("Timecode,BlendShapeCount,Mâchoire\n00:00:00:01.0,1,0.5\n").encode("latin-1"), "latin1.csv is not UTF-8 text"),
        ("zero_frames.csv", (header + "\n").encode(), "zero_frames.csv"),
        ("no_shapes.glb", (tmp_path / "plain.glb").read_bytes(), "no_shapes.glb has no blend shapes"),
        ("over_limit.csv", over, "over_limit.csv is"),
        ("../../escape.csv", (header + "\n").encode(), "escape.csv"),
    ]


@pytest.mark.slow
def test_bad_files_get_messages_and_the_other_page_is_served(tmp_path):
    from core.store import Store

    rc.register_models()
    data = tmp_path / "data"
    sid = rc.sample_shot(data, "bad input")
    store = Store(data)
    before = store.get(sid)[0].to_json()
    store.close()
    cases = corpus(tmp_path)
    ART.mkdir(exist_ok=True)
    log = ART / "server_review_bad_input.log"
    out: dict = {}

    with rc.Server("--data-dir", str(data), "--max-upload-mb", str(LIMIT_MB), log=log) as srv:
        async def run():
            texts: dict = {"a": [], "b_frames": {}}

            def on_patch(page, changes, t):
                for mid, attr, new in changes:
                    if page.index == 0 and attr == "text" and isinstance(new, str) and ("Error:" in new or "Note:" in new):
                        texts["a"].append((t, new))
                    if page.index == 1 and attr == "frame":
                        texts["b_frames"][new] = t

            pages, _ = await rc.open_pages(srv.base, sid, 2, on_patch=on_patch)
            a, b = pages
            upload = a.one("FileInput")
            guard = next(m for m in a.doc.models if getattr(m, "class_name", None) == "UploadGuard")
            b_frame = b.one("Slider", title="Frame")
            f = 0
            for name, payload, want in cases:
                n0 = len(texts["a"])
                t0 = time.monotonic()
                if len(payload) <= LIMIT_MB * 2**20:  # the guard's script announces a file it lets through
                    a.send_msg(guard, {"starting": name, "size": len(payload)})
                a.set(upload, value=base64.b64encode(payload).decode(), filename=name, mime_type="text/csv")
                # the other page scrubs while the server reads the file: it must be answered
                b_waits = []

                def fresh():  # the first note after this upload started is this file's (test_a_new_upload_clears...)
                    return texts["a"][n0:]

                while not fresh() and time.monotonic() - t0 < 60:
                    f = (f + 7) % 290 + 1
                    ts = time.monotonic()
                    b.set(b_frame, value=f, value_throttled=f)
                    while f not in texts["b_frames"] and time.monotonic() - ts < 30:
                        await asyncio.sleep(0.02)
                    assert f in texts["b_frames"], f"{name}: the other page got no answer for 30 s"
                    b_waits.append(texts["b_frames"][f] - ts)
                    await asyncio.sleep(0.2)
                assert fresh(), f"{name}: no message in the page within 60 s"
                t_msg, msg = fresh()[0]
                plain = re.sub(r"<[^>]+>", "", html.unescape(msg))
                out[name] = dict(bytes=len(payload), message_s=round(t_msg - t0, 2), other_page_max_s=round(max(b_waits), 2),
                                 message=plain[:300])
                print(f"{name}: {out[name]}")
                kind = "Note:" if name in TAKEN else "Error:"
                assert plain.startswith(kind) and want in plain, (name, plain)
                assert "Traceback" not in plain and "/tmp/" not in plain and "face-retarget-upload" not in plain, plain
            for p in pages:
                await p.close()
            return pages

        pages = rc.run(run())
        assert srv.alive()
        assert not [e for p in pages for e in p.errors]
    (ART / "review_bad_input.json").write_text(json.dumps(out, indent=2) + "\n")
    errors = [ln for ln in log.read_text(errors="replace").splitlines() if re.search(r"\bERROR\b", ln)]
    assert not errors, "\n".join(errors[:10])
    # a refused file changes nothing in the shot (only the takes that were taken became its source)
    # and nothing escaped the data folder
    store = Store(data)
    shot = store.get(sid)[0]
    store.close()
    old = json.loads(before)
    assert {k: v for k, v in json.loads(shot.to_json())["files"].items() if k != "source"} == \
        {k: v for k, v in old["files"].items() if k != "source"}
    assert shot.files["source"].path.endswith(TAKEN[-1]) or shot.files["source"].path == old["files"]["source"]["path"]
    assert not (tmp_path / "escape.csv").exists() and not (data.parent / "escape.csv").exists()


@pytest.mark.slow
def test_a_new_upload_clears_the_old_note_and_gets_its_own(tmp_path):
    """The browser sends an upload as three messages (content, then file name, then type); a loaded
    server may read them apart (here the name comes 0.3 s after the content). The next file's
    content must not be read under the previous file's name (before: the previous note came back,
    "truncated.glb: ..." about garbage.glb's bytes): the page's upload guard announces the file's
    name as it starts, the old note goes then, and the new file's own message is the first note."""
    rc.register_models()
    data = tmp_path / "data"
    sid = rc.sample_shot(data, "two uploads", last_frame=59)
    tiger = (RIGS / "jeeliz_tiger.glb").read_bytes()
    files = [("truncated.glb", tiger[:len(tiger) // 3]), ("garbage.glb", b"glTF" + bytes(range(256)) * 40)]

    ART.mkdir(exist_ok=True)
    with rc.Server("--data-dir", str(data), log=ART / "server_review_two_uploads.log") as srv:
        async def run():
            notes, shown = [], []

            def on_patch(page, changes, t):
                for mid, attr, new in changes:
                    if attr == "text" and isinstance(new, str) and ("Error:" in new or "Note:" in new):
                        notes.append(re.sub(r"<[^>]+>", "", html.unescape(new)))
                    if attr == "visible" and mid == alert_id[0]:
                        shown.append((len(notes), new))

            alert_id = [None]
            (a,), _ = await rc.open_pages(srv.base, sid, 1, on_patch=on_patch)
            alert_id[0] = next(m.id for m in a.doc.models if "fr-error" in (getattr(m, "css_classes", None) or []))
            upload = a.one("FileInput")
            guard = next(m for m in a.doc.models if getattr(m, "class_name", None) == "UploadGuard")
            seen = []
            for name, payload in files:
                n0 = len(notes)
                a.send_msg(guard, {"starting": name, "size": len(payload)})  # the guard's script, as the input changes
                a.set(upload, value=base64.b64encode(payload).decode())
                await asyncio.sleep(0.3)  # the server reads the name a moment later
                a.set(upload, filename=name, mime_type="model/gltf-binary")
                t0 = time.monotonic()
                while len(notes) == n0 and time.monotonic() - t0 < 60:
                    await asyncio.sleep(0.05)
                await asyncio.sleep(1.0)  # anything else the page is sent for this upload
                seen.append((n0, list(notes[n0:])))
            await a.close()
            return seen, shown

        (first, second), shown = rc.run(run())
        assert srv.alive()
    assert first[1] and first[1][0].startswith("Error:") and "truncated.glb" in first[1][0], first
    n0, after = second
    assert after and after[0].startswith("Error:") and "garbage.glb" in after[0], after
    assert not [m for m in after if "truncated.glb" in m], after  # the old note never came back
    assert (n0, False) in shown, (shown, first, second)  # hidden when the second upload started, before its note
