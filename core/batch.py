"""Many shots on Dask distributed: a local cluster by default, an existing cluster by address.

A shot (:mod:`core.shot`) fully describes a job, so a batch is a list of shots and one output
folder. The same code runs every batch — ``face-retarget batch``, the dashboard and scripts
call :func:`run_batch`:

* **inputs** (:func:`collect_shots`): shot files, folders of them, list files (one path per
  line) and globs; captures (any other file) together with one *template* shot whose settings
  and rigs are applied to each capture (its ``source`` file replaced by the capture).
* **where it runs**: ``client=None`` starts a :class:`distributed.LocalCluster` (processes, one
  thread each, BLAS threads 1 through ``distributed.nanny.pre-spawn-environ``) and closes it at
  the end; an address (``"tcp://host:8786"``) or a :class:`distributed.Client` uses an existing
  cluster. Tasks, results and writing are the same in both.
* **input files** reach the workers in one of two ways (``files=``):

  - ``"shared"``: workers read the paths the shots record (a shared disk mounted at the same
    path, or the same machine) and check each file against the shot's content hash
    (:meth:`core.shot.Shot.resolve`);
  - ``"scatter"``: the client reads each distinct file once and sends it to the cluster once
    (:meth:`distributed.Client.scatter`, one future per content hash); a task depends only on
    the files of its shot, a worker fetches each once, writes it once per machine to a
    folder named by its hash (original file name kept) and checks its hash before use.

  ``"auto"`` (the default) is ``shared`` on a local cluster and ``scatter`` on a remote one.
  Each worker process keeps a stage cache (:class:`core.pipeline.StageCache`), so a rig is
  loaded and its marker shapes computed once per worker, not once per shot.
* **outputs** (``out_dir/<shot>/``): ``<shot>.glb``, ``<shot>.csv`` (``<shot>_regions.csv``
  with ``--method local``), ``evaluation.json`` (:func:`core.evaluate.summarize`), ``log.txt``,
  ``shot.json`` (the shot as run, reproducible with ``face-retarget retarget --shot``) and
  ``manifest.json``, written last; ``out_dir/summary.csv`` and ``summary.html`` (self-contained)
  list every shot with its status, time and key metrics.
* **workers compute, the client writes**: a task returns its files as bytes, and the client
  writes them into a hidden temporary folder and renames it into place; the rename is atomic,
  so an interrupted batch (Ctrl-C, a killed process) leaves finished shots and nothing
  half-written (leftover temporary folders are removed on the next run). Remote workers need
  no access to the output folder.
* **resumable**: a shot whose ``manifest.json`` says ``ok`` for the same content hash
  (:meth:`core.shot.Shot.content_hash`) and output options, with its files present, is
  skipped; a failed shot records its error, does not stop the others, and is retried on the
  next run.

Nothing here imports panel; dask is imported by the functions that need it.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import html
import io
import json
import os
import re
import shutil
import socket
import tempfile
import threading
import time
import traceback
import uuid
import warnings
import zipfile
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib.metadata import version
from pathlib import Path
from typing import Callable, Iterable, Optional

from .cores import affinity
from .evaluate import summarize
from .io.layout import sidecar_layout_path
from .io.rigs import NoLayoutError
from .io.sequence import FRAME_SUFFIXES
from .outputs import write_outputs
from .pipeline import Pipeline, StageCache, file_key
from .progress import ProgressFn
from .registration import place_missing_layouts
from .report import readable
from .shot import FileRef, Shot

#: version of the output folder layout (``manifest.json``'s ``format``)
OUTPUT_FORMAT = 1
MANIFEST = "manifest.json"
LOCK = ".batch.lock"
#: suffixes of list files (one input per line); shot files end in .json; anything else is a capture
LIST_SUFFIXES = (".txt", ".lst", ".list")
#: the environment of every local worker process: one BLAS/OpenMP thread (the solvers factor many
#: small matrices; threads only add contention when every core already runs a worker)
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
#: the columns of summary.csv / summary.html (metrics from :func:`core.evaluate.summarize`)
SUMMARY_COLUMNS = ("shot", "status", "seconds", "frames", "frames_without_data", "marker_mean_mm",
                   "marker_p95_mm", "marker_max_mm", "velocity_error_mm_per_frame",
                   "velocity_error_p95_mm_per_frame", "velocity_error_max_mm_per_frame", "weight_min", "weight_max",
                   "active_per_frame", "runs", "worker", "finished", "content_hash", "error")
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _version() -> str:
    try:

        return version("face-retarget")
    except Exception:  # a source checkout without an install
        return "unknown"


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="microseconds")


# --------------------------------------------------------------------------------------
# inputs


@dataclass(frozen=True)
class BatchShot:
    """One job of a batch: a shot and the name of its output folder.

    ``base`` is the folder relative file paths of the shot are also looked for in (the shot
    file's, or the template's); ``origin`` the file it came from. A shot file that could not be
    read is a ``BatchShot`` with ``shot=None`` and its ``error``: it is reported as failed
    without stopping the others.
    """

    name: str
    shot: Optional[Shot]
    base: Optional[str] = None
    origin: str = ""
    error: str = ""


def _is_pattern(s: str) -> bool:
    return any(c in s for c in "*?[")


def _is_sequence(folder: Path) -> bool:

    return any(c.suffix.lower() in FRAME_SUFFIXES for c in folder.iterdir() if c.is_file())


def _expand(item, base: Optional[Path] = None, _seen=None) -> list:
    """Paths an input names: itself, a folder's shot files, a list file's lines, a glob's matches."""
    seen = set() if _seen is None else _seen
    s = str(item)
    p = Path(s)
    if base is not None and not p.is_absolute():
        p = base / p
    if _is_pattern(s) and not p.exists():
        found = sorted(glob.glob(str(p), recursive=True))
        if not found:
            raise FileNotFoundError(f"{s}: no file matches this pattern")
        return [Path(f) for f in found]
    if p.is_dir():
        if _is_sequence(p):  # a mesh-sequence capture (one OBJ/PLY per frame), not a folder of shots
            return [p]
        found = sorted(p.glob("*.json"))
        if not found:
            raise FileNotFoundError(f"{p}: folder holds no shot files (*.json) and no mesh frames")
        return found
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such shot file, capture or list file")
    if p.suffix.lower() in LIST_SUFFIXES:
        key = p.resolve()
        if key in seen:
            raise ValueError(f"{p}: list file includes itself")
        seen.add(key)
        out = []
        for line in p.read_text(encoding="utf-8-sig").splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                out.extend(_expand(line, p.parent, seen))
        return out
    return [p]


