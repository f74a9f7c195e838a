"""The shot document: everything that says what a retargeting session computes.

A shot is plain data — JSON with a ``schema_version`` — holding

* ``files``: every input file by role (``source``, ``target_rig``, ``target_layout`` ...) with
  its path and the BLAKE2 hash of its bytes, so a shot opened elsewhere finds the same
  content or says which file differs;
* ``settings``: every stage's settings, ``{stage: {setting: value}}`` (all of them, not only
  the changed ones, so a shot keeps meaning the same when a default changes);
* ``edits``: the edit list of each editor with its undo/redo history — ``spacetime`` (poses
  set at frames, Seol 2012 §6), ``transfer`` (large-scale constraints, Xu 2014 §4.3),
  ``detail`` (fine-scale detail edits, Xu 2014 §5.2); ``done`` is what the results contain,
  ``undone`` the redo stack (most recently undone last);
* ``frame`` (the current frame of a review) and ``notes`` (frame-anchored review notes).

:meth:`core.pipeline.Pipeline.from_shot` builds a pipeline from a shot and
:meth:`core.pipeline.Pipeline.shot` writes one; the CLI's ``--shot`` / ``--save-shot`` and the
dashboard's download/open use exactly these. Nothing here imports the pipeline: a version-0
document needs the map of settings to stages, so :meth:`~core.pipeline.Pipeline.from_shot` hands
:func:`migrate` the upgrade (``flat``) that routes them.

Schema history (:func:`migrate` upgrades any older document on load):

* 0 — a flat ``{setting: value}`` dict as ``Pipeline(**settings)`` takes it, file settings as
  paths (what a script or a CLI flag set could say before shots existed);
* 1 — the document described above.
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

SCHEMA_VERSION = 1
_deepcopy = copy.deepcopy  # the methods' ``copy`` arguments shadow the module
#: the editors whose edit lists a shot holds, and the stage setting each list is
EDITORS = {"spacetime": "edits", "transfer": "transfer_edits", "detail": "detail_edits"}


_HASHES: dict = {}


def file_hash(path) -> str:
    """BLAKE2b-128 of a file's bytes; of a folder, of its files' names and hashes (sorted).

    A file's hash is remembered by the file itself as last written (device, inode, size,
    modification time): a shot opened, a stage keyed or a page built again does not read a
    20 MB rig again. Not ``resolve()``: a syscall per path component, and every page of a shared
    shot keys its stages per change."""
    p = Path(path)
    if p.is_dir():
        h = hashlib.blake2b(digest_size=16)
        for c in sorted(q for q in p.iterdir() if q.is_file()):
            h.update(c.name.encode() + b"\0" + file_hash(c).encode())
        return h.hexdigest()
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no such file") from None
    memo = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    if memo not in _HASHES:
        h = hashlib.blake2b(digest_size=16)
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        _HASHES[memo] = h.hexdigest()
    return _HASHES[memo]


@dataclass
class FileRef:
    """An input file: where it was (``path``) and what it held (``sha``, :func:`file_hash`)."""

    path: str
    sha: str

    @classmethod
    def of(cls, path) -> "FileRef":
        return cls(str(path), file_hash(path))


@dataclass
class EditHistory:
    """An edit list with undo/redo: ``done`` (applied, in order) and ``undone`` (the redo
    stack, most recently undone last). Edits are plain dicts (JSON)."""

    done: list = field(default_factory=list)
    undone: list = field(default_factory=list)

    def add(self, edit: dict) -> None:
        """Append an edit; a new edit clears the redo stack (as every editor does)."""
        self.done.append(copy.deepcopy(edit))
        self.undone.clear()

    def undo(self) -> bool:
        if not self.done:
            return False
        self.undone.append(self.done.pop())
        return True

    def redo(self) -> bool:
        if not self.undone:
            return False
        self.done.append(self.undone.pop())
        return True

    def remove(self, index: int) -> dict:
        """Take out edit ``index`` (it goes onto the redo stack, so redo brings it back last)."""
        if not -len(self.done) <= index < len(self.done):
            raise IndexError(f"edit {index}: there are {len(self.done)} edits")
        e = self.done.pop(index)
        self.undone.append(e)
        return e

    def to_dict(self) -> dict:
        return {"done": copy.deepcopy(self.done), "undone": copy.deepcopy(self.undone)}

    @classmethod
    def from_dict(cls, d, copy: bool = True) -> "EditHistory":
        """From ``{"done": [...], "undone": [...]}`` (or a bare done list); ``copy=False`` takes
        over the lists' items instead of copying them."""
        dup = _deepcopy if copy else (lambda x: x)
        if isinstance(d, list):  # a bare list is the done list
            return cls(dup(list(d)), [])
        return cls(dup(list(d.get("done", []))), dup(list(d.get("undone", []))))


