"""The retargeting stages, from files to weights and diagnostics.

::

    take ─────────┐
    source_face ──┼── load ── shapes ───────────────────────────── segment ──┐
    target_face ──┘     │        │                                           │
    frames ─────────────┴── stabilize ── calibrate ── personalize ──┬────── solve ── edit ── synthesize ── evaluate
                                                                    └─ prior ─┘

Each stage is a pure function of its inputs and settings (see :mod:`core.stage`); the
pipeline caches them by content. Method modules are imported inside the functions that use
them, so a missing optional piece fails only the method that needs it.
"""

from __future__ import annotations

import difflib
import functools
import json
import os
import warnings
from dataclasses import replace

import numpy as np
import param

from ..controls import cancel_pairs, default_table, filter_weights, merge_table, resolve
from ..controls.mirror import mirror_performance
from ..correspondence import MAX_POINTS, capture_correspondence, rig_correspondence
from ..evaluate import evaluate
from ..metrics import error_products
from ..gaps import fill_gaps
from ..io.layout import default_layout_path
from ..io.performance import read_performance
from ..io.rigs import load_rig, read_layout_for
from ..motion_alignment import apply_alignment, covariance_alignment, matched_alignment
from ..names import ARKIT_NAMES, NameMap, bundled_vocabulary_files, canonical, load_vocabularies
from ..personalize import personalize
from ..prior import PCAPrior, prior_quadratic
from ..progress import report
from ..retarget import common_markers, source_marker_names, source_markers, target_markers
from ..segment import marker_weights, segment
from ..shot import file_hash
from ..solvers.baselines import data_gram
from ..solvers.local import masks_at
from ..solvers.spacetime import PoseEdit, SpacetimeSolver, data_products
from ..stage import Stage, register
from .methods import AUTO_MOTION_SCALE, METHODS, method_of, named_target, names_carry, weighted_markers

#: a shape whose largest marker displacement is below this fraction of the largest shape's
#: is invisible to the markers
INVISIBLE = 1e-3


@register("take")
class Take(Stage):
    """The source performance file (or folder of per-frame meshes)."""

    files = ("source",)
    group, title = "files", "Source performance"
    source = param.String(default="", doc=(
        "Source performance: Live Link Face CSV, marker CSV/TRC/C3D, a GLB or USD with a weight animation, or a mesh "
        "sequence (a folder of per-frame OBJ/PLY files, a USD mesh with time-sampled points)"))
    source_kind = param.Selector(default="auto", objects=["auto", "meshes"], doc=(
        "What to read from the source: auto = what the file holds (weight curves for a GLB/UsdSkel animation); "
        "meshes = a GLB's or UsdSkel file's animated mesh as a dense mesh sequence (no source rig needed)"))
    source_fps = param.Number(default=0.0, bounds=(0, None), doc=(
        "Frame rate of a mesh-sequence folder, GLB or USD source (0: the file's own, a folder's sequence.json, else 30)"))
    mirror_source = param.Boolean(default=False, label="Mirror the take (left ↔ right)", doc=(
        "Swap the take's left and right (curve names, marker names and positions; core.controls.mirror_performance)"))

    def run(self, inputs, s, progress=None):

        if not s.source:
            raise ValueError("no source performance chosen (--source)")
        report(progress, 0.1, "reading source")
        perf = read_performance(s.source, kind=s.source_kind, fps=s.source_fps or None)
        if s.mirror_source:

            perf = mirror_performance(perf)
        return {"source": perf}


def _with_default_layout(paths: dict, rig: str, layout: str) -> dict:
    """``paths`` with the rig's default layout (its sidecar, else the bundled one) filled in
    when no layout is chosen: the file read is an input like any other (editing it re-keys)."""

    if paths[rig] and not paths[layout]:
        default = default_layout_path(paths[rig])
        paths[layout] = str(default) if default is not None else ""
    return paths


@register("source_face")
class SourceFace(Stage):
    """The rig the source curves drive, its marker layout and the channel name map."""

    files = ("source_rig", "source_layout", "name_map")
    group, title = "files", "Source rig"
    source_rig = param.String(default="", doc="Rig the source curves drive (GLB); needed for weight-curve sources")
    source_layout = param.String(default="", doc="Marker layout JSON on the source rig (default: data/layouts/<rig stem>.json)")
    name_map = param.String(default="", doc="Name map JSON from source channels to source-rig shapes (default: automatic ARKit names)")

    def file_paths(self, cfg):
        return _with_default_layout(super().file_paths(cfg), "source_rig", "source_layout")

    def run(self, inputs, s, progress=None):

        report(progress, 0.2, "reading the source rig")
        rig = load_rig(s.source_rig) if s.source_rig else None
        layout = read_layout_for(s.source_layout, s.source_rig, rig) if rig is not None else None
        name_map = NameMap.from_json(s.name_map) if s.name_map else None
        # without a rig the layout belongs to a mesh sequence's topology: read by sequence_face
        return {"source_rig": rig, "source_layout": layout, "name_map": name_map, "source_layout_path": s.source_layout}


@register("target_face")
class TargetFace(Stage):
    """The target rig and its marker layout."""

    files = ("target_rig", "target_layout")
    group, title = "files", "Target rig"
    target_rig = param.String(default="", doc="Target blendshape rig (GLB or OBJ folder)")
    target_layout = param.String(default="", doc="Marker layout JSON on the target rig (default: data/layouts/<rig stem>.json)")

    def file_paths(self, cfg):
        return _with_default_layout(super().file_paths(cfg), "target_rig", "target_layout")

    def run(self, inputs, s, progress=None):

        if not s.target_rig:
            raise ValueError("no target rig chosen (--target-rig)")
        report(progress, 0.2, "reading the target rig")
        rig = load_rig(s.target_rig)
        return {"target_rig": rig, "target_layout": read_layout_for(s.target_layout, s.target_rig, rig)}


@register("vocabulary")
class Vocabulary(Stage):
    """The naming schemes rigs use (ARKit, SRanipal, FACS, Unified Expressions, Meta, visemes ...;
    :mod:`core.names`, docs/names.md): the bundled ``data/namemaps/vocabulary_*.json`` and any
    given here. What the name prior, the ``names`` method and ``auto`` read a shape's meaning from;
    the bundled files' content is part of the key, so editing one re-runs what used it."""

    files = ("vocabularies",)
    group, title = "files", "Vocabularies"
    vocabularies = param.String(default="", doc=(
        "More vocabulary JSON, or a folder of vocabulary_*.json, on top of the bundled ones (docs/names.md)"))

    def content(self, cfg):
        return [file_hash(p) for p in bundled_vocabulary_files()]

    def run(self, inputs, s, progress=None):
        return {"vocabularies": load_vocabularies([s.vocabularies] if s.vocabularies else [])}