def shot_from_capture(template: Shot, capture) -> Shot:
    """``template`` (rigs, settings, edits) applied to ``capture``: its ``source`` file replaced."""
    shot = Shot.from_dict(template.to_dict())
    shot.files["source"] = FileRef.of(Path(capture).resolve())
    return shot


def _absolute(shot: Shot, base: Optional[Path]) -> Shot:
    """``shot`` with relative file paths made absolute when they exist relative to ``base``."""
    if base is None:
        return shot
    shot = Shot.from_dict(shot.to_dict())
    for ref in shot.files.values():
        if not Path(ref.path).is_absolute() and not Path(ref.path).exists() and (base / ref.path).exists():
            ref.path = str((base / ref.path).resolve())
    return shot


def collect_shots(inputs: Iterable, template=None) -> list:
    """The jobs of a batch from command-line style inputs.

    Parameters
    ----------
    inputs : paths or patterns: a shot file (``.json``), a folder (its ``*.json`` shot files), a
        list file (``.txt``/``.lst``/``.list``: one input per line, ``#`` comments, paths relative
        to the list file) or a glob (``"takes/*.csv"``; quote it so the shell does not expand it,
        or let it: both work). Any other file is a capture, and so is a folder of per-frame
        OBJ/PLY meshes (a mesh sequence).
    template : a shot (or its path) applied to every capture (:func:`shot_from_capture`);
        needed when there are captures.

    Returns
    -------
    list of :class:`BatchShot` in input order, with unique folder names (the file stem;
    ``-2``, ``-3`` ... on a clash). A shot file that cannot be read becomes a failed job.

    Raises
    ------
    FileNotFoundError
        An input names nothing.
    ValueError
        Captures without a template.
    """
    tbase = None
    if template is not None and not isinstance(template, Shot):
        tbase = Path(template).resolve().parent
        template = Shot.from_json(template)
    if template is not None:
        template = _absolute(template, tbase)
    jobs = []
    for item in inputs:
        for p in _expand(item):
            if p.suffix.lower() == ".json":
                try:
                    shot = _absolute(Shot.from_json(p), p.resolve().parent)
                    jobs.append(BatchShot(p.stem, shot, str(p.resolve().parent), str(p)))
                except (ValueError, FileNotFoundError) as e:
                    jobs.append(BatchShot(p.stem, None, str(p.parent), str(p), f"{type(e).__name__}: {e}"))
            elif template is None:
                raise ValueError(f"{p}: a capture, not a shot file: give --template SHOT.json (the rigs and settings "
                                 "to apply to each capture)")
            else:
                jobs.append(BatchShot(p.stem, shot_from_capture(template, p), str(tbase) if tbase else None, str(p)))
    return _unique(jobs)


def _unique(jobs: list) -> list:
    out, used = [], {"summary.csv", "summary.html"}  # the folder's own files
    for j in jobs:
        stem = _SAFE.sub("_", j.name).strip("._") or "shot"
        name, n = stem, 1
        while name.lower() in used:
            n += 1
            name = f"{stem}-{n}"
        used.add(name.lower())
        out.append(BatchShot(name, j.shot, j.base, j.origin, j.error))
    return out


def _as_jobs(shots) -> list:
    """Normalise what :func:`run_batch` accepts into unique :class:`BatchShot` jobs."""
    if isinstance(shots, (str, Path)):
        shots = [shots]
    if isinstance(shots, dict):
        shots = [BatchShot(str(k), v if isinstance(v, Shot) else Shot.from_json(v)) for k, v in shots.items()]
    jobs = []
    for s in shots:
        if isinstance(s, BatchShot):
            jobs.append(s)
        elif isinstance(s, Shot):
            jobs.append(BatchShot(f"shot-{s.content_hash()[:10]}", s))
        elif isinstance(s, (str, Path)):
            jobs.extend(collect_shots([s]))
        else:
            raise TypeError(f"run_batch: shots: expected Shot, BatchShot or a path, got {type(s).__name__}")
    return _unique(jobs)


