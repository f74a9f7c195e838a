"""The retargeting pipeline: stages with param settings, one content-keyed cache, and the
dependency graph that says which stages a setting invalidates.

    load -> stabilize -> calibrate -> personalize -> solve -> edit -> synthesize -> evaluate
       \\-> segment -----------------------------------/
                         calibrate -> prior ------------/

Each stage has a ``param.Parameterized`` settings object (bounds, docs, defaults from the
papers) and a pure run function ``run(inputs, settings) -> dict``. A stage's cache key is a
hash of its name, the settings that matter to it and its upstream stages' keys (the load
stage hashes the input files' bytes), so:

* changing alpha re-runs solve and what follows it, never calibrate or segment;
* setting a value back is a cache hit (an LRU keeps recent results, not only the last);
* cached arrays are read-only, so no consumer can corrupt a cached result.

The same settings objects generate the dashboard's widgets and the CLI's flags
(:func:`cli_flags`), so the two never drift. Nothing here imports panel.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from collections import Counter, OrderedDict
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import param

from .progress import ProgressFn

# --------------------------------------------------------------------------------------
# settings


class LoadSettings(param.Parameterized):
    """Which files to retarget: the source performance, its rig, the target rig, layouts."""

    source = param.String(default="", doc="Source performance: Live Link Face CSV, marker CSV/TRC/C3D, or a GLB with a weight animation")
    source_rig = param.String(default="", doc="Rig the source curves drive (GLB); needed for weight-curve sources")
    source_layout = param.String(default="", doc="Marker layout JSON on the source rig (default: data/layouts/<rig stem>.json)")
    target_rig = param.String(default="", doc="Target blendshape rig (GLB or OBJ folder)")
    target_layout = param.String(default="", doc="Marker layout JSON on the target rig (default: data/layouts/<rig stem>.json)")
    name_map = param.String(default="", doc="Name map JSON from source channels to source-rig shapes (default: automatic ARKit names)")


class StabilizeSettings(param.Parameterized):
    """Source markers: rigid head-motion removal (Seol 2012 §3.1) and the frame range."""

    head_motion = param.Selector(default="auto", objects=["auto", "remove", "keep"], doc="Remove rigid head motion from captured markers (auto: captures only)")
    neutral_frame = param.Integer(default=0, bounds=(0, None), doc="Frame of a captured take that shows the neutral face")
    first_frame = param.Integer(default=0, bounds=(0, None), doc="First frame to retarget")
    last_frame = param.Integer(default=-1, bounds=(-1, None), doc="Last frame to retarget (-1: the end)")


class CalibrateSettings(param.Parameterized):
    """Scale-proportion matching of the target's marker blendshapes (Seol 2012 §3.2)."""

    calibrate = param.Boolean(default=True, doc="Warp the target's marker blendshapes into the actor's proportions with an RBF")
    target_shapes = param.String(default="", doc=(
        "Target shapes the solvers may use: empty = all; 'arkit' = the shapes with an ARKit name (all when the rig has "
        "none); or comma-separated shape names. The others stay at zero"))
    rbf_smoothing = param.Number(default=0.0, bounds=(0, 1), softbounds=(0, 0.1), doc="RBF ridge relative to the mean marker distance (0: exact interpolation)")


class PersonalizeSettings(param.Parameterized):
    """Actor-specific blendshapes by range-of-motion alignment (Ribera 2017 §4)."""

    personalize = param.Boolean(default=False, doc="Align the target's marker blendshapes to the actor's range of motion")
    rom = param.String(default="", doc="Range-of-motion take of the actor (default: the source itself)")
    align_beta = param.Number(default=0.01, bounds=(0, None), softbounds=(0, 1), doc="E_Mesh weight beta (Ribera 2017 eq. 4)")
    align_gamma = param.Number(default=0.1, bounds=(0, None), softbounds=(0, 1), doc="E_CEG weight gamma (Ribera 2017 eq. 4)")


class SegmentSettings(param.Parameterized):
    """Automatic segmentation of the target rig into regions (Liu 2011 §3.2.1)."""

    regions = param.Integer(default=12, bounds=(1, 64), softbounds=(1, 24), doc="Number of regions R")
    min_region_size = param.Number(default=0.01, bounds=(0, 0.5), doc="Smallest region as a fraction of the vertices; smaller clusters are merged")
    mask_smoothing = param.Integer(default=10, bounds=(0, 200), doc="Laplacian smoothing iterations of the region masks (overlap for blending)")


class PriorSettings(param.Parameterized):
    """Model-specific PCA prior (Seol 2012 §5)."""

    prior_shapes = param.String(default="", doc="Comma-separated shapes the prior is built from (default: all, Fig. 13 a)")