@register("load")
class Load(Stage):
    """The take and the rigs together, checked against each other. A mesh sequence without a
    source rig brings its own source face (:mod:`.sequence`): its layout is the source layout."""

    deps = ("take", "source_face", "target_face", "sequence_face")

    def run(self, inputs, s, progress=None):
        src = inputs["take"]["source"]
        rig = inputs["source_face"]["source_rig"]
        if src.kind == "curves" and rig is None:
            raise ValueError(f"{src.name}: weight curves need the rig they drive (--source-rig); a GLB or USD file whose "
                             "animation drives its own mesh can be read as a mesh sequence with --source-kind meshes")
        if src.kind == "meshes" and rig is not None and src.data.shape[1] != rig.n_vertices:
            raise ValueError(f"{src.name}: the mesh sequence has {src.data.shape[1]} vertices, source rig {rig.name!r} "
                             f"{rig.n_vertices}; give the rig whose topology it has, or no --source-rig")
        out = {"source": src, **inputs["source_face"], **inputs["target_face"]}
        sq = inputs.get("sequence_face")
        if rig is None and sq and sq["source_layout"] is not None:
            out["source_layout"] = sq["source_layout"]
        return out


@register("dense_correspondence")
class DenseCorrespondence(Stage):
    """The source rig's face points in farthest-point order (up to 20,000), each carried onto the
    target by the rig pair's registration (:func:`core.correspondence.rig_correspondence`), with
    its weight: computed once per rig pair; ``correspond`` takes the first ``dense_points``
    (a prefix of a farthest-point order is the farthest-point sample of that size). Runs only
    with a source rig (a capture is densified by ``correspond``), for ``correspondence = dense``
    or a method that chooses its configuration (``auto``: its shape map compares the rigs' shapes
    over the face when no name is shared, :func:`core.stages.methods.dense_shape_map`)."""

    deps = ("source_face", "target_face", "weld", "register")
    persist = True

    def active(self, cfg):
        # auto compares the rigs' shapes over the face (its shape map without shared names)
        return (cfg.correspond.correspondence == "dense" or auto_maps_shapes(cfg)) and bool(cfg.source_face.source_rig)

    def run(self, inputs, s, progress=None):

        sf, tf, reg = inputs["source_face"], inputs["target_face"], inputs["register"]
        report(progress, 0.5, "dense correspondence: face points onto the target")
        src, tgt, w = rig_correspondence(sf["source_rig"], sf["source_layout"], inputs["weld"]["welded"],
                                         reg["registration"], tf["target_rig"], MAX_POINTS)
        return {"source_layout": src, "target_layout": tgt, "weights": w}


@register("correspond")
class Correspond(Stage):
    """The points both faces are compared at: the 41-marker layouts, or dense correspondence
    (:mod:`core.correspondence`): ``dense_points`` face points, weighted by how well the rig
    pair's registration fits there — for a marker capture, through the RBF of its layout."""

    deps = ("load", "dense_correspondence")
    group, title = "calibrate", "Source & calibration"
    correspondence = param.Selector(label='Compare the faces at', default="markers", objects=["markers", "dense"], doc=(
        "What the solvers fit: markers = the layouts' 41 markers; dense = many points on the face, carried to the "
        "target by the registration dense transfer computes (the first time per rig pair takes tens of seconds)"))
    dense_points = param.Integer(label='Face points (dense)', default=1000, bounds=(10, 20000), doc="Number of face points of dense correspondence")

    def relevant(self, cfg):
        return ("correspondence", "dense_points") if cfg.correspond.correspondence == "dense" else ("correspondence",)

    def reads(self, cfg):
        # the markers alone need no registration: auto's shape map reads the dense stage itself
        return self.deps if cfg.correspond.correspondence == "dense" else ("load",)

    def run(self, inputs, s, progress=None):
        ld = inputs["load"]
        out = {"source": ld["source"], "source_layout": ld["source_layout"], "target_layout": ld["target_layout"],
               "weights": None, "kind": s.correspondence}
        if s.correspondence == "markers":
            return out
        dc = inputs.get("dense_correspondence")
        if dc is not None:
            names = dc["source_layout"].names[:s.dense_points]
            out.update(source_layout=dc["source_layout"].select(names), target_layout=dc["target_layout"].select(names),
                       weights=dict(zip(names, dc["weights"][:len(names)])))
            return out
        if ld["source"].kind != "markers":
            raise ValueError("dense correspondence needs the source rig the curves drive (--source-rig) or a marker capture")

        report(progress, 0.3, "densifying the capture's markers (RBF of the layout)")
        perf, tgt = capture_correspondence(ld["source"], ld["target_rig"], ld["target_layout"], s.dense_points)
        out.update(source=perf, source_layout=None, target_layout=tgt)
        return out


@register("frames")
class Frames(Stage):
    """The frame range of the take that is retargeted."""

    deps = ("take",)
    group, title = "source", "Frame range"
    first_frame = param.Integer(label='First frame', default=0, bounds=(0, None), doc="First frame to retarget")
    last_frame = param.Integer(label='Last frame', default=-1, bounds=(-1, None), doc="Last frame to retarget (-1: the end)")

    def run(self, inputs, s, progress=None):
        n = inputs["take"]["source"].n_frames
        stop = n if s.last_frame < 0 else min(s.last_frame + 1, n)
        if not 0 <= s.first_frame < stop:
            raise ValueError(f"frame range [{s.first_frame}, {s.last_frame}] is empty for {n} frames")
        return {"first": int(s.first_frame), "stop": int(stop), "n_frames": int(n)}


def solver_shapes(rig, spec: str) -> list:
    """Indices of the target shapes the solvers may use: ``""`` all; ``"arkit"`` the shapes
    with a canonical ARKit name (all shapes when the rig has none); else comma-separated names."""

    spec = (spec or "").strip()
    if not spec:
        return list(range(rig.n_shapes))
    if spec.lower() == "arkit":
        idx = [i for i, n in enumerate(rig.names) if canonical(n) in ARKIT_NAMES]
        return idx or list(range(rig.n_shapes))
    return [rig.index(n.strip()) for n in spec.split(",") if n.strip()]


def _stamp(path: str):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=8)
def _names_carry_the_take(source, source_kind, target_rig, target_shapes, stamps) -> bool:
    """Whether ``auto`` can go by names (so never compares the rigs' shapes over the face): the take
    is not weight curves, or enough of the solver's target shapes have a channel of the take by
    their ARKit name (:func:`~core.stages.methods.names_carry`, the rule ``auto_choice`` applies to the loaded data). Read
    from the files (``stamps``: their modification times and sizes, so an edited file is read
    again); a file that cannot be read says True (the load stage reports it)."""
    try:
        perf = read_performance(source, kind=source_kind)
        rig = load_rig(target_rig)
    except Exception:  # noqa: BLE001 - the stages that read these files raise the user's error
        return True
    if perf.kind != "curves":
        return True
    channels = {canonical(n) for n in perf.names} & set(ARKIT_NAMES)
    try:
        idx = solver_shapes(rig, target_shapes)
    except (KeyError, ValueError):
        return True
    named = sum(canonical(rig.names[i]) in channels for i in idx)
    return names_carry(named, len(idx))


