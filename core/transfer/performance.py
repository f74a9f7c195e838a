"""Dense transfer of a whole performance, from files' objects to a new target rig.

Glue between the data model and :func:`core.transfer.transfer_sequence` (Xu et al. 2014):
a weight-curve source drives its rig into a dense sequence; the marker layouts give the
landmarks that register the target to the source topology (§3).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..gaps import fill_gaps
from ..model import MarkerLayout, Performance, Rig
from ..progress import ProgressFn, report
from ..retarget import drive_rig
from . import TransferSettings, transfer_sequence
from .features import feature_lines_near


def dense_sequence(source: Performance, rig: Optional[Rig], name_map=None) -> tuple:
    """``(meshes (T, V, 3), valid (T,))``: a mesh sequence as is (on ``rig``'s topology when a rig
    is given, else its own), or weight curves driving ``rig``. Frames without data (tracking loss) are gaps, filled by :func:`core.gaps.fill_gaps`
    (interpolated, held at the ends — never a neutral face) and flagged in ``valid``."""

    if source.kind == "meshes":
        if rig is not None and source.data.shape[1] != rig.n_vertices:
            raise ValueError(f"transfer: the mesh sequence {source.name!r} has {source.data.shape[1]} vertices, the source "
                             f"rig {rig.name!r} {rig.n_vertices}; give the rig whose topology it has, or no source rig")
        valid = np.asarray(source.valid, dtype=bool).reshape(len(source.data), -1).all(1)
        return fill_gaps(source.data, valid), valid
    if source.kind == "curves":
        if rig is None:
            raise ValueError(f"transfer: weight curves {source.name!r} need the rig they drive (--source-rig)")

        W, _ = drive_rig(source, rig, name_map)
        valid = np.isfinite(W).all(1)
        return rig.evaluate(fill_gaps(W, valid)), valid
    raise ValueError("transfer needs a dense source (a mesh sequence, or weight curves with --source-rig); "
                     f"{source.name!r} is {source.kind}: use a marker-based method (lsq, bounded, spacetime, local, geometric)")


def dense_source(source: Performance, rig: Optional[Rig], name_map=None) -> np.ndarray:
    """(T, V, 3) meshes of :func:`dense_sequence` (gaps filled)."""
    return dense_sequence(source, rig, name_map)[0]


def shared_landmarks(source_layout: MarkerLayout, target_layout: MarkerLayout, target_positions,
                     min_shared: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Registration landmarks from the markers two layouts share (by name).

    Each shared marker gives the source vertex of its largest barycentric weight and the
    marker's point on ``target_positions`` (the target neutral, (V', 3)): the hand-placed
    correspondences of Xu et al. 2014 §3 ("semi-automatic"). The bundled layouts of ICT,
    Rocketbox and the Jeeliz tiger/triceratops share 41 names.

    Returns
    -------
    source vertex ids (M,) int, target points (M, 3)

    Raises
    ------
    ValueError
        Fewer than ``min_shared`` shared markers.
    """
    common = [n for n in source_layout.names if n in set(target_layout.names)]
    if len(common) < min_shared:
        raise ValueError(f"transfer: the layouts share only {len(common)} markers; need >= {min_shared} landmarks")
    src = source_layout.select(common)
    ids = src.vertices[np.arange(len(common)), np.argmax(src.weights, axis=1)]
    return ids.astype(np.int64), target_layout.select(common).points(np.asarray(target_positions))


EYE_MOUTH_MARKERS = ("Leye_Up", "Leye_Down", "Leye_Inside", "Leye_Outside", "Reye_Up", "Reye_Down", "Reye_Inside",
                     "Reye_Outside", "Mouth_Up", "Mouth_Down", "Mouth_Lend", "Mouth_Rend")


def default_feature_lines(rig: Rig, layout: Optional[MarkerLayout], radius: Optional[float] = None) -> Optional[list]:
    """The eye and mouth feature lines of ``rig`` for eq. 9 (Xu et al. 2014 Fig. 2d): hole and
    UV-seam rims passing within ``radius`` (default 5 % of the layout's marker spread: 12 mm on
    ICT) of the layout's eye and mouth markers. None when the layout has none of those
    markers or no rim passes near them (eq. 9 then has no line term)."""

    if layout is None:
        return None
    names = [n for n in EYE_MOUTH_MARKERS if n in layout.names]
    if not names:
        return None
    pts = layout.select(names).points(rig.neutral)
    if radius is None:
        allp = layout.points(rig.neutral)
        radius = 0.05 * float(np.linalg.norm(np.ptp(allp, axis=0)))
    lines = feature_lines_near(rig.neutral, rig.faces, pts, radius)
    return lines or None


def transfer_performance(source: Performance, source_rig: Rig, source_layout: MarkerLayout, target_rig: Rig,
                         target_layout: MarkerLayout, name_map=None, progress: Optional[ProgressFn] = None, **settings):
    """Transfer ``source`` onto ``target_rig``'s face; returns the :class:`TransferResult`.

    Landmarks are the markers both layouts share (:func:`shared_landmarks`); unless
    ``settings`` has ``feature_lines``, eq. 9's feature lines are :func:`default_feature_lines`
    of the source rig and layout (pass ``feature_lines=None`` to leave them out). The result's
    meshes have the source's topology fitted to the target surface, as in the paper.
    ``settings`` are :class:`~core.transfer.TransferSettings` fields; the registration crops
    the source to its face for a target without the rest of the head (``crop="auto"``,
    e.g. ICT -> the Jeeliz tiger), ``crop="face"`` / ``"none"`` force either way.
    """

    report(progress, 0.02, "dense source")
    seq = dense_source(source, source_rig, name_map)
    ids, pts = shared_landmarks(source_layout, target_layout, target_rig.neutral)
    report(progress, 0.1, f"transferring {len(seq)} frames")
    if "feature_lines" not in settings:
        report(progress, 0.05, "feature lines (eye and mouth rims)")
        settings = {**settings, "feature_lines": default_feature_lines(source_rig, source_layout)}
    cfg = TransferSettings(**{**settings, "landmarks": (ids, pts)})
    stage = None if progress is None else (lambda f, m: progress(0.1 + 0.9 * min(f, 0.999), m))
    result = transfer_sequence(source_rig.neutral, source_rig.faces, seq, target_rig.neutral, target_rig.faces, cfg,
                               progress=stage)
    report(progress, 1.0, "done")
    return result
