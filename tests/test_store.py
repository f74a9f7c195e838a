"""The review store (core/store.py): schema and migrations, the concurrency rule, export/import,
the data directory's safety, and durability under kill -9."""

import ast
import io
import json
import os
import select
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import platformdirs
import pytest

from core import store as store_mod
from core.changes import replay_edits, safe_name
from core.pipeline import shot_from_settings
from core.shot import EDITORS, FileRef, Shot, file_hash
from core.store import MAX_UPLOAD, SCHEMA_VERSION, Conflict, Store, UnknownShot, UnsafePath, UploadTooLarge, data_dir
from datapaths import PERFORMANCES, RIGS, ROOT

WRITER = ROOT / "tests" / "store_writer.py"
EVIL = "'; DROP TABLE shots; --"
POSE = {"frame": 30, "weights": {"mouthOpen": 0.5}, "window": [20, 40]}


def small_shot(store, **kw) -> Shot:
    """A shot with a stored source file and settings of two stages (what the tests change)."""
    sha = store.put_file(b"time,jawOpen\n0,0.1\n1,0.2\n", "take.csv")
    return Shot(files={"source": FileRef("take.csv", sha)},
                settings={"solve": {"method": "spacetime", "alpha": 0.01, "beta": 0.0},
                          "frames": {"first_frame": 0, "last_frame": -1}}, **kw)


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "data")
    yield s
    s.close()


@pytest.fixture
def shot_id(store):
    return store.create_shot(small_shot(store), "take 7", "ana")


def add_edit(editor="spacetime", **edit):
    return {"kind": "edit", "editor": editor, "op": "add", "edit": {**POSE, **edit}}


def setting(**values):
    return {"kind": "settings", "values": values}


# -- schema, documents, histories --------------------------------------------------------------------
def test_schema_wal_foreign_keys_one_writer_and_random_ids(store, shot_id):
    assert store.journal_mode == "wal" and store.schema_version() == SCHEMA_VERSION
    assert store._db.execute("PRAGMA foreign_keys").fetchone()[0] == 1
    assert store._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    tables = {r[0] for r in store._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"schema_version", "shots", "changes", "settings_history", "edits", "notes", "participants", "files",
            "file_names", "folder_members", "shot_files"} <= tables
    assert len(shot_id) == 16  # token_urlsafe(12): 96 random bits
    other = store.create_shot(small_shot(store), "take 8", "ana")
    assert other != shot_id and [r["id"] for r in store.recent(5)] == [other, shot_id]
    with pytest.raises(sqlite3.IntegrityError):  # foreign keys are enforced
        store._db.execute("INSERT INTO notes (shot_id, note_id, frame, author, text, created, updated) "
                          "VALUES ('nope', 'n1', 0, 'a', 't', 0, 0)")


def test_settings_edits_and_notes_are_queryable_and_the_log_replays_every_version(store, shot_id):
    changes = [
        ("ana", setting(alpha=0.05)),
        ("bob", add_edit(frame=10)),
        ("bob", add_edit(frame=20)),
        ("ana", {"kind": "edit", "editor": "spacetime", "op": "undo"}),
        ("ana", add_edit("transfer", frame=3)),
        ("bob", {"kind": "edit", "editor": "spacetime", "op": "redo"}),
        ("bob", {"kind": "edit", "editor": "spacetime", "op": "remove", "index": 0}),
        ("ana", {"kind": "settings", "values": {"frames": {"last_frame": 99}, "solve": {"beta": 0.5}}}),
        ("cy", {"kind": "note", "op": "add", "frame": 12, "frame_end": 20, "text": "jaw late"}),
        ("ana", {"kind": "frame", "frame": 12}),
        ("ana", {"kind": "note", "op": "resolve", "note_id": "n1"}),
    ]
    seen = {1: store.get(shot_id)[0].to_dict()}
    for who, ch in changes:
        _, version = store.get(shot_id)
        a = store.apply(shot_id, ch, version, who)
        assert a.version == version + 1 and not a.rebased
        seen[a.version] = a.shot.to_dict()
    shot, version = store.get(shot_id)
    assert version == 1 + len(changes) and shot.to_dict() == seen[version]
    assert shot.edits["spacetime"].done == [{**POSE, "frame": 20}] and shot.edits["spacetime"].undone == [{**POSE, "frame": 10}]
    assert shot.settings["solve"] == {"method": "spacetime", "alpha": 0.05, "beta": 0.5} and shot.frame == 12
    for v, doc in seen.items():  # every version replays from the log
        assert store.at_version(shot_id, v).to_dict() == doc, v
    hist = store.settings_history(shot_id)
    assert [(h["version"], h["author"], h["stage"], h["setting"], h["old"], h["new"]) for h in hist] == [
        (2, "ana", "solve", "alpha", 0.01, 0.05), (9, "ana", "frames", "last_frame", -1, 99), (9, "ana", "solve", "beta", 0.0, 0.5)]
    assert store.settings_history(shot_id, setting="alpha")[0]["new"] == 0.05
    rows = store.edit_history(shot_id)
    assert [(r["editor"], r["op"]) for r in rows] == [("spacetime", "add"), ("spacetime", "add"), ("spacetime", "undo"),
                                                      ("transfer", "add"), ("spacetime", "redo"), ("spacetime", "remove")]
    lists = replay_edits(rows)
    assert all(lists[e].to_dict() == shot.edits[e].to_dict() for e in EDITORS)
    notes = store.notes(shot_id)
    assert [(n["id"], n["frame"], n["frame_end"], n["author"], n["text"], n["resolved"]) for n in notes] == [
        ("n1", 12, 20, "cy", "jaw late", True)]
    assert shot.notes[0]["resolved"] is True and store.notes(shot_id, unresolved_only=True) == []
    assert [h["summary"] for h in store.history(shot_id, since=10)] == ["moved the review to frame 12", "resolved note n1"]
    assert {p["name"] for p in store.participants(shot_id)} == {"ana", "bob", "cy"}


