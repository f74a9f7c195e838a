"""Building blocks shared by every retargeting method: from a source of any kind to marker
deltas on both faces.

    source curves + source rig + layout  ->  virtual markers (the rig driven by the curves)
    source meshes + layout               ->  markers read off the meshes
    source markers (capture)             ->  stabilised markers (Seol 2012 §3.1)
    target rig + layout                  ->  marker blendshapes, calibrated (Seol 2012 §3.2)

All functions are pure; the pipeline (core/pipeline.py) caches their results.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .calibrate import calibrate_deltas
from .geometry import marker_triangulation
from .model import MarkerLayout, Performance, Rig
from .names import NameMap
from .stabilize import stabilize


def drive_rig(curves: Performance, rig: Rig, name_map: Optional[NameMap] = None):
    """Weights (T, K_rig) for ``rig`` from weight curves, and the list of rig shapes no
    channel drives.

    The map defaults to :meth:`NameMap.automatic` (same canonical ARKit name; split shapes
    such as ICT's ``browInnerUp_L`` follow their sideless channel). Missing samples stay NaN.
    """
    if curves.kind != "curves":
        raise ValueError(f"drive_rig: needs weight curves, got a {curves.kind!r} performance")
    nm = name_map or NameMap.automatic(curves.names, rig.names)
    G = nm.matrix(curves.names, rig.names)
    if not G.any():
        raise ValueError(
            f"no channel of {curves.name!r} drives a shape of rig {rig.name!r}: their names share no ARKit "
            "name; give a name map JSON (see `face-retarget names --help`)"
        )
    data = np.where(curves.valid, curves.data, np.nan)
    used = G != 0
    W = np.nan_to_num(data) @ G.T
    # a target shape is missing where any channel that drives it is missing
    missing = (~curves.valid).astype(float) @ used.T.astype(float) > 0
    W[missing] = np.nan
    return W, nm.unmapped(rig.names)


@dataclass(frozen=True, eq=False)
class SourceMarkers:
    """Source marker deltas ready for solving.

    deltas (T, M, 3) = stabilised positions - neutral (NaN where missing), valid (T, M),
    neutral (M, 3), names (M,), fps, times, head motion (rotations (T,3,3), translations (T,3))
    or None, and ``weights`` (T, K_src) when the markers came from a driven rig (the ground
    truth for same-curve comparisons).
    """

    deltas: np.ndarray
    valid: np.ndarray
    neutral: np.ndarray
    names: tuple
    fps: float
    times: np.ndarray
    rotations: Optional[np.ndarray] = None
    translations: Optional[np.ndarray] = None
    source_weights: Optional[np.ndarray] = None
    info: dict = field(default_factory=dict)

    @property
    def positions(self) -> np.ndarray:
        return self.neutral[None] + self.deltas


def source_markers(source: Performance, rig: Optional[Rig] = None, layout: Optional[MarkerLayout] = None,
                   name_map: Optional[NameMap] = None, head_motion: str = "auto", neutral_frame: int = 0) -> SourceMarkers:
    """Turn any source into marker deltas.

    Parameters
    ----------
    source : curves (needs ``rig`` and ``layout``), meshes (needs ``layout`` on its
        topology) or markers.
    head_motion : "auto" | "remove" | "keep"
        "auto" removes rigid head motion from captured markers only (a driven rig has none).
    neutral_frame : int
        For captured markers: the frame whose (stabilised) markers are the neutral
        (Seol 2012 asks the actor for a neutral at the start). Driven rigs use the rig neutral.
    """
    info = {}
    if source.kind == "curves":
        if rig is None or layout is None:
            raise ValueError(
                f"source {source.name!r} is weight curves: give a source rig and its marker layout "
                "(--source-rig, --source-layout) so the curves can drive it"
            )
        W, unmapped = drive_rig(source, rig, name_map)
        info["unmapped_source_shapes"] = unmapped
        n, d = layout.on_rig(rig)
        pos = n[None] + np.einsum("tk,kmc->tmc", np.nan_to_num(W), d)
        valid = np.repeat(np.isfinite(W).all(1)[:, None], layout.n_markers, 1)
        pos[~valid] = np.nan
        return SourceMarkers(pos - n, valid, n, layout.names, source.fps, source.times, source_weights=W, info=info)
    if source.kind == "meshes":
        if layout is None:
            raise ValueError(f"source {source.name!r} is a mesh sequence: give the marker layout of its topology")
        V = source.data.shape[1]
        if layout.vertices.max() >= V:
            raise ValueError(f"layout for {layout.rig!r} indexes vertex {layout.vertices.max()} but the mesh sequence has {V} vertices")
        pos = layout.points(source.data)
        neutral = layout.points(rig.neutral) if rig is not None else pos[neutral_frame]
        valid = np.repeat(source.valid[:, None], layout.n_markers, 1)
        return SourceMarkers(pos - neutral, valid, neutral, layout.names, source.fps, source.times, info=info)
    # captured markers
    if head_motion not in ("auto", "remove", "keep"):
        raise ValueError(f"head_motion must be auto, remove or keep, got {head_motion!r}")
    neutral_frame = _first_complete_frame(source, neutral_frame)
    if head_motion in ("auto", "remove"):
        st = stabilize(source, neutral_frame=neutral_frame)
        info["rigid_markers"] = st.rigid
        info["stabilize_rms_mm"] = float(np.median(st.residual) * 1e3)
        pos = st.markers.data
        R, t = st.rotations, st.translations
    else:
        pos, R, t = source.data, None, None
    neutral = pos[neutral_frame]
    info["neutral_frame"] = neutral_frame
    return SourceMarkers(pos - neutral, source.valid, neutral, source.names, source.fps, source.times, R, t, info=info)


def source_marker_names(source: Performance, layout: Optional[MarkerLayout] = None) -> tuple:
    """The marker names :func:`source_markers` will give ``source``, without computing them:
    a capture's own names, else the names of the layout on the source rig or mesh."""
    if source.kind == "markers":
        return tuple(source.names)
    if layout is None:
        what = "weight curves: give a source rig and its marker layout (--source-rig, --source-layout)" \
            if source.kind == "curves" else "a mesh sequence: give the marker layout of its topology"
        raise ValueError(f"source {source.name!r} is {what}")
    return tuple(layout.names)


def _first_complete_frame(perf: Performance, start: int) -> int:
    if not 0 <= start < perf.n_frames:
        raise ValueError(f"neutral_frame {start} outside 0..{perf.n_frames - 1}")
    complete = np.flatnonzero(perf.valid.all(1))
    after = complete[complete >= start]
    if not len(after):
        raise ValueError(f"{perf.name!r}: no frame at or after {start} has every marker tracked; cannot pick a neutral")
    if after[0] != start:
        warnings.warn(f"{perf.name!r}: frame {start} misses markers; using frame {after[0]} as the neutral")
    return int(after[0])


@dataclass(frozen=True, eq=False)
class TargetMarkers:
    """The target's marker blendshapes: raw (on the rig) and calibrated into the actor's
    proportions (Seol 2012 §3.2). names (M,), neutral (M, 3), deltas (K, M, 3),
    calibrated (K, M, 3)."""

    names: tuple
    neutral: np.ndarray
    deltas: np.ndarray
    calibrated: np.ndarray
    warp: object = None


def common_markers(source_names, layout: MarkerLayout, minimum: int = 4) -> list:
    """Markers present in both, in the layout's order; ValueError naming what is missing."""
    common = [n for n in layout.names if n in set(source_names)]
    if len(common) < minimum:
        raise ValueError(
            f"only {len(common)} markers are shared by the source and the target layout ({layout.rig!r}); need >= {minimum}. "
            f"source has {sorted(source_names)[:8]}..., layout has {sorted(layout.names)[:8]}..."
        )
    return common


def target_markers(rig: Rig, layout: MarkerLayout, names, source_neutral: Optional[np.ndarray] = None,
                   calibrate: bool = True, smoothing: float = 0.0) -> TargetMarkers:
    """Marker blendshapes of ``rig`` at ``names``; calibrated to ``source_neutral`` (M, 3)."""
    sub = layout.select(names)
    n, d = sub.on_rig(rig)
    if calibrate and source_neutral is not None:
        cal, warp = calibrate_deltas(n, d, source_neutral, smoothing)
    else:
        cal, warp = d, None
    return TargetMarkers(tuple(names), n, d, cal, warp)


def marker_rig(positions) -> tuple:
    """A displayable surface for captured markers: (Rig, (T, 1) zero track).

    The neutral is the first frame (missing markers filled with their mean over the take);
    triangles are :func:`core.geometry.marker_triangulation` in the plane of the markers' two
    principal axes (``unroll="plane"``: a face's marker set is a height field over that plane,
    whatever frame the capture has), rim slivers peeled. The rig has one zero shape so viewers
    that play a weight track can show it; the markers themselves move via ``marker_track``.
    """

    P = np.asarray(positions, dtype=np.float64)
    mean = np.nanmean(P, axis=0)
    neutral = np.where(np.isfinite(P[0]), P[0], mean)
    neutral = np.nan_to_num(neutral)
    faces = marker_triangulation(neutral, unroll="plane")
    rig = Rig(neutral, faces, np.zeros((1,) + neutral.shape), ["rest"], name="markers")
    return rig, np.zeros((len(P), 1))
