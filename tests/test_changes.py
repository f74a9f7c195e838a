"""The change algebra of a shot (core/changes.py) on its own, with no store: parse, apply, replay
and the commutation rules a stale change is rebased or refused by."""

import ast
from pathlib import Path

import pytest

from core import changes
from core.changes import (apply_change, conflict_reason, describe, drop_noops, parse_change, replay_changes,
                          replay_edits)
from core.shot import EDITORS, FileRef, Shot

POSE = {"frame": 30, "weights": {"mouthOpen": 0.5}, "window": [20, 40]}


def small_shot() -> Shot:
    return Shot(files={"source": FileRef("take.csv", "0" * 32)},
                settings={"solve": {"method": "spacetime", "alpha": 0.01, "beta": 0.0},
                          "frames": {"first_frame": 0, "last_frame": -1}})


def test_applied_changes_replay_to_the_same_document_and_edit_lists():
    first = small_shot()
    shot = small_shot()
    log, edit_rows = [(1, "ana", 0.0, {"kind": "create", "doc": first.to_dict()})], []
    steps = [{"kind": "settings", "values": {"alpha": 0.05}},
             {"kind": "edit", "editor": "spacetime", "op": "add", "edit": POSE},
             {"kind": "edit", "editor": "spacetime", "op": "add", "edit": {**POSE, "frame": 10}},
             {"kind": "edit", "editor": "spacetime", "op": "undo"},
             {"kind": "note", "op": "add", "frame": 12, "text": "jaw late"},
             {"kind": "note", "op": "resolve", "note_id": "n1"},
             {"kind": "frame", "frame": 12}]
    for v, step in enumerate(steps, start=2):
        ch = drop_noops(parse_change(step, shot), shot)
        shot, rec, fx = apply_change(shot, ch, "bob", float(v))
        log.append((v, "bob", float(v), rec))
        edit_rows += [{"editor": e, "op": op, "position": pos, "edit": ed} for e, op, pos, ed in fx["edits"]]
    assert shot.settings["solve"]["alpha"] == 0.05 and shot.frame == 12
    assert shot.edits["spacetime"].done == [POSE] and shot.edits["spacetime"].undone == [{**POSE, "frame": 10}]
    assert [(n["id"], n["resolved"], n["author"]) for n in shot.notes] == [("n1", True, "bob")]
    assert replay_changes(log).to_dict() == shot.to_dict()
    lists = replay_edits(edit_rows)
    assert all(lists[e].to_dict() == shot.edits.get(e, lists[e]).to_dict() for e in EDITORS)
    assert [describe(r) for _, _, _, r in log[1:3]] == ["set solve.alpha to 0.05", "added a spacetime edit"]


def test_noops_and_bad_changes():
    shot = small_shot()
    assert drop_noops(parse_change({"kind": "settings", "values": {"alpha": 0.01}}, shot), shot) is None
    assert drop_noops(parse_change({"kind": "frame", "frame": 0}, shot), shot) is None
    with pytest.raises(ValueError, match="did you mean 'alpha'"):
        parse_change({"kind": "settings", "values": {"alpah": 1}}, shot)
    with pytest.raises(ValueError, match="nothing to undo"):
        apply_change(shot, parse_change({"kind": "edit", "editor": "spacetime", "op": "undo"}, shot), "ana", 0.0)


def test_which_changes_commute():
    def ch(**kw):
        return parse_change(kw, small_shot())

    alpha = ch(kind="settings", values={"alpha": 0.05})
    assert conflict_reason(alpha, ch(kind="settings", values={"alpha": 0.2})) == "solve.alpha changed"
    assert conflict_reason(alpha, ch(kind="settings", values={"alpha": 0.05})) is None  # the same value
    assert conflict_reason(alpha, ch(kind="settings", values={"beta": 0.5})) is None
    add = ch(kind="edit", editor="spacetime", op="add", edit=POSE)
    undo = ch(kind="edit", editor="spacetime", op="undo")
    assert conflict_reason(add, add) is None
    assert conflict_reason(undo, add) == "the spacetime edit list changed"
    assert conflict_reason(undo, ch(kind="edit", editor="transfer", op="add", edit=POSE)) is None
    assert conflict_reason(ch(kind="frame", frame=3), ch(kind="frame", frame=4)) is None


def test_the_algebra_is_pure():
    """No SQLite, files, panel or pipeline in the change algebra: the store does the persistence."""
    tree = ast.parse(Path(changes.__file__).read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 0}
    local = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 1}
    assert not imported & {"sqlite3", "os", "shutil", "tempfile", "panel"}, imported
    assert local == {"shot"}, local
