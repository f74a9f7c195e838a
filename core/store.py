"""Review persistence: shots, their histories, notes and files in SQLite under a data directory.

The review server keeps one in-memory hub per open shot; every change a reviewer makes goes
through :meth:`Store.apply`, which commits it to SQLite before it returns. A change the server
acknowledged therefore survives a crash of the server process (``kill -9``, tested), and with the
default ``synchronous=FULL`` a power cut too (SQLite fsyncs the WAL on every commit).

Data directory (:func:`data_dir`; ``face-retarget serve --data-dir``)::

    review.sqlite3            the database (WAL mode: review.sqlite3-wal/-shm beside it)
    files/<ab>/<abcdef…>      every stored file by content hash (BLAKE2b-128, as core.shot.file_hash), read-only
    views/<hash>/<name>       a stored file under a name (a hard link to its blob) — what locate() returns,
                              because readers choose the format by suffix; a folder: views/<hash>/<name>/<member>.
                              Derived: deleting views/ loses nothing.
    tmp/                      uploads being written (renamed into files/ once hashed)

Schema (version :data:`SCHEMA_VERSION`; ``schema_version`` lists the versions applied)

================  ==============================================================================
shots             id (``secrets.token_urlsafe(12)``: 96 random bits), title, created, updated
                  (unix seconds), version (bumped by every applied change), doc (the current
                  :class:`core.shot.Shot` JSON), content_hash (:meth:`Shot.content_hash`)
changes           one row per version: shot_id, version, base_version (what the writer saw; less
                  than version - 1 when rebased), author, at, kind, change (JSON, as applied).
                  Version 1 is the ``create`` (or ``import``) holding the first document, so the
                  log replays to any version (:meth:`Store.at_version`)
settings_history  shot_id, version, author, at, stage, setting, old, new (JSON); file roles as
                  stage ``files`` (old/new: content hashes)
edits             shot_id, version, author, at, editor (``spacetime``/``transfer``/``detail``),
                  op (add/undo/redo/remove), position (index in ``done`` added at/taken from),
                  edit (JSON): :func:`core.changes.replay_edits` rebuilds every done/undone list from these rows
notes             shot_id, note_id (``n1``, ``n2`` … per shot), frame, frame_end (NULL: one frame),
                  author, text, resolved (0/1), created, updated
participants      shot_id, name, first_seen, last_seen
files             sha, kind (file/folder), size, created; file_names (sha, name, added): the
                  names it was stored under (metadata only: never a path); folder_members
                  (folder, name, sha)
shot_files        shot_id, role, sha, path: the files each shot uses (no foreign key to files: a
                  light import names files the store does not hold yet, :meth:`Store.missing_files`)
================  ==============================================================================

Migrations: :data:`MIGRATIONS` maps a version to the function that brings a database from the
version before it (a fresh database runs them all, so every step runs in every test). Opening an
older database copies it to ``review.sqlite3.v<old>.bak`` and migrates it in one transaction; a
newer one is refused ("update face-retarget").

* 1 — shots, changes, settings_history, edits, notes (one frame each), files, shot_files;
* 2 — notes get an optional frame range (``frame_end``; the documents' notes gain the key), and
  the ``participants`` table.

Concurrency (:meth:`Store.apply`): a change carries the version its writer saw. The store is
one writer per process (a connection behind a lock); every write is one ``BEGIN IMMEDIATE``
transaction that reads the head version inside it, so several processes on one data directory
are serialised by SQLite as well. A change made against the head applies. Against an older
version it is *rebased* when it commutes with everything applied since:

* a note added, or the review frame moved (last writer wins: it is a cursor, not content);
* an edit added to a list that others only added to since (appended after theirs);
* a setting (or file role) nobody else changed since — or changed to the same value;
* anything touching another editor, another setting, another note;

and *refused* (:class:`Conflict`, naming the change it conflicts with: who, which version,
what) when someone else, since that version, changed the same setting or file role to another
value, changed the same note, or did anything but add to the same edit list (undo/redo/remove
act on the list as the writer saw it). A change whose result already holds (a setting set to its
value, a resolved note resolved) is a no-op: ``Applied.change`` is None and no version is made.
Nothing is dropped silently. These rules, and parsing, applying, describing and replaying a change,
are the pure functions of :mod:`core.changes`; this module keeps SQLite, the files and persistence.

Security of the data directory: every path the store builds is checked to stay inside it
(:meth:`Store._path`: no ``..``, no absolute path, no separator in a name, no symbolic link
leading out); user-given names are metadata only, files live under their hash; uploads stop
at :attr:`Store.max_upload` bytes while they are being read (default 200 MiB); every SQL
statement takes user values as parameters; nothing user-given reaches ``eval``, ``pickle`` or a
shell. Archives (:meth:`Store.import_`) are never extracted by name: each ``files/<hash>`` entry
is streamed through the same size limit and must hash to its name. A process with write access
to the data directory itself is trusted (it could edit the database anyway).

Nothing here imports panel or the pipeline.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import sqlite3
import stat
import tempfile
import threading
import time
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Optional

import platformdirs

from .changes import (CONTENT_HASH, apply_change, canonical_json, checked_sha, checked_text, conflict_reason, describe,
                      drop_noops, initial_edit_rows, normal_note, parse_change, replay_changes, safe_name)
from .shot import FileRef, Shot, file_hash

#: the database schema this program writes (see the module docstring)
SCHEMA_VERSION = 2
DB_NAME = "review.sqlite3"
APP_NAME = "face-retarget"
#: overrides the per-user default of :func:`data_dir`
ENV_DATA_DIR = "FACE_RETARGET_DATA_DIR"
#: default upload limit in bytes (200 MiB)
MAX_UPLOAD = 200 * 2**20
#: format version of :meth:`Store.export` archives
EXPORT_FORMAT = 1
EXPORT_KIND = "face-retarget-review"
CHUNK = 1 << 20
MAX_JSON = 64 * 2**20   # bytes of a JSON member of an archive

_SHOT_ID = re.compile(r"[A-Za-z0-9_-]{8,64}\Z")


# -- errors and results --------------------------------------------------------------------------
class Conflict(ValueError):
    """A change made against a version others have changed since, in a way it does not commute
    with. ``version``, ``author`` and ``change`` are the conflicting change's; ``head`` the
    shot's version now."""

    def __init__(self, message: str, *, version: int, author: str, change: dict, head: int):
        super().__init__(message)
        self.version, self.author, self.change, self.head = version, author, change, head


class UploadTooLarge(ValueError):
    """An upload went over the size limit (it was stopped there; nothing was kept)."""


class UnsafePath(ValueError):
    """A path would leave the data directory (``..``, an absolute path, a symbolic link)."""


