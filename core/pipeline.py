"""The pipeline: every stage of every method, one content-keyed cache, and the shot document.

Stages are declared once in :mod:`core.stages` (each a ``param.Parameterized`` whose parameters
are its settings, with its dependencies, the settings that matter now and a pure ``run``; see
:mod:`core.stage`). The pipeline orders them by their dependencies and keys each result by a
hash of its name, its relevant settings (files by their content), any extra content it declares
and its dependencies' keys, so

* changing alpha re-runs solve and what follows it, never calibrate or segment;
* a setting of a disabled feature (``align_beta`` with personalisation off) re-runs nothing;
* setting a value back is a cache hit (an LRU keeps recent results, not only the last);
* cached arrays are read-only, so no consumer can corrupt a cached result;
* the warnings a stage gave when it ran are kept with its result and given again on a hit.

A run takes one snapshot of all settings under the pipeline's lock: keys and runs read that
snapshot, so a widget moved during a long solve changes the next run, not this one.

The same settings generate the dashboard's widgets, the CLI's flags (:func:`cli_flags`) and
the shot's ``settings`` (:meth:`Pipeline.shot`, :meth:`Pipeline.from_shot`). The edit lists
(spacetime poses, transfer constraints, detail edits) are stage settings too, with their redo
stacks kept here. Nothing here imports panel.
"""

from __future__ import annotations

import argparse
import copy
import difflib
import functools
import hashlib
import json
import os
import pickle
import threading
import time
import warnings
from collections import Counter, OrderedDict
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, Optional

import numpy as np
import param
import platformdirs

from . import stages as _stages  # noqa: F401  (registers every stage and method)
from .progress import ProgressFn, TimeLeft
from .shot import EDITORS, EditHistory, FileRef, Shot, file_hash
from .stage import STAGES, SettingsView, setting_owners
from .stages.methods import METHODS as _METHODS

#: the registered solve methods, and the settings each reads (derived from the registrations)
METHODS = tuple(_METHODS)
METHOD_PARAMS = {n: m.params for n, m in _METHODS.items()}

# --------------------------------------------------------------------------------------
# cache


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return {"__array__": hashlib.blake2b(np.ascontiguousarray(v).tobytes(), digest_size=16).hexdigest(), "shape": v.shape, "dtype": str(v.dtype)}
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"cannot hash {type(v).__name__}")


def content_key(*parts) -> str:
    """A stable hash of JSON-able parts (arrays are hashed in full, never sampled)."""
    text = json.dumps(parts, sort_keys=True, default=_jsonable)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def file_key(path: str) -> str:
    """:func:`core.shot.file_hash` of a file (or folder); "" for no file."""
    return file_hash(path) if path else ""