def auto_maps_shapes(cfg) -> bool:
    """Whether ``auto`` will map a source rig's curves through the rigs' shape map over their dense
    correspondence (:func:`core.stages.methods.auto_choice`; with example poses too, as their base): a
    chooser method, a source rig, and a target whose shapes do not carry the take by name. Decided from the files
    before anything runs, so the rig pair's registration (tens of seconds the first time) is paid
    only when that map is made: never for the sample's ARKit-named pair."""
    if not (method_of(cfg).chooses and cfg.source_face.source_rig and cfg.take.source and cfg.target_face.target_rig):
        return False
    t, f = cfg.take, cfg.target_face
    return not _names_carry_the_take(t.source, t.source_kind, f.target_rig, cfg.shapes.target_shapes,
                                     (_stamp(t.source), _stamp(f.target_rig)))


@register("shapes")
class Shapes(Stage):
    """Which markers both faces share, and which target shapes the solvers may use.

    Reads only the rigs, the layouts and the source's marker names: the frame range, the
    neutral frame and the calibration do not change it (so segmentation does not re-run).
    """

    deps = ("load", "correspond")
    group, title = "calibrate", "Source & calibration"
    target_shapes = param.String(label='Target shapes the solver may use', default="", doc=(
        "Target shapes the solvers may use: empty = all; 'arkit' = the shapes with an ARKit name (all when the rig has "
        "none); or comma-separated shape names. The others stay at zero"))

    def run(self, inputs, s, progress=None):
        ld, cor = inputs["load"], inputs["correspond"]
        rig, layout = ld["target_rig"], cor["target_layout"]
        names = tuple(common_markers(source_marker_names(cor["source"], cor["source_layout"]), layout))
        idx = solver_shapes(rig, s.target_shapes)
        # shapes that move no marker (tongue, eyeball-only, empty shapes) cannot be determined from
        # markers: solving for them only injects noise (weights of 1e3 through near-null modes)
        sub = layout.select(names)
        reach = np.linalg.norm(sub.points(rig.deltas), axis=2).max(1)
        unseen = [i for i in idx if reach[i] <= INVISIBLE * reach.max()]
        if unseen:
            warnings.warn(f"{len(unseen)} target shapes move no marker and stay at zero: "
                          + ", ".join(rig.names[i] for i in unseen[:8]) + (" ..." if len(unseen) > 8 else ""))
            idx = [i for i in idx if i not in set(unseen)]
        solver_rig = rig.subset([rig.names[i] for i in idx]) if len(idx) < rig.n_shapes else rig
        w = cor["weights"]
        weights = None if w is None else np.array([w[n] for n in names])
        return {"names": names, "shape_index": np.asarray(idx), "rig": solver_rig, "layout": sub, "weights": weights,
                "unseen": [rig.names[i] for i in unseen]}


@register("stabilize")
class Stabilize(Stage):
    """Source markers over the frame range: rigid head-motion removal (Seol 2012 §3.1)."""

    deps = ("load", "correspond", "frames", "shapes")
    group, title = "source", "Frame range"
    head_motion = param.Selector(label='Remove head motion (captures)', default="auto", objects=["auto", "remove", "keep"], doc="Remove rigid head motion from captured markers (auto: captures only)")
    neutral_frame = param.Integer(label='Neutral frame (captures)', default=0, bounds=(0, None), doc="Frame of a captured take that shows the neutral face")

    def run(self, inputs, s, progress=None):
        ld, cor, fr = inputs["load"], inputs["correspond"], inputs["frames"]
        src = cor["source"]
        if fr["first"] or fr["stop"] != src.n_frames:
            src = src.frames(fr["first"], fr["stop"])
        sm = source_markers(src, ld["source_rig"], cor["source_layout"], ld["name_map"], s.head_motion,
                            min(s.neutral_frame, src.n_frames - 1))
        names = inputs["shapes"]["names"]
        idx = [sm.names.index(n) for n in names]
        # frame-major and contiguous: every stage after reads the take as (T, 3M) rows, and the fancy
        # index leaves the markers outermost in memory (each reshape of a dense take was a 24 MB copy)
        sm = replace(sm, deltas=np.ascontiguousarray(sm.deltas[:, idx]), valid=np.ascontiguousarray(sm.valid[:, idx]),
                     neutral=sm.neutral[idx], names=tuple(names))
        return {"source": sm, "names": tuple(names)}