def place_layouts(jobs: list, place: bool = True, progress: Optional[ProgressFn] = None,
                  log: Optional[Callable[[str], None]] = None) -> list:
    """The jobs with a marker layout for every rig (and mesh-sequence source) that has none, as
    ``face-retarget retarget`` does (:func:`core.registration.place_missing_layouts`: placed
    automatically and written beside the rig as ``<rig>.layout.json``), each layout a file of the
    shot (``target_layout`` / ``source_layout``), so its content is part of the shot's hash.

    A rig's sidecar layout that exists already (placed by an earlier run, or by hand) becomes a file
    of the shot too: a resumed batch then finds the same shot content and skips what is done, and an
    edited sidecar re-runs its shots. Markers are placed once per rig, on this machine (the client),
    before any shot runs.

    Parameters
    ----------
    jobs : list of :class:`BatchShot`
    place : False to refuse instead (``--no-auto-markers``): a shot whose rig has no layout fails
        with the message saying how to make one, and nothing is written
    progress : ``progress(fraction, message)`` of the placements
    log : ``log(line)``: each placement's report (which markers need a hand) and where it went

    Returns
    -------
    list of :class:`BatchShot` in the same order: the shot with its layouts, or (refused) a failed
    job. A shot whose files cannot be read is returned unchanged (:func:`run_batch` reports it).
    """
    log = log or (lambda line: None)
    placed: dict = {}  # (layout setting, file) -> layout written by this call (a read-only folder's goes to tmp)
    out = []
    for j in jobs:
        if j.shot is None:
            out.append(j)
            continue
        try:
            paths = {role: _resolve(j, role) for role in j.shot.files}
        except (ValueError, FileNotFoundError):
            out.append(j)
            continue
        settings = {k: v for st in j.shot.settings.values() for k, v in st.items()}
        settings.update(paths)
        found = {}
        for what, owner, rig in (("target_layout", paths.get("target_rig"), True),
                                 ("source_layout", paths.get("source_rig") or paths.get("source"), bool(paths.get("source_rig")))):
            if owner and what not in paths:
                if (what, owner) in placed:
                    found[what] = placed[(what, owner)]
                elif rig and sidecar_layout_path(owner).exists():
                    found[what] = str(sidecar_layout_path(owner))
        settings.update(found)
        try:
            updates, reports = place_missing_layouts(settings, place=place, progress=progress)
        except NoLayoutError as e:
            out.append(BatchShot(j.name, None, j.base, j.origin, f"NoLayoutError: {e}"))
            continue
        except (ValueError, FileNotFoundError):  # a file it cannot read: the shot's run says so
            out.append(j)
            continue
        for what, path, report in reports:
            placed[(what, settings.get(what.replace("_layout", "_rig")) or settings.get("source"))] = str(path)
            log(f"{j.name}: {report['message']} Wrote {path} (the {what.replace('_', ' ')} from now on: edit it to "
                "move a marker)")
        found.update(updates)
        if not found:
            out.append(j)
            continue
        shot = Shot.from_dict(j.shot.to_dict())
        for role, path in found.items():
            shot.files[role] = FileRef.of(path)
        out.append(BatchShot(j.name, shot, j.base, j.origin, j.error))
    return out


# --------------------------------------------------------------------------------------
# the task (runs on a worker)

_WORKER_CACHE = None
_CACHE_LOCK = threading.Lock()


def worker_cache(fresh: bool = False):
    """The stage cache of this process (one per worker: rigs load once per worker); ``fresh``
    starts a new, empty one (a cold start, as in a new worker)."""
    global _WORKER_CACHE

    with _CACHE_LOCK:
        if _WORKER_CACHE is None or fresh:
            _WORKER_CACHE = StageCache(max_entries=64)
        return _WORKER_CACHE


def _file_store() -> Path:
    """Where a worker machine keeps scattered input files, by content hash: ``$FACE_RETARGET_BATCH_FILES``,
    else ``<tmp>/face-retarget-batch-files-<uid>`` (kept between batches: the same rig is written once)."""
    env = os.environ.get("FACE_RETARGET_BATCH_FILES")
    if env:
        return Path(env)
    return Path(tempfile.gettempdir()) / f"face-retarget-batch-files-{os.getuid() if hasattr(os, 'getuid') else 'u'}"


def _materialise(blobs: dict) -> dict:
    """Write scattered files (``{sha: (file name, bytes or {name: bytes})}``) once per machine
    under their content hash; return ``{sha: path}``. A stored copy whose content no longer
    hashes to its name is written again; the caller's :meth:`Shot.resolve` checks each file
    against the shot's hash as it does any input."""

    paths = {}
    for sha, (name, data) in blobs.items():
        folder = _file_store() / sha
        target = folder / name
        if target.exists() and file_key(str(target)) != sha:
            shutil.rmtree(target, ignore_errors=True) if target.is_dir() else target.unlink(missing_ok=True)
        if not target.exists():
            folder.mkdir(parents=True, exist_ok=True)
            tmp = folder / f".{name}.{os.getpid()}.{uuid.uuid4().hex[:6]}.tmp"
            if isinstance(data, dict):  # a folder rig (OBJ files)
                tmp.mkdir()
                for fname, b in data.items():
                    (tmp / fname).write_bytes(b)
            else:
                tmp.write_bytes(data)
            try:
                os.rename(tmp, target)
            except OSError:  # another worker of this machine was first (same content)
                shutil.rmtree(tmp, ignore_errors=True) if tmp.is_dir() else tmp.unlink(missing_ok=True)
        paths[sha] = str(target)
    return paths


def _where() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except Exception:
        return f"local:{os.getpid()}"