def test_created_edit_lists_and_notes_are_kept(store):
    shot = small_shot(store, notes=[{"frame": 12, "author": "lead", "text": "jaw late"}])
    shot.edits["spacetime"].done = [POSE]
    shot.edits["spacetime"].undone = [{**POSE, "frame": 1}, {**POSE, "frame": 2}]
    sid = store.create_shot(shot, "t", "ana")
    got, _ = store.get(sid)
    assert got.edits["spacetime"].to_dict() == shot.edits["spacetime"].to_dict()
    assert replay_edits(store.edit_history(sid))["spacetime"].to_dict() == shot.edits["spacetime"].to_dict()
    assert got.content_hash() == shot.content_hash()
    assert [(n["id"], n["author"], n["frame_end"], n["resolved"]) for n in got.notes] == [("n1", "lead", None, False)]
    a = store.apply(sid, {"kind": "edit", "editor": "spacetime", "op": "redo"}, 1, "ana")
    assert a.shot.edits["spacetime"].done == [POSE, {**POSE, "frame": 2}]


def test_noops_make_no_version_and_bad_changes_name_the_field(store, shot_id):
    for ch in (setting(alpha=0.01), {"kind": "frame", "frame": 0}):
        a = store.apply(shot_id, ch, 1, "ana")
        assert a.change is None and a.version == 1
    a = store.apply(shot_id, setting(alpha=0.01, beta=2.0), 1, "ana")  # only beta changes
    assert a.change["values"] == {"solve": {"beta": 2.0}}
    bad = [({"kind": "setings"}, "did you mean 'settings'"),
           (setting(alpah=0.1), "did you mean 'alpha'"),
           ({"kind": "settings", "values": {"solve": {"gamma": 1}}}, "solve.gamma is not a setting"),
           (setting(alpha=float("nan")), "not plain JSON"),
           ({"kind": "edit", "editor": "spacetim", "op": "add", "edit": {}}, "did you mean 'spacetime'"),
           ({"kind": "edit", "editor": "spacetime", "op": "undo"}, "nothing to undo"),
           ({"kind": "edit", "editor": "spacetime", "op": "remove", "index": 3}, "does not exist"),
           ({"kind": "note", "op": "add", "frame": 5}, "needs 'frame' and 'text'"),
           ({"kind": "note", "op": "add", "frame": 5, "frame_end": 2, "text": "x"}, "before frame"),
           ({"kind": "note", "op": "resolve", "note_id": "n7"}, "no note 'n7'"),
           ({"kind": "frame", "frame": -1}, "integer >= 0"),
           ({"kind": "files", "values": {"source": "0" * 32}}, "upload it first")]
    for ch, msg in bad:
        with pytest.raises(ValueError, match=msg):
            store.apply(shot_id, ch, 2, "ana")
    with pytest.raises(ValueError, match="versions 1 to 2"):
        store.apply(shot_id, setting(alpha=0.3), 3, "ana")
    with pytest.raises(UnknownShot):
        store.apply("nope-nope-nope", setting(alpha=0.3), 1, "ana")
    assert store.get(shot_id)[1] == 2  # nothing else was written


def test_shot_dicts_without_copies_hold_the_same_data_and_the_default_still_copies():
    shot = Shot(files={"source": FileRef("a.csv", "0" * 32)}, settings={"solve": {"alpha": 0.1, "shapes": ["a", "b"]}},
                frame=4, notes=[{"id": "n1", "frame": 2, "text": "x"}])
    shot.edits["spacetime"].add(POSE)
    shot.edits["spacetime"].add({**POSE, "frame": 40})
    shot.edits["spacetime"].undo()
    doc = shot.to_dict()
    assert shot.to_dict(copy=False) == doc
    assert Shot.from_dict(json.loads(json.dumps(doc)), copy=False).to_dict() == doc
    shared = shot.to_dict(copy=False)
    assert shared["settings"] is shot.settings and shared["edits"]["spacetime"]["done"] is shot.edits["spacetime"].done
    fresh = Shot.from_dict(doc)  # the default copies: changing it leaves doc alone
    fresh.settings["solve"]["shapes"].append("c")
    fresh.edits["spacetime"].done[0]["weights"]["mouthOpen"] = 1.0
    fresh.notes[0]["text"] = "y"
    assert doc == shot.to_dict() and doc["settings"]["solve"]["shapes"] == ["a", "b"]
    old = {"alpha": 0.1}  # a version-0 document is still migrated when copy=False
    with pytest.raises(ValueError, match="unknown settings"):
        Shot.from_dict({"nonsense": 1}, copy=False, flat=shot_from_settings)
    assert Shot.from_dict(old, copy=False, flat=shot_from_settings).settings["solve"]["alpha"] == 0.1


def test_check_hook_refuses_before_commit(tmp_path):
    def check(shot):
        if shot.settings["solve"]["alpha"] < 0:
            raise ValueError("alpha must be >= 0")

    with Store(tmp_path / "d", check=check) as s:
        sid = s.create_shot(small_shot(s), "t", "ana")
        with pytest.raises(ValueError, match="alpha must be"):
            s.apply(sid, setting(alpha=-1.0), 1, "ana")
        assert s.get(sid)[1] == 1 and s.history(sid)[-1]["version"] == 1