def _freeze(obj):
    """Make every array in a (nested) result read-only."""
    if isinstance(obj, np.ndarray):
        obj.setflags(write=False)
    elif isinstance(obj, dict):
        for v in obj.values():
            _freeze(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _freeze(v)
    return obj


def stage_cache_dir() -> Path:
    """Where stage results kept across processes live: ``$FACE_RETARGET_CACHE`` or the per-user
    cache folder (``platformdirs.user_cache_dir("face-retarget")/stages``)."""
    return Path(os.environ.get("FACE_RETARGET_CACHE") or Path(platformdirs.user_cache_dir("face-retarget")) / "stages")


@functools.lru_cache(maxsize=None)
def code_version() -> str:
    """A hash of this package's source: a result kept on disk by other code is not read back."""
    root = Path(__file__).resolve().parent
    h = hashlib.blake2b(digest_size=16)
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


#: bytes of persisted stage results a :class:`StageCache` keeps on disk by default (2 GiB; a rig
#: pair's registration and dense correspondence are 1-20 MB each): ``$FACE_RETARGET_CACHE_MAX_MB``
#: or ``StageCache(disk_max_bytes=...)`` changes it
DISK_MAX_BYTES = 2 << 30


def default_disk_max_bytes() -> int:
    """The default bound of the on-disk stage cache: ``$FACE_RETARGET_CACHE_MAX_MB`` megabytes,
    else :data:`DISK_MAX_BYTES`."""
    mb = os.environ.get("FACE_RETARGET_CACHE_MAX_MB")
    if not mb:
        return DISK_MAX_BYTES
    try:
        return max(0, int(float(mb) * (1 << 20)))
    except ValueError:
        raise ValueError(f"FACE_RETARGET_CACHE_MAX_MB: expected a number of megabytes, got {mb!r}") from None


def evict_disk(folder: Path, max_bytes: int, keep=()) -> list:
    """Delete the least recently used results (``*.pkl``, by modification time: written or
    read back, :meth:`StageCache.compute` touches a file it reads) of ``folder`` until the rest
    takes at most ``max_bytes``; the paths in ``keep`` stay whatever their size. Files other
    processes delete meanwhile are skipped. Returns the deleted paths."""
    entries = []
    try:
        for p in Path(folder).glob("*.pkl"):
            try:
                st = p.stat()
            except OSError:  # deleted by another process meanwhile
                continue
            entries.append((st.st_mtime, st.st_size, p))
    except OSError:
        return []
    keep = {Path(k) for k in keep}
    total = sum(size for _, size, _ in entries)
    gone = []
    for _, size, p in sorted(entries, key=lambda e: (e[0], str(e[2]))):  # oldest first
        if total <= max_bytes:
            break
        if p in keep:
            continue
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        except OSError:
            continue
        total -= size
        gone.append(p)
    return gone


def _write_atomic(path: Path, value) -> None:
    """Pickle ``value`` to ``path`` through a temporary file (a reader never sees half a file);
    a folder that cannot be written keeps nothing, it does not fail the run."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}")
        with open(tmp, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)
    except OSError:
        pass


class StageCache:
    """A thread-safe LRU of stage results keyed by content hash.

    Pipelines that share one cache (the pages of a review server) also share the work in
    flight: :meth:`compute` of a key another thread is computing waits for that result
    instead of computing it again (20 pages of one shot recompute a setting change once)."""

    def __init__(self, max_entries: int = 96, disk=True, disk_max_bytes: Optional[int] = None):
        self.max_entries = max_entries
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._inflight: dict = {}
        #: where the results of stages marked ``persist`` (a rig pair's registration) are kept across
        #: processes: a folder, True for :func:`stage_cache_dir`, None/False for nowhere
        self.disk = stage_cache_dir() if disk is True else (Path(disk) if disk else None)
        #: after every write the folder is cut to this many bytes, least recently used first
        #: (:func:`evict_disk`); default :func:`default_disk_max_bytes`
        self.disk_max_bytes = default_disk_max_bytes() if disk_max_bytes is None else int(disk_max_bytes)

    def get(self, key):
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                return True, self._data[key]
            return False, None

    def has(self, key) -> bool:
        """Whether ``key``'s result is in memory (a run will not compute it; not a use)."""
        with self._lock:
            return key in self._data

    def put(self, key, value):
        with self._lock:
            self._data[key] = value
            self._data.move_to_end(key)
            while len(self._data) > self.max_entries:
                self._data.popitem(last=False)

    def compute(self, key, fn, persist: bool = False):
        """``(hit, value)``: the cached value of ``key`` (waiting for another thread computing
        it), or ``fn()`` computed here and cached (``hit`` False). When the other thread's
        computation fails, this one computes (and raises its own error). ``persist``: the value
        is also kept on :attr:`disk` and read from there by any process (a disk hit is a hit)."""
        while True:
            with self._lock:
                if key in self._data:
                    self._data.move_to_end(key)
                    return True, self._data[key]
                ev = self._inflight.get(key)
                if ev is None:
                    ev = self._inflight[key] = threading.Event()
                    break
            ev.wait()
        try:
            path = self._disk_path(key) if persist and self.disk is not None else None
            if path is not None and path.exists():
                try:
                    with open(path, "rb") as f:
                        value = pickle.load(f)
                    self.put(key, value)
                    try:
                        os.utime(path)  # recently used: the eviction keeps it longest
                    except OSError:
                        pass
                    return True, value
                except Exception:  # a file cut short or from another numpy: computed again
                    path.unlink(missing_ok=True)
            value = fn()
            self.put(key, value)
            if path is not None:
                _write_atomic(path, value)
                evict_disk(self.disk, self.disk_max_bytes, keep=[path])
            return False, value
        finally:
            with self._lock:
                self._inflight.pop(key, None)
            ev.set()

    def _disk_path(self, key) -> Path:
        name, k = key
        return self.disk / f"{name}-{content_key(k, code_version())}.pkl"

    def clear(self):
        with self._lock:
            self._data.clear()

    def __len__(self):
        return len(self._data)


def shot_from_settings(doc: dict) -> dict:
    """A version-0 shot (a flat ``{setting: value}`` dict, as ``Pipeline(**settings)`` takes it,
    file settings as paths) as a version-1 document, each setting routed to the stage that owns it."""
    owners = setting_owners()
    unknown = [k for k in doc if k not in owners]
    if unknown:
        raise ValueError(f"version-0 shot: unknown settings {unknown}")
    out = {"schema_version": 1, "files": {}, "settings": {}, "edits": {}, "frame": 0, "notes": []}
    editors = {setting: editor for editor, setting in EDITORS.items()}
    for k, v in doc.items():
        stage, is_file = owners[k]
        if is_file:
            if v:
                out["files"][k] = {"path": str(v), "sha": file_hash(v)}
        elif k in editors:
            out["edits"][editors[k]] = {"done": list(v or []), "undone": []}
        else:
            out["settings"].setdefault(stage, {})[k] = v
    return out


# --------------------------------------------------------------------------------------
# the stage graph


def _stage_order() -> list:
    """Registered stage names, dependencies first (registration order among equals)."""
    order, seen = [], set()

    def visit(n, path=()):
        if n in seen:
            return
        if n in path:
            raise ValueError(f"stage dependency cycle: {' -> '.join(path + (n,))}")
        if n not in STAGES:
            raise ValueError(f"stage {path[-1]!r} depends on unknown stage {n!r}")
        for d in STAGES[n].deps:
            visit(d, path + (n,))
        seen.add(n)
        order.append(n)

    for n in STAGES:
        visit(n)
    return order


class Pipeline:
    """Runs stale stages in dependency order and caches every result by content.

    Parameters
    ----------
    cache : StageCache, optional — share one between sessions to share work.
    **settings : any stage's settings by name (``alpha=0.1``, ``source="take.csv"``).

    Attributes
    ----------
    stages : OrderedDict name -> stage object (its parameters are the settings); a stage is also
        an attribute: ``pipe.solve.method``.
    runs : Counter of stage executions (cache misses), for tests and the timings panel.
    timings : dict stage -> seconds of its last execution (0 for a hit).
    keys : dict stage -> key of the result last returned.
    redo : dict editor -> redo stack of that editor's edit list (see :data:`core.shot.EDITORS`).
    frame, notes : the review state a shot carries (current frame, frame-anchored notes).
    """

    def __init__(self, cache: Optional[StageCache] = None, **settings):
        self.cache = cache if cache is not None else StageCache()
        self.stages = OrderedDict((n, STAGES[n](name=n)) for n in _stage_order())
        self.runs: Counter = Counter()
        self.timings: dict = {}
        self.keys: dict = {}
        self.redo: dict = {e: [] for e in EDITORS}
        #: ``f(editor, op, arg)`` called after each edit operation (op: add | undo | redo | remove;
        #: arg: the edit, None, or the index) — a shared review page sends them to the review store
        self.listeners: list = []
        self.frame = 0
        self.notes: list = []
        self._lock = threading.RLock()
        self._told: Optional[list] = None  # edit operations heard when the open transaction completes
        self._warned: dict = {}  # the warnings registry of the stages' warnings given again
        self._last: dict = {}  # stage -> the last result returned: the warm start of a ``warm_start`` stage
        self._owners = {p: st for st in self.stages.values() for p in st.setting_names()}
        self.configure(**settings)

    def __getattr__(self, name):
        stages = self.__dict__.get("stages")
        if stages is not None and name in stages:
            return stages[name]
        raise AttributeError(f"{type(self).__name__!r} has no attribute or stage {name!r}")

    # settings -------------------------------------------------------------------------
    @property
    def settings_objects(self) -> dict:
        """stage name -> stage object, for the stages that have settings (widgets, CLI flags)."""
        return {n: s for n, s in self.stages.items() if s.setting_names()}

    def configure(self, **values) -> None:
        """Set settings by name, whichever stage owns it (``alpha=0.1``); KeyError with a
        "did you mean" for an unknown name."""
        unknown = [k for k in values if k not in self._owners]
        if unknown:
            hints = {k: difflib.get_close_matches(k, self._owners, n=2) for k in unknown}
            raise KeyError(f"unknown settings {unknown}; did you mean {hints}?")
        by_stage: dict = {}
        for k, v in values.items():
            by_stage.setdefault(self._owners[k].stage_name, {})[k] = v
        with self._lock:
            for n, vals in by_stage.items():
                for editor, setting in EDITORS.items():  # an edit list set from outside starts a new history
                    if setting in vals and list(vals[setting]) != list(getattr(self.stages[n], setting)):
                        self.redo[editor] = []
                self.stages[n].param.update(**vals)

    def config(self) -> SimpleNamespace:
        """A frozen snapshot of every stage's settings: ``cfg.solve.method``."""
        with self._lock:
            return SimpleNamespace(**{n: SimpleNamespace(**s.settings()) for n, s in self.stages.items()})

    # edits (their undo/redo history) --------------------------------------------------
    def _edit_stage(self, editor: str):
        if editor not in EDITORS:
            raise KeyError(f"unknown editor {editor!r}; editors are {sorted(EDITORS)}")
        setting = EDITORS[editor]
        return self._owners[setting], setting

    def edits(self, editor: str) -> EditHistory:
        """The edit list of ``editor`` ("spacetime", "transfer", "detail") with its redo stack (a copy)."""
        st, setting = self._edit_stage(editor)
        with self._lock:
            return EditHistory(copy.deepcopy(list(getattr(st, setting))), copy.deepcopy(self.redo[editor]))

    def _set_edits(self, editor: str, history: EditHistory) -> None:
        st, setting = self._edit_stage(editor)
        with self._lock:
            st.param.update(**{setting: history.done})
            self.redo[editor] = history.undone

    def _tell(self, editor: str, op: str, arg=None) -> None:
        if self._told is not None:  # inside a transaction: heard when it completes
            self._told.append((editor, op, arg))
            return
        for f in list(self.listeners):
            f(editor, op, arg)

    @contextmanager
    def transaction(self):
        """Changes made inside the block — settings, edits and their redo stacks — are kept only if
        it completes. On an exception everything returns to what it was before the block, the
        listeners (a review page's store) hear nothing of it, and the exception propagates; on
        success they hear every edit operation, in order. The pipeline stays locked meanwhile, so
        a run inside the block (the check that the edit solves) sees exactly its changes::

            with pipe.transaction():
                pipe.add_edit("transfer", spec)
                pipe.results(["transfer_edit"])   # raises: the edit is gone, redo stack as it was
        """
        with self._lock:
            outer = self._told is None
            saved = ({n: st.settings() for n, st in self.stages.items()}, copy.deepcopy(self.redo))
            if outer:
                self._told = []
            try:
                yield self
            except BaseException:
                settings, redo = saved
                for n, st in self.stages.items():
                    changed = {k: v for k, v in settings[n].items() if getattr(st, k) != v}
                    if changed:
                        st.param.update(**changed)
                self.redo = redo
                if outer:
                    self._told = None
                raise
            if outer:
                told, self._told = self._told, None
                for args in told:
                    self._tell(*args)

    def add_edit(self, editor: str, edit: dict) -> None:
        """Append an edit (clears that editor's redo stack)."""
        h = self.edits(editor)
        h.add(edit)
        self._set_edits(editor, h)
        self._tell(editor, "add", copy.deepcopy(edit))

    def undo(self, editor: str) -> bool:
        h = self.edits(editor)
        ok = h.undo()
        if ok:
            self._set_edits(editor, h)
            self._tell(editor, "undo")
        return ok

    def redo_edit(self, editor: str) -> bool:
        h = self.edits(editor)
        ok = h.redo()
        if ok:
            self._set_edits(editor, h)
            self._tell(editor, "redo")
        return ok

    def remove_edit(self, editor: str, index: int) -> dict:
        h = self.edits(editor)
        e = h.remove(index)
        self._set_edits(editor, h)
        self._tell(editor, "remove", index)
        return e

    # the shot -------------------------------------------------------------------------
    def shot(self) -> Shot:
        """The shot document of this pipeline: files (the path each file setting reads, e.g. a
        rig's default layout, with its content hash), every stage's settings, every edit list with
        its redo stack, the frame and the notes."""
        with self._lock:
            cfg = self.config()
            files, settings = {}, {}
            for n, st in self.stages.items():
                for k, v in vars(getattr(cfg, n)).items():
                    if k not in st.files and k not in EDITORS.values():
                        settings.setdefault(n, {})[k] = v
                for k, path in st.file_paths(cfg).items():
                    if path:
                        files[k] = FileRef(str(path), file_key(str(path)))
            edits = {e: self.edits(e) for e in EDITORS}
            return Shot(files, settings, edits, int(self.frame), copy.deepcopy(self.notes))

    @classmethod
    def from_shot(cls, shot, cache: Optional[StageCache] = None, base=None, locate: Optional[Callable] = None,
                  **overrides) -> "Pipeline":
        """A pipeline that computes exactly what ``shot`` describes.

        Parameters
        ----------
        shot : Shot, its plain-data dict, or a path / JSON text of one (:meth:`Shot.from_json`);
            a version-0 document (flat settings) is upgraded by :func:`shot_from_settings`
        base : folder relative file paths are also looked for in (default: the shot file's folder)
        locate : ``(role, FileRef) -> path or None``, e.g. a review store's files by hash
        **overrides : settings that replace the shot's (like CLI flags); an overridden file is
            not checked against the shot's hash.

        Raises
        ------
        FileNotFoundError / ValueError
            A file of the shot is missing or its content changed (see :meth:`Shot.resolve`);
            unknown settings in the shot.
        """
        if isinstance(shot, dict):
            shot = Shot.from_dict(shot, flat=shot_from_settings)
        elif not isinstance(shot, Shot):
            if base is None and isinstance(shot, (str, Path)) and not str(shot).lstrip().startswith("{"):
                base = Path(shot).resolve().parent
            shot = Shot.from_json(shot, flat=shot_from_settings)
        owners = setting_owners()
        values = {}
        for stage, vals in shot.settings.items():
            for k, v in vals.items():
                if k not in owners or owners[k][0] != stage:
                    where = f"stage {owners[k][0]!r}" if k in owners else "no stage"
                    raise ValueError(f"shot: settings.{stage}.{k}: unknown setting ({k!r} belongs to {where})")
                values[k] = v
        for role in shot.files:
            if role not in owners or not owners[role][1]:
                raise ValueError(f"shot: files.{role}: not a file setting")
            if role not in overrides:
                values[role] = shot.resolve(role, base, locate)
        pipe = cls(cache=cache, **values)
        for editor in EDITORS:
            pipe._set_edits(editor, copy.deepcopy(shot.edits.get(editor, EditHistory())))
        pipe.frame, pipe.notes = int(shot.frame), copy.deepcopy(shot.notes)
        if overrides:
            pipe.configure(**overrides)
        return pipe

    # running ------------------------------------------------------------------------
    def view(self, name: str, cfg=None) -> SettingsView:
        """What stage ``name``'s ``run`` reads now: its declared settings (:meth:`Stage.declared`),
        a file setting as the path it reads (:meth:`Stage.file_paths`, e.g. a rig's default layout)."""
        cfg = cfg if cfg is not None else self.config()
        stage = self.stages[name]
        own = getattr(cfg, name)
        values = {k: getattr(own, k) for k in stage.declared(cfg)}
        values.update({k: v for k, v in stage.derived(cfg).items() if k in values})
        for f, path in stage.file_paths(cfg).items():
            if f in values:
                values[f] = path
        return SettingsView(name, values)

    def key(self, name: str, _memo=None, _cfg=None) -> str:
        """The cache key stage ``name`` would have now (no computation): a hash of exactly what its
        ``run`` reads (:meth:`view`, files by content) and its dependencies' keys."""
        memo = {} if _memo is None else _memo
        cfg = _cfg if _cfg is not None else self.config()
        if name in memo:
            return memo[name]
        stage = self.stages[name]
        if not stage.active(cfg):
            memo[name] = content_key(name, "inactive")
            return memo[name]
        values = self.view(name, cfg).values()
        for f in stage.files:
            if f in values:
                values[f] = file_key(values[f])
        extra = stage.content(cfg)
        memo[name] = content_key(name, values, [self.key(d, memo, cfg) for d in stage.reads(cfg)],
                                 *(() if extra is None else (extra,)))
        return memo[name]

    def _run(self, targets: list, progress: Optional[ProgressFn] = None) -> dict:
        with self._lock:
            cfg = self.config()
            order = self._order(*targets, cfg=cfg)
            memo: dict = {}
            results: dict = {}
            self.timings = {}
            if progress:
                # one bar and one time left for the run: each stage to compute takes its share by
                # its cost (a cached or inactive one none)
                progress = TimeLeft(progress)
                share = np.array([self.stages[n].cost if self.stages[n].active(cfg)
                                  and not self.cache.has((n, self.key(n, memo, cfg))) else 0.0 for n in order])
                ends = np.cumsum(share) / max(share.sum(), 1e-12)
            for i, name in enumerate(order):
                stage = self.stages[name]
                k = self.key(name, memo, cfg)
                if not stage.active(cfg):
                    results[name], self.keys[name], self.timings[name] = None, k, 0.0
                    continue
                def compute(name=name, stage=stage, i=i):
                    inner = None
                    if progress:
                        lo, hi = (ends[i - 1] if i else 0.0), ends[i]
                        progress(lo, f"{name}…")
                        inner = lambda f, m, lo=lo, hi=hi: progress(lo + f * (hi - lo), f"{name}: {m}")  # noqa: E731
                    # a warm start is a hint (where an iterative solve begins), not an input: it is in no key
                    hint = {"warm": self._last.get(name)} if stage.warm_start else {}
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always")
                        value = stage.run({d: results[d] for d in stage.reads(cfg)}, self.view(name, cfg), inner, **hint)
                    _freeze(value)
                    return value, tuple((w.message, w.category, w.filename, w.lineno) for w in caught)

                t0 = time.perf_counter()
                hit, (value, warned) = self.cache.compute((name, k), compute, persist=stage.persist)
                # a result's warnings are part of it: said again however it is reached (a page
                # whose results came from another's run, a batch shot sharing a registration)
                for message, category, filename, lineno in warned:  # once per pipeline, unless "always"
                    warnings.warn_explicit(message, category, filename, lineno, registry=self._warned)
                dt = time.perf_counter() - t0
                # computed here: its time; a cache hit: 0, or the wait for another pipeline's run of it
                self.timings[name] = dt if not hit or dt > 1e-3 else 0.0
                if not hit:
                    self.runs[name] += 1
                results[name] = value
                self.keys[name] = k
                if stage.warm_start:  # only a warm start reads it: other results stay the cache's to drop
                    self._last[name] = value
            if progress:
                progress(1.0, "done")
            return results

    def run(self, upto=None, progress: Optional[ProgressFn] = None):
        """Run every stage ``upto`` needs (default: the retargeting result, ``evaluate``) whose
        key is not cached; return the result of ``upto`` (the last, for a list).

        ``progress(fraction, message)`` hears about stage starts and long stages' progress.
        """
        targets = [upto] if isinstance(upto, str) else list(upto or ["evaluate"])
        return self._run(targets, progress)[targets[-1]]

    def results(self, names=None, progress: Optional[ProgressFn] = None) -> dict:
        """Results of several stages (running what is stale); default: the retargeting stages."""
        names = list(names or self._order("evaluate"))
        res = self._run(names, progress)
        return {n: res[n] for n in names}

    def _order(self, *targets: str, cfg=None) -> list:
        """The stages ``targets`` need, in dependency order. An inactive stage needs nothing:
        its inputs are not computed for it (they run only if an active stage needs them)."""
        for t in targets:
            if t not in self.stages:
                raise KeyError(f"no stage {t!r}; stages are {list(self.stages)}")
        cfg = cfg if cfg is not None else self.config()
        need, stack = set(), list(targets)
        while stack:
            n = stack.pop()
            if n not in need:
                need.add(n)
                if self.stages[n].active(cfg):
                    stack.extend(self.stages[n].reads(cfg))
        return [n for n in self.stages if n in need]


# --------------------------------------------------------------------------------------
# CLI flags from the same settings


def cli_flags(pipeline_or_cls=None):
    """(flag, param name, parameter object, owner) for every tunable setting, e.g.
    ``--alpha`` -> ("alpha", Number). One definition serves the dashboard and the CLI.
    Edit lists and tables (the per-shape controls) are not flags: they come from a shot, or a
    JSON file (``--controls``)."""
    objs = pipeline_or_cls.settings_objects if pipeline_or_cls is not None else Pipeline().settings_objects
    out = []
    for stage, obj in objs.items():
        for pname in obj.tunable_names():
            out.append(("--" + pname.replace("_", "-"), pname, obj.param[pname], stage))
    return out


def add_cli_arguments(parser, skip=()) -> None:
    """Add one argparse option per setting (types, choices, defaults and help from param)."""
    for flag, pname, p, stage in cli_flags():
        if pname in skip:
            continue
        default = "" if p.default in ("", None) else f" (default: {p.default})"
        kw = {"dest": pname, "default": argparse.SUPPRESS, "help": f"[{stage}] {p.doc}{default}"}
        if isinstance(p, param.Boolean):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, **kw)
            continue
        if isinstance(p, param.Selector):
            kw["choices"] = list(p.objects)
            if all(isinstance(o, int) and not isinstance(o, bool) for o in p.objects):
                kw["type"] = int
        elif isinstance(p, param.Integer):
            kw["type"] = int
        elif isinstance(p, param.Number):
            kw["type"] = float
        parser.add_argument(flag, **kw)
