"""Changes to a shot: the pure algebra the review store records (no SQLite here).

A *change* is a small JSON dict that one reviewer makes to a :class:`core.shot.Shot`::

    {"kind": "settings", "values": {stage: {setting: value}}}   # or {setting: value}
    {"kind": "files", "values": {role: content hash or None}}
    {"kind": "edit", "editor": "spacetime"|"transfer"|"detail", "op": "add", "edit": {...}}
    {"kind": "edit", "editor": ..., "op": "undo" | "redo"}
    {"kind": "edit", "editor": ..., "op": "remove", "index": i}
    {"kind": "frame", "frame": f}
    {"kind": "note", "op": "add", "frame": f, "text": "...", "frame_end": g or None}
    {"kind": "note", "op": "resolve" | "reopen", "note_id": "n3"}
    {"kind": "note", "op": "edit", "note_id": "n3", "text"?, "frame"?, "frame_end"?}

What :meth:`core.store.Store.apply` does with one, each step a function of plain data:

* :func:`parse_change` checks its shape against the shot and normalises it (a setting named
  without its stage gets it), with errors that name the field and "did you mean";
* :func:`drop_noops` leaves out what already holds (a setting set to its value, a resolved note
  resolved): nothing left means no new version;
* :func:`conflict_reason` says whether a change made before another one still commutes with it
  (then it is rebased over it) or not (then it is refused, with the reason): a note added or the
  frame moved always commute; an edit added commutes with others only added to the same list; a
  setting, file role or note commutes unless the other change set it to another value;
* :func:`apply_change` applies it (deterministic given the change as recorded, which carries
  note ids, file paths and indices) and returns the rows of the store's derived tables;
* :func:`describe` says it in words, :func:`replay_changes` replays a changes log to the
  document it ends with, :func:`replay_edits` rebuilds the edit lists from the edit rows.

The bounds on user input (:data:`MAX_NAME`, :data:`MAX_TEXT`, :data:`MAX_CHANGE`), the canonical
JSON the store writes (:func:`canonical_json`) and the checks of names, texts and content hashes
(:func:`safe_name`, :func:`checked_text`, :func:`checked_sha`) live here too, because both the
changes and the store apply them.
"""

from __future__ import annotations

import copy
import difflib
import json
import re
from pathlib import Path
from typing import Callable, Optional

from .shot import EDITORS, EditHistory, FileRef, Shot

__all__ = ["CONTENT_HASH", "MAX_NAME", "MAX_TEXT", "MAX_CHANGE", "NOTE_OPS", "EDIT_OPS", "KINDS", "safe_name", "checked_text",
           "checked_sha", "canonical_json", "parse_change", "drop_noops", "describe", "conflict_reason", "normal_note",
           "apply_change", "replay_edits", "initial_edit_rows", "replay_changes"]

MAX_NAME = 200          # characters of an author, a title or a file name
MAX_TEXT = 20_000       # characters of a note
MAX_CHANGE = 4 * 2**20  # bytes of one change as JSON
#: the ops of a note change, of an edit change, and the kinds of change
NOTE_OPS = ("add", "resolve", "reopen", "edit")
EDIT_OPS = ("add", "undo", "redo", "remove")
KINDS = ("settings", "files", "edit", "frame", "note")

#: a content hash as :func:`core.shot.file_hash` gives it
CONTENT_HASH = re.compile(r"[0-9a-f]{32}\Z")
_ROLE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}\Z")


def safe_name(name, default: str = "file") -> str:
    """A user-given file name reduced to a plain name: its last component (``/`` and ``\\``
    both separate), printable characters only, at most :data:`MAX_NAME` characters (the
    suffix kept); ``""``, ``.`` and ``..`` become ``default``. Metadata only: files are stored
    under their hash."""
    n = str(name or "").replace("\\", "/").split("/")[-1]
    n = "".join(c for c in n if c.isprintable()).strip()
    if n in ("", ".", ".."):
        return default
    if len(n) > MAX_NAME:
        suffix = Path(n).suffix[:20]
        n = n[:MAX_NAME - len(suffix)] + suffix
    return n