def test_a_real_pipeline_shot_keeps_working_after_a_restart_from_the_store_alone(tmp_path):
    from core.pipeline import Pipeline, StageCache

    inputs = tmp_path / "uploads"
    inputs.mkdir()
    files = {}
    for key, src in (("source", PERFORMANCES / "livelinkface_take_s07.csv"), ("source_rig", RIGS / "ict_facekit.glb"),
                     ("target_rig", RIGS / "jeeliz_tiger.glb")):
        files[key] = str(shutil.copy(src, inputs / src.name))
    shutil.copy(ROOT / "data/layouts/jeeliz_tiger.json", inputs / "jeeliz_tiger.layout.json")  # the rig's sidecar layout
    pipe = Pipeline(cache=StageCache(), method="spacetime", alpha=0.05, last_frame=59, **files)
    pipe.add_edit("spacetime", POSE)
    shot = pipe.shot()
    keys = {name: pipe.key(name) for name in pipe.stages}
    with Store(tmp_path / "data") as s:
        sid = s.create_shot(shot, "take s07 on the tiger", "ana")
    shutil.rmtree(inputs)  # the upload folder is gone, the server restarts
    with Store(tmp_path / "data") as s:
        again, version = s.get(sid)
        assert version == 1 and again.content_hash() == shot.content_hash() and s.missing_files(sid) == {}
        other = Pipeline.from_shot(again, cache=StageCache(), locate=s.locate)
        root = os.path.realpath(s.root)
        for role in shot.files:
            found = again.resolve(role, locate=s.locate)
            assert os.path.realpath(found).startswith(root + os.sep) and Path(found).name == Path(shot.files[role].path).name
    cfg = other.config()
    assert {name: other.key(name, _cfg=cfg) for name in other.stages} == keys
    assert other.edits("spacetime").done == [POSE] and other.solve.alpha == 0.05


# -- concurrency ------------------------------------------------------------------------------------------
REBASE_CASES = [
    # (what others applied since v1, what the stale writer sends, expected: "rebased" | "conflict" | "noop")
    (setting(beta=1.0), setting(alpha=0.5), "rebased"),
    (setting(alpha=0.2), setting(alpha=0.5), "conflict"),
    (setting(alpha=0.5), setting(alpha=0.5), "noop"),
    (add_edit(frame=1), add_edit(frame=2), "rebased"),
    (add_edit("transfer", frame=1), {"kind": "edit", "editor": "spacetime", "op": "undo"}, "rebased"),
    ({"kind": "edit", "editor": "spacetime", "op": "undo"}, add_edit(frame=2), "conflict"),
    (add_edit(frame=1), {"kind": "edit", "editor": "spacetime", "op": "undo"}, "conflict"),
    (add_edit(frame=1), {"kind": "edit", "editor": "spacetime", "op": "remove", "index": 0}, "conflict"),
    ({"kind": "frame", "frame": 7}, {"kind": "frame", "frame": 9}, "rebased"),
    (setting(alpha=0.2), {"kind": "note", "op": "add", "frame": 3, "text": "x"}, "rebased"),
    ({"kind": "note", "op": "add", "frame": 4, "text": "y"}, {"kind": "note", "op": "add", "frame": 3, "text": "x"}, "rebased"),
    ({"kind": "note", "op": "edit", "note_id": "n1", "text": "jaw very late"}, {"kind": "note", "op": "resolve", "note_id": "n1"},
     "conflict"),
    ({"kind": "note", "op": "resolve", "note_id": "n1"}, {"kind": "note", "op": "resolve", "note_id": "n1"}, "noop"),
    ({"kind": "note", "op": "resolve", "note_id": "n1"}, {"kind": "note", "op": "edit", "note_id": "n2", "text": "z"}, "rebased"),
]


@pytest.mark.parametrize("theirs, mine, expected", REBASE_CASES)
def test_a_stale_change_rebases_where_it_commutes_and_is_refused_naming_the_conflict(store, theirs, mine, expected):
    shot = small_shot(store, notes=[{"frame": 1, "text": "jaw late"}, {"frame": 2, "text": "blink"}])
    shot.edits["spacetime"].done = [POSE]
    sid = store.create_shot(shot, "t", "ana")
    t = store.apply(sid, theirs, 1, "bob")
    assert t.version == 2
    if expected == "conflict":
        with pytest.raises(Conflict) as e:
            store.apply(sid, mine, 1, "cy")
        assert e.value.version == 2 and e.value.author == "bob" and e.value.head == 2
        assert "bob" in str(e.value) and "version 2" in str(e.value) and "Reload" in str(e.value)
        assert store.get(sid)[1] == 2
        return
    a = store.apply(sid, mine, 1, "cy")
    if expected == "noop":
        assert a.change is None and a.version == 2
        return
    assert a.rebased and a.version == 3
    # the result is the change applied on top of theirs: the same as a writer who had seen version 2
    ref = Store(store.root / "ref")
    rid = ref.create_shot(shot, "t", "ana")
    ref.apply(rid, theirs, 1, "bob")
    b = ref.apply(rid, mine, 2, "cy").shot
    ref.close()
    assert b.content_hash() == a.shot.content_hash() and b.frame == a.shot.frame
    assert [(n["id"], n["text"], n["resolved"]) for n in b.notes] == [(n["id"], n["text"], n["resolved"]) for n in a.shot.notes]
    row = store.history(sid)[-1]
    assert row["base_version"] == 1 and row["version"] == 3


def test_conflict_message_names_the_setting_author_and_version(store, shot_id):
    store.apply(shot_id, setting(alpha=0.2), 1, "bob")
    with pytest.raises(Conflict, match=r"solve\.alpha changed since: bob set solve\.alpha to 0\.2 in version 2"):
        store.apply(shot_id, setting(alpha=0.5, beta=1.0), 1, "cy")
    assert store.get(shot_id)[0].settings["solve"]["beta"] == 0.0  # all or nothing