@register("calibrate")
class Calibrate(Stage):
    """Scale-proportion matching of the target's marker blendshapes (Seol 2012 §3.2), and,
    optionally, range-of-motion matching of the source's motion (``motion_scale``).

    ``motion_scale = "rom"`` maps the actor's range of motion onto the character's, point by
    point: each source point's motion is scaled by ``s(p) = ROM_target(p) / ROM_source(p)``,
    ``ROM(p)`` the largest displacement any of the rig's shapes gives the point (the target's
    solver shapes, calibrated; the source rig's shapes — or, for a capture, the 99th percentile
    of the take's own motion), clipped to [0.1, 10]. An actor whose full jaw drop moves the chin
    twice as far as the character's full jaw drop then drives the character's full jaw drop, not
    a clipped one. ``motion_scale = "covariance"`` maps each point's motion by a 3×3 matrix
    instead (:func:`core.motion_alignment.covariance_alignment`): the source rig's shapes' motion
    at the point whitened and coloured with the target's, so an actor's chin that drops back
    drives a character's chin that drops down; it needs the source rig's shapes at the points
    (a capture without a source rig falls back to ``rom``, with a warning). ``motion_scale =
    "matched"`` refits that map on the take (:func:`core.motion_alignment.matched_alignment`):
    each source shape paired with the target shape nearest to it under the covariance map, the
    map fitted so that the take's motion built from the source shapes lands on the same curves
    driving their partners; it needs the take's weight curves (without them: ``covariance``, with a
    warning). The result's ``source`` is the motion the solvers fit (mapped or not), ``source_map``
    the (M, 3, 3) map (None for ``none``), ``source_scale`` the (M,) scale of ``rom`` (else None)
    ``alignment`` the mode that ran (after any fallback) and ``covariance_map`` the covariance map
    (under ``covariance`` and ``matched``, else None).
    """

    deps = ("load", "correspond", "shapes", "stabilize")
    group, title = "calibrate", "Source & calibration"
    calibrate = param.Boolean(label="Match the actor's proportions (Seol RBF)", default=True, doc="Warp the target's marker blendshapes into the actor's proportions with an RBF")
    rbf_smoothing = param.Number(label='Proportion warp smoothing', default=0.0, bounds=(0, 1), softbounds=(0, 0.1), doc="RBF ridge relative to the mean marker distance (0: exact interpolation)")
    motion_scale = param.Selector(label="Match the actor's range of motion", default="none", objects=["none", "rom", "covariance", "matched"], doc=(
        "Match the actor's range of motion to the character's, point by point (rom: an actor's full jaw drop drives "
        "the character's full jaw drop; covariance: also the direction each point moves in, a 3x3 map learned from "
        "both rigs' shapes; matched: that map refitted on the take, each source shape paired with the nearest "
        "target shape); none = the actor's motion as captured"))

    def relevant(self, cfg):
        c = cfg.calibrate
        return ("calibrate", "motion_scale") + (("rbf_smoothing",) if c.calibrate else ())

    def derived(self, cfg):
        # a method that chooses its configuration (auto) matches the actor's range of motion
        # (its motion space aligned, when a source rig's shapes say how the actor's points move;
        # a capture without one: its range of motion, by scale)
        if not method_of(cfg).chooses:
            return {}
        return {"motion_scale": AUTO_MOTION_SCALE if cfg.source_face.source_rig else "rom"}

    def run(self, inputs, s, progress=None):
        sh, st = inputs["shapes"], inputs["stabilize"]
        src = st["source"]
        tm = target_markers(sh["rig"], sh["layout"], st["names"], src.neutral, s.calibrate,
                            s.rbf_smoothing if s.calibrate else 0.0)
        scale = amap = cov = None
        source_rig, source_layout = inputs["load"]["source_rig"], inputs["correspond"]["source_layout"]
        mode = s.motion_scale
        if mode in ("covariance", "matched") and (source_rig is None or source_layout is None):
            warnings.warn(f"motion_scale = {mode} needs the source rig's shapes at the points; "
                          "this source has none: the range of motion is matched by scale (rom)")
            mode = "rom"
        if mode == "matched" and src.source_weights is None:
            warnings.warn("motion_scale = matched needs the take's weight curves; this source has none: "
                          "the motion space is aligned by the rigs' shapes alone (covariance)")
            mode = "covariance"
        if mode == "rom":
            scale = rom_scale(tm.calibrated, src, source_rig, source_layout, st["names"])
            amap = scale[:, None, None] * np.eye(3)
            src = replace(src, deltas=src.deltas * scale[None, :, None])
        elif mode in ("covariance", "matched"):
            Bs = source_layout.select(list(st["names"])).points(source_rig.deltas)
            amap = cov = covariance_alignment(Bs, tm.calibrated)
            if mode == "matched":
                amap = matched_alignment(Bs, tm.calibrated, src.source_weights, initial=cov)
            src = replace(src, deltas=apply_alignment(amap, src.deltas))
        return {"target": tm, "deltas": tm.calibrated, "shape_index": sh["shape_index"], "rig": sh["rig"],
                "unseen": sh["unseen"], "source": src, "source_scale": scale, "source_map": amap, "alignment": mode,
                "covariance_map": cov}


def rom_scale(target_deltas, source, source_rig=None, source_layout=None, names=None) -> np.ndarray:
    """(M,) ``ROM_target / ROM_source`` per point, clipped to [0.1, 10] (see :class:`Calibrate`)."""
    rom_t = np.linalg.norm(np.asarray(target_deltas), axis=2).max(0)
    if source_rig is not None and source_layout is not None:
        rom_s = np.linalg.norm(source_layout.select(list(names)).points(source_rig.deltas), axis=2).max(0)
    else:
        d = np.linalg.norm(np.where(source.valid[..., None], source.deltas, 0.0), axis=2)
        rom_s = np.percentile(d, 99, axis=0)
    return np.clip(rom_t / np.maximum(rom_s, 1e-12), 0.1, 10.0)


@register("personalize")
class Personalize(Stage):
    """Actor-specific blendshapes by range-of-motion alignment (Ribera 2017 §4).

    The ROM take is the source itself unless ``rom`` names another capture of the same
    actor (its markers are matched by name and stabilised the same way).
    """

    deps = ("load", "correspond", "stabilize", "calibrate")
    files = ("rom",)
    group, title = "personalize", "Actor personalisation (Ribera 2017)"
    personalize = param.Boolean(label="Align the rig to the actor's range of motion (Ribera)", default=False, doc="Align the target's marker blendshapes to the actor's range of motion")
    rom = param.String(label='Range-of-motion take', default="", doc="Range-of-motion take of the actor (default: the source itself)")
    align_beta = param.Number(label='Keep the marker mesh smooth (Ribera β)', default=0.01, bounds=(0, None), softbounds=(0, 1), doc="E_Mesh weight beta (Ribera 2017 eq. 4)")
    align_gamma = param.Number(label='Keep contact edges (Ribera γ)', default=0.1, bounds=(0, None), softbounds=(0, 1), doc="E_CEG weight gamma (Ribera 2017 eq. 4)")

    def relevant(self, cfg):
        return None if cfg.personalize.personalize else ("personalize",)

    def run(self, inputs, s, progress=None):
        cal = inputs["calibrate"]
        if not s.personalize:
            return {"deltas": cal["deltas"], "personalized": False}

        st = inputs["stabilize"]
        src = cal["source"]
        rom_deltas, rom_valid = src.deltas, src.valid
        if s.rom:

            ld, cor = inputs["load"], inputs["correspond"]
            if cor["kind"] == "dense" and cor["source_layout"] is None:
                raise ValueError("a range-of-motion take with dense correspondence needs a source rig (the capture's "
                                 "dense points are interpolated per take); use correspondence = markers")
            rom = source_markers(read_performance(s.rom), ld["source_rig"], cor["source_layout"], ld["name_map"])
            missing = [n for n in st["names"] if n not in rom.names]
            if missing:
                raise ValueError(f"{s.rom}: the range-of-motion take lacks markers {missing}")
            idx = [rom.names.index(n) for n in st["names"]]
            rom_deltas, rom_valid = rom.deltas[:, idx], rom.valid[:, idx]
            if cal["source_map"] is not None:  # the ROM take in the character's motion space, as the take
                rom_deltas = apply_alignment(cal["source_map"], rom_deltas)
        out = personalize(rom_deltas, cal["deltas"], src.neutral, names=st["names"], rig_deltas=cal["target"].deltas,
                          valid=rom_valid, beta=s.align_beta, gamma=s.align_gamma)
        return {"deltas": out.deltas, "personalized": True, "diagnostics": out}