class UnknownShot(KeyError):
    """No shot with that id in this store."""

    def __str__(self):
        return str(self.args[0]) if self.args else "unknown shot"


class Applied(NamedTuple):
    """What :meth:`Store.apply` did: the shot's ``version`` and document after it, the
    ``change`` as recorded (None: nothing to do, the requested state already held) and whether
    it was ``rebased`` over others' changes."""

    version: int
    shot: Shot
    change: Optional[dict]
    rebased: bool


# -- the data directory ----------------------------------------------------------------------------
def data_dir(path=None, create: bool = True) -> Path:
    """The review data directory: ``path`` when given, else ``$FACE_RETARGET_DATA_DIR``, else
    the per-user data folder (``platformdirs.user_data_dir("face-retarget")``:
    ``~/.local/share/face-retarget`` on Linux, ``~/Library/Application Support/face-retarget``
    on macOS, ``%LOCALAPPDATA%\\face-retarget`` on Windows). Created (mode 0700) when missing."""
    if path is None or str(path) == "":
        path = os.environ.get(ENV_DATA_DIR) or platformdirs.user_data_dir(APP_NAME, appauthor=False)
    p = Path(path).expanduser()
    if create:
        p.mkdir(parents=True, exist_ok=True, mode=0o700)
    return p


def _member_name(name) -> str:
    """A folder member's name, refused (not changed: the folder's hash covers it) when unsafe."""
    if not isinstance(name, str) or safe_name(name, default="") != name:
        raise UnsafePath(f"folder member name {name!r}: expected a plain file name (no path, no control characters)")
    return name


def _chunks(data) -> Iterable[bytes]:
    """Chunks of ``data``: bytes-like, a binary file object (``read``), or an iterable of bytes."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        view = memoryview(data).cast("B")
        for i in range(0, len(view), CHUNK):
            yield view[i:i + CHUNK]
        return
    if isinstance(data, str):
        raise TypeError("put_file: expected bytes or a binary stream, got str")
    if hasattr(data, "read"):
        while True:
            chunk = data.read(CHUNK)
            if not chunk:
                return
            if isinstance(chunk, str):
                raise TypeError("put_file: the stream gave str; open it in binary mode")
            yield chunk
        return
    for chunk in data:
        if not isinstance(chunk, (bytes, bytearray, memoryview)):
            raise TypeError(f"put_file: expected bytes chunks, got {type(chunk).__name__}")
        yield chunk


def _folder_hash(members: dict) -> str:
    """:func:`core.shot.file_hash` of a folder, from its members' names and hashes."""
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(members):
        h.update(name.encode() + b"\0" + members[name].encode())
    return h.hexdigest()


# -- schema ----------------------------------------------------------------------------------------
_V1 = [
    """CREATE TABLE shots (
        id TEXT PRIMARY KEY,
        title TEXT NOT NULL,
        created REAL NOT NULL,
        updated REAL NOT NULL,
        version INTEGER NOT NULL CHECK (version >= 1),
        doc TEXT NOT NULL,
        content_hash TEXT NOT NULL)""",
    "CREATE INDEX shots_updated ON shots (updated)",
    """CREATE TABLE changes (
        shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE,
        version INTEGER NOT NULL,
        base_version INTEGER NOT NULL,
        author TEXT NOT NULL,
        at REAL NOT NULL,
        kind TEXT NOT NULL,
        change TEXT NOT NULL,
        PRIMARY KEY (shot_id, version))""",
    """CREATE TABLE settings_history (
        id INTEGER PRIMARY KEY,
        shot_id TEXT NOT NULL,
        version INTEGER NOT NULL,
        author TEXT NOT NULL,
        at REAL NOT NULL,
        stage TEXT NOT NULL,
        setting TEXT NOT NULL,
        old TEXT,
        new TEXT,
        FOREIGN KEY (shot_id, version) REFERENCES changes (shot_id, version) ON DELETE CASCADE)""",
    "CREATE INDEX settings_history_setting ON settings_history (shot_id, stage, setting, version)",
    """CREATE TABLE edits (
        id INTEGER PRIMARY KEY,
        shot_id TEXT NOT NULL,
        version INTEGER NOT NULL,
        author TEXT NOT NULL,
        at REAL NOT NULL,
        editor TEXT NOT NULL,
        op TEXT NOT NULL CHECK (op IN ('add', 'undo', 'redo', 'remove')),
        position INTEGER NOT NULL,
        edit TEXT NOT NULL,
        FOREIGN KEY (shot_id, version) REFERENCES changes (shot_id, version) ON DELETE CASCADE)""",
    "CREATE INDEX edits_shot ON edits (shot_id, editor, id)",
    """CREATE TABLE notes (
        shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE,
        note_id TEXT NOT NULL,
        frame INTEGER NOT NULL,
        author TEXT NOT NULL,
        text TEXT NOT NULL,
        resolved INTEGER NOT NULL DEFAULT 0 CHECK (resolved IN (0, 1)),
        created REAL NOT NULL,
        updated REAL NOT NULL,
        PRIMARY KEY (shot_id, note_id))""",
    """CREATE TABLE files (
        sha TEXT PRIMARY KEY,
        kind TEXT NOT NULL CHECK (kind IN ('file', 'folder')),
        size INTEGER NOT NULL,
        created REAL NOT NULL)""",
    """CREATE TABLE file_names (
        sha TEXT NOT NULL REFERENCES files (sha) ON DELETE CASCADE,
        name TEXT NOT NULL,
        added REAL NOT NULL,
        PRIMARY KEY (sha, name))""",
    """CREATE TABLE folder_members (
        folder TEXT NOT NULL REFERENCES files (sha) ON DELETE CASCADE,
        name TEXT NOT NULL,
        sha TEXT NOT NULL REFERENCES files (sha),
        PRIMARY KEY (folder, name))""",
    """CREATE TABLE shot_files (
        shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE,
        role TEXT NOT NULL,
        sha TEXT NOT NULL,
        path TEXT NOT NULL,
        PRIMARY KEY (shot_id, role))""",
]


def _migrate_1(db: sqlite3.Connection) -> None:
    """An empty database -> version 1."""
    for sql in _V1:
        db.execute(sql)


def _migrate_2(db: sqlite3.Connection) -> None:
    """1 -> 2: notes over a frame range (``frame_end``), and who took part (``participants``)."""
    db.execute("ALTER TABLE notes ADD COLUMN frame_end INTEGER")
    db.execute("""CREATE TABLE participants (
        shot_id TEXT NOT NULL REFERENCES shots (id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        first_seen REAL NOT NULL,
        last_seen REAL NOT NULL,
        PRIMARY KEY (shot_id, name))""")
    # the documents' notes gain the key, so a document and its notes rows say the same
    for shot_id, doc in db.execute("SELECT id, doc FROM shots").fetchall():
        d = json.loads(doc)
        for n in d.get("notes", []):
            if isinstance(n, dict):
                n.setdefault("frame_end", None)
        db.execute("UPDATE shots SET doc = ? WHERE id = ?", (json.dumps(d, allow_nan=False), shot_id))
    # authors of past changes are participants
    db.execute("""INSERT OR IGNORE INTO participants (shot_id, name, first_seen, last_seen)
                  SELECT shot_id, author, MIN(at), MAX(at) FROM changes GROUP BY shot_id, author""")