def job_payload(job: BatchShot, csv_precision=6, paths: Optional[dict] = None) -> dict:
    """The plain-data task argument of :func:`run_shot` for ``job`` (``paths``: {role: path}
    replacing the recorded paths, e.g. where the client found them)."""
    shot = Shot.from_dict(job.shot.to_dict())
    for role, path in (paths or {}).items():
        shot.files[role].path = str(path)
    return {"name": job.name, "shot": shot.to_dict(), "base": job.base, "csv_precision": csv_precision}


def run_shot(job: dict, blobs: Optional[dict] = None) -> dict:
    """Retarget one shot and return its output files as bytes (the task of a batch).

    Parameters
    ----------
    job : ``{"name", "shot": Shot.to_dict(), "base", "csv_precision"}``
    blobs : ``{sha: (file name, bytes)}`` of the shot's files when they were scattered

    Returns
    -------
    dict: ``name``, ``status`` ("ok" / "failed"), ``content_hash``, ``error`` (``"Type: message"``),
    ``log`` (text), ``files`` ({file name: bytes}), ``evaluation`` (:func:`core.evaluate.summarize`),
    ``started``, ``finished``, ``seconds`` (wall), ``cpu_seconds`` (this process's CPU time),
    ``worker``, ``host``, ``pid``. Never raises for a
    bad shot: the error is the result.
    """

    name = job["name"]
    started, t0, c0 = _now(), time.perf_counter(), time.process_time()
    out = {"name": name, "status": "failed", "content_hash": "", "error": "", "files": {}, "evaluation": None,
           "worker": _where(), "host": socket.gethostname(), "pid": os.getpid(), "started": started}
    lines = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            shot = Shot.from_dict(job["shot"])
            out["content_hash"] = shot.content_hash()
            located = _materialise(blobs) if blobs else {}
            locate = (lambda role, ref: located.get(ref.sha)) if located else None
            pipe = Pipeline.from_shot(shot, cache=worker_cache(), base=job.get("base"), locate=locate)
            for role, ref in sorted(shot.files.items()):
                lines.append(f"file {role}: {located.get(ref.sha, ref.path)} (sha {ref.sha})")
            with tempfile.TemporaryDirectory(prefix="face-retarget-shot-") as tmp:
                res = write_outputs(pipe, Path(tmp) / f"{name}.glb", Path(tmp) / f"{name}.csv", job.get("csv_precision", 6))
                out["files"] = {p.name: p.read_bytes() for p in res.paths}
            out["evaluation"] = summarize(res.evaluation, res.weights, res.valid, res.names)
            lines.append(res.summary)
            out["status"] = "ok"
        except Exception as e:  # a bad shot is a result, not a crash of the batch
            msg = e.args[0] if isinstance(e, KeyError) and e.args else e
            out["error"] = f"{type(e).__name__}: {msg}"
            lines.append(f"error: {out['error']}\n{traceback.format_exc()}")
    for w in caught:
        lines.append(f"warning: {w.message}")
    out["finished"], out["seconds"], out["cpu_seconds"] = _now(), time.perf_counter() - t0, time.process_time() - c0
    out["log"] = "\n".join(lines)
    return out


# --------------------------------------------------------------------------------------
# results on disk


@dataclass
class ShotResult:
    """The outcome of one shot of a batch.

    ``status``: ``"ok"`` computed by this run, ``"skipped"`` already done (kept from an earlier
    run), ``"failed"`` (``error`` says why; retried next run), ``"pending"`` not run (the batch
    was stopped). ``seconds`` is the compute time on its worker, ``runs`` how many times the
    shot's folder was computed, ``metrics`` the evaluation summary's numbers.
    """

    name: str
    status: str
    content_hash: str = ""
    seconds: float = 0.0
    metrics: dict = field(default_factory=dict)
    error: str = ""
    folder: str = ""
    worker: str = ""
    runs: int = 0
    finished: str = ""
    files: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status in ("ok", "skipped")

    def row(self) -> dict:
        """One row of the summary table (:data:`SUMMARY_COLUMNS`)."""
        r = {"shot": self.name, "status": self.status, "seconds": round(self.seconds, 3), "runs": self.runs,
             "worker": self.worker, "finished": self.finished, "content_hash": self.content_hash,
             "error": self.error.splitlines()[0] if self.error else ""}
        r.update({k: self.metrics.get(k) for k in SUMMARY_COLUMNS if k not in r})
        return r


def _manifest_result(folder: Path, status: Optional[str] = None) -> Optional[ShotResult]:
    try:
        m = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return ShotResult(m.get("name", folder.name), status or m.get("status", ""), m.get("content_hash", ""),
                      float(m.get("seconds", 0.0)), dict(m.get("metrics") or {}), m.get("error", ""), str(folder),
                      m.get("worker", ""), int(m.get("runs", 0)), m.get("finished", ""), sorted(m.get("files", {})))


def read_results(out_dir) -> dict:
    """``{shot name: ShotResult}`` of every finished folder (a ``manifest.json``) in ``out_dir``."""
    out = {}
    root = Path(out_dir)
    if root.is_dir():
        for d in sorted(root.iterdir()):
            if d.is_dir() and not d.name.startswith("."):
                r = _manifest_result(d)
                if r is not None:
                    out[r.name] = r
    return out


def output_options(csv_precision=6) -> dict:
    """The output options a finished shot must have been written with to be skipped (recorded
    in its manifest; the argument of :func:`write_result`)."""
    return {"csv_precision": csv_precision, "format": OUTPUT_FORMAT}