@register("segment")
class Segment(Stage):
    """Automatic segmentation of the target rig into regions (Liu 2011 §3.2.1), and the
    per-region marker weights (§3.2.2). Reads the solver's shapes and the shared markers only."""

    deps = ("shapes",)
    group, title = "solve", "Regions (Liu 2011)"
    regions = param.Integer(label='Regions (Liu R)', default=12, bounds=(1, 64), softbounds=(1, 24), doc="Number of regions R")
    min_region_size = param.Number(label='Smallest region', default=0.01, bounds=(0, 0.5), doc="Smallest region as a fraction of the vertices; smaller clusters are merged")
    mask_smoothing = param.Integer(label='Region overlap (smoothing iterations)', default=10, bounds=(0, 200), doc="Laplacian smoothing iterations of the region masks (overlap for blending)")

    def active(self, cfg):
        return "segment" in method_of(cfg).needs

    def run(self, inputs, s, progress=None):

        rig, layout = inputs["shapes"]["rig"], inputs["shapes"]["layout"]
        seg = segment(rig, n_regions=s.regions, min_size=max(1, int(round(s.min_region_size * rig.n_vertices))),
                      smooth_iters=s.mask_smoothing)
        report(progress, 0.8, "marker weights")
        return {"labels": seg.labels, "masks": seg.masks, "marker_weights": marker_weights(rig, layout, seg.masks),
                "marker_masks": masks_at(layout, seg.masks), "info": dict(seg.info)}


@register("prior")
class Prior(Stage):
    """Model-specific PCA prior (Seol 2012 §5) from all of the solver's shapes or a subset
    (Fig. 13: e.g. the mouth shapes only constrain the mouth)."""

    deps = ("personalize", "shapes")
    group, title = "solve", "Prior (Seol 2012)"
    prior_shapes = param.String(label='Prior built from (Seol Fig. 13)', default="", doc=(
        "Shapes the PCA prior is built from: empty = all the solver's shapes (Seol 2012 Fig. 13 a), 'arkit', or "
        "comma-separated names (Fig. 13 b, c: e.g. the mouth shapes only)"))

    def active(self, cfg):
        return "prior" in method_of(cfg).needs

    def run(self, inputs, s, progress=None):

        deltas = inputs["personalize"]["deltas"]
        subset = None
        if s.prior_shapes.strip():
            rig = inputs["shapes"]["rig"]
            subset = solver_shapes(rig, s.prior_shapes)
            if len(subset) < 2:
                raise ValueError(f"prior_shapes {s.prior_shapes!r}: the prior needs at least 2 of the solver's shapes, "
                                 f"got {len(subset)}")
        return {"prior": PCAPrior().fit(deltas, subset=subset), "subset": subset}


@register("gram")
class Gram(Stage):
    """The per-frame data term in weight space (:func:`core.solvers.baselines.data_gram` of the
    weighted markers): it depends on the take and the rig, not on the solve's settings, so a
    setting change re-solves without the products with the whole take (1,000 frames x 1,000
    dense points: most of a prior_pf solve). For the methods that declare it (``needs``)."""

    deps = ("calibrate", "personalize", "shapes")

    def active(self, cfg):
        return "gram" in method_of(cfg).needs

    def run(self, inputs, s, progress=None):
        return data_gram(*weighted_markers(inputs))


@register("motion_gram")
class MotionGram(Stage):
    """The spacetime energy's data in weight space (:func:`core.solvers.spacetime.data_products`
    of the markers the solvers fit): like ``gram`` it depends on the take and the rig, not on
    alpha, beta or the bounds, so a setting change builds its solver without the products with
    the whole take and the SVD of the rig's marker matrix (1,000 frames x 1,000 dense points:
    ~0.1 s of every spacetime solve). For the methods that declare it (``needs``)."""

    deps = ("calibrate", "personalize", "shapes")

    def active(self, cfg):
        return "motion_gram" in method_of(cfg).needs

    def run(self, inputs, s, progress=None):
        from .methods import _marker_weights, _markers

        return {"products": data_products(*_markers(inputs), _marker_weights(inputs))}


@register("error_products")
class ErrorGram(Stage):
    """The take's products that the marker and velocity errors of any weights need
    (:func:`core.metrics.error_products`: ``B^T B``, ``S B``, the squared norms of the take): they
    depend on the take and the rig, not on a setting, so every setting change's ``evaluate`` sums
    its errors in weight space (1,000 dense points: evaluate ~62 -> ~12 ms a change). None with a missing
    sample or few points (``3M <= 2K``: the 41 markers score faster from their residual)."""

    deps = ("calibrate", "personalize")

    def active(self, cfg):
        return not method_of(cfg).dense

    def run(self, inputs, s, progress=None):
        st = inputs["calibrate"]["source"]  # the motion the solve fitted (evaluate's)
        B = inputs["personalize"]["deltas"]
        if 3 * B.shape[1] <= 2 * B.shape[0]:
            return {"products": None}
        return {"products": error_products(B, st.deltas, st.valid)}