METHODS = ("lsq", "bounded", "range_pf", "prior_pf", "spacetime", "local", "geometric")


class SolveSettings(param.Parameterized):
    """The retargeting solver and its term weights."""

    method = param.Selector(default="bounded", objects=list(METHODS), doc=(
        "lsq: per-frame least squares; bounded: per-frame with lower<=w<=upper; range_pf/prior_pf: Seol 2012 §7 baselines; "
        "spacetime: Seol 2012 movement matching; local: Liu 2011 regions; geometric: Ribera 2017 prior + L1"))
    lower = param.Number(default=0.0, softbounds=(-1, 0), doc="Lower weight bound (bounded)")
    upper = param.Number(default=1.0, softbounds=(1, 2), doc="Upper weight bound (bounded)")
    alpha = param.Number(default=0.01, bounds=(0, None), softbounds=(0, 1), step=0.001, doc="PCA prior weight alpha (Seol 2012 eq. 4)")
    beta = param.Number(default=0.0, bounds=(0, None), softbounds=(0, 1), step=0.001, doc="Sobolev position weight beta (Seol 2012 §7.1)")
    boundary = param.Selector(default="perframe", objects=["perframe", "neutral", "none"], doc=(
        "Spacetime boundary frames: perframe = first/last frame from the Prior PF solution (takes rarely start and end "
        "neutral); neutral = zero weights at both ends as in Seol 2012 §3.1; none = free (needs beta > 0)"))
    ridge = param.Number(default=1e-5, bounds=(0, 1), softbounds=(0, 1e-3), doc=(
        "Relative Tikhonov weight rho / sigma_max(B)^2 on the weights (bounded, range_pf, prior_pf, spacetime): pulls "
        "combinations of shapes the markers barely see (e.g. eye-wide vs look-up vs blink) to zero; 0 = the papers' methods"))
    mu = param.Number(default=0.3, bounds=(0, None), softbounds=(0, 2), step=0.01, doc="Geometric prior weight mu (Ribera 2017 eq. 16)")
    lam = param.Number(default=0.6, bounds=(0, None), softbounds=(0, 2), step=0.01, doc="L1 sparsity weight lambda (Ribera 2017 eq. 16)")
    constraint = param.Selector(default="simplex", objects=["simplex", "box"], doc=(
        "Local solve constraint: simplex = the paper's convex combination of poses (w >= 0, sum w <= 1 in delta form, "
        "Liu 2011 eq. 2); box = 0 <= w <= 1"))
    local_temporal = param.Selector(default="perframe", objects=["perframe", "spacetime"], doc=(
        "Local method in time: perframe = Liu 2011's per-frame constrained QP (optionally Gaussian-filtered); spacetime = "
        "Seol 2012 movement matching inside each region (uses alpha/beta; unconstrained between the end frames)"))
    geometric_prior = param.Selector(default="geometric", objects=["geometric", "pca", "l2", "none"], doc=(
        "Prior of the geometric method (Ribera 2017 Fig. 14): cotangent-Laplacian bending, Seol's PCA, plain L2, none"))
    sigma = param.Number(default=0.0, bounds=(0, None), softbounds=(0, 5), doc="Gaussian temporal filter of the weights in frames (Liu 2011; 0: off)")


#: which solve settings matter to which method (a change elsewhere is a cache hit)
METHOD_PARAMS = {
    "lsq": (),
    "bounded": ("lower", "upper", "ridge"),
    "range_pf": ("ridge",),
    "prior_pf": ("alpha", "ridge"),
    "spacetime": ("alpha", "beta", "boundary", "ridge"),
    "local": ("constraint", "local_temporal", "alpha", "beta", "sigma"),
    "geometric": ("geometric_prior", "mu", "lam"),
}


class EditSettings(param.Parameterized):
    """Spacetime edits (Seol 2012 §6): poses set at frames, propagated in a window."""

    edits = param.List(default=[], item_type=dict, doc="Edits: {frame, weights: {shape: value}, window: [a, b] or null}")


class EvaluateSettings(param.Parameterized):
    """Diagnostics."""

    jitter_window = param.Integer(default=1, bounds=(1, 10), doc="Frame step of the jitter measure")


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


_FILE_HASHES: dict = {}


def file_key(path: str) -> str:
    """Hash of a file's bytes, memoised on (path, size, mtime)."""
    if not path:
        return ""
    p = Path(path)
    if p.is_dir():
        return content_key([file_key(str(c)) for c in sorted(p.iterdir()) if c.is_file()])
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    st = p.stat()
    memo = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if memo not in _FILE_HASHES:
        _FILE_HASHES[memo] = hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()
    return _FILE_HASHES[memo]


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