def checked_text(value, what: str, limit: int = MAX_NAME, allow_empty: bool = False) -> str:
    """``value`` stripped; ValueError naming ``what`` unless it is text of at most ``limit``
    characters, not empty (unless ``allow_empty``), without control characters but newline and tab."""
    if not isinstance(value, str):
        raise ValueError(f"{what}: expected text, got {type(value).__name__}")
    v = value.strip()
    if not v and not allow_empty:
        raise ValueError(f"{what}: must not be empty")
    if len(v) > limit:
        raise ValueError(f"{what}: {len(v)} characters, at most {limit}")
    if any(not c.isprintable() and c not in "\n\t" for c in v):
        raise ValueError(f"{what}: contains control characters")
    return v


def checked_sha(value, what: str = "file") -> str:
    """``value`` when it is a content hash (:data:`CONTENT_HASH`), else ValueError naming ``what``."""
    if not isinstance(value, str) or not CONTENT_HASH.match(value):
        raise ValueError(f"{what}: {value!r} is not a content hash (32 lowercase hex digits, core.shot.file_hash)")
    return value


def canonical_json(value) -> str:
    """``value`` as the store writes JSON: keys sorted, compact, no NaN (ValueError for NaN)."""
    return json.dumps(value, sort_keys=True, allow_nan=False, separators=(",", ":"))


def _same(a, b) -> bool:
    """Equal as JSON (so ``True`` differs from ``1``)."""
    return canonical_json(a) == canonical_json(b)


def _int(value, what: str, low: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{what}: expected an integer >= {low}, got {value!r}")
    return int(value)


def _did_you_mean(word: str, options) -> str:
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=3)
    return f"; did you mean {', '.join(map(repr, close))}?" if close else ""


def parse_change(change: dict, shot: Shot) -> dict:
    """Check a change's shape and normalise it (settings by stage, indices non-negative later).

    Raises ValueError naming the field that is wrong."""
    if not isinstance(change, dict):
        raise ValueError(f"change: expected a dict, got {type(change).__name__}")
    kind = change.get("kind")
    if kind not in KINDS:
        raise ValueError(f"change: unknown kind {kind!r}; expected one of {KINDS}" + _did_you_mean(kind, KINDS))
    try:
        size = len(canonical_json(change))
    except (TypeError, ValueError) as e:
        raise ValueError(f"change: not plain JSON data ({e})") from None
    if size > MAX_CHANGE:
        raise ValueError(f"change: {size} bytes as JSON, at most {MAX_CHANGE}")
    if kind == "settings":
        values = change.get("values")
        if not isinstance(values, dict) or not values:
            raise ValueError("settings change: 'values' must be a non-empty {stage: {setting: value}} (or {setting: value})")
        out: dict = {}
        for key, val in values.items():
            if key in shot.settings and isinstance(val, dict):
                items = [(key, k, v) for k, v in val.items()]
            else:
                owners = [st for st, d in shot.settings.items() if key in d]
                if len(owners) != 1:
                    known = sorted({k for d in shot.settings.values() for k in d} | set(shot.settings))
                    what = "is in several stages; give {stage: {setting: value}}" if owners else "is not a setting of this shot"
                    raise ValueError(f"settings change: {key!r} {what}" + ("" if owners else _did_you_mean(key, known)))
                items = [(owners[0], key, val)]
            for stage, k, v in items:
                if k not in shot.settings[stage]:
                    raise ValueError(f"settings change: {stage}.{k} is not a setting of this shot"
                                     + _did_you_mean(k, shot.settings[stage]))
                out.setdefault(stage, {})[k] = copy.deepcopy(v)
        return {"kind": "settings", "values": out}
    if kind == "files":
        values = change.get("values")
        if not isinstance(values, dict) or not values:
            raise ValueError("files change: 'values' must be a non-empty {role: content hash or None}")
        out = {}
        for role, sha in values.items():
            if not isinstance(role, str) or not _ROLE.match(role):
                raise ValueError(f"files change: {role!r} is not a file role (e.g. 'source', 'target_rig')")
            if isinstance(sha, dict):  # as recorded: {"sha", "path"}
                sha = {"sha": checked_sha(sha.get("sha"), f"files change: {role}"), "path": safe_name(sha.get("path"))}
            elif sha is not None:
                sha = checked_sha(sha, f"files change: {role}")
            out[role] = sha
        return {"kind": "files", "values": out}
    if kind == "frame":
        return {"kind": "frame", "frame": _int(change.get("frame"), "frame change: frame")}
    if kind == "edit":
        editor, op = change.get("editor"), change.get("op")
        if editor not in EDITORS:
            raise ValueError(f"edit change: unknown editor {editor!r}; expected one of {sorted(EDITORS)}"
                             + _did_you_mean(editor, EDITORS))
        if op not in EDIT_OPS:
            raise ValueError(f"edit change: unknown op {op!r}; expected one of {EDIT_OPS}")
        out = {"kind": "edit", "editor": editor, "op": op}
        if op == "add":
            if not isinstance(change.get("edit"), dict):
                raise ValueError("edit change: op 'add' needs 'edit', a dict (the edit as the editor takes it)")
            out["edit"] = copy.deepcopy(change["edit"])
        if op == "remove":
            index = change.get("index")
            if isinstance(index, bool) or not isinstance(index, int):
                raise ValueError(f"edit change: op 'remove' needs 'index', an integer, got {index!r}")
            out["index"] = index
        return out
    # note
    op = change.get("op")
    if op not in NOTE_OPS:
        raise ValueError(f"note change: unknown op {op!r}; expected one of {NOTE_OPS}")
    out = {"kind": "note", "op": op}
    if op != "add":
        if not isinstance(change.get("note_id"), str):
            raise ValueError(f"note change: op {op!r} needs 'note_id'")
        out["note_id"] = change["note_id"]
    elif "note_id" in change:  # as recorded
        out["note_id"] = checked_text(change["note_id"], "note change: note_id", 32)
    if op in ("add", "edit"):
        fields = [f for f in ("frame", "frame_end", "text") if f in change]
        if op == "add" and ("frame" not in change or "text" not in change):
            raise ValueError("note change: op 'add' needs 'frame' and 'text'")
        if op == "edit" and not fields:
            raise ValueError("note change: op 'edit' needs one of 'frame', 'frame_end', 'text'")
        if "frame" in change:
            out["frame"] = _int(change["frame"], "note change: frame")
        if "frame_end" in change:
            out["frame_end"] = None if change["frame_end"] is None else _int(change["frame_end"], "note change: frame_end")
        if "text" in change:
            out["text"] = checked_text(change["text"], "note change: text", MAX_TEXT)
        if op == "add":
            out.setdefault("frame_end", None)
    return out