@register("solve")
class Solve(Stage):
    """The retargeting solver and its term weights. Each method is registered in
    :mod:`core.stages.methods` with the settings it reads and the stages it needs."""

    deps = ("load", "correspond", "frames", "stabilize", "calibrate", "personalize", "shapes", "segment", "prior",
            "vocabulary", "gram", "motion_gram", "dense_correspondence")
    group, title = "solve", "Solver"
    method = param.Selector(label='Method', default="auto", objects={m.label: n for n, m in METHODS.items()}, doc=(
        "auto: what serves this pair and take best, said in one sentence (the default); lsq: per-frame least squares (unregularised diagnostic); bounded: per-frame with lower<=w<=upper; "
        "range_pf/prior_pf: Seol 2012 §7 baselines; spacetime: Seol 2012 movement matching; local: Liu 2011 "
        "regions; geometric: Ribera 2017 prior + L1; transfer: Xu 2014 dense transfer (a new rig)"))
    # one scale for both (-1..2): with -1..0 and 1..2 the lowest sat at its slider's right end and the
    # highest at its left, and they looked swapped
    lower = param.Number(label='Lowest weight', default=0.0, softbounds=(-1, 2), doc="Lower weight bound (bounded, geometric, spacetime, local box; per shape in the controls)")
    upper = param.Number(label='Highest weight', default=1.0, softbounds=(-1, 2), doc="Upper weight bound (bounded, geometric, spacetime, local box; per shape in the controls)")
    alpha = param.Number(label="Stay near the rig's own expressions (Seol α)", default=0.01, bounds=(0, None), softbounds=(0, 1), step=0.001, doc="PCA prior weight alpha (Seol 2012 eq. 4)")
    beta = param.Number(label='Hold positions, not only motion (Seol β)', default=0.0, bounds=(0, None), softbounds=(0, 1), step=0.001, doc="Sobolev position weight beta (Seol 2012 §7.1)")
    boundary = param.Selector(label='First and last frame (Seol boundary)', default="perframe", objects=["perframe", "neutral", "none"], doc=(
        "Spacetime boundary frames: perframe = first/last frame from the Prior PF solution (takes rarely start and end "
        "neutral); neutral = zero weights at both ends as in Seol 2012 §3.1; none = free (needs beta > 0)"))
    ridge = param.Number(label="Damp shapes the markers can't tell apart (ridge)", default=1e-3, bounds=(0, 1), softbounds=(0, 1e-2), doc=(
        "Relative Tikhonov weight rho / sigma_max(B)^2 on the weights (bounded, range_pf, prior_pf, spacetime): pulls "
        "combinations of shapes the markers barely see (e.g. eye-wide vs look-up vs blink) to zero; 0 = the papers' methods. "
        "The default 1e-3 (was 1e-5): on S07 -> Rocketbox it lowers bounded's error (all shapes 1.23 -> 0.80 mm, ARKit "
        "0.88 -> 0.57), moves spacetime's by < 0.015 mm and makes its bounded solve exact 10x sooner (165 shapes 14 -> 1.4 s)"))
    mu = param.Number(label='Keep the mesh smooth (Ribera μ)', default=0.3, bounds=(0, None), softbounds=(0, 2), step=0.01, doc="Geometric prior weight mu (Ribera 2017 eq. 16)")
    lam = param.Number(label='Use few shapes (Ribera λ)', default=0.6, bounds=(0, None), softbounds=(0, 2), step=0.01, doc="L1 sparsity weight lambda (Ribera 2017 eq. 16)")
    constraint = param.Selector(label='Region weights (Liu constraint)', default="simplex", objects=["simplex", "box"], doc=(
        "Local solve constraint: simplex = the paper's convex combination of poses (w >= 0, sum w <= 1 in delta form, "
        "Liu 2011 eq. 2); box = 0 <= w <= 1"))
    local_temporal = param.Selector(label='Regions in time (Liu / Seol)', default="perframe", objects=["perframe", "spacetime"], doc=(
        "Local method in time: perframe = Liu 2011's per-frame constrained QP (optionally Gaussian-filtered); spacetime = "
        "Seol 2012 movement matching inside each region (uses alpha/beta; unconstrained between the end frames)"))
    geometric_prior = param.Selector(label='Prior (Ribera Fig. 14)', default="geometric", objects=["geometric", "pca", "l2", "none"], doc=(
        "Prior of the geometric method (Ribera 2017 Fig. 14): cotangent-Laplacian bending, Seol's PCA, plain L2, none"))
    sigma = param.Number(label='Smooth the curves over frames (Gaussian σ)', default=0.0, bounds=(0, None), softbounds=(0, 5), doc="Gaussian temporal filter of the weights in frames (Liu 2011; 0: off)")
    spacetime_bounds = param.Boolean(label='Keep weights between lowest and highest', default=True, doc=(
        "Spacetime within lower <= w <= upper (exact bounded solve: curves an animator can key); off = Seol 2012's "
        "unbounded solve"))
    l1 = param.Number(label='Use few shapes (L1)', default=0.0, bounds=(0, None), softbounds=(0, 1e-3), doc=(
        "L1 sparsity of the spacetime weights, relative to sigma_max(B)^2 like ridge: fewer shapes per frame"))
    controls = param.Dict(default={}, label="Per-shape controls", doc=(
        "Per-shape controls (core.controls): {shapes: {name: {lower, upper, gain, offset, active}}, symmetry: [[L, R]], "
        "cancel: [[a, b]]}; empty = every shape active within lowest…highest, gain 1, the automatic left/right pairs"))
    symmetry_weight = param.Number(default=0.0, bounds=(0, None), softbounds=(0, 1), label="Solve left and right alike (μ_s)",
                                   doc="Weight of the symmetry pairs' term μ_s ||w_L - w_R||², relative to sigma_max(B)^2; 0 = off")
    cancel_threshold = param.Number(default=0.0, bounds=(0, 1), label="Cancel pairs: fire above", doc=(
        "Two shapes of a cancel pair never both exceed this weight (the weaker is held at 0 and the rest re-solved)"))
    weights_filter = param.Selector(default="none", objects=["none", "one_euro", "gaussian"], label="Jitter filter (per-frame methods)",
                                    doc="Post-solve filter of per-frame methods: One Euro (causal) or a zero-phase Gaussian of sigma frames")
    filter_min_cutoff = param.Number(default=1.0, bounds=(0.01, None), softbounds=(0.1, 10), label="One Euro: cutoff at rest (Hz)",
                                     doc="One Euro filter's minimum cutoff frequency (Casiez et al. 2012)")
    filter_beta = param.Number(default=0.0, bounds=(0, None), softbounds=(0, 1), label="One Euro: follow fast motion (β)",
                               doc="One Euro filter's speed coefficient: higher = less lag on fast motion")
    example_poses = param.List(default=[], item_type=dict, doc=(
        "Example poses (auto): [{frame, weights: {target shape: w}}]: the target posed by an animator at a few take "
        "frames; auto learns from them a correspondence for the whole take (core.examples)"))
    name_weight = param.Number(label='Follow the same-named source curves (names)', default=0.0, bounds=(0, None), softbounds=(0, 1e-2), doc=(
        "Pull of each target shape towards its namesake source curve (same canonical ARKit name), relative to "
        "sigma_max(B)^2; 0 = off. Only where the source is weight curves sharing names with the target"))

    #: the settings each capability of a method (:data:`~.methods.CAPABILITIES`) adds to what it reads
    BY_CAPABILITY = {"symmetry": ("symmetry_weight",), "cancel": ("cancel_threshold",)}
    #: the last result's weights start a method that takes them (``Method.warm``: the bounded
    #: spacetime solve; the minimiser is unique, so only the time changes)
    warm_start = True

    def relevant(self, cfg):
        """The method's own settings, the per-shape controls over lowest…highest (every method's
        result gets their gain and offset after the solve), and what its capabilities read."""
        m = method_of(cfg)
        out = ("method",) + m.params + ("controls", "lower", "upper")
        for cap in sorted(m.honours):
            out += self.BY_CAPABILITY.get(cap, ())
        if "filter" in m.honours:
            f = cfg.solve.weights_filter
            out += ("weights_filter",) + (("filter_min_cutoff", "filter_beta") if f == "one_euro" else
                                          ("sigma",) if f == "gaussian" else ())
        return tuple(dict.fromkeys(out))

    def hidden(self, cfg):
        """Lowest/highest weight under a method that does not honour bounds: they stay in the key
        (the per-shape controls' table is made over them), but moving them changes nothing."""
        return () if "bounds" in method_of(cfg).honours else ("lower", "upper")

    def active(self, cfg):
        return not method_of(cfg).dense

    def reads(self, cfg):
        # the rig pair's dense correspondence only for auto's shape map (auto_maps_shapes)
        return self.deps if auto_maps_shapes(cfg) else tuple(d for d in self.deps if d != "dense_correspondence")

    def run(self, inputs, s, progress=None, warm=None):
        m = METHODS[s.method]
        names = list(inputs["shapes"]["rig"].names)
        ctl = _controls(json.dumps(s.controls or {}, sort_keys=True), tuple(names), float(s.lower), float(s.upper))
        lo, hi = ctl.bounds()
        sym = None
        if "symmetry" in m.honours and s.symmetry_weight > 0 and len(ctl.symmetry):
            sym = ctl.symmetry_matrix(s.symmetry_weight)
        zero = ctl.zero() if "active" in m.honours and (~ctl.active).any() else None
        aug = s.with_values(lower=lo, upper=hi, quadratic=sym, zero=zero)
        hint = warm["weights"] if m.warm and warm is not None and warm.get("method") == m.name else None
        out = m.run(inputs, aug, warm=hint) if hint is not None else m.run(inputs, aug)
        W = np.asarray(out["weights"], dtype=np.float64)
        info = dict(out.get("info", {}))
        if "cancel" in m.honours and len(ctl.cancel):
            def again(z):
                held = z if zero is None else z | zero[None]
                return np.asarray(m.run(inputs, aug.with_values(zero=held))["weights"], dtype=np.float64)

            W, cinfo = cancel_pairs(again, W, ctl.cancel, s.cancel_threshold)
            info["cancel"] = {k: v for k, v in cinfo.items() if k != "held"}
        if "filter" in m.honours and s.weights_filter != "none":
            fps = inputs["calibrate"]["source"].fps
            kw = ({"sigma": max(s.sigma, 1e-3)} if s.weights_filter == "gaussian" else
                  {"min_cutoff": s.filter_min_cutoff, "beta": s.filter_beta})
            W = filter_weights(np.nan_to_num(W), fps, s.weights_filter, **kw)
        return {"weights": W, "method": m.name, "info": info, "edit": out["edit"], "controls": ctl}