def test_two_writers_race_on_one_shot(tmp_path):
    """Two writers with their own connections (as two server processes) start every round from
    the same version: notes and edit adds all land (one of each pair rebased), same-setting
    writes apply once and are refused once, naming the other; nothing is lost or duplicated."""
    data = tmp_path / "data"
    with Store(data) as s:
        sid = s.create_shot(small_shot(s), "race", "lead")
    rounds = 25
    barrier = threading.Barrier(2, timeout=30)
    results = {"ana": [], "bob": []}
    errors = []

    def writer(name, value):
        try:
            with Store(data) as st:
                for i in range(rounds):
                    for ch in ({"kind": "note", "op": "add", "frame": i, "text": f"{name} {i}"},
                               add_edit(frame=i, writer=name),
                               setting(alpha=value + i)):
                        barrier.wait()
                        _, base = st.get(sid)
                        barrier.wait()  # both hold the same base version now
                        try:
                            a = st.apply(sid, ch, base, name)
                            results[name].append((ch["kind"], "applied", a.rebased))
                        except Conflict as e:
                            results[name].append((ch["kind"], "conflict", e.author))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))
            barrier.abort()

    threads = [threading.Thread(target=writer, args=("ana", 1.0)), threading.Thread(target=writer, args=("bob", 100.0))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors and not any(t.is_alive() for t in threads)
    with Store(data) as s:
        shot, version = s.get(sid)
        assert sorted(n["text"] for n in shot.notes) == sorted(f"{w} {i}" for w in ("ana", "bob") for i in range(rounds))
        assert sorted((e["writer"], e["frame"]) for e in shot.edits["spacetime"].done) == sorted(
            (w, i) for w in ("ana", "bob") for i in range(rounds))
        for kind in ("note", "edit"):
            got = [r for w in results for r in results[w] if r[0] == kind]
            assert all(r[1] == "applied" for r in got) and sum(r[2] for r in got) == rounds  # one of each pair rebased
        sets = [(w, r) for w in results for r in results[w] if r[0] == "settings"]
        assert sum(r[1] == "applied" for _, r in sets) == rounds and sum(r[1] == "conflict" for _, r in sets) == rounds
        assert all(r[2] == ("bob" if w == "ana" else "ana") for w, r in sets if r[1] == "conflict")
        hist = s.history(sid)
        assert [h["version"] for h in hist] == list(range(1, version + 1)) and version == 1 + 3 * 2 * rounds - rounds
        last = [h for h in hist if h["kind"] == "settings"][-1]
        assert shot.settings["solve"]["alpha"] == last["change"]["values"]["solve"]["alpha"]
        assert s.integrity_check() == "ok"


def _read_lines(proc, until, timeout):
    """stdout lines of ``proc`` until ``until(lines)`` or EOF or ``timeout`` seconds."""
    lines, buf, end = [], b"", time.monotonic() + timeout
    fd = proc.stdout.fileno()
    while not until(lines) and time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            break
        chunk = os.read(fd, 65536)
        if not chunk:
            break
        buf += chunk
        *done, buf = buf.split(b"\n")
        lines += [d.decode() for d in done]
    return lines, buf


def _writer(data, sid, label, count, wait=False):
    return subprocess.Popen([sys.executable, str(WRITER), str(data), sid, label, str(count)] + (["wait"] if wait else []),
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.PIPE if wait else subprocess.DEVNULL)


def test_two_writer_processes_race(tmp_path):
    data = tmp_path / "data"
    with Store(data) as s:
        sid = s.create_shot(small_shot(s), "race", "lead")
    n = 40
    procs = [_writer(data, sid, label, n, wait=True) for label in ("p1", "p2")]
    try:
        for p in procs:  # both started and opened the store
            assert _read_lines(p, lambda ls: bool(ls), 60)[0][:1] == [f"READY {'p1' if p is procs[0] else 'p2'}"]
        for p in procs:
            p.stdin.write(b"go\n")
            p.stdin.flush()
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            p.kill() if p.poll() is None else None
    assert all(p.returncode == 0 for p in procs), [o[1].decode()[-2000:] for o in outs]
    with Store(data) as s:
        shot, version = s.get(sid)
        assert version == 1 + 2 * 2 * n
        assert sorted((e["writer"], e["i"]) for e in shot.edits["spacetime"].done) == sorted(
            (w, i) for w in ("p1", "p2") for i in range(n))
        assert len({n_["id"] for n_ in shot.notes}) == 2 * n and len(s.notes(sid)) == 2 * n
        rebased = sum(h["base_version"] < h["version"] - 1 for h in s.history(sid))
        assert rebased > 0  # both began from version 1: the later one's first change at least was rebased
        assert s.integrity_check() == "ok"
        print(f"two processes: {version - 1} changes, {rebased} rebased")


# -- durability ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kill_after, delay", [(37, 0.0), (150, 0.0031), (300, 0.0117)])
def test_kill_9_mid_burst_loses_no_acknowledged_change(tmp_path, kill_after, delay):
    data = tmp_path / "data"
    with Store(data) as s:
        sid = s.create_shot(small_shot(s), "burst", "lead")
    proc = _writer(data, sid, "w", 5000)  # stops by itself after 5000 iterations if not killed
    try:
        lines, _ = _read_lines(proc, lambda ls: sum(line.startswith("ACK") for line in ls) >= kill_after, 60)
        time.sleep(delay)  # land somewhere else in the write cycle
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        more, tail = _read_lines(proc, lambda ls: False, 5)  # what it printed before it died
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    acks = [line.split() for line in lines + more if line.startswith("ACK")]
    edits = {int(a[2]) for a in acks if a[3] == "edit"}
    notes = {(int(a[2]), a[5]) for a in acks if a[3] == "note"}
    assert len(acks) >= kill_after
    with Store(data) as s:
        assert s.integrity_check() == "ok"
        shot, version = s.get(sid)
        done = {e["i"] for e in shot.edits["spacetime"].done}
        texts = {n["id"]: n["text"] for n in s.notes(sid)}
        found_edits = edits & done
        found_notes = {(i, nid) for i, nid in notes if texts.get(nid) == f"w {i}"}
        max_acked = max(int(a[4]) for a in acks)
        assert found_edits == edits and found_notes == notes and version >= max_acked
        assert replay_edits(s.edit_history(sid))["spacetime"].to_dict() == shot.edits["spacetime"].to_dict()
        unacked = version - 1 - len(acks)  # committed but killed before it could print: at most one
        assert 0 <= unacked <= 1
    print(f"kill -9 after {kill_after}: {len(acks)} acknowledged ({len(edits)} edits, {len(notes)} notes), "
          f"{len(found_edits) + len(found_notes)} found, {unacked} committed unacknowledged, integrity ok")


# -- export / import ------------------------------------------------------------------------------------------
def _busy_shot(store):
    sid = store.create_shot(small_shot(store), "take 7", "ana")
    for who, ch in [("ana", setting(alpha=0.05)), ("bob", add_edit(frame=3)),
                    ("bob", {"kind": "note", "op": "add", "frame": 3, "frame_end": 9, "text": "lip sync off"}),
                    ("ana", {"kind": "note", "op": "resolve", "note_id": "n1"}), ("ana", {"kind": "frame", "frame": 3})]:
        store.apply(sid, ch, store.get(sid)[1], who)
    return sid


def test_export_import_gives_the_same_shot_notes_history_and_files(store, tmp_path):
    sid = _busy_shot(store)
    path = tmp_path / "take7.review.zip"
    review = store.export(sid, path)
    assert review["with_files"] and set(zipfile.ZipFile(path).namelist()) == {
        "shot.json", "review.json", "history.json", f"files/{store.get(sid)[0].files['source'].sha}"}
    with Store(tmp_path / "elsewhere") as other:
        got = other.import_(path)
        assert got == sid
        a, b = store.get(sid), other.get(got)
        assert a[0].to_dict() == b[0].to_dict() and a[1] == b[1] and a[0].content_hash() == b[0].content_hash()
        assert other.notes(got) == store.notes(sid)
        assert other.history(got) == store.history(sid) and other.settings_history(got) == store.settings_history(sid)
        assert other.edit_history(got) == store.edit_history(sid)
        assert other.info(got)["title"] == "take 7"
        ref = b[0].files["source"]
        assert file_hash(other.locate("source", ref)) == ref.sha and other.missing_files(got) == {}
        copy_id = other.import_(path)  # a second import is a copy under a new id
        assert copy_id != got and other.get(copy_id)[0].to_dict() == b[0].to_dict()
        buf = io.BytesIO()  # to and from file objects (a download, an upload)
        other.export(got, buf)
        buf.seek(0)
        assert other.get(other.import_(buf))[0].content_hash() == a[0].content_hash()


def test_light_export_names_files_by_hash_and_links_them_when_uploaded(store, tmp_path):
    sid = _busy_shot(store)
    path = tmp_path / "light.zip"
    store.export(sid, path, with_files=False)
    assert not any(n.startswith("files/") for n in zipfile.ZipFile(path).namelist())
    with Store(tmp_path / "elsewhere") as other:
        got = other.import_(path)
        shot, _ = other.get(got)
        assert shot.content_hash() == store.get(sid)[0].content_hash() and other.notes(got) == store.notes(sid)
        assert set(other.missing_files(got)) == {"source"}
        with pytest.raises(FileNotFoundError, match="not in the review store"):
            other.locate("source", shot.files["source"])
        other.put_file(b"time,jawOpen\n0,0.1\n1,0.2\n", "whatever-name.csv")
        assert other.missing_files(got) == {} and Path(other.locate("source", shot.files["source"])).name == "take.csv"


def test_folders_are_stored_by_member_and_round_trip(store, tmp_path):
    seq = tmp_path / "capture"
    seq.mkdir()
    for i in range(3):
        (seq / f"frame_{i:04d}.obj").write_text(f"v {i} 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n")
    (seq / "sequence.json").write_text('{"fps": 30}')
    sha = file_hash(seq)
    assert store.put_path(seq) == sha and store.file_info(sha)["kind"] == "folder"
    shot = small_shot(store)
    shot.files["source"] = FileRef(str(seq), sha)
    sid = store.create_shot(shot, "4D", "ana")
    view = store.locate("source", shot.files["source"])
    assert Path(view).is_dir() and file_hash(view) == sha and Path(view).name == "capture"
    store.export(sid, tmp_path / "4d.zip")
    with Store(tmp_path / "elsewhere") as other:
        got = other.import_(tmp_path / "4d.zip")
        assert file_hash(other.locate("source", other.get(got)[0].files["source"])) == sha


def test_import_refuses_a_tampered_archive_and_ignores_paths_in_member_names(store, tmp_path):
    sid = _busy_shot(store)
    good = tmp_path / "good.zip"
    store.export(sid, good)
    src = zipfile.ZipFile(good)
    sha = store.get(sid)[0].files["source"].sha

    def rewrite(name, edit):
        out = tmp_path / name
        with zipfile.ZipFile(out, "w") as z:
            for n in src.namelist():
                data = edit(n, src.read(n))
                if data is not None:
                    z.writestr(n, data)
        return out

    swapped = rewrite("swapped.zip", lambda n, d: b"other bytes" if n.startswith("files/") else d)
    edited = rewrite("edited.zip", lambda n, d: d.replace(b'"alpha": 0.05', b'"alpha": 9.0') if n == "shot.json" else d)
    outside = tmp_path / "outside"
    outside.mkdir()
    traversal = rewrite("traversal.zip", lambda n, d: d)
    with zipfile.ZipFile(traversal, "a") as z:
        z.writestr("../outside/evil.txt", b"x")
        z.writestr(str(outside / "abs.txt"), b"x")
        z.writestr("files/../../outside/evil2.txt", b"x")
        z.writestr(f"files/{sha}/../../evil3", b"x")
    with Store(tmp_path / "elsewhere") as other:
        with pytest.raises(ValueError, match="hashes to"):
            other.import_(swapped)
        with pytest.raises(ValueError, match="does not reproduce shot.json"):
            other.import_(edited)
        assert other.recent() == []  # neither came in (the edited one's file did: it is sound, and unused)
        with pytest.raises(ValueError, match="not a review archive"):
            other.import_(io.BytesIO(b"not a zip"))
        got = other.import_(traversal)  # the extra members are never read, let alone extracted
        assert other.get(got)[0].content_hash() == store.get(sid)[0].content_hash()
    assert sorted(p.name for p in outside.iterdir()) == [] and not (tmp_path / "evil3").exists()
    assert not any(p.name.startswith("evil") for p in tmp_path.rglob("*"))


# -- security of the data directory -------------------------------------------------------------------------------
def test_every_server_side_path_stays_inside_the_data_directory(store, shot_id):
    for parts in (("..",), ("files", ".."), ("/etc",), ("files", "/etc/passwd"), ("a/b",), ("a\\b",), ("x\0y",), ("",)):
        with pytest.raises(UnsafePath):
            store._path(*parts)
    sha = store.put_file(b"secret?", "../../../../etc/passwd")
    assert store.file_info(sha)["names"] == ["passwd"] and safe_name("C:\\Users\\x\\take.csv") == "take.csv"
    assert safe_name("..") == "file" and safe_name("a\x00b\n.csv") == "ab.csv"
    root = os.path.realpath(store.root) + os.sep
    for path in ("../../etc/passwd", "/etc/passwd", "..", "", "a/../../b.csv"):
        view = store.locate("source", FileRef(path, sha))
        assert os.path.realpath(view).startswith(root), path
    for bad in ("../../etc/passwd", "/etc/passwd", "0" * 31 + "/", "A" * 32):
        with pytest.raises(ValueError, match="not a content hash"):
            store.locate("source", FileRef("x.csv", bad))
    with pytest.raises(UnsafePath):
        store._put_folder({"../x": sha}, "f")


def test_symlinks_cannot_lead_out_of_the_data_directory(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "d1").mkdir()
    os.symlink(outside, tmp_path / "d1" / "files")  # the blob folder itself
    with pytest.raises(UnsafePath):
        Store(tmp_path / "d1")
    s = Store(tmp_path / "d2")
    data = b"a blob"
    sha = file_hash_bytes(data)
    os.symlink(outside, s.root / "files" / sha[:2])  # one fan-out folder
    with pytest.raises(UnsafePath):
        s.put_file(data, "x.csv")
    os.unlink(s.root / "files" / sha[:2])
    assert s.put_file(data, "x.csv") == sha
    (outside / "target.csv").write_bytes(data)
    blob = s.root / "files" / sha[:2] / sha
    os.chmod(blob, 0o600)
    os.unlink(blob)
    os.symlink(outside / "target.csv", blob)  # a blob swapped for a link out
    with pytest.raises(UnsafePath):
        s.locate("source", FileRef("x.csv", sha))
    os.unlink(blob)
    s.put_file(data, "x.csv")
    shutil.rmtree(s.root / "views" / sha)
    os.symlink(outside, s.root / "views" / sha)  # a view folder swapped for a link out
    with pytest.raises(UnsafePath):
        s.locate("source", FileRef("x.csv", sha))
    assert list(outside.iterdir()) == [outside / "target.csv"]
    s.close()


def file_hash_bytes(data: bytes) -> str:
    import hashlib

    return hashlib.blake2b(data, digest_size=16).hexdigest()


class Endless(io.RawIOBase):
    """A stream that never ends (a client that keeps sending): counts what was read."""

    def __init__(self):
        self.reads = 0

    def readable(self):
        return True

    def read(self, n=-1):
        self.reads += 1
        return b"\0" * (n if n and n > 0 else 1 << 20)


def test_uploads_stop_at_the_limit_while_streaming_and_keep_nothing(store, tmp_path):
    assert store.max_upload == MAX_UPLOAD == 200 * 2**20
    stream = Endless()
    with pytest.raises(UploadTooLarge, match="upload limit"):
        store.put_file(stream, "huge.glb", limit=3 * 2**20)
    assert stream.reads == 4  # stopped at the first chunk past 3 MiB, not after reading everything
    with pytest.raises(UploadTooLarge):
        store.put_file(iter([b"x" * 600_000] * 10), "huge.csv", limit=2**20)
    small = Store(tmp_path / "small", max_upload=1000)
    with pytest.raises(UploadTooLarge):
        small.put_file(b"x" * 1001, "a.csv")
    assert small.put_file(b"x" * 1000, "a.csv")
    small.close()
    assert list((store.root / "tmp").iterdir()) == []
    assert not store._db.execute("SELECT 1 FROM file_names WHERE name LIKE 'huge%'").fetchone()


def test_a_shot_document_cannot_make_the_server_read_outside_the_store(store, tmp_path):
    secret = tmp_path / "secret.csv"
    secret.write_bytes(b"time,jawOpen\n0,0.9\n")
    shot = Shot(files={"source": FileRef(str(secret), file_hash(secret))})
    with pytest.raises(FileNotFoundError, match="not in the review store"):  # strict locate: no fallback to the path
        shot.resolve("source", locate=store.locate)
    assert shot.resolve("source", locate=lambda r, ref: store.locate(r, ref, strict=False)) == str(secret)  # a local CLI
    uploaded = Shot(files={"source": FileRef(str(secret), "")})
    with pytest.raises(ValueError, match="not a content hash"):  # no hash, no reading
        store.create_shot(uploaded, "t", "eve")
    sid = store.create_shot(shot, "t", "eve", import_files=False)
    assert set(store.missing_files(sid)) == {"source"}


def test_user_text_never_reaches_sql_as_code(store):
    names = [EVIL, "Robert'); DROP TABLE notes;--", "x\" OR 1=1 --"]
    sha = store.put_file(b"data", EVIL + ".csv")
    shot = small_shot(store)
    sid = store.create_shot(shot, EVIL, names[1])
    for n in names:
        a = store.apply(sid, {"kind": "note", "op": "add", "frame": 1, "text": n}, store.get(sid)[1], n)
        store.touch(sid, n)
    store.apply(sid, {"kind": "files", "values": {"source_rig": sha}}, store.get(sid)[1], EVIL)
    with pytest.raises(ValueError, match="not a setting"):
        store.apply(sid, setting(**{EVIL: 1}), a.version, EVIL)
    with pytest.raises(ValueError, match="not a file role"):
        store.apply(sid, {"kind": "files", "values": {EVIL: sha}}, a.version, EVIL)
    with pytest.raises(UnknownShot):
        store.get(EVIL)
    assert store.info(sid)["title"] == EVIL and [n["text"] for n in store.notes(sid)] == names
    assert {p["name"] for p in store.participants(sid)} == set(names)
    assert store.file_info(sha)["names"] == [EVIL + ".csv"]
    assert store.get(sid)[0].files["source_rig"].path == EVIL + ".csv"
    assert store.integrity_check() == "ok" and len(store.recent()) == 1
    tables = {r[0] for r in store._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"shots", "notes"} <= tables


def test_sql_is_literal_and_nothing_reaches_eval_pickle_or_a_shell():
    """Every execute() takes a literal SQL string (or an f-string of fixed, checked parts) and
    the module has no eval/exec/pickle/subprocess/os.system."""
    src = Path(store_mod.__file__).read_text()
    tree = ast.parse(src)
    allowed = {"journal_mode.upper()", "synchronous.upper()", "int(timeout * 1000)", "','.join('?' * len(members))"}
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ("execute", "executemany"):
            sql = node.args[0]
            if isinstance(sql, ast.JoinedStr):
                parts = {ast.get_source_segment(src, v.value) for v in sql.values if isinstance(v, ast.FormattedValue)}
                assert parts <= allowed, ast.get_source_segment(src, node)
            elif isinstance(sql, ast.Name):  # _migrate_1's loop over the schema's statements
                assert sql.id == "sql" and all(isinstance(c, str) for c in store_mod._V1)
            else:
                assert isinstance(sql, ast.Constant) and isinstance(sql.value, str), ast.get_source_segment(src, node)
        if isinstance(node, ast.Name):
            assert node.id not in ("eval", "exec", "pickle", "subprocess", "marshal"), node.id
        if isinstance(node, ast.Attribute):
            assert node.attr not in ("system", "popen", "loads_pickle"), node.attr
    assert "import pickle" not in src and "import subprocess" not in src and "shell=True" not in src


# -- migrations ---------------------------------------------------------------------------------------------------
V1_SCHEMA = """
CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied REAL NOT NULL);
INSERT INTO schema_version VALUES (1, 1700000000.0);
CREATE TABLE shots (id TEXT PRIMARY KEY, title TEXT NOT NULL, created REAL NOT NULL, updated REAL NOT NULL,
    version INTEGER NOT NULL CHECK (version >= 1), doc TEXT NOT NULL, content_hash TEXT NOT NULL);
CREATE INDEX shots_updated ON shots (updated);
CREATE TABLE changes (shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE, version INTEGER NOT NULL,
    base_version INTEGER NOT NULL, author TEXT NOT NULL, at REAL NOT NULL, kind TEXT NOT NULL, change TEXT NOT NULL,
    PRIMARY KEY (shot_id, version));
CREATE TABLE settings_history (id INTEGER PRIMARY KEY, shot_id TEXT NOT NULL, version INTEGER NOT NULL, author TEXT NOT NULL,
    at REAL NOT NULL, stage TEXT NOT NULL, setting TEXT NOT NULL, old TEXT, new TEXT,
    FOREIGN KEY (shot_id, version) REFERENCES changes (shot_id, version) ON DELETE CASCADE);
CREATE INDEX settings_history_setting ON settings_history (shot_id, stage, setting, version);
CREATE TABLE edits (id INTEGER PRIMARY KEY, shot_id TEXT NOT NULL, version INTEGER NOT NULL, author TEXT NOT NULL,
    at REAL NOT NULL, editor TEXT NOT NULL, op TEXT NOT NULL CHECK (op IN ('add', 'undo', 'redo', 'remove')),
    position INTEGER NOT NULL, edit TEXT NOT NULL,
    FOREIGN KEY (shot_id, version) REFERENCES changes (shot_id, version) ON DELETE CASCADE);
CREATE INDEX edits_shot ON edits (shot_id, editor, id);
CREATE TABLE notes (shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE, note_id TEXT NOT NULL,
    frame INTEGER NOT NULL, author TEXT NOT NULL, text TEXT NOT NULL,
    resolved INTEGER NOT NULL DEFAULT 0 CHECK (resolved IN (0, 1)), created REAL NOT NULL, updated REAL NOT NULL,
    PRIMARY KEY (shot_id, note_id));
CREATE TABLE files (sha TEXT PRIMARY KEY, kind TEXT NOT NULL CHECK (kind IN ('file', 'folder')), size INTEGER NOT NULL,
    created REAL NOT NULL);
CREATE TABLE file_names (sha TEXT NOT NULL REFERENCES files (sha) ON DELETE CASCADE, name TEXT NOT NULL,
    added REAL NOT NULL, PRIMARY KEY (sha, name));
CREATE TABLE folder_members (folder TEXT NOT NULL REFERENCES files (sha) ON DELETE CASCADE, name TEXT NOT NULL,
    sha TEXT NOT NULL REFERENCES files (sha), PRIMARY KEY (folder, name));
CREATE TABLE shot_files (shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE, role TEXT NOT NULL,
    sha TEXT NOT NULL, path TEXT NOT NULL, PRIMARY KEY (shot_id, role));
"""


def test_a_version_1_database_written_by_hand_opens_migrated(tmp_path):
    data = tmp_path / "old"
    data.mkdir()
    note = {"id": "n1", "frame": 12, "author": "lead", "text": "jaw late", "resolved": False, "created": 1.7e9, "updated": 1.7e9}
    doc = Shot(settings={"solve": {"alpha": 0.01}}, notes=[note]).to_dict()
    db = sqlite3.connect(data / "review.sqlite3")
    db.executescript(V1_SCHEMA)
    db.execute("INSERT INTO shots VALUES ('oldshot00001', 'old take', 1.7e9, 1.7e9, 1, ?, ?)",
               (json.dumps(doc), Shot.from_dict(doc).content_hash()))
    db.execute("INSERT INTO changes VALUES ('oldshot00001', 1, 0, 'lead', 1.7e9, 'create', ?)",
               (json.dumps({"kind": "create", "doc": doc}),))
    db.execute("INSERT INTO notes VALUES ('oldshot00001', 'n1', 12, 'lead', 'jaw late', 0, 1.7e9, 1.7e9)")
    db.commit()
    db.close()
    with Store(data) as s:
        assert s.schema_version() == 2
        assert [r[0] for r in s._db.execute("SELECT version FROM schema_version ORDER BY version")] == [1, 2]
        assert s.notes("oldshot00001") == [{**note, "frame_end": None}]
        shot, version = s.get("oldshot00001")
        assert version == 1 and shot.notes == [{**note, "frame_end": None}]
        assert s.participants("oldshot00001")[0]["name"] == "lead"
        a = s.apply("oldshot00001", {"kind": "note", "op": "add", "frame": 3, "frame_end": 8, "text": "blink"}, 1, "ana")
        assert a.version == 2 and s.notes("oldshot00001")[0]["frame_end"] == 8
        assert s.at_version("oldshot00001", 1).notes == [note]  # the log replays the document as it was written
        assert s.integrity_check() == "ok"
    bak = sqlite3.connect(data / "review.sqlite3.v1.bak")  # what was there before, kept
    assert bak.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] == 1
    assert "frame_end" not in {r[1] for r in bak.execute("PRAGMA table_info(notes)")}
    bak.close()