@dataclass
class Shot:
    """The shot document (see the module docstring). Plain data; :meth:`to_json` /
    :meth:`from_json` round-trip it exactly."""

    files: dict = field(default_factory=dict)        # role -> FileRef
    settings: dict = field(default_factory=dict)     # stage -> {setting: value}
    edits: dict = field(default_factory=lambda: {k: EditHistory() for k in EDITORS})
    frame: int = 0
    notes: list = field(default_factory=list)
    schema_version: int = SCHEMA_VERSION

    # -- plain data ------------------------------------------------------------------------
    def to_dict(self, copy: bool = True) -> dict:
        """The shot as plain data. ``copy=False`` shares the settings, edit lists and notes
        with the shot instead of copying them (for serialising at once, e.g. the review store's
        writes, where the deep copies were most of the time); do not modify that dict."""
        dup = _deepcopy if copy else (lambda x: x)
        return {
            "schema_version": self.schema_version,
            "files": {k: {"path": v.path, "sha": v.sha} for k, v in sorted(self.files.items())},
            "settings": dup(self.settings),
            "edits": {k: ({"done": dup(self.edits[k].done), "undone": dup(self.edits[k].undone)} if k in self.edits
                          else EditHistory().to_dict()) for k in EDITORS},
            "frame": int(self.frame),
            "notes": dup(self.notes),
        }

    @classmethod
    def from_dict(cls, doc: dict, copy: bool = True, flat: Optional[Callable] = None) -> "Shot":
        """A shot from its plain-data form, migrated from an older schema when needed.
        ``copy=False`` lets the shot take over ``doc``'s lists and dicts instead of copying them
        (for a document just parsed from JSON that nothing else holds); ``flat`` upgrades a
        version-0 document (see :func:`migrate`).

        Raises
        ------
        ValueError
            Not a shot, a newer schema than this program knows, or malformed fields (named).
        """
        if copy or not isinstance(doc, dict) or type(doc.get("schema_version")) is not int or doc["schema_version"] != SCHEMA_VERSION:
            doc = migrate(doc, flat)
        files = {}
        for role, ref in doc.get("files", {}).items():
            if not isinstance(ref, dict) or "path" not in ref:
                raise ValueError(f"shot: files.{role}: expected {{'path': ..., 'sha': ...}}, got {ref!r}")
            files[role] = FileRef(str(ref["path"]), str(ref.get("sha", "")))
        settings = doc.get("settings", {})
        if not isinstance(settings, dict) or not all(isinstance(v, dict) for v in settings.values()):
            raise ValueError("shot: settings: expected {stage: {setting: value}}")
        edits = {k: EditHistory.from_dict(doc.get("edits", {}).get(k, {}), copy=False) for k in EDITORS}  # doc is ours
        unknown = set(doc.get("edits", {})) - set(EDITORS)
        if unknown:
            raise ValueError(f"shot: edits: unknown editors {sorted(unknown)}; expected {sorted(EDITORS)}")
        notes = doc.get("notes", [])
        if not isinstance(notes, list):
            raise ValueError(f"shot: notes: expected a list, got {type(notes).__name__}")
        return cls(files, settings, edits, int(doc.get("frame", 0)), notes)

    def to_json(self, path=None, indent: int = 1) -> str:
        """The shot as JSON text (written to ``path`` when given)."""
        text = json.dumps(self.to_dict(), indent=indent, sort_keys=False, allow_nan=False)
        if path is not None:
            Path(path).write_text(text + "\n", encoding="utf-8")
        return text

    @classmethod
    def from_json(cls, source, flat: Optional[Callable] = None) -> "Shot":
        """A shot from a JSON file path or JSON text (``flat``: see :func:`migrate`).

        Raises
        ------
        ValueError
            Not JSON, or not a shot (the message names the file and what is wrong).
        """
        where = "shot"
        text = source
        if isinstance(source, Path) or (isinstance(source, str) and not source.lstrip().startswith("{")):
            where = str(source)
            try:
                text = Path(source).read_text(encoding="utf-8-sig")
            except FileNotFoundError:
                raise FileNotFoundError(f"{source}: no such shot file") from None
            except UnicodeDecodeError:
                raise ValueError(f"{where}: not a shot file (not UTF-8 text)") from None
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{where}: not a shot file (invalid JSON at line {e.lineno}, column {e.colno}: {e.msg})") from None
        if not isinstance(doc, dict):
            raise ValueError(f"{where}: not a shot file (expected a JSON object, got {type(doc).__name__})")
        try:
            return cls.from_dict(doc, flat=flat)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None

    # -- identity --------------------------------------------------------------------------
    def content_hash(self) -> str:
        """A hash of what determines the results: the files' contents, the settings and the
        applied edits (not paths, the frame, notes or redo stacks). Two shots with equal
        hashes compute the same results."""
        doc = {"files": {k: v.sha for k, v in sorted(self.files.items())}, "settings": self.settings,
               "edits": {k: self.edits[k].done for k in EDITORS if k in self.edits}}
        return hashlib.blake2b(json.dumps(doc, sort_keys=True, allow_nan=False).encode(), digest_size=16).hexdigest()

    def resolve(self, role: str, base: Optional[Path] = None, locate: Optional[Callable] = None) -> str:
        """The path to read for file ``role``: ``locate(role, ref)`` when given (e.g. a review
        store that keeps files by hash), else the recorded path, else that path relative to
        ``base`` (the shot file's folder). The content must hash to the recorded ``sha``.

        Raises
        ------
        FileNotFoundError
            No file found for the role.
        ValueError
            A file is found but its content differs from what the shot recorded.
        """
        ref = self.files[role]
        candidates = []
        if locate is not None:
            found = locate(role, ref)
            if found:
                candidates.append(Path(found))
        candidates.append(Path(ref.path))
        if base is not None and not Path(ref.path).is_absolute():
            candidates.append(Path(base) / ref.path)
        changed = None
        for c in candidates:
            if c.exists():
                if not ref.sha or file_hash(c) == ref.sha:
                    return str(c)
                changed = changed or c  # another candidate may still hold the recorded content
        if changed is not None:
            raise ValueError(f"shot: {role} file {changed} has changed since the shot was saved "
                             f"(content hash {file_hash(changed)[:12]}…, the shot recorded {ref.sha[:12]}…); "
                             f"give the file it was made with, or override it (e.g. --{role.replace('_', '-')})")
        raise FileNotFoundError(f"shot: {role} file {ref.path} not found"
                                + (f" (also looked in {base})" if base is not None else ""))