@functools.lru_cache(maxsize=16)
def _controls(table_json: str, names: tuple, lower: float, upper: float):
    """The per-shape controls a solve runs with: the user's table over the rig's defaults, resolved.
    A pure function of its arguments, remembered: the defaults' symmetry pairs are matched by name
    each time (10-25 ms), and an alpha change would pay it again for the same table and rig. The
    arrays are read-only (one object serves every result made with this table)."""
    ctl = resolve(merge_table(json.loads(table_json), default_table(names, lower, upper)), names)
    for v in vars(ctl).values():
        if isinstance(v, np.ndarray):
            v.setflags(write=False)
    return ctl


def edited_poses(W, names, edits) -> list:
    """The edits as whole poses: ``[(frame, (K,) pose, window or None), ...]``.

    An edit sets some weights of a frame; the frame's other weights keep the values shown
    (``W[frame]``), and several edits of one frame combine (the later wins on a shape they share).
    The whole pose is the boundary condition of Seol et al. 2012 §6 ("the animator adjusts the
    target blendshape weights at a selected frame"): with only the edited weight fixed, the
    movement match is kept at that frame alone by the other shapes, which cancel the edit's
    marker motion there (jawOpen 0.12 → 1.00 → 0.11 at frames 418–420, other mouth shapes dropping
    at 419) instead of letting the change propagate over the window.

    Parameters
    ----------
    W : (T, K) float, the weights the edits start from (NaN where the frame had no sample: the
        pose keeps the NaN, the solver leaves those weights free)
    names : K shape names of ``W``'s columns
    edits : list of ``{"frame": int, "weights": {name: value} or (K,) values, "shapes": names or
        None, "window": [a, b] or None}``

    Raises
    ------
    ValueError
        A shape name not in ``names`` (with the closest ones), a frame outside ``W``.
    """
    T, K = W.shape
    poses: dict = {}
    for i, e in enumerate(edits):
        f = int(e["frame"])
        if not 0 <= f < T:
            raise ValueError(f"edits[{i}].frame: {f} is outside [0, {T})")
        weights = e["weights"]
        shapes = list(weights) if isinstance(weights, dict) else e.get("shapes")
        values = np.asarray(list(weights.values()) if isinstance(weights, dict) else weights, float).ravel()
        if shapes is None:
            idx = np.arange(K)
        else:
            missing = [n for n in shapes if n not in names]
            if missing:
                close = difflib.get_close_matches(str(missing[0]), names, n=3)
                raise ValueError(f"edits[{i}]: no shape {missing[0]!r}" + (f"; did you mean {close}?" if close else ""))
            idx = np.array([names.index(n) for n in shapes], dtype=np.int64)
        if values.shape != idx.shape:
            raise ValueError(f"edits[{i}].weights: expected {len(idx)} values, got {values.shape}")
        pose = poses.setdefault(f, np.array(W[f], dtype=np.float64))
        pose[idx] = values
    return [(int(e["frame"]), poses[int(e["frame"])], tuple(e["window"]) if e.get("window") else None) for e in edits]


#: weight of the curves' own movement in an edit, relative to ``sigma_max(B)^2`` (see with_curve_motion)
EDIT_CURVE_MOTION = 1.0