#: version -> the function that migrates a database from the version before it
MIGRATIONS: dict = {1: _migrate_1, 2: _migrate_2}


# -- the store ---------------------------------------------------------------------------------------
class Store:
    """The review store of one data directory (see the module docstring).

    Parameters
    ----------
    path : the data directory (:func:`data_dir` resolves ``None`` to the per-user default)
    max_upload : bytes an upload may have (:data:`MAX_UPLOAD`, 200 MiB), enforced while reading
    check : ``check(shot)`` called with every new document before it is committed; raise
        ValueError to refuse the change (e.g. the server checks settings with the pipeline)
    synchronous, journal_mode : SQLite pragmas. The defaults (``FULL``, ``WAL``) make a commit
        durable against power loss; other values exist for the benchmark's reference.
    timeout : seconds to wait for another process's write transaction

    Thread-safe: writes go through one connection behind a lock, reads through another
    (WAL: readers see the last commit and never block the writer).
    """

    def __init__(self, path=None, *, max_upload: int = MAX_UPLOAD, check: Optional[Callable[[Shot], None]] = None,
                 synchronous: str = "FULL", journal_mode: str = "WAL", timeout: float = 30.0):
        if synchronous.upper() not in ("OFF", "NORMAL", "FULL", "EXTRA"):
            raise ValueError(f"synchronous: {synchronous!r}; expected OFF, NORMAL, FULL or EXTRA")
        if journal_mode.upper() not in ("WAL", "DELETE", "TRUNCATE", "PERSIST"):
            raise ValueError(f"journal_mode: {journal_mode!r}; expected WAL, DELETE, TRUNCATE or PERSIST")
        self.root = data_dir(path)
        self._real_root = Path(os.path.realpath(self.root))
        self.max_upload = int(max_upload)
        self.check = check
        self._lock = threading.RLock()
        self._rlock = threading.Lock()
        self._stat_hashes: dict = {}  # put_path: (real path, size, mtime_ns, inode, name) -> content hash
        for sub in ("files", "views", "tmp"):
            self._path(sub).mkdir(exist_ok=True, mode=0o700)
        self._clean_tmp()
        self.db_path = self._path(DB_NAME)
        self._db = self._connect(timeout, synchronous, journal_mode)
        self.journal_mode = self._db.execute("PRAGMA journal_mode").fetchone()[0]
        try:
            self._migrate()
            self._reader = self._connect(timeout, synchronous, None)
        except BaseException:
            self._db.close()
            raise

    def _connect(self, timeout, synchronous, journal_mode) -> sqlite3.Connection:
        db = sqlite3.connect(str(self.db_path), timeout=timeout, isolation_level=None, check_same_thread=False)
        if journal_mode:
            db.execute(f"PRAGMA journal_mode = {journal_mode.upper()}")  # checked against a fixed list above
        db.execute(f"PRAGMA synchronous = {synchronous.upper()}")
        db.execute("PRAGMA foreign_keys = ON")
        db.execute(f"PRAGMA busy_timeout = {int(timeout * 1000)}")
        return db

    def __repr__(self):
        return f"Store({str(self.root)!r})"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Close the database connections (idempotent)."""
        with self._lock, self._rlock:
            for name in ("_db", "_reader"):
                db = getattr(self, name, None)
                if db is not None:
                    db.close()
                    setattr(self, name, None)

    # -- plumbing ---------------------------------------------------------------------------------
    def _path(self, *parts: str) -> Path:
        """``root/parts...``, refused (:class:`UnsafePath`) unless every part is a plain name
        (no separator, not ``.``/``..``, not absolute, no NUL) and the real path, symbolic links
        followed, stays inside the data directory."""
        for p in parts:
            if (not isinstance(p, str) or p in ("", ".", "..") or "/" in p or "\\" in p or "\0" in p
                    or os.path.isabs(p) or (os.altsep and os.altsep in p)):
                raise UnsafePath(f"unsafe path component {p!r} in the data directory {self.root}")
        path = self.root.joinpath(*parts)
        real = Path(os.path.realpath(path))
        if real != self._real_root and self._real_root not in real.parents:
            raise UnsafePath(f"{'/'.join(parts)} leads outside the data directory {self.root} (to {real})")
        return path

    def _blob(self, sha: str) -> Path:
        return self._path("files", checked_sha(sha)[:2], sha)

    def _clean_tmp(self, age: float = 86400.0) -> None:
        """Remove uploads abandoned more than ``age`` seconds ago (a crashed process's)."""
        tmp = self._path("tmp")
        now = time.time()
        for p in tmp.iterdir():
            try:
                st = p.lstat()
                if now - st.st_mtime > age:
                    shutil.rmtree(p) if stat.S_ISDIR(st.st_mode) else p.unlink()
            except OSError:
                pass

    @contextmanager
    def _txn(self):
        """One write transaction (``BEGIN IMMEDIATE``: the head read inside it is the head)."""
        with self._lock:
            if self._db is None:
                raise ValueError("the store is closed")
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise

    @contextmanager
    def _read(self):
        """The reader connection, inside one read transaction (a consistent snapshot)."""
        with self._rlock:
            if self._reader is None:
                raise ValueError("the store is closed")
            db = self._reader
            db.execute("BEGIN")
            try:
                yield db
            finally:
                db.execute("COMMIT")

    def _migrate(self) -> None:
        db = self._db
        db.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied REAL NOT NULL)")
        current = db.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] or 0
        if current > SCHEMA_VERSION:
            raise ValueError(f"{self.db_path}: database schema version {current} is newer than this program's "
                             f"({SCHEMA_VERSION}); update face-retarget")
        if current == SCHEMA_VERSION:
            return
        if current > 0:  # keep a copy of what we are about to change
            with sqlite3.connect(str(self._path(f"{DB_NAME}.v{current}.bak"))) as bak:
                db.backup(bak)
            bak.close()
        with self._txn():
            current = db.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] or 0  # another process?
            for v in range(current + 1, SCHEMA_VERSION + 1):
                MIGRATIONS[v](db)
                db.execute("INSERT INTO schema_version (version, applied) VALUES (?, ?)", (v, time.time()))
        bad = db.execute("PRAGMA foreign_key_check").fetchall()
        if bad:
            raise ValueError(f"{self.db_path}: foreign keys broken after migrating: {bad[:5]}")

    def schema_version(self) -> int:
        """The database's schema version."""
        with self._read() as db:
            return db.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]

    def integrity_check(self) -> str:
        """SQLite's ``PRAGMA integrity_check`` (``"ok"`` when the file is sound)."""
        with self._read() as db:
            return "\n".join(r[0] for r in db.execute("PRAGMA integrity_check"))

    # -- files ----------------------------------------------------------------------------------
    def put_file(self, data, name: str, *, limit: Optional[int] = None) -> str:
        """Store a file's bytes under their content hash; returns the hash (:func:`core.shot.file_hash`).

        Parameters
        ----------
        data : bytes-like, a binary stream (``read``) or an iterable of bytes chunks. Read in
            1 MiB chunks and stopped as soon as it exceeds the limit (never read whole first).
        name : the file's name (metadata: reduced by :func:`safe_name`; never used as a path
            except as the last part of its view, ``views/<hash>/<name>``)
        limit : bytes allowed (default :attr:`max_upload`)

        Raises
        ------
        UploadTooLarge
            More than ``limit`` bytes (nothing is kept).
        """
        return self._put(data, name, self.max_upload if limit is None else limit)

    def _put(self, data, name, limit, expect: Optional[str] = None) -> str:
        name = safe_name(name)
        fd, tmp = tempfile.mkstemp(dir=self._path("tmp"), prefix="upload-")
        h = hashlib.blake2b(digest_size=16)
        size = 0
        try:
            with os.fdopen(fd, "wb") as out:
                for chunk in _chunks(data):
                    size += len(chunk)
                    if size > limit:
                        raise UploadTooLarge(f"{name}: larger than the upload limit of {limit} bytes "
                                             f"({limit / 2**20:.0f} MiB); nothing was stored")
                    h.update(chunk)
                    out.write(chunk)
                out.flush()
                os.fsync(out.fileno())
            sha = h.hexdigest()
            if expect is not None and sha != expect:
                raise ValueError(f"{name}: its content hashes to {sha}, not {expect} as it claims; nothing was stored")
            self._install(tmp, sha, size)
        finally:
            if os.path.lexists(tmp):
                os.unlink(tmp)
        now = time.time()
        with self._txn() as db:
            db.execute("INSERT OR IGNORE INTO files (sha, kind, size, created) VALUES (?, 'file', ?, ?)", (sha, size, now))
            db.execute("INSERT OR IGNORE INTO file_names (sha, name, added) VALUES (?, ?, ?)", (sha, name, now))
        return sha

    def _install(self, tmp: str, sha: str, size: int) -> None:
        """Move a written, fsynced temporary file to its blob path (kept if a sound copy is there)."""
        dest = self._blob(sha)
        dest.parent.mkdir(exist_ok=True, mode=0o700)
        self._path("files", sha[:2])  # the folder itself is inside (not a link out)
        if os.path.lexists(dest):
            st = dest.lstat()
            if stat.S_ISREG(st.st_mode) and st.st_size == size:
                return  # content-addressed: the same bytes are there
            if stat.S_ISDIR(st.st_mode):
                raise UnsafePath(f"files/{sha[:2]}/{sha} is a folder; the store makes none")
            # a truncated copy or a link: replaced (os.replace swaps the entry, it does not follow a link)
        os.chmod(tmp, 0o444)
        os.replace(tmp, dest)
        dfd = os.open(dest.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)

    def put_path(self, path, name: Optional[str] = None) -> str:
        """Store a file or a folder (its files, not subfolders, as :func:`core.shot.file_hash`
        counts them) that is on this server: the shots' bundled or CLI-given files. Not for
        paths a user typed. No size limit. Returns the content hash."""
        p = Path(path)
        if p.is_dir():
            members = {}
            for q in sorted(c for c in p.iterdir() if c.is_file()):
                with open(q, "rb") as f:
                    members[_member_name(q.name)] = self._put(f, q.name, math.inf)
            return self._put_folder(members, name or p.name)
        # a file stored before under this name and unchanged since (same size, mtime and inode,
        # as git's index tells) is not read, copied and fsynced again: every page of a shot set
        # its files (17 MB for the sample) once more when it opened
        st = p.stat()
        key = (os.path.realpath(p), st.st_size, st.st_mtime_ns, st.st_ino, name or p.name)
        sha = self._stat_hashes.get(key)
        if sha is not None and self._blob(sha).is_file():
            return sha
        with open(p, "rb") as f:
            sha = self._put(f, name or p.name, math.inf)
        self._stat_hashes[key] = sha
        return sha

    def _put_folder(self, members: dict, name: str, expect: Optional[str] = None) -> str:
        members = {_member_name(k): checked_sha(v, f"folder member {k}") for k, v in members.items()}
        sha = _folder_hash(members)
        if expect is not None and sha != expect:
            raise ValueError(f"folder {name}: its members hash to {sha}, not {expect}")
        now = time.time()
        with self._txn() as db:
            sizes = dict(db.execute(f"SELECT sha, size FROM files WHERE sha IN ({','.join('?' * len(members))})",
                                    list(members.values())).fetchall()) if members else {}
            missing = [k for k, v in members.items() if v not in sizes]
            if missing:
                raise ValueError(f"folder {name}: members {missing} are not stored")
            db.execute("INSERT OR IGNORE INTO files (sha, kind, size, created) VALUES (?, 'folder', ?, ?)",
                       (sha, sum(sizes[v] for v in members.values()), now))
            db.execute("INSERT OR IGNORE INTO file_names (sha, name, added) VALUES (?, ?, ?)", (sha, safe_name(name, "folder"), now))
            db.executemany("INSERT OR IGNORE INTO folder_members (folder, name, sha) VALUES (?, ?, ?)",
                           [(sha, k, v) for k, v in members.items()])
        return sha

    def file_info(self, sha: str) -> Optional[dict]:
        """``{"sha", "kind", "size", "names", "members"}`` of a stored file (None if not stored)."""
        checked_sha(sha)
        with self._read() as db:
            row = db.execute("SELECT kind, size FROM files WHERE sha = ?", (sha,)).fetchone()
            if row is None:
                return None
            names = [r[0] for r in db.execute("SELECT name FROM file_names WHERE sha = ? ORDER BY added DESC, name", (sha,))]
            members = dict(db.execute("SELECT name, sha FROM folder_members WHERE folder = ? ORDER BY name", (sha,)).fetchall())
        return {"sha": sha, "kind": row[0], "size": row[1], "names": names, "members": members}

    def has_file(self, sha: str) -> bool:
        return self.file_info(sha) is not None

    def locate(self, role: str, ref, strict: bool = True) -> Optional[str]:
        """The path of a shot's file in this store, for :meth:`core.pipeline.Pipeline.from_shot`'s
        ``locate`` hook: ``views/<hash>/<name>`` (a hard link to the blob, named as the shot
        names it so readers see its suffix; a folder's members linked the same way).

        ``ref`` : a :class:`core.shot.FileRef` (or ``{"sha", "path"}``). With ``strict`` (the
        default, what a server uses) a file the store does not hold raises FileNotFoundError, so
        :meth:`Shot.resolve` never falls back to the path a shot document claims; with
        ``strict=False`` it returns None (a local CLI may then read the recorded path).

        Raises
        ------
        FileNotFoundError
            The store does not hold it (strict), or its blob is gone.
        ValueError
            ``ref`` has no valid content hash (strict).
        """
        sha = ref.sha if isinstance(ref, FileRef) else (ref or {}).get("sha")
        path = ref.path if isinstance(ref, FileRef) else (ref or {}).get("path", "")
        if not isinstance(sha, str) or not CONTENT_HASH.match(sha):
            if strict:
                raise ValueError(f"shot: {role} file {path!r}: {sha!r} is not a content hash")
            return None
        info = self.file_info(sha)
        if info is None:
            if strict:
                raise FileNotFoundError(f"shot: {role} file {safe_name(path)} (content {sha[:12]}…) is not in the review "
                                        f"store {self.root}; upload it")
            return None
        name = safe_name(path, default="") or (info["names"][0] if info["names"] else sha)
        return str(self._view(sha, info, name))

    def _view(self, sha: str, info: dict, name: str) -> Path:
        view = self._path("views", sha, name)
        if os.path.lexists(view):
            if os.path.islink(view):
                raise UnsafePath(f"views/{sha}/{name} is a symbolic link; the store makes none")
            return view
        folder = self._path("views", sha)
        folder.mkdir(exist_ok=True, mode=0o700)
        tmp = Path(tempfile.mkdtemp(dir=folder, prefix=".tmp-"))
        try:
            if info["kind"] == "file":
                self._link(sha, tmp / "f")
                os.replace(tmp / "f", view)
            else:
                for member, msha in info["members"].items():
                    self._link(msha, tmp / _member_name(member))
                try:
                    os.rename(tmp, view)
                except OSError:  # made by another thread meanwhile
                    if not view.is_dir():
                        raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return view

    def _link(self, sha: str, dest: Path) -> None:
        blob = self._blob(sha)
        if not blob.is_file() or blob.is_symlink():
            raise FileNotFoundError(f"the review store has lost file {sha} (files/{sha[:2]}/{sha})")
        try:
            os.link(blob, dest)
        except OSError:  # a file system without hard links
            shutil.copyfile(blob, dest)

    # -- shots ----------------------------------------------------------------------------------
    def create_shot(self, shot, title: str = "", author: str = "", import_files: bool = True) -> str:
        """Store a new shot; returns its id (``secrets.token_urlsafe(12)``).

        Parameters
        ----------
        shot : a :class:`core.shot.Shot` (or its dict / JSON text)
        title, author : shown in lists; the author becomes a participant
        import_files : copy into the store each file of the shot that it does not hold yet and
            that is on this server at its recorded path with its recorded hash (so the shot
            keeps working when that path goes away: an upload folder, a restart). Meant for the
            server's own shots (``Pipeline.shot()`` of files it chose); a shot document a user
            uploaded should come in with ``import_files=False`` (its files uploaded, or
            :meth:`import_` an archive): reading is then limited to the data directory.

        Notes get ids (``n1`` …) and the store's fields (frame_end, resolved, created, updated).
        Raises ValueError for a malformed shot, title or author.
        """
        shot = _as_shot(shot)
        author = checked_text(author or "anonymous", "author")
        title = checked_text(title or "untitled", "title")
        at = time.time()
        taken: set = set()
        shot.notes = [normal_note(n, i, author, at, taken) for i, n in enumerate(shot.notes)]
        for role, ref in shot.files.items():
            checked_sha(ref.sha, f"shot: files.{role}")
            if import_files and not self.has_file(ref.sha) and Path(ref.path).exists():
                # read only when the recorded hash matches: a shot cannot make the store copy a file it
                # does not already know the content of
                if file_hash(ref.path) != ref.sha:
                    raise ValueError(f"shot: {role} file {ref.path} has changed since the shot was saved "
                                     f"(content hash {file_hash(ref.path)[:12]}…, the shot recorded {ref.sha[:12]}…)")
                self.put_path(ref.path)
        for _ in range(3):
            shot_id = secrets.token_urlsafe(12)
            try:
                with self._txn() as db:
                    self._insert_shot(db, shot_id, title, at, at, 1, shot, author, "create")
                return shot_id
            except sqlite3.IntegrityError:  # an id taken (2^-96): draw another
                continue
        raise RuntimeError("could not draw a free shot id")

    def _insert_shot(self, db, shot_id, title, created, at, version, shot: Shot, author, kind) -> None:
        doc = shot.to_dict()
        db.execute("INSERT INTO shots (id, title, created, updated, version, doc, content_hash) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (shot_id, title, created, at, version, canonical_json(doc), shot.content_hash()))
        db.execute("INSERT INTO changes (shot_id, version, base_version, author, at, kind, change) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (shot_id, version, version - 1, author, at, kind, canonical_json({"kind": kind, "doc": doc})))
        fx = {"settings": [], "edits": initial_edit_rows(shot), "notes": shot.notes,
              "files": [(r, f.sha, f.path) for r, f in shot.files.items()]}
        self._effects(db, shot_id, version, author, at, fx)

    def _effects(self, db, shot_id, version, author, at, fx) -> None:
        """Write the derived rows of one change (settings history, edit history, notes, files, participant)."""
        db.executemany("INSERT INTO settings_history (shot_id, version, author, at, stage, setting, old, new) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       [(shot_id, version, author, at, st, k, canonical_json(old), canonical_json(new))
                        for st, k, old, new in fx["settings"]])
        db.executemany("INSERT INTO edits (shot_id, version, author, at, editor, op, position, edit) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       [(shot_id, version, author, at, e, op, pos, canonical_json(ed)) for e, op, pos, ed in fx["edits"]])
        db.executemany("""INSERT INTO notes (shot_id, note_id, frame, frame_end, author, text, resolved, created, updated)
                          VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)
                          ON CONFLICT (shot_id, note_id) DO UPDATE SET frame = excluded.frame, frame_end = excluded.frame_end,
                          text = excluded.text, resolved = excluded.resolved, updated = excluded.updated""",
                       [(shot_id, n["id"], n["frame"], n.get("frame_end"), n["author"], n["text"], int(bool(n["resolved"])),
                         n["created"], n["updated"]) for n in fx["notes"]])
        for role, sha, path in fx["files"]:
            if sha is None:
                db.execute("DELETE FROM shot_files WHERE shot_id = ? AND role = ?", (shot_id, role))
            else:
                db.execute("INSERT OR REPLACE INTO shot_files (shot_id, role, sha, path) VALUES (?, ?, ?, ?)", (shot_id, role, sha, path))
        db.execute("""INSERT INTO participants (shot_id, name, first_seen, last_seen) VALUES (?, ?, ?, ?)
                      ON CONFLICT (shot_id, name) DO UPDATE SET last_seen = MAX(last_seen, excluded.last_seen)""",
                   (shot_id, author, at, at))

    def get(self, shot_id: str) -> tuple:
        """``(Shot, version)`` of a shot as last committed. Raises :class:`UnknownShot`."""
        with self._read() as db:
            row = db.execute("SELECT doc, version FROM shots WHERE id = ?", (shot_id,)).fetchone()
        if row is None:
            raise UnknownShot(f"no shot {shot_id!r} in the review store {self.root}")
        return Shot.from_dict(json.loads(row[0]), copy=False), row[1]

    def info(self, shot_id: str) -> dict:
        """``{"id", "title", "created", "updated", "version", "content_hash"}`` of a shot."""
        with self._read() as db:
            row = db.execute("SELECT id, title, created, updated, version, content_hash FROM shots WHERE id = ?", (shot_id,)).fetchone()
        if row is None:
            raise UnknownShot(f"no shot {shot_id!r} in the review store {self.root}")
        return dict(zip(("id", "title", "created", "updated", "version", "content_hash"), row))

    def recent(self, n: int = 20) -> list:
        """The ``n`` most recently changed shots (:meth:`info` dicts), newest first."""
        with self._read() as db:
            rows = db.execute("SELECT id, title, created, updated, version, content_hash FROM shots "
                              "ORDER BY updated DESC, id LIMIT ?", (int(n),)).fetchall()
        return [dict(zip(("id", "title", "created", "updated", "version", "content_hash"), r)) for r in rows]

    def _head(self, db, shot_id) -> tuple:
        row = db.execute("SELECT version, doc FROM shots WHERE id = ?", (shot_id,)).fetchone()
        if row is None:
            raise UnknownShot(f"no shot {shot_id!r} in the review store {self.root}")
        return row[0], Shot.from_dict(json.loads(row[1]), copy=False)

    def _file_name(self, db) -> Callable[[str], str]:
        def name(sha):
            row = db.execute("SELECT name FROM file_names WHERE sha = ? ORDER BY added DESC, name LIMIT 1", (sha,)).fetchone()
            return row[0] if row else sha
        return name

    def apply(self, shot_id: str, change: dict, base_version: int, author: str) -> Applied:
        """Apply one change made against version ``base_version``, committed before returning.

        Change kinds: :mod:`core.changes` (files by the hashes :meth:`put_file` returns).

        A stale ``base_version`` is rebased where the change commutes with every change since,
        else refused (the module docstring lists which). Returns :class:`Applied`.

        Raises
        ------
        Conflict
            ``base_version`` is stale and the change does not commute; the message names the
            change it conflicts with (who, which version, what).
        ValueError
            A malformed change (the field named), a base version the shot has not reached, an
            undo with nothing to undo, a note that does not exist, ``check`` refused it.
        UnknownShot
            No such shot.
        """
        author = checked_text(author or "anonymous", "author")
        at = time.time()
        with self._txn() as db:
            version, shot = self._head(db, shot_id)
            if isinstance(base_version, bool) or not isinstance(base_version, int) or not 1 <= base_version <= version:
                raise ValueError(f"base_version {base_version!r}: shot {shot_id} has versions 1 to {version}")
            ch = drop_noops(parse_change(change, shot), shot)
            if ch is None:
                return Applied(version, shot, None, False)
            if ch["kind"] == "files":
                for role, v in ch["values"].items():
                    sha = v["sha"] if isinstance(v, dict) else v
                    if sha is not None and db.execute("SELECT 1 FROM files WHERE sha = ?", (sha,)).fetchone() is None:
                        raise ValueError(f"files change: {role}: no stored file {sha}; upload it first (put_file)")
            if base_version < version:
                for v, who, theirs in db.execute("SELECT version, author, change FROM changes WHERE shot_id = ? AND version > ? "
                                                 "ORDER BY version", (shot_id, base_version)).fetchall():
                    theirs = json.loads(theirs)
                    why = conflict_reason(ch, theirs)
                    if why:
                        raise Conflict(f"refused: you {describe(ch)} on version {base_version}, but {why} since: {who} "
                                       f"{describe(theirs)} in version {v}. Reload the shot (now version {version}) and "
                                       f"try again.", version=v, author=who, change=theirs, head=version)
            new, rec, fx = apply_change(shot, ch, author, at, self._file_name(db))
            if self.check is not None:
                self.check(new)
            self._commit_change(db, shot_id, version + 1, base_version, author, at, rec, new, fx)
        return Applied(version + 1, new, rec, base_version < version)

    def _commit_change(self, db, shot_id, version, base_version, author, at, rec, new: Shot, fx) -> None:
        cur = db.execute("UPDATE shots SET version = ?, updated = ?, doc = ?, content_hash = ? WHERE id = ? AND version = ?",
                         (version, at, canonical_json(new.to_dict(copy=False)), new.content_hash(), shot_id, version - 1))
        if cur.rowcount != 1:
            raise RuntimeError(f"shot {shot_id}: version {version - 1} is not the head")
        db.execute("INSERT INTO changes (shot_id, version, base_version, author, at, kind, change) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (shot_id, version, base_version, author, at, rec["kind"], canonical_json(rec)))
        self._effects(db, shot_id, version, author, at, fx)

    def at_version(self, shot_id: str, version: int) -> Shot:
        """The shot as it was at ``version``, replayed from its changes log."""
        with self._read() as db:
            rows = db.execute("SELECT version, author, at, change FROM changes WHERE shot_id = ? AND version <= ? ORDER BY version",
                              (shot_id, int(version))).fetchall()
            head = db.execute("SELECT version FROM shots WHERE id = ?", (shot_id,)).fetchone()
        if head is None:
            raise UnknownShot(f"no shot {shot_id!r} in the review store {self.root}")
        if not rows or rows[-1][0] != version:
            raise ValueError(f"shot {shot_id} has versions 1 to {head[0]}, not {version}")
        return replay_changes([(v, a, t, json.loads(c)) for v, a, t, c in rows])

    # -- queries ----------------------------------------------------------------------------------
    def notes(self, shot_id: str, unresolved_only: bool = False) -> list:
        """The shot's notes (dicts: id, frame, frame_end, author, text, resolved, created, updated),
        by frame then creation."""
        self.info(shot_id)
        with self._read() as db:
            rows = db.execute("SELECT note_id, frame, frame_end, author, text, resolved, created, updated FROM notes "
                              "WHERE shot_id = ? AND (? = 0 OR resolved = 0) ORDER BY frame, created, note_id",
                              (shot_id, int(bool(unresolved_only)))).fetchall()
        keys = ("id", "frame", "frame_end", "author", "text", "resolved", "created", "updated")
        return [{**dict(zip(keys, r)), "resolved": bool(r[5])} for r in rows]

    def history(self, shot_id: str, since: int = 0) -> list:
        """The changes after version ``since`` (dicts: version, base_version, author, at, kind,
        change, summary); the first document of a ``create``/``import`` is left out of
        ``change`` (see :meth:`at_version`)."""
        self.info(shot_id)
        with self._read() as db:
            rows = db.execute("SELECT version, base_version, author, at, kind, change FROM changes "
                              "WHERE shot_id = ? AND version > ? ORDER BY version", (shot_id, int(since))).fetchall()
        out = []
        for v, b, a, t, k, c in rows:
            c = json.loads(c)
            c.pop("doc", None)
            out.append({"version": v, "base_version": b, "author": a, "at": t, "kind": k, "change": c, "summary": describe(c)})
        return out

    def settings_history(self, shot_id: str, stage: Optional[str] = None, setting: Optional[str] = None) -> list:
        """Every setting change (dicts: version, author, at, stage, setting, old, new), oldest first;
        file roles appear as stage ``files`` with content hashes."""
        self.info(shot_id)
        with self._read() as db:
            rows = db.execute("SELECT version, author, at, stage, setting, old, new FROM settings_history WHERE shot_id = ? "
                              "AND (? IS NULL OR stage = ?) AND (? IS NULL OR setting = ?) ORDER BY id",
                              (shot_id, stage, stage, setting, setting)).fetchall()
        return [{"version": v, "author": a, "at": t, "stage": s, "setting": k, "old": json.loads(o), "new": json.loads(n)}
                for v, a, t, s, k, o, n in rows]

    def edit_history(self, shot_id: str, editor: Optional[str] = None) -> list:
        """Every edit-list change (dicts: version, author, at, editor, op, position, edit), oldest
        first; :func:`core.changes.replay_edits` turns them into the done/undone lists."""
        self.info(shot_id)
        with self._read() as db:
            rows = db.execute("SELECT version, author, at, editor, op, position, edit FROM edits WHERE shot_id = ? "
                              "AND (? IS NULL OR editor = ?) ORDER BY id", (shot_id, editor, editor)).fetchall()
        return [{"version": v, "author": a, "at": t, "editor": e, "op": o, "position": p, "edit": json.loads(ed)}
                for v, a, t, e, o, p, ed in rows]

    def touch(self, shot_id: str, name: str) -> None:
        """Record that ``name`` is looking at the shot now (participants' last seen)."""
        name = checked_text(name or "anonymous", "participant")
        self.info(shot_id)
        now = time.time()
        with self._txn() as db:
            db.execute("""INSERT INTO participants (shot_id, name, first_seen, last_seen) VALUES (?, ?, ?, ?)
                          ON CONFLICT (shot_id, name) DO UPDATE SET last_seen = MAX(last_seen, excluded.last_seen)""",
                       (shot_id, name, now, now))

    def participants(self, shot_id: str) -> list:
        """Who has taken part (dicts: name, first_seen, last_seen), most recently seen first."""
        self.info(shot_id)
        with self._read() as db:
            rows = db.execute("SELECT name, first_seen, last_seen FROM participants WHERE shot_id = ? ORDER BY last_seen DESC, name",
                              (shot_id,)).fetchall()
        return [{"name": n, "first_seen": f, "last_seen": s} for n, f, s in rows]

    def missing_files(self, shot_id: str) -> dict:
        """``{role: FileRef}`` of the shot's files this store does not hold (after a light import)."""
        shot, _ = self.get(shot_id)
        return {r: ref for r, ref in shot.files.items() if not (CONTENT_HASH.match(ref.sha or "") and self.has_file(ref.sha))}

    # -- export / import ----------------------------------------------------------------------------
    def export(self, shot_id: str, dest, with_files: bool = True) -> dict:
        """Write a shot as one zip archive (to a path, or a binary file object such as a download).

        Members: ``shot.json`` (the document, notes included), ``review.json`` (format, id,
        title, times, version, the files by role with their hashes, names and sizes, folders'
        members, participants), ``history.json`` (the changes log, so an import has the same
        history) and, with ``with_files``, ``files/<hash>`` for every file and folder member the
        shot uses. Without files (a "light" export) the archive names them by hash only.
        Returns the ``review.json`` dict.
        """
        shot, version = self.get(shot_id)
        info = self.info(shot_id)
        with self._read() as db:
            log = [{"version": v, "base_version": b, "author": a, "at": t, "change": json.loads(c)}
                   for v, b, a, t, c in db.execute("SELECT version, base_version, author, at, change FROM changes "
                                                   "WHERE shot_id = ? AND version <= ? ORDER BY version", (shot_id, version))]
        files, folders, blobs = {}, {}, []
        for role, ref in sorted(shot.files.items()):
            fi = self.file_info(ref.sha) if CONTENT_HASH.match(ref.sha or "") else None
            files[role] = {"sha": ref.sha, "path": ref.path, "kind": fi["kind"] if fi else None,
                           "size": fi["size"] if fi else None, "names": fi["names"] if fi else []}
            if fi and fi["kind"] == "folder":
                folders[ref.sha] = fi["members"]
                blobs += list(fi["members"].values())
            elif fi:
                blobs.append(ref.sha)
        review = {"format": EXPORT_KIND, "format_version": EXPORT_FORMAT, "schema_version": SCHEMA_VERSION,
                  "id": shot_id, "title": info["title"], "created": info["created"], "updated": info["updated"],
                  "version": version, "content_hash": shot.content_hash(), "exported": time.time(),
                  "with_files": bool(with_files), "files": files, "folders": folders,
                  "participants": self.participants(shot_id)}
        target, part = dest, None
        if isinstance(dest, (str, os.PathLike)):
            part = Path(str(dest) + ".part")
            target = part
        try:
            with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as z:
                z.writestr("shot.json", shot.to_json() + "\n")
                z.writestr("review.json", json.dumps(review, indent=1, allow_nan=False) + "\n")
                z.writestr("history.json", json.dumps(log, indent=None, allow_nan=False) + "\n")
                if with_files:
                    for sha in dict.fromkeys(blobs):
                        z.write(self._blob(sha), f"files/{sha}")
            if part is not None:
                os.replace(part, dest)
        finally:
            if part is not None and part.exists():
                part.unlink()
        return review

    def import_(self, source, author: str = "import") -> str:
        """Import an :meth:`export` archive (a path or a binary file object, e.g. an upload);
        returns the shot's id here — the archive's when it is free, else a new one (a copy).

        The files in the archive are stored by hash (each must hash to its name and stay within
        :attr:`max_upload`); folders are checked against their hash. The history is replayed
        (same versions, authors, times) and must reproduce ``shot.json``; without a history the
        shot starts at version 1 by ``author``. Files a light archive does not carry are listed
        by :meth:`missing_files`. Archive member names are never used as paths.

        Raises ValueError for anything that is not such an archive or does not add up (named).
        """
        author = checked_text(author or "import", "author")
        try:
            z = zipfile.ZipFile(source)
        except zipfile.BadZipFile:
            raise ValueError(f"{source if isinstance(source, (str, os.PathLike)) else 'the upload'}: not a review archive "
                             f"(not a zip file)") from None
        with z:
            review = _read_json(z, "review.json")
            if not isinstance(review, dict) or review.get("format") != EXPORT_KIND:
                raise ValueError("archive: review.json does not describe a face-retarget review export")
            if not isinstance(review.get("format_version"), int) or review["format_version"] > EXPORT_FORMAT:
                raise ValueError(f"archive: format_version {review.get('format_version')!r} is newer than this program's "
                                 f"({EXPORT_FORMAT}); update face-retarget")
            shot = _as_shot(_read_json(z, "shot.json"))
            history = _read_json(z, "history.json") if "history.json" in z.namelist() else None
            infos = z.infolist()
            if len(infos) > 100_000:
                raise ValueError(f"archive: {len(infos)} members; a review export has a few")
            members = {i.filename[len("files/"):]: i for i in infos if i.filename.startswith("files/")}
            listed = review.get("files") or {}
            folders = review.get("folders") or {}
            if not isinstance(listed, dict) or not isinstance(folders, dict):
                raise ValueError("archive: review.json files/folders must be {role: {...}} / {hash: {name: hash}}")
            # only the blobs the shot uses are read (anything else in the archive is ignored, never extracted)
            wanted: dict = {}   # blob hash -> name
            for role, ref in shot.files.items():
                fm = folders.get(ref.sha)
                if isinstance(fm, dict):
                    wanted.update({v: k for k, v in fm.items()})
                else:
                    wanted[ref.sha] = Path(ref.path).name
            for sha, name in wanted.items():
                if not isinstance(sha, str) or not CONTENT_HASH.match(sha) or self.has_file(sha) or sha not in members:
                    continue  # not a hash (the folder check below refuses it), held already, or a light export
                with z.open(members[sha]) as f:
                    self._put(f, name, self.max_upload, expect=sha)
            for role, ref in shot.files.items():
                fm = folders.get(ref.sha)
                if isinstance(fm, dict) and not self.has_file(ref.sha):
                    if all(isinstance(v, str) and CONTENT_HASH.match(v) and self.has_file(v) for v in fm.values()):
                        self._put_folder(fm, Path(ref.path).name, expect=checked_sha(ref.sha))
        title = checked_text(str(review.get("title") or "untitled"), "title")
        wanted = review.get("id")
        with self._txn() as db:
            taken = not isinstance(wanted, str) or not _SHOT_ID.match(wanted) or \
                db.execute("SELECT 1 FROM shots WHERE id = ?", (wanted,)).fetchone() is not None
            shot_id = secrets.token_urlsafe(12) if taken else wanted
            if history:
                self._replay_into(db, shot_id, title, history)
                _, got = self._head(db, shot_id)
                if got.to_dict() != shot.to_dict():
                    raise ValueError("archive: history.json does not reproduce shot.json (the archive was edited?); "
                                     "nothing was imported")
            else:
                at = time.time()
                taken_ids: set = set()
                shot.notes = [normal_note(n, i, author, at, taken_ids) for i, n in enumerate(shot.notes)]
                self._insert_shot(db, shot_id, title, at, at, 1, shot, author, "import")
        return shot_id

    def _replay_into(self, db, shot_id: str, title: str, history: list) -> None:
        """Insert a shot by replaying an exported changes log (versions, authors and times kept)."""
        if not isinstance(history, list) or not history or not isinstance(history[0], dict):
            raise ValueError("archive: history.json must be a non-empty list of changes")
        first = history[0]
        if first.get("version") != 1 or (first.get("change") or {}).get("kind") not in ("create", "import"):
            raise ValueError("archive: history.json must start with the shot's creation (version 1)")
        at0 = float(first.get("at", time.time()))
        shot = _as_shot(first["change"].get("doc"))
        author0 = checked_text(str(first.get("author") or "import"), "author")
        taken: set = set()
        shot.notes = [normal_note(n, i, author0, at0, taken) for i, n in enumerate(shot.notes)]
        self._insert_shot(db, shot_id, title, at0, at0, 1, shot, author0, first["change"]["kind"])
        version = 1
        for i, row in enumerate(history[1:], start=2):
            if not isinstance(row, dict) or row.get("version") != i:
                raise ValueError(f"archive: history.json entry {i}: expected version {i}")
            who = checked_text(str(row.get("author") or "import"), f"archive: history.json entry {i}: author")
            at = float(row.get("at", at0))
            base = row.get("base_version", version)
            base = base if isinstance(base, int) and 1 <= base <= version else version
            ch = parse_change(row.get("change"), shot)
            shot, rec, fx = apply_change(shot, ch, who, at, self._file_name(db))
            self._commit_change(db, shot_id, i, base, who, at, rec, shot, fx)
            version = i


def _as_shot(shot) -> Shot:
    if isinstance(shot, Shot):
        return copy.deepcopy(shot)
    if isinstance(shot, dict):
        return Shot.from_dict(shot)
    if isinstance(shot, str) and shot.lstrip().startswith("{"):
        return Shot.from_json(shot)
    raise ValueError(f"shot: expected a Shot, its dict or its JSON text, got {type(shot).__name__}")


def _read_json(z: zipfile.ZipFile, name: str):
    try:
        info = z.getinfo(name)
    except KeyError:
        raise ValueError(f"archive: no {name}; not a face-retarget review export") from None
    if info.file_size > MAX_JSON:
        raise ValueError(f"archive: {name} is {info.file_size} bytes, at most {MAX_JSON}")
    with z.open(info) as f:
        data = f.read(MAX_JSON + 1)
    if len(data) > MAX_JSON:
        raise ValueError(f"archive: {name} is larger than {MAX_JSON} bytes")
    try:
        return json.loads(data.decode("utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"archive: {name} is not JSON ({e})") from None