class StageCache:
    """A thread-safe LRU of stage results keyed by content hash."""

    def __init__(self, max_entries: int = 96):
        self.max_entries = max_entries
        self._data: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                return True, self._data[key]
            return False, None

    def put(self, key, value):
        with self._lock:
            self._data[key] = value
            self._data.move_to_end(key)
            while len(self._data) > self.max_entries:
                self._data.popitem(last=False)

    def clear(self):
        with self._lock:
            self._data.clear()


# --------------------------------------------------------------------------------------
# stages


class Stage:
    """A named pure function of its upstream results and its settings."""

    def __init__(self, name: str, settings: param.Parameterized, deps: tuple, run: Callable,
                 relevant: Optional[Callable] = None, active: Optional[Callable] = None):
        self.name, self.settings, self.deps, self.run = name, settings, deps, run
        self._relevant = relevant
        self._active = active

    @property
    def active(self) -> bool:
        """An inactive stage (e.g. segment when the method is not local) yields None."""
        return self._active is None or bool(self._active())

    def settings_values(self) -> dict:
        values = {k: v for k, v in self.settings.param.values().items() if k != "name"}
        if self._relevant is not None:
            keep = self._relevant(self.settings)
            values = {k: v for k, v in values.items() if k in keep}
        return values


class Pipeline:
    """Runs stale stages in dependency order and caches every result by content.

    Parameters
    ----------
    cache : StageCache, optional — share one between sessions to share work.

    Attributes
    ----------
    runs : Counter of stage executions (cache misses), for tests and the timings panel.
    timings : dict stage -> seconds of its last execution (0 for a hit).
    keys : dict stage -> key of the result last returned.
    """

    def __init__(self, cache: Optional[StageCache] = None, **settings):
        from . import stages as S

        self.cache = cache or StageCache()
        self.load = LoadSettings()
        self.stabilize = StabilizeSettings()
        self.calibrate = CalibrateSettings()
        self.personalize = PersonalizeSettings()
        self.segment = SegmentSettings()
        self.prior = PriorSettings()
        self.solve = SolveSettings()
        self.edit = EditSettings()
        self.evaluate = EvaluateSettings()
        method = lambda: self.solve.method  # noqa: E731
        self.stages = OrderedDict((s.name, s) for s in [
            Stage("load", self.load, (), S.run_load),
            Stage("stabilize", self.stabilize, ("load",), S.run_stabilize),
            Stage("calibrate", self.calibrate, ("load", "stabilize"), S.run_calibrate),
            Stage("personalize", self.personalize, ("stabilize", "calibrate"), S.run_personalize),
            Stage("segment", self.segment, ("load", "calibrate"), S.run_segment,
                  active=lambda: method() == "local"),
            Stage("prior", self.prior, ("personalize",), S.run_prior,
                  active=lambda: method() in S.PRIOR_METHODS),
            Stage("solve", self.solve, ("load", "stabilize", "calibrate", "personalize", "segment", "prior"), S.run_solve,
                  relevant=lambda s: ("method",) + METHOD_PARAMS[s.method]),
            Stage("edit", self.edit, ("solve", "personalize", "stabilize", "prior", "calibrate"), S.run_edit),
            Stage("synthesize", param.Parameterized(), ("load", "edit", "calibrate"), S.run_synthesize),
            Stage("evaluate", self.evaluate, ("stabilize", "personalize", "solve", "edit", "load"), S.run_evaluate),
        ])
        self.runs: Counter = Counter()
        self.timings: dict = {}
        self.keys: dict = {}
        self._lock = threading.RLock()
        self.configure(**settings)

    # settings -------------------------------------------------------------------------
    @property
    def settings_objects(self) -> dict:
        """stage name -> settings object (the widgets and CLI flags come from these)."""
        return {n: s.settings for n, s in self.stages.items() if len(list(s.settings.param)) > 1}

    def configure(self, **values) -> None:
        """Set settings by parameter name, whichever stage owns it (``alpha=0.1``)."""
        owners = {}
        for obj in self.settings_objects.values():
            for p in obj.param:
                if p != "name":
                    owners[p] = obj
        unknown = [k for k in values if k not in owners]
        if unknown:
            import difflib

            hints = {k: difflib.get_close_matches(k, owners, n=2) for k in unknown}
            raise KeyError(f"unknown settings {unknown}; did you mean {hints}?")
        by_obj: dict = {}
        for k, v in values.items():
            by_obj.setdefault(id(owners[k]), (owners[k], {}))[1][k] = v
        for obj, vals in by_obj.values():
            obj.param.update(**vals)

    # running ------------------------------------------------------------------------
    def key(self, name: str, _memo=None) -> str:
        """The cache key stage ``name`` would have now (no computation)."""
        memo = {} if _memo is None else _memo
        if name in memo:
            return memo[name]
        stage = self.stages[name]
        if not stage.active:
            memo[name] = content_key(name, "inactive")
            return memo[name]
        values = stage.settings_values()
        if name == "load":
            values = {k: file_key(v) if v else "" for k, v in values.items()}
        if name == "personalize" and values.get("rom"):
            values["rom"] = file_key(values["rom"])
        memo[name] = content_key(name, values, [self.key(d, memo) for d in stage.deps])
        return memo[name]

    def run(self, upto: Optional[str] = None, progress: Optional[ProgressFn] = None) -> dict:
        """Run every stage ``upto`` needs (default: all stages) whose key is not cached;
        return the result of ``upto`` (default: the last stage).

        ``progress(fraction, message)`` hears about stage starts and long stages' progress.
        """
        with self._lock:
            if upto is None:
                order, upto = list(self.stages), list(self.stages)[-1]
            elif isinstance(upto, (list, tuple)):
                order, upto = self._order(*upto), upto[-1]
            else:
                order = self._order(upto)
            memo: dict = {}
            results: dict = {}
            for i, name in enumerate(order):
                stage = self.stages[name]
                k = self.key(name, memo)
                hit, value = self.cache.get((name, k))
                if not stage.active:
                    hit, value = True, None
                if not hit:
                    if progress:
                        progress(i / len(order), f"{name}…")
                    inner = None
                    if progress:
                        lo, hi = i / len(order), (i + 1) / len(order)
                        inner = lambda f, m, lo=lo, hi=hi, name=name: progress(lo + f * (hi - lo), f"{name}: {m}")  # noqa: E731
                    t0 = time.perf_counter()
                    value = stage.run({d: results[d] for d in stage.deps}, stage.settings, inner)
                    self.timings[name] = time.perf_counter() - t0
                    _freeze(value)
                    self.cache.put((name, k), value)
                    self.runs[name] += 1
                else:
                    self.timings[name] = 0.0
                results[name] = value
                self.keys[name] = k
            if progress:
                progress(1.0, "done")
            return results[upto]

    def results(self, names=None, progress: Optional[ProgressFn] = None) -> dict:
        """Results of several stages (running what is stale)."""
        names = list(names or self.stages)
        self.run(names, progress)
        return {n: self.cache.get((n, self.keys[n]))[1] for n in names}

    def _order(self, *targets: str) -> list:
        for t in targets:
            if t not in self.stages:
                raise KeyError(f"no stage {t!r}; stages are {list(self.stages)}")
        need, stack = set(), list(targets)
        while stack:
            n = stack.pop()
            if n not in need:
                need.add(n)
                stack.extend(self.stages[n].deps)
        return [n for n in self.stages if n in need]