def test_a_newer_database_is_refused(tmp_path):
    Store(tmp_path / "d").close()
    db = sqlite3.connect(tmp_path / "d" / "review.sqlite3")
    db.execute("INSERT INTO schema_version VALUES (99, 0)")
    db.commit()
    db.close()
    with pytest.raises(ValueError, match="newer than this program's.*update face-retarget"):
        Store(tmp_path / "d")


def test_migrations_cover_every_version():
    assert sorted(store_mod.MIGRATIONS) == list(range(1, SCHEMA_VERSION + 1))


# -- the data directory -------------------------------------------------------------------------------------------
def test_data_dir_defaults_to_the_per_user_data_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("FACE_RETARGET_DATA_DIR", raising=False)
    assert data_dir(create=False) == Path(platformdirs.user_data_dir("face-retarget", appauthor=False))
    monkeypatch.setenv("FACE_RETARGET_DATA_DIR", str(tmp_path / "env"))
    assert data_dir() == tmp_path / "env" and (tmp_path / "env").is_dir()
    made = data_dir(tmp_path / "given" / "deeper")
    assert made == tmp_path / "given" / "deeper" and made.stat().st_mode & 0o777 == 0o700


def test_put_path_reads_an_unchanged_file_once(store, tmp_path, monkeypatch):
    """Every page of a shot sets its files again: a file already stored and unchanged since
    (size, mtime, inode) is not read, copied and fsynced again; a changed file is, and so is one
    whose blob has gone."""
    f = tmp_path / "take.csv"
    f.write_bytes(b"Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.5\n")
    reads = []
    put = store._put
    monkeypatch.setattr(store, "_put", lambda data, name, limit, expect=None: reads.append(name) or put(data, name, limit, expect))
    sha = store.put_path(f)
    assert store.put_path(f) == sha and store.put_path(f) == sha and len(reads) == 1
    # under another name it is stored again, so the store knows the name
    assert store.put_path(f, name="renamed.csv") == sha and len(reads) == 2
    assert store.put_path(f, name="renamed.csv") == sha and len(reads) == 2
    assert "renamed.csv" in store.file_info(sha)["names"]
    f.write_bytes(b"Timecode,BlendShapeCount,JawOpen\n00:00:00:00.000,1,0.7\n")
    os.utime(f, ns=(time.time_ns(), time.time_ns() + 10**9))  # a new mtime even on a coarse clock
    sha2 = store.put_path(f)
    assert sha2 != sha and len(reads) == 3 and sha2 == file_hash(f)
    store._blob(sha2).unlink()
    assert store.put_path(f) == sha2 and len(reads) == 4 and store._blob(sha2).is_file()