def _done(folder: Path, content_hash: str, options: dict) -> Optional[ShotResult]:
    """The earlier result in ``folder`` if it is complete for this shot, else None."""
    try:
        m = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if m.get("status") != "ok" or m.get("content_hash") != content_hash or m.get("options") != options:
        return None
    for fname, info in m.get("files", {}).items():
        f = folder / fname
        if not f.is_file() or f.stat().st_size != info.get("bytes"):
            return None
    return _manifest_result(folder, "skipped")


def _commit(out_dir: Path, name: str, files: dict) -> Path:
    """Write ``files`` ({name: bytes or text}) as ``out_dir/name`` atomically: into a hidden
    temporary folder, the manifest last, then renamed into place (replacing an older folder)."""
    final = out_dir / name
    tag = uuid.uuid4().hex[:8]
    tmp, old = out_dir / f".{name}.tmp-{tag}", out_dir / f".{name}.old-{tag}"
    tmp.mkdir()
    try:
        for fname, data in files.items():
            if fname == MANIFEST:
                continue
            (tmp / fname).write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
        (tmp / MANIFEST).write_text(files[MANIFEST], encoding="utf-8")
        if final.exists():  # two renames: between them the older folder waits as .old (restored on failure)
            os.rename(final, old)
        os.rename(tmp, final)
    except BaseException:
        if old.exists() and not final.exists():
            os.rename(old, final)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return final


def _json(obj) -> str:
    return json.dumps(obj, indent=1, allow_nan=False) + "\n"