def _note(shot: Shot, note_id: str) -> Optional[dict]:
    return next((n for n in shot.notes if isinstance(n, dict) and n.get("id") == note_id), None)


def drop_noops(ch: dict, shot: Shot) -> Optional[dict]:
    """``ch`` without the parts whose result already holds in ``shot``; None when nothing is left."""
    kind = ch["kind"]
    if kind == "settings":
        left = {st: {k: v for k, v in vals.items() if not _same(shot.settings[st][k], v)} for st, vals in ch["values"].items()}
        left = {st: vals for st, vals in left.items() if vals}
        return {**ch, "values": left} if left else None
    if kind == "files":
        def current(role):
            return shot.files[role].sha if role in shot.files else None
        left = {r: v for r, v in ch["values"].items() if current(r) != (v["sha"] if isinstance(v, dict) else v)}
        return {**ch, "values": left} if left else None
    if kind == "frame":
        return None if shot.frame == ch["frame"] else ch
    if kind == "note" and ch["op"] != "add":
        n = _note(shot, ch["note_id"])
        if n is None:
            return ch  # refused by apply_change with the reason
        if ch["op"] in ("resolve", "reopen"):
            return None if bool(n.get("resolved")) == (ch["op"] == "resolve") else ch
        left = {f: ch[f] for f in ("frame", "frame_end", "text") if f in ch and not _same(n.get(f), ch[f])}
        return {**{k: v for k, v in ch.items() if k not in ("frame", "frame_end", "text")}, **left} if left else None
    return ch


def describe(change: dict) -> str:
    """A change in words, e.g. ``set solve.alpha to 0.05``, ``undid the last spacetime edit``."""
    kind = change.get("kind")
    if kind == "settings":
        return "set " + ", ".join(f"{st}.{k} to {json.dumps(v)}" for st, vals in change["values"].items() for k, v in vals.items())
    if kind == "files":
        parts = []
        for role, v in change["values"].items():
            if v is None:
                parts.append(f"removed the {role} file")
            else:
                sha, name = (v["sha"], v.get("path")) if isinstance(v, dict) else (v, None)
                parts.append(f"set the {role} file to {name + ' ' if name else ''}({sha[:12]}…)")
        return ", ".join(parts)
    if kind == "frame":
        return f"moved the review to frame {change['frame']}"
    if kind == "edit":
        e, op = change["editor"], change["op"]
        return {"add": f"added a {e} edit", "undo": f"undid the last {e} edit", "redo": f"redid a {e} edit",
                "remove": f"removed {e} edit {change.get('index')}"}[op]
    if kind == "note":
        nid = change.get("note_id", "")
        if change["op"] == "add":
            return f"added note {nid} at frame {change.get('frame')}".replace("note  ", "a note ")
        return {"resolve": f"resolved note {nid}", "reopen": f"reopened note {nid}", "edit": f"edited note {nid}"}[change["op"]]
    if kind in ("create", "import"):
        return f"{'created' if kind == 'create' else 'imported'} the shot"
    return str(kind)