def with_curve_motion(B, S, W, valid, marker_weights, weight: float):
    """Marker data extended so that movement matching also matches the weight curves' own motion.

    Appends ``ceil(K / 3)`` virtual markers whose coordinates are the weights scaled by
    ``sqrt(weight * sigma_max(B)^2)`` and whose captured positions are the same of ``W``: the
    velocity term of :class:`~core.solvers.spacetime.SpacetimeSolver` (Seol 2012 eq. 2) then gains

        weight * sigma_max(B)^2 * sum_t ||(w_t - w_{t-1}) - (W_t - W_{t-1})||^2,

    the movement matching of the curves themselves. Without it a pose edit propagates only
    through the markers: shapes the markers see alike (two jaw-open shapes, mouth stretch) share
    the change differently at the edited frame and next to it, so each curve pops at the edit
    (jawOpen 0.18 → 1.00 → 0.17) while the face moves smoothly; with it the change spreads over
    the window in the curves too (Seol §6: "smoothly propagated across neighboring frames").
    The virtual markers have no Sobolev weight beyond the given ``marker_weights`` (1) and are
    missing where ``W`` is NaN (frames without samples).

    Parameters
    ----------
    B : (K, M, 3) target marker deltas; S : (T, M, 3) source deltas; W : (T, K) weights
    valid : (T, M) bool or None; marker_weights : (M,) or None; weight : float >= 0

    Returns
    -------
    (B', S', valid', marker_weights') with ``M + ceil(K / 3)`` markers (the inputs when ``weight`` is 0).
    """
    if weight <= 0:
        return B, S, valid, marker_weights
    K, M = B.shape[:2]
    T = len(W)
    n = -(-K // 3)
    scale = np.sqrt(weight * np.linalg.norm(B.reshape(K, -1), 2) ** 2)
    Bv = np.zeros((K, 3 * n))
    Bv[np.arange(K), np.arange(K)] = scale
    finite = np.isfinite(W)
    Sv = np.zeros((T, 3 * n))
    Sv[:, :K] = scale * np.where(finite, W, 0.0)
    vv = np.ones((T, 3 * n), bool)
    vv[:, :K] = finite
    v = np.ones((T, M), bool) if valid is None else np.asarray(valid, bool)
    mw = None if marker_weights is None else np.r_[np.asarray(marker_weights, float), np.ones(n)]
    return (np.concatenate([B, Bv.reshape(K, n, 3)], axis=1), np.concatenate([S, Sv.reshape(T, n, 3)], axis=1),
            np.concatenate([v, vv.reshape(T, n, 3).all(axis=2)], axis=1), mw)


@register("edit")
class Edit(Stage):
    """Spacetime edits (Seol 2012 §6) on top of any method's solution."""

    deps = ("solve", "personalize", "calibrate", "prior", "shapes", "load", "frames", "vocabulary")
    edits = param.List(default=[], item_type=dict, doc="Edits: {frame, weights: {shape: value}, window: [a, b] or null}")

    def active(self, cfg):
        return not method_of(cfg).dense

    def run(self, inputs, s, progress=None):
        W = inputs["solve"]["weights"]
        if not s.edits:
            return {"weights": W, "edits": []}

        st = inputs["calibrate"]["source"]  # the motion the solve fitted
        names = inputs["shapes"]["rig"].names
        poses = edited_poses(W, names, s.edits)
        # the frames re-solved: the windows' span (their ends keep W, so the terms outside do not
        # count, SpacetimeSolver.edit), the whole take when an edit has none
        lo, hi = ((min(w[0] for _, _, w in poses), max(w[1] for _, _, w in poses))
                  if all(w is not None for _, _, w in poses) else (0, len(W) - 1))
        edits = []
        for f, pose, win in poses:
            known = np.flatnonzero(np.isfinite(pose))  # a frame without samples (NaN) keeps those free
            edits.append(PoseEdit(f - lo, pose[known], known, None if win is None else (win[0] - lo, win[1] - lo)))
        span = slice(lo, hi + 1)
        Ws = W[span]
        opt = inputs["solve"]["edit"]
        named = named_target(inputs)[span] if opt["name_weight"] > 0 else None
        deltas = inputs["personalize"]["deltas"]
        B, S, valid, mw = with_curve_motion(deltas, st.deltas[span], Ws, None if st.valid is None else st.valid[span],
                                            inputs["shapes"].get("weights"), EDIT_CURVE_MOTION)
        K = W.shape[1]
        # sigma_max^2 grows from s to (1 + EDIT_CURVE_MOTION) s: the relative settings keep their absolute size
        rel = 1.0 / (1.0 + EDIT_CURVE_MOTION)
        prior = prior_quadratic(inputs["prior"]["prior"] if inputs.get("prior") else None, deltas.reshape(K, -1).T, K)
        quad = opt.get("quadratic")
        solver = SpacetimeSolver(B, S, alpha=opt["alpha"], beta=opt["beta"], prior=prior,
                                 known={0: Ws[0], len(Ws) - 1: Ws[-1]}, valid=valid, names=names,
                                 ridge=opt["ridge"] if isinstance(opt["ridge"], str) else opt["ridge"] * rel,
                                 lower=opt["lower"], upper=opt["upper"], l1=opt["l1"] * rel,
                                 marker_weights=mw, name_target=named, name_weight=opt["name_weight"] * rel,
                                 quadratic=None if quad is None else np.asarray(quad) * rel)
        out = W.copy()
        out[span] = solver.edit(Ws, edits=edits)
        return {"weights": out, "edits": list(s.edits)}


@register("synthesize")
class Synthesize(Stage):
    """Weights for every shape of the target rig.

    Shapes the solver did not use (``target_shapes``, shapes no marker sees) stay at zero.
    Frames the solver could not determine (no marker sample: tracking loss) are gaps: they are
    filled by :func:`core.gaps.fill_gaps` (linear across a gap, held at the ends) in the
    ``weights`` that are played and written, and flagged in ``valid`` (T,) bool; ``raw`` keeps
    the NaN."""

    deps = ("load", "solve", "edit", "calibrate", "stabilize")

    def active(self, cfg):
        return not method_of(cfg).dense

    def run(self, inputs, s, progress=None):
        cal = inputs["calibrate"]
        Wsub = np.asarray(inputs["edit"]["weights"], dtype=np.float64)
        st = inputs["stabilize"]["source"]
        valid = np.isfinite(Wsub).all(1) & st.valid.any(1)
        Wfill = fill_gaps(Wsub, valid)
        ctl = inputs["solve"]["controls"]
        if (ctl.gain != 1).any() or (ctl.offset != 0).any():  # the per-shape remap, after the solve (clamped)
            Wfill = ctl.remap(Wfill)
        # (no target marker positions here: nothing read them, and with dense correspondence their
        # (T, 3M) product was a third of a setting change; B w_t is evaluate's residual)
        full = np.zeros((len(Wsub), inputs["load"]["target_rig"].n_shapes))
        full[:, cal["shape_index"]] = Wfill
        raw = np.zeros_like(full)
        raw[:, cal["shape_index"]] = np.where(valid[:, None], Wsub, np.nan)
        return {"weights": full, "raw": raw, "valid": valid}


@register("evaluate")
class Evaluate(Stage):
    """Diagnostics (marker error, Seol 2012 Fig. 11 velocity error, weight range, jitter);
    frames without data (``synthesize["valid"]`` False) are excluded from every statistic."""

    deps = ("calibrate", "personalize", "solve", "edit", "synthesize", "error_products")
    group, title = "source", "Frame range"
    jitter_window = param.Integer(label='Jitter measured over (frames)', default=1, bounds=(1, 10), doc="Frame step of the jitter measure")

    def active(self, cfg):
        return not method_of(cfg).dense

    def run(self, inputs, s, progress=None):

        st = inputs["calibrate"]["source"]  # the motion the solve fitted
        predicted = inputs["solve"]["info"].get("predicted") if not inputs["edit"]["edits"] else None
        return evaluate(inputs["personalize"]["deltas"], inputs["edit"]["weights"], st.deltas, st.valid, step=s.jitter_window,
                        predicted=predicted, frame_valid=inputs["synthesize"]["valid"],
                        products=inputs["error_products"]["products"])