# -- migrations --------------------------------------------------------------------------------
#: schema version -> upgrade of a document of that version to the next (version 0 is upgraded by
#: the ``flat`` function :func:`migrate` is given: it needs the stage registry)
MIGRATIONS: dict = {}


def migrate(doc: dict, flat: Optional[Callable] = None) -> dict:
    """Upgrade a shot document of any older schema to :data:`SCHEMA_VERSION` (a new dict).

    A dict without ``schema_version`` is version 0: a flat ``{setting: value}`` dict, upgraded by
    ``flat(doc)`` (:func:`core.pipeline.shot_from_settings`, which knows which stage owns each
    setting). Raises ValueError for a version newer than this program's (a newer program wrote
    it), one it has no migration for, or a version-0 document without ``flat``.
    """
    if not isinstance(doc, dict):
        raise ValueError(f"shot: expected a JSON object, got {type(doc).__name__}")
    v = doc.get("schema_version", 0)
    if not isinstance(v, int) or isinstance(v, bool):
        raise ValueError(f"shot: schema_version must be an integer, got {v!r}")
    if v > SCHEMA_VERSION:
        raise ValueError(f"shot: schema_version {v} is newer than this program's ({SCHEMA_VERSION}); update face-retarget")
    doc = copy.deepcopy(doc)
    if v == 0:
        if flat is None:
            raise ValueError("shot: a version-0 document (flat settings, no schema_version) is opened by "
                             "Pipeline.from_shot or `face-retarget retarget --shot`, which know each setting's stage")
        doc = flat(doc)
        v = doc["schema_version"]
    while v < SCHEMA_VERSION:
        if v not in MIGRATIONS:
            raise ValueError(f"shot: no migration from schema_version {v}")
        doc = MIGRATIONS[v](doc)
        v = doc["schema_version"]
    return doc