def conflict_reason(mine: dict, theirs: dict) -> Optional[str]:
    """What ``mine`` (made before ``theirs`` was applied) and ``theirs`` both changed, when that
    stops ``mine`` from being rebased over it; None when it can be."""
    k, tk = mine["kind"], theirs.get("kind")
    if k != tk:
        return None
    if k == "settings":
        both = [f"{st}.{s}" for st, vals in mine["values"].items() for s, v in vals.items()
                if s in theirs["values"].get(st, {}) and not _same(theirs["values"][st][s], v)]
        return f"{', '.join(both)} changed" if both else None
    if k == "files":
        both = [r for r, v in mine["values"].items() if r in theirs["values"] and not _same(theirs["values"][r], v)]
        return f"the {', '.join(both)} file changed" if both else None
    if k == "edit" and mine["editor"] == theirs["editor"] and not (mine["op"] == "add" and theirs["op"] == "add"):
        return f"the {mine['editor']} edit list changed"
    if k == "note" and mine["op"] != "add" and theirs.get("note_id") == mine["note_id"]:
        return f"note {mine['note_id']} changed"
    return None


def normal_note(n, i: int, author: str, at: float, taken: set) -> dict:
    """A note of a document as the store keeps it (id, frame, frame_end, author, text, resolved,
    created, updated), from whatever subset a shot file carries."""
    if not isinstance(n, dict):
        raise ValueError(f"shot: notes[{i}]: expected a dict, got {type(n).__name__}")
    nid = n.get("id")
    if not isinstance(nid, str) or not nid or len(nid) > 32 or nid in taken:
        nid = _next_note_id(taken)
    taken.add(nid)
    frame = _int(n.get("frame", 0), f"shot: notes[{i}].frame")
    frame_end = n.get("frame_end")
    if frame_end is not None:
        frame_end = _int(frame_end, f"shot: notes[{i}].frame_end", frame)
    created = n.get("created", at)
    created = float(created) if isinstance(created, (int, float)) and not isinstance(created, bool) else at
    updated = n.get("updated", created)
    updated = float(updated) if isinstance(updated, (int, float)) and not isinstance(updated, bool) else created
    return {**n, "id": nid, "frame": frame, "frame_end": frame_end,
            "author": checked_text(str(n.get("author") or author), f"shot: notes[{i}].author"),
            "text": checked_text(str(n.get("text", "")), f"shot: notes[{i}].text", MAX_TEXT, allow_empty=True),
            "resolved": bool(n.get("resolved", False)), "created": created, "updated": updated}


def _next_note_id(taken) -> str:
    i = len(taken) + 1
    while f"n{i}" in taken:
        i += 1
    return f"n{i}"


