"""One browser session's state: the chosen files, the pipeline, the latest results.

The session owns a :class:`core.pipeline.Pipeline`: its stages' settings are the widgets'
models, its edit lists (with undo/redo) and its frame and notes are the session's whole state,
so :meth:`shot` is everything the page shows and :meth:`open_shot` brings a saved one back.
``recompute()`` runs whatever is stale (the pipeline knows) and publishes a plain snapshot that
views turn into panes; :meth:`dense` runs the dense-transfer stages. Errors become a message,
never a stack trace. No numerics live here: only choosing files, calling the pipeline and
packaging results.
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import param

from core.pipeline import Pipeline, StageCache, file_key
from core.stages.methods import suggested_frames
from core.shot import EDITORS, Shot

log = logging.getLogger("face_retarget.dashboard")

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
NONE = "(none)"
UPLOAD = "⤒ "

#: one cache for every session of this server process: results are keyed by content,
#: so two reviewers looking at the same take share the work
SHARED_CACHE = StageCache(max_entries=128)
#: the largest upload a page may send, in bytes (``face-retarget serve --max-upload-mb`` sets it)
MAX_UPLOAD = 200 * 2**20


def largest_message_file() -> int:
    """The largest file a page's websocket takes, in bytes: twice :data:`MAX_UPLOAD`, so that a
    file just over the limit still arrives and gets its message (``face-retarget serve`` sizes the
    websocket for it, as base64); a review import (a shot with its files) may be that large."""
    return 2 * MAX_UPLOAD


def too_large(name: str, size: int, limit: int | None = None, what: str = "") -> str:
    """The message for a file over ``limit`` bytes (default :data:`MAX_UPLOAD`; the server's check
    and the browser's), ``what`` naming the kind of file when the limit is not the upload's."""
    limit = MAX_UPLOAD if limit is None else limit
    return (f"{name} is {size / 2**20:.0f} MB, more than this server takes{what} ({limit / 2**20:.0f} MB): "
            "ask whoever runs it to raise the upload limit")


#: the stages the dense-transfer tab shows
DENSE_STAGES = ["transfer", "transfer_edit", "detail_edit"]


def bundled(kind: str) -> dict:
    """label -> path of the bundled sample files of ``kind`` ("performances" or "rigs")."""
    folder = DATA / kind
    pats = {"performances": ("*.csv", "*.trc", "*.c3d"), "rigs": ("*.glb", "*.gltf")}[kind]
    files = sorted(p for pat in pats for p in folder.glob(pat))
    return {p.name: str(p) for p in files}


#: the temp folders of sessions' uploads are named ``<prefix><server pid>-<random>``
UPLOAD_PREFIX = "face-retarget-upload-"


def sweep_orphan_uploads(root=None) -> int:
    """Remove the upload folders of servers that are gone (a killed server cannot remove its
    sessions' folders: each holds every file uploaded into it). Only folders named with the PID
    of a process that no longer exists are touched. Returns how many were removed."""
    import shutil

    removed = 0
    for d in Path(root or tempfile.gettempdir()).glob(f"{UPLOAD_PREFIX}*-*"):
        pid = d.name[len(UPLOAD_PREFIX):].split("-", 1)[0]
        if not (pid.isdigit() and d.is_dir()) or _alive(int(pid)):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed += not d.exists()
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _content(path: str) -> str:
    """The content hash of a file or folder (memoised by its stat), "" for none or a missing one."""
    try:
        return file_key(path)
    except FileNotFoundError:
        return ""


@dataclass(frozen=True)
class Upload:
    """What an uploaded file became (:meth:`Session.upload`): its ``kind`` ("take", "rig",
    "layout", "controls", "name_map" or "shot"), its ``label`` in the file lists (``⤒ <name>``)
    and the ``message`` the page shows (the file named as uploaded, never a server path)."""

    kind: str
    label: str
    message: str


class Session(param.Parameterized):
    """Selections + pipeline + results for one browser tab."""

    source = param.Selector(default=None, objects=[], doc="Source performance")
    source_rig = param.Selector(default=None, objects=[], doc="Rig the source curves drive")
    target_rig = param.Selector(default=None, objects=[], doc="Target rig")
    auto_update = param.Boolean(default=True, doc="Recompute as soon as a setting changes (off: press Apply)")

    busy = param.Boolean(default=False)
    progress = param.Integer(default=0, bounds=(0, 100))
    status = param.String(default="")
    error = param.String(default="")
    version = param.Integer(default=0, doc="Bumped whenever new results are published")

    def __init__(self, cache: StageCache | None = None, **params):
        self.files = {"performances": bundled("performances"), "rigs": bundled("rigs")}
        super().__init__(**params)
        self.pipeline = Pipeline(cache=cache if cache is not None else SHARED_CACHE)
        self._refresh_options()
        perf, rigs = self.files["performances"], self.files["rigs"]
        self.source = next((k for k in perf if "take_s07" in k), next(iter(perf), None))
        self.source_rig = next((k for k in rigs if k.startswith("ict")), NONE)
        self.target_rig = next((k for k in rigs if k.startswith("rocketbox")), next(iter(rigs), None))
        # the sample's target has 175 shapes of which 52 are ARKit: solving on those gives curves an
        # animator recognises (a rig without ARKit names keeps all its shapes, see core.stages.solver_shapes);
        # the dense transfer starts on 300 frames (2,000 ICT frames take minutes); the page opens on the
        # default method, auto, and says what it chose
        self.pipeline.configure(target_shapes="arkit", transfer_last_frame=299)  # the method: auto, the default
        self.snapshot: dict = {}
        self.package = None
        self._lock = threading.Lock()
        self._apply_selection()
        # the pipeline always holds the selected files (views may run stages without a recompute)
        self.param.watch(lambda *events: self._apply_selection(), ["source", "source_rig", "target_rig"])
        self._upload_dir: Path | None = None

    @property
    def upload_dir(self) -> Path:
        """This session's folder for uploaded files, made on first use and removed with the
        session (a page that never uploads leaves nothing behind; a long-running server used to
        keep one empty folder per page ever opened, and every uploaded file, in the temp dir)."""
        if self._upload_dir is None:
            import shutil
            import weakref

            self._upload_dir = Path(tempfile.mkdtemp(prefix=f"{UPLOAD_PREFIX}{os.getpid()}-"))
            weakref.finalize(self, shutil.rmtree, str(self._upload_dir), ignore_errors=True)
        return self._upload_dir

    # -- files --------------------------------------------------------------------------
    def _refresh_options(self):
        self.param.source.objects = list(self.files["performances"])
        self.param.source_rig.objects = [NONE] + list(self.files["rigs"])
        self.param.target_rig.objects = list(self.files["rigs"])

    def add_upload(self, filename: str, data: bytes) -> str:
        """:meth:`upload`'s message (what the file became)."""
        return self.upload(filename, data).message

    def upload(self, filename: str, data: bytes) -> "Upload":
        """Store an uploaded file, check it with the program's readers (:func:`core.io.check.check_upload`)
        and put it where it belongs: a take becomes the source, a rig joins the rig lists, a marker
        layout applies to the chosen target rig, a name map to the source's channels, a shot is
        opened. Returns what it became (:class:`Upload`: its kind, its list label, the message); raises ValueError in plain words (naming the file as it
        was uploaded) and keeps nothing of a bad file."""
        from core.io.check import check_upload

        name = Path(str(filename or "").replace("\\", "/")).name.strip()
        if not name or name in (".", "..") or name.startswith(".") or "\x00" in name:
            raise ValueError(f"the upload's file name {str(filename)[:80]!r} is not usable: rename the file and upload it again")
        if not data:
            raise ValueError(f"{name} is empty: upload the file again (the upload may have been cut off)")
        if len(data) > MAX_UPLOAD:
            raise ValueError(too_large(name, len(data)))
        path = self.upload_dir / name
        # the file stays in this session's upload folder: no name reaches outside it, and a link
        # planted under the name is replaced, not written through
        if path.resolve().parent != self.upload_dir.resolve():
            raise ValueError(f"the upload's file name {name!r} is not usable")
        if path.is_symlink():
            path.unlink()
        path.write_bytes(data)
        try:
            info = check_upload(path, name, target_rig=self._target_rig_object() if name.lower().endswith(".json") else None)
        except ValueError:
            path.unlink(missing_ok=True)
            raise
        label = UPLOAD + name
        kind = info["kind"]
        if kind == "rig":
            self.files["rigs"][label] = str(path)
            self._refresh_options()
            return Upload("rig", label, f"{info['summary']} — added to the rig lists: use it as the target or as the source rig")
        if kind == "take":
            self.files["performances"][label] = str(path)
            self._refresh_options()
            self.source = label
            return Upload("take", label, f"{info['summary']} — selected as the source")
        if kind == "layout":
            self.pipeline.configure(target_layout=str(path))
            return Upload("layout", label, f"{info['summary']} — the target rig's markers")
        if kind == "controls":
            table = {k: v for k, v in info["controls"].items() if k not in ("format", "version")}
            self.pipeline.configure(controls=table)
            return Upload("controls", label, f"{info['summary']} — the solver's per-shape controls")
        if kind == "name_map":
            self.pipeline.configure(name_map=str(path))
            return Upload("name_map", label, f"{info['summary']} — maps the source's channels to the source rig's shapes")
        self.open_shot(data.decode("utf-8-sig", errors="replace"), name=name)
        return Upload("shot", label, f"shot {name} opened")

    def _target_rig_object(self):
        from core.io.rigs import load_rig

        path = self.files["rigs"].get(self.target_rig, "")
        try:
            return load_rig(path) if path else None
        except (ValueError, OSError):
            return None

    # -- markers on a rig without a layout ------------------------------------------------------
    def missing_layout(self, role: str = "target") -> str:
        """The file name of the selected ``role`` rig ("target" or "source") when it has no marker
        layout (none chosen, no sidecar, none bundled), else ""."""
        from core.io.layout import default_layout_path

        label = self.target_rig if role == "target" else self.source_rig
        rig = self.files["rigs"].get(label, "") if label not in (None, NONE) else ""
        if not rig or getattr(getattr(self.pipeline, f"{role}_face"), f"{role}_layout") or default_layout_path(rig) is not None:
            return ""
        return Path(rig).name

    @property
    def needs_layout(self) -> str:
        """The name of the selected target rig when it has no marker layout (else "")."""
        return self.missing_layout("target")

    def layout_path(self, role: str = "target") -> Path:
        """Where the ``role`` rig's layout made or edited here is kept: beside an uploaded rig (its
        sidecar, so the rig finds it by default), else in the upload folder."""
        from core.io.layout import sidecar_layout_path

        rig = Path(self.files["rigs"][self.target_rig if role == "target" else self.source_rig])
        return sidecar_layout_path(rig) if self._upload_dir is not None and rig.parent == self._upload_dir else self.upload_dir / f"{rig.stem}.layout.json"

    def place_markers(self, progress=None, role: str = "target") -> dict:
        """Place the 41 markers on the ``role`` rig ("target" or "source") automatically
        (:func:`core.registration.place_markers`), keep them as the rig's layout; returns the report
        (its ``message`` says which markers need a hand)."""
        from core.io.layout import write_layout
        from core.io.rigs import load_rig
        from core.registration import place_markers

        path = self.files["rigs"][self.target_rig if role == "target" else self.source_rig]
        rig = load_rig(path)
        layout, report = place_markers(rig, progress=progress)
        out = self.layout_path(role)
        write_layout(out, layout, Path(path).name, notes="placed by face-retarget (automatic), check the flagged markers")
        self.pipeline.configure(**{f"{role}_layout": str(out)})
        return report

    def move_marker(self, name: str, vertex: int, weights=(1.0, 0.0, 0.0)) -> tuple:
        """Put marker ``name`` of the target layout on ``vertex`` (with barycentric ``weights``
        over it and its layout row's other two vertices) and keep the layout. Returns where it was,
        ``(vertex, weights)``: passed back here, that undoes the move."""
        import dataclasses

        from core.io.layout import write_layout

        ld = self.pipeline.results(["target_face"])["target_face"]
        layout, rig = ld["target_layout"], ld["target_rig"]
        i = layout.names.index(name)
        V, W = layout.vertices.copy(), layout.weights.copy()
        was = (V[i].copy(), W[i].copy())
        V[i], W[i] = vertex, weights
        out = self.layout_path()
        write_layout(out, dataclasses.replace(layout, vertices=V, weights=W), Path(self.files["rigs"][self.target_rig]).name)
        self.pipeline.configure(target_layout=str(out))
        return was

    def layout_json(self) -> bytes:
        """The target rig's current layout as JSON (a download)."""
        import tempfile as _tf

        from core.io.layout import write_layout

        ld = self.pipeline.results(["target_face"])["target_face"]
        with _tf.TemporaryDirectory() as d:
            p = Path(d) / "layout.json"
            write_layout(p, ld["target_layout"], Path(self.files["rigs"][self.target_rig]).name)
            return p.read_bytes()

    def result_bytes(self, kind: str) -> bytes:
        """The current result as a file a browser user can download: ``"glb"`` (the target rig with
        the animation), ``"csv"`` (the weight curves) or ``"shot"`` (the shot JSON)."""
        import tempfile as _tf

        from core.outputs import write_outputs

        if kind == "shot":
            return self.shot().to_json().encode("utf-8")
        with _tf.TemporaryDirectory() as d:
            p = Path(d) / f"result.{kind}"
            write_outputs(self.pipeline, out=p if kind == "glb" else None, weights_csv=p if kind == "csv" else None)
            return p.read_bytes()

    def _label_for(self, kind: str, path: str) -> str:
        """The list label of a file path — the listed file with that path or that content (a
        shared shot reads its files from the review store) — adding it to the list when new."""
        from core.pipeline import file_key

        files = self.files[kind]
        for label, p in files.items():
            if Path(p).resolve() == Path(path).resolve():
                return label
        if Path(path).is_file():
            want = file_key(str(path))
            for label, p in files.items():
                if Path(p).is_file() and Path(p).suffix.lower() == Path(path).suffix.lower() and file_key(p) == want:
                    return label
        label = UPLOAD + Path(path).name
        files[label] = str(path)
        return label

    def use_files(self, source: str = None, source_rig: str = None, target_rig: str = None) -> None:
        """Select files by path (added to the lists when they are not there yet)."""
        labels = {}
        if source is not None:
            labels["source"] = self._label_for("performances", source)
        if source_rig is not None:
            labels["source_rig"] = self._label_for("rigs", source_rig) if source_rig else NONE
        if target_rig is not None:
            labels["target_rig"] = self._label_for("rigs", target_rig)
        self._refresh_options()
        self.param.update(**labels)

    def _apply_selection(self):
        """The selected files into the pipeline. A rig that changes takes its own layout (its
        sidecar or bundled one; none: markers to place), never the previous rig's: that one's
        vertex ids mean nothing on another mesh (a layout set by a shot or an upload stays while
        its rig does)."""
        rigs = self.files["rigs"]
        files = dict(source=self.files["performances"].get(self.source, ""),
                     source_rig="" if self.source_rig in (None, NONE) else rigs[self.source_rig],
                     target_rig=rigs.get(self.target_rig, ""))
        for role in ("source", "target"):
            new, old = files[f"{role}_rig"], getattr(getattr(self.pipeline, f"{role}_face"), f"{role}_rig")
            if new != old and _content(new) != _content(old):  # (a shared shot's copy of a listed rig is that rig)
                files[f"{role}_layout"] = ""
        self.pipeline.configure(**files)

    # -- the shot -----------------------------------------------------------------------
    def shot(self) -> Shot:
        """Everything this page shows, as a shot document (files, settings, edits, frame, notes)."""
        self._apply_selection()
        return self.pipeline.shot()

    def sync_selection(self) -> None:
        """Make the selectors show the pipeline's files (after a shared shot changed them)."""
        take, sf, tf = self.pipeline.take.source, self.pipeline.source_face.source_rig, self.pipeline.target_face.target_rig
        self.use_files(source=take or None, source_rig=sf, target_rig=tf or None)

    def open_shot(self, shot, name: str = "shot", locate=None) -> None:
        """Make this session the shot's (a Shot, a path or JSON text): its files become the
        selections (added to the lists when new), its settings and edit lists the pipeline's.

        Raises ValueError / FileNotFoundError naming what is missing or wrong.
        """
        other = Pipeline.from_shot(shot, cache=self.pipeline.cache, locate=locate)
        cfg = other.config()
        values = {}
        for n, st in other.stages.items():
            values.update({k: v for k, v in vars(getattr(cfg, n)).items() if k not in EDITORS.values()})
        self.pipeline.configure(**values)
        for editor in EDITORS:
            self.pipeline._set_edits(editor, other.edits(editor))
        self.pipeline.frame, self.pipeline.notes = other.frame, list(other.notes)
        src, srig, trig = other.take.source, other.source_face.source_rig, other.target_face.target_rig
        self.use_files(source=src or None, source_rig=srig, target_rig=trig or None)
        log.info("opened shot %s", name)

    # -- running ------------------------------------------------------------------------
    def recompute(self) -> bool:
        """Run the stale retargeting stages and publish a snapshot; False on error (see ``error``)."""
        with self._lock:
            # busy and the progress bar move only once a stage takes a while (see _progress): the
            # pages of a shared shot recompute every change from the cache, and each of their
            # widget updates costs the server, on every page
            if self.error:
                self.error = ""
            t0 = self._t0 = time.perf_counter()
            try:
                self._apply_selection()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    #: the results as every page showing them shares them (the pipeline's snapshot
                    #: stage); this page's snapshot = it + its timings and the warnings its run gave
                    self.package = self.pipeline.run("snapshot", progress=self._progress)
                timings = {k: v * 1e3 for k, v in self.pipeline.timings.items()}
                self.snapshot = dict(self.package)
                self.snapshot["warnings"] = list(dict.fromkeys(self.without_paths(str(w.message)) for w in caught))
                self.snapshot["timings"] = timings
                self.snapshot["server_ms"] = (time.perf_counter() - t0) * 1e3
                self.status = self._status_line()
                log.info("recompute %.1f ms: %s", self.snapshot["server_ms"], timings)
                self.version += 1
                return True
            except Exception as e:  # shown as a notification; the trace goes to the log only
                log.warning("recompute failed: %s", traceback.format_exc())
                self.error = self.readable(e)
                self.status = "error — see the message at the top of the page"  # the message itself is shown once
                return False
            finally:
                self.param.update(busy=False, progress=100)

    def dense(self, progress=None) -> dict:
        """Run the dense-transfer stages (Xu 2014) of this session's shot; returns their results
        (``transfer``, ``transfer_edit``, ``detail_edit``) and the stage timings. Raises."""
        self._apply_selection()
        res = self.pipeline.results(DENSE_STAGES, progress=progress)
        res["timings"] = dict(self.pipeline.timings)
        return res

    def suggest_poses(self, n: int = 8) -> list:
        """Take frames to pose next: far apart in expression, not posed yet (core.examples)."""
        return suggested_frames(self.pipeline.results(["frames", "stabilize"]), n, self.pipeline.solve.example_poses)

    def readable(self, e: Exception) -> str:
        """An exception as a message for the page: uploads by their own name, no server paths, no
        command-line flags."""
        from core.io.rigs import NoLayoutError

        if isinstance(e, NoLayoutError):
            return (f"{Path(e.rig_path).name} has no marker layout yet: press “Place markers automatically” in the "
                    "Markers card, or upload the rig's layout (.json)")
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        if not isinstance(e, (ValueError, KeyError, FileNotFoundError)):
            msg = f"{type(e).__name__}: {msg}"
        msg = self.without_paths(msg)
        # what the command line would say with a flag, the page says with its own controls
        for flag, words in (("(--source-rig)", "(choose the rig the curves drive under Source rig)"),
                            ("--source-rig", "the Source rig list"), ("--target-rig", "the Target rig list"),
                            ("(--source)", "(choose a take under Source performance)")):
            msg = msg.replace(flag, words)
        return msg

    def without_paths(self, msg: str) -> str:
        """``msg`` with this page's upload folder and the sample data folder taken off the file
        paths it names: the files by the names the user knows."""
        if self._upload_dir is not None:
            msg = msg.replace(str(self._upload_dir) + "/", "")
        return msg.replace(str(DATA) + "/", "")

    _t0 = 0.0

    def _progress(self, fraction: float, message: str):
        if time.perf_counter() - self._t0 < 0.2:
            return  # a quick recompute (cached stages) shows its result, not eight progress steps
        self.param.update(busy=True, progress=int(round(100 * min(max(fraction, 0), 1))), status=message)

    def _status_line(self) -> str:
        s = self.snapshot
        ev = s["evaluate"]
        gaps = int((~np.asarray(s["valid"])).sum())
        return (f"{len(s['times'])} frames @ {s['fps']:g} fps · {len(s['marker_names'])} markers · {s['method']} · "
                f"marker error median {np.nanmedian(ev['marker_error_mm']):.2f} mm · server {s['server_ms']:.0f} ms"
                + (f" · {gaps} frames without data" if gaps else ""))


def derived(snap: dict, name: str, make):
    """``make()`` of a snapshot, made once and kept with it (read-only arrays): every page showing
    the snapshot shares it (e.g. the viewers' NaN-free tracks)."""
    d = snap["derived"]
    if name not in d:
        v = make()
        for a in (v if isinstance(v, tuple) else (v,)):
            if isinstance(a, np.ndarray):
                a.flags.writeable = False
        d[name] = v
    return d[name]