# --------------------------------------------------------------------------------------
# CLI flags from the same settings


def cli_flags(pipeline_or_cls=None):
    """(flag, param name, parameter object, owner) for every tunable setting, e.g.
    ``--alpha`` -> ("alpha", Number). One definition serves the dashboard and the CLI."""
    objs = pipeline_or_cls.settings_objects if pipeline_or_cls is not None else Pipeline().settings_objects
    out = []
    for stage, obj in objs.items():
        for pname, p in obj.param.objects("existing").items():
            if pname == "name" or isinstance(p, param.List):
                continue
            out.append(("--" + pname.replace("_", "-"), pname, p, stage))
    return out


def add_cli_arguments(parser, skip=(), extra_methods=()) -> None:
    """Add one argparse option per setting (types, choices, defaults and help from param).

    ``extra_methods`` are accepted by ``--method`` without being pipeline stages (the CLI's
    dense ``transfer``, which produces a new rig rather than weights for the target's shapes).
    """
    import argparse

    for flag, pname, p, stage in cli_flags():
        if pname in skip:
            continue
        default = "" if p.default in ("", None) else f" (default: {p.default})"
        kw = {"dest": pname, "default": argparse.SUPPRESS, "help": f"[{stage}] {p.doc}{default}"}
        if isinstance(p, param.Boolean):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, **kw)
            continue
        if isinstance(p, param.Selector):
            kw["choices"] = list(p.objects) + (list(extra_methods) if pname == "method" else [])
        elif isinstance(p, param.Integer):
            kw["type"] = int
        elif isinstance(p, param.Number):
            kw["type"] = float
        parser.add_argument(flag, **kw)