def apply_change(shot: Shot, ch: dict, author: str, at: float, file_name: Callable[[str], str] = lambda sha: "") -> tuple:
    """Apply a parsed change to ``shot`` *in place* (callers pass a document they just parsed and
    drop it when this raises): ``(shot, change as recorded, effects)``.

    Effects are the rows of the derived tables: ``settings`` [(stage, setting, old, new)],
    ``edits`` [(editor, op, position, edit)], ``notes`` [note], ``files`` [(role, sha or None, path)].
    Deterministic given the recorded change (note ids, file paths and indices are in it), so
    the changes log replays. Raises ValueError when the change cannot apply to this shot."""
    new = shot
    rec = copy.deepcopy(ch)
    fx: dict = {"settings": [], "edits": [], "notes": [], "files": []}
    kind = ch["kind"]
    if kind == "settings":
        for st, vals in ch["values"].items():
            for k, v in vals.items():
                fx["settings"].append((st, k, new.settings[st][k], v))
                new.settings[st][k] = copy.deepcopy(v)
    elif kind == "files":
        for role, v in ch["values"].items():
            old = new.files[role].sha if role in new.files else None
            if v is None:
                if role not in new.files:
                    raise ValueError(f"files change: the shot has no {role} file to remove")
                del new.files[role]
                fx["files"].append((role, None, None))
            else:
                sha, path = (v["sha"], v["path"]) if isinstance(v, dict) else (v, safe_name(file_name(v)))
                new.files[role] = FileRef(path, sha)
                rec["values"][role] = {"sha": sha, "path": path}
                fx["files"].append((role, sha, path))
            fx["settings"].append(("files", role, old, None if v is None else rec["values"][role]["sha"]))
    elif kind == "frame":
        new.frame = ch["frame"]
    elif kind == "edit":
        e, op = ch["editor"], ch["op"]
        hist = new.edits.setdefault(e, EditHistory())
        if op == "add":
            fx["edits"].append((e, op, len(hist.done), ch["edit"]))
            hist.add(ch["edit"])
        elif op == "undo":
            if not hist.done:
                raise ValueError(f"edit change: nothing to undo in the {e} edits")
            fx["edits"].append((e, op, len(hist.done) - 1, hist.done[-1]))
            hist.undo()
        elif op == "redo":
            if not hist.undone:
                raise ValueError(f"edit change: nothing to redo in the {e} edits")
            fx["edits"].append((e, op, len(hist.done), hist.undone[-1]))
            hist.redo()
        else:
            n = len(hist.done)
            if not -n <= ch["index"] < n:
                raise ValueError(f"edit change: {e} edit {ch['index']} does not exist (there are {n})")
            index = ch["index"] % n
            rec["index"] = index
            fx["edits"].append((e, op, index, hist.remove(index)))
    else:  # note
        op = ch["op"]
        if op == "add":
            taken = {n.get("id") for n in new.notes if isinstance(n, dict)}
            nid = ch.get("note_id") or _next_note_id(taken)
            if nid in taken:
                raise ValueError(f"note change: note {nid} exists already")
            if ch["frame_end"] is not None and ch["frame_end"] < ch["frame"]:
                raise ValueError(f"note change: frame_end {ch['frame_end']} is before frame {ch['frame']}")
            note = {"id": nid, "frame": ch["frame"], "frame_end": ch["frame_end"], "author": author, "text": ch["text"],
                    "resolved": False, "created": at, "updated": at}
            new.notes.append(note)
            rec["note_id"] = nid
        else:
            note = _note(new, ch["note_id"])
            if note is None:
                ids = [n.get("id") for n in new.notes if isinstance(n, dict)]
                raise ValueError(f"note change: no note {ch['note_id']!r} in this shot" + _did_you_mean(ch["note_id"], ids))
            if op in ("resolve", "reopen"):
                note["resolved"] = op == "resolve"
            else:
                for f in ("frame", "frame_end", "text"):
                    if f in ch:
                        note[f] = ch[f]
                if note.get("frame_end") is not None and note["frame_end"] < note["frame"]:
                    raise ValueError(f"note change: frame_end {note['frame_end']} is before frame {note['frame']}")
            note["updated"] = at
        fx["notes"].append(copy.deepcopy(note))
    return new, rec, fx


def replay_edits(rows) -> dict:
    """The edit lists ``{editor: EditHistory}`` that the ``edits`` rows (in order; dicts with
    editor, op, position, edit — :meth:`Store.edit_history`) produce."""
    out = {e: EditHistory() for e in EDITORS}
    for r in rows:
        h = out[r["editor"]]
        if r["op"] == "add":
            h.add(r["edit"])
        elif r["op"] == "undo":
            h.undo()
        elif r["op"] == "redo":
            h.redo()
        else:
            h.remove(r["position"])
    return out


def initial_edit_rows(shot: Shot) -> list:
    """Rows that build a document's existing edit lists: its done edits added, its redo stack
    added (most recently undone last) and undone."""
    rows = []
    for e in EDITORS:
        h = shot.edits.get(e, EditHistory())
        for i, ed in enumerate(h.done + h.undone[::-1]):
            rows.append((e, "add", i, ed))
        for j in range(len(h.undone)):
            rows.append((e, "undo", len(h.done) + len(h.undone) - 1 - j, h.undone[j]))
    return rows


def replay_changes(rows) -> Shot:
    """The document a changes log (version, author, at, change) ends with."""
    _, _, _, first = rows[0]
    shot = Shot.from_dict(first["doc"])
    for _, author, at, ch in rows[1:]:
        shot, _, _ = apply_change(shot, parse_change(ch, shot), author, at)
    return shot