def write_result(out_dir, job: BatchShot, result: dict, options: dict) -> ShotResult:
    """Write one task's result (:func:`run_shot`) as ``out_dir/<name>/`` (atomically) and
    return its :class:`ShotResult`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    previous = _manifest_result(out_dir / job.name)
    runs = (previous.runs if previous else 0) + 1
    files = dict(result.get("files") or {})
    evaluation = result.get("evaluation")
    if evaluation is not None:
        files["evaluation.json"] = _json(evaluation)
    if job.shot is not None:
        files["shot.json"] = job.shot.to_json() + "\n"
    where = (f"on {result['worker']} (host {result.get('host', '')}, pid {result.get('pid', '')})"
             if result.get("worker") else "(not started on a worker)")
    head = (f"shot {job.name} (from {job.origin or 'a Shot object'})\ncontent hash {result.get('content_hash', '')}\n"
            f"run {runs} {where}, face-retarget {_version()}\n"
            f"started {result.get('started', '')}, finished {result.get('finished', '')} ({result.get('seconds', 0.0):.2f} s)\n"
            f"status {result['status']}" + (f": {result['error']}" if result.get("error") else "") + "\n")
    files["log.txt"] = head + (result.get("log") or "") + "\n"
    metrics = {k: v for k, v in (evaluation or {}).items() if not isinstance(v, dict)}
    listing = {f: {"bytes": len(d if isinstance(d, bytes) else d.encode("utf-8")),
                   "blake2b": hashlib.blake2b(d if isinstance(d, bytes) else d.encode("utf-8"), digest_size=16).hexdigest()}
               for f, d in sorted(files.items())}
    manifest = {"format": OUTPUT_FORMAT, "name": job.name, "status": result["status"],
                "content_hash": result.get("content_hash", ""), "options": options, "runs": runs,
                "started": result.get("started", ""), "finished": result.get("finished", ""),
                "seconds": float(result.get("seconds", 0.0)), "cpu_seconds": float(result.get("cpu_seconds", 0.0)),
                "worker": result.get("worker", ""),
                "host": result.get("host", ""), "pid": result.get("pid", ""), "face_retarget": _version(),
                "origin": job.origin, "error": result.get("error", ""), "metrics": metrics, "files": listing}
    files[MANIFEST] = _json(manifest)
    folder = _commit(out_dir, job.name, files)
    return ShotResult(job.name, result["status"], manifest["content_hash"], manifest["seconds"], metrics,
                      manifest["error"], str(folder), manifest["worker"], runs, manifest["finished"], sorted(listing))


def _failure(job: BatchShot, error: str, content_hash: str = "") -> dict:
    now = _now()
    return {"name": job.name, "status": "failed", "content_hash": content_hash, "error": error, "files": {},
            "evaluation": None, "worker": "", "host": socket.gethostname(), "pid": os.getpid(), "started": now,
            "finished": now, "seconds": 0.0, "log": error}


def _clean_leftovers(out_dir: Path) -> None:
    """Tidy what a killed run left: temporary folders (``.<shot>.tmp-*``) are removed; an older
    result moved aside (``.<shot>.old-*``) is put back if its replacement never arrived."""
    for d in out_dir.glob(".*.tmp-*"):
        shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink(missing_ok=True)
    for d in out_dir.glob(".*.old-*"):
        final = out_dir / d.name[1:d.name.rindex(".old-")]
        if not final.exists() and (d / MANIFEST).exists():
            os.rename(d, final)
        else:
            shutil.rmtree(d, ignore_errors=True)


class _Lock:
    """``out_dir/.batch.lock``: one batch writes to an output folder at a time."""

    def __init__(self, out_dir: Path):
        self.path = out_dir / LOCK
        self.token = f"{socket.gethostname()} {os.getpid()} {uuid.uuid4().hex}"

    def __enter__(self):
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                host, pid = (self.path.read_text().split() + ["", ""])[:2]
                alive = host != socket.gethostname()  # another machine's: assume alive
                if not alive and pid.isdigit():
                    try:
                        os.kill(int(pid), 0)
                        alive = True
                    except ProcessLookupError:
                        alive = False
                    except PermissionError:
                        alive = True
                if alive:
                    raise ValueError(f"{self.path.parent}: another batch (host {host}, pid {pid}) is writing to this "
                                     f"folder; wait for it, or remove {self.path} if it is gone") from None
                self.path.unlink(missing_ok=True)  # stale: its process is gone
                continue
            with os.fdopen(fd, "w") as f:
                f.write(self.token)
            return self
        raise ValueError(f"{self.path}: could not take the batch lock")

    def __exit__(self, *exc):
        try:
            if self.path.read_text() == self.token:
                self.path.unlink()
        except OSError:
            pass


# --------------------------------------------------------------------------------------
# summary and zip


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return readable(v, digits=4)  # never 1.235e+04 in a page for people
    return str(v)


def write_summary(out_dir, results: list, wall_seconds: Optional[float] = None) -> tuple:
    """``summary.csv`` and ``summary.html`` (one self-contained page, no external resources) of
    ``results`` in ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    rows = [r.row() for r in results]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(SUMMARY_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r.get(k) for k in SUMMARY_COLUMNS})
    counts = {s: sum(r.status == s for r in results) for s in ("ok", "skipped", "failed", "pending")}
    compute = sum(r.seconds for r in results if r.status == "ok")
    head = "".join(f"<th>{html.escape(c)}</th>" for c in SUMMARY_COLUMNS)
    body = []
    for r, row in zip(results, rows):
        cells = []
        for c in SUMMARY_COLUMNS:
            text = html.escape(_fmt(row.get(c)))
            if c == "shot" and r.folder and Path(r.folder).exists():
                text = f'<a href="{html.escape(Path(r.folder).name)}/log.txt">{text}</a>'
            cells.append(f'<td class="{c}">{text}</td>')
        body.append(f'<tr class="{html.escape(r.status)}">{"".join(cells)}</tr>')
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>face-retarget batch: {html.escape(out_dir.name)}</title>
<style>
body{{font:13px/1.4 system-ui,sans-serif;margin:1.5em;color:#222}}
table{{border-collapse:collapse}} th,td{{border:1px solid #ccc;padding:3px 6px;text-align:right;white-space:nowrap}}
th{{background:#f0f0f0;position:sticky;top:0}} td.shot,td.status,td.worker,td.error,td.content_hash{{text-align:left}}
td.error{{white-space:normal;max-width:40em}} tr.failed td{{background:#fde8e8}} tr.pending td{{color:#888}}
tr.skipped td.status{{color:#666}} tr.ok td.status{{color:#17692b}}
</style></head><body>
<h1>face-retarget batch</h1>
<p>{len(results)} shots: {counts['ok']} computed, {counts['skipped']} already done, {counts['failed']} failed, {counts['pending']} not run;
compute {compute:.1f} s{f", wall {wall_seconds:.1f} s" if wall_seconds is not None else ""}; written {html.escape(_now())}.
Errors in mm; velocity error per marker per frame (Seol 2012 eq. 2); active per frame: shapes with |w| &gt; 0.05.</p>
<table><thead><tr>{head}</tr></thead><tbody>
{chr(10).join(body)}
</tbody></table></body></html>
"""
    paths = []
    for fname, text in (("summary.csv", buf.getvalue()), ("summary.html", page)):
        tmp = out_dir / f".{fname}.tmp-{uuid.uuid4().hex[:8]}"
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out_dir / fname)
        paths.append(out_dir / fname)
    return tuple(paths)


def zip_results(out_dir, dest=None) -> Path:
    """Zip a batch's output folder (every shot folder and the summary; no temporary files) into
    ``dest`` (default: ``<out_dir>.zip`` beside it), written to a temporary name and renamed."""
    out_dir = Path(out_dir)
    dest = Path(dest) if dest is not None else out_dir.with_name(out_dir.name + ".zip")
    tmp = dest.with_name(f".{dest.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for p in sorted(out_dir.rglob("*")):
                rel = p.relative_to(out_dir)
                if p.is_file() and not any(part.startswith(".") for part in rel.parts) and p.resolve() != dest.resolve():
                    z.write(p, str(Path(out_dir.name) / rel))
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return dest


# --------------------------------------------------------------------------------------
# the cluster


def start_local_cluster(workers: Optional[int] = None, dashboard_address: Optional[str] = ":8787"):
    """A :class:`distributed.Client` on a new :class:`distributed.LocalCluster`: ``workers``
    processes (default: one per core) with one thread each and one BLAS thread
    (:data:`WORKER_ENV` through ``distributed.nanny.pre-spawn-environ``, which the nannies read
    before they spawn a worker; ``LocalCluster(env=...)`` would apply only after BLAS loaded).
    Close both with ``client.close(); client.cluster.close()``."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as e:
        raise ImportError(f"batch needs dask distributed ({e}); pip install 'dask[distributed]'") from None
    n = workers or affinity()
    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {})
    env.update(WORKER_ENV)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
        cluster = LocalCluster(n_workers=int(n), threads_per_worker=1, processes=True, dashboard_address=dashboard_address)
    return Client(cluster, set_as_default=False)


def _check_workers(client, log, timeout: float) -> dict:
    """Wait for a worker, and check every worker imports this package (same version)."""
    if not client.nthreads():
        log(f"no workers on {client.scheduler.address} yet: waiting up to {timeout:.0f} s "
            f"(start some with `dask worker {client.scheduler.address}`)")
        try:
            client.wait_for_workers(1, timeout=timeout)
        except Exception:
            raise ValueError(f"no dask worker joined {client.scheduler.address} in {timeout:.0f} s; start workers with "
                             f"`dask worker {client.scheduler.address} --nthreads 1` on machines that have face-retarget") from None

    def probe():  # pickled by value: runs even where face-retarget is missing, and says so
        import os as _os  # noqa: lazy (runs on a worker that may lack face-retarget)

        try:
            import core.batch as b  # noqa: lazy (ditto)

            return {"ok": True, "path": _os.path.dirname(_os.path.dirname(b.__file__)), "version": b._version(),
                    "blas": _os.environ.get("OPENBLAS_NUM_THREADS", "")}
        except Exception as e:
            return {"ok": False, "error": f"{type(e).__name__}: {e}"}

    found = client.run(probe)
    bad = {w: r["error"] for w, r in found.items() if not r["ok"]}
    if bad:
        raise ImportError("dask workers cannot import face-retarget: " + "; ".join(f"{w}: {e}" for w, e in bad.items())
                          + ". Install it on every worker machine (pip install <checkout>), or start `dask worker` with "
                          "PYTHONPATH=<checkout>")
    mine = _version()
    for w, r in found.items():
        if r["version"] != mine:
            log(f"warning: worker {w} runs face-retarget {r['version']}, this client {mine}")
        if r["blas"] not in ("1",):
            log(f"warning: worker {w} has OPENBLAS_NUM_THREADS={r['blas'] or 'unset'}: BLAS threads compete with "
                "the other workers (start workers with a nanny, the default, or set it to 1)")
    return found


def _scatter_files(client, jobs: list, resolved: dict) -> dict:
    """Send each distinct input file once: ``{sha: future of (file name, bytes)}``."""
    blobs = {}
    for j in jobs:
        for role, ref in j.shot.files.items():
            if ref.sha in blobs:
                continue
            p = Path(resolved[(j.name, role)])
            data = {c.name: c.read_bytes() for c in sorted(p.iterdir()) if c.is_file()} if p.is_dir() else p.read_bytes()
            blobs[ref.sha] = (p.name, data)
    if not blobs:
        return {}
    keys = list(blobs)
    futures = client.scatter([blobs[k] for k in keys], hash=False)
    return dict(zip(keys, futures))


# --------------------------------------------------------------------------------------
# the batch


def run_batch(shots, out_dir, client=None, progress: Optional[ProgressFn] = None, *, workers: Optional[int] = None,
              files: str = "auto", csv_precision=6, force: bool = False, stop: Optional[threading.Event] = None,
              log: Optional[Callable[[str], None]] = None, dashboard_address: Optional[str] = ":8787",
              worker_timeout: float = 120.0, summary: bool = True, auto_markers: bool = True) -> list:
    """Retarget many shots on Dask and write one output folder per shot (see the module docstring).

    Parameters
    ----------
    shots : list of :class:`BatchShot` (:func:`collect_shots`), :class:`core.shot.Shot` or shot
        file paths; or a dict ``{name: Shot}``
    out_dir : the output folder (created)
    client : None (start a LocalCluster of ``workers`` processes, closed at the end), a scheduler
        address ``"tcp://host:8786"``, or a :class:`distributed.Client` (left open)
    progress : ``progress(fraction, message)`` after each shot (fraction of shots done), called
        from the calling thread
    files : ``"auto"``, ``"shared"`` or ``"scatter"``: how input files reach the workers
    csv_precision : decimals of the CSV weights, or ``"full"``
    force : recompute shots that are already done
    stop : a :class:`threading.Event`; when set, unfinished shots are cancelled and reported
        ``pending`` (a dashboard's Stop button)
    log : ``log(line)`` for messages (the dashboard link, skipped shots, warnings); default silent
    dashboard_address : of the LocalCluster's dashboard (``":0"`` a free port, None none)
    worker_timeout : seconds to wait for a first worker on an existing cluster
    summary : write ``summary.csv`` / ``summary.html``
    auto_markers : place markers on a rig or mesh sequence without a layout first (:func:`place_layouts`,
        as ``face-retarget retarget`` does); False: such a shot fails saying how to make one

    Returns
    -------
    list of :class:`ShotResult`, in the order of ``shots``.

    Usable from any thread. A KeyboardInterrupt cancels the unfinished shots, closes a cluster
    it started and propagates; finished shots stay written, nothing is left half-written.

    Raises
    ------
    ValueError
        ``files`` unknown; another batch writes to ``out_dir``; no worker on the cluster.
    ImportError
        dask distributed missing here, or face-retarget missing on a worker.
    """
    if files not in ("auto", "shared", "scatter"):
        raise ValueError(f"run_batch: files must be 'auto', 'shared' or 'scatter', got {files!r}")
    log = log or (lambda line: None)
    t_start = time.perf_counter()
    jobs = _as_jobs(shots)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    options = output_options(csv_precision)
    results: dict = {}
    with _Lock(out_dir):
        _clean_leftovers(out_dir)
        jobs = place_layouts(jobs, place=auto_markers, log=log, progress=None if progress is None else (
            lambda f, m: progress(0.0, f"placing markers: {m}")))
        todo, resolved = [], {}
        for j in jobs:
            if j.shot is None:
                results[j.name] = write_result(out_dir, j, _failure(j, j.error), options)
                continue
            h = j.shot.content_hash()
            done = None if force else _done(out_dir / j.name, h, options)
            if done is not None:
                results[j.name] = done
                continue
            try:  # check every file here first: a missing or changed file fails its shot at once
                for role in j.shot.files:
                    resolved[(j.name, role)] = _resolve(j, role)
            except (ValueError, FileNotFoundError) as e:
                results[j.name] = write_result(out_dir, j, _failure(j, f"{type(e).__name__}: {e}", h), options)
                continue
            todo.append(j)
        n_total, skipped = len(jobs), sum(r.status == "skipped" for r in results.values())
        if skipped:
            log(f"{skipped} of {n_total} shots already done in {out_dir} (same shot content): skipped")
        count = [len(results)]

        def tick(r: ShotResult):
            count[0] += 1
            if progress is not None:
                progress(count[0] / max(n_total, 1), f"{count[0]}/{n_total} {r.name}: {r.status}"
                         + (f" ({r.error.splitlines()[0][:80]})" if r.error else ""))

        if progress is not None and results:
            progress(len(results) / max(n_total, 1), f"{len(results)}/{n_total} done before this run")
        try:
            if todo:
                _run_on_dask(todo, out_dir, options, client, workers, files, resolved, results, tick, stop, log,
                             dashboard_address, worker_timeout, csv_precision)
        finally:
            ordered = [results.get(j.name) or ShotResult(j.name, "pending", j.shot.content_hash() if j.shot else "")
                       for j in jobs]
            if summary:
                write_summary(out_dir, ordered, time.perf_counter() - t_start)
    return ordered


_RESOLVED: dict = {}


def _resolve(job: BatchShot, role: str) -> str:
    """Where the client finds file ``role`` of a shot (hash checked, memoised per file)."""

    ref = job.shot.files[role]
    key = (ref.path, ref.sha, job.base)
    hit = _RESOLVED.get(key)
    if hit is not None:
        try:  # unchanged since it was checked (file_key is memoised on size and mtime)
            if file_key(hit) == ref.sha:
                return hit
        except FileNotFoundError:
            pass
    path = job.shot.resolve(role, Path(job.base) if job.base else None)
    _RESOLVED[key] = str(Path(path).resolve())
    return _RESOLVED[key]


def _task():
    """The function a batch submits, pickled by value (a local function): the scheduler, which
    unpickles task graphs, then needs only dask, not face-retarget; workers import
    :func:`run_shot` from this module when the task runs."""
    module = __name__

    def retarget_shot(job, blobs):
        import importlib  # noqa: lazy (pickled by value, runs on the worker)

        return importlib.import_module(module).run_shot(job, blobs)

    return retarget_shot


def _run_on_dask(todo, out_dir, options, client, workers, files, resolved, results, tick, stop, log,
                 dashboard_address, worker_timeout, csv_precision) -> None:
    from distributed import Client, LocalCluster, as_completed

    owned = client is None or isinstance(client, str)
    if client is None:
        client = start_local_cluster(workers or min(len(todo), affinity()), dashboard_address)
    elif isinstance(client, str):
        client = Client(client, set_as_default=False)
    futures: dict = {}
    try:
        local = isinstance(getattr(client, "cluster", None), LocalCluster)
        where = "a local cluster" if local else f"the cluster at {client.scheduler.address}"
        log(f"running {len(todo)} shots on {where}; dask dashboard: {client.dashboard_link}")
        _check_workers(client, log, worker_timeout)
        mode = files if files != "auto" else ("shared" if local else "scatter")
        blobs = _scatter_files(client, todo, resolved) if mode == "scatter" else {}
        if blobs:
            log(f"sent {len(blobs)} distinct input files to the cluster once (scatter); workers check their hashes")
        by_key, task = {}, _task()
        for i, j in enumerate(todo):
            # shared: the paths the client checked (workers check the hashes again)
            job = job_payload(j, csv_precision, {role: resolved[(j.name, role)] for role in j.shot.files}
                              if mode == "shared" else None)
            mine = {ref.sha: blobs[ref.sha] for ref in j.shot.files.values()} if blobs else None
            f = client.submit(task, job, mine, key=f"retarget_shot-{i}-{uuid.uuid4().hex[:8]}", pure=False)
            futures[f.key] = f
            by_key[f.key] = j
        ac = as_completed(list(futures.values()), loop=client.loop)
        while futures:
            if stop is not None and stop.is_set():
                log(f"stopped: {len(futures)} shots not run")
                break
            done = ac.next_batch(block=False)
            if not done:
                time.sleep(0.1)  # short, so a stop or Ctrl-C is heard at once
                continue
            for f in done:
                j = by_key[f.key]
                try:
                    res = f.result()
                except Exception as e:  # the worker died (KilledWorker), the task was lost ...
                    res = _failure(j, f"{type(e).__name__}: {e}", j.shot.content_hash())
                futures.pop(f.key, None)
                f.release()
                results[j.name] = r = write_result(out_dir, j, res, options)
                tick(r)
    finally:
        if futures:
            try:
                client.cancel(list(futures.values()))
            except Exception:
                pass
        if owned:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and isinstance(cluster, LocalCluster):
                cluster.close()


