"""Dense transfer of a whole performance, from files' objects to a new target rig.

Glue between the data model and :func:`core.transfer.transfer_sequence` (Xu et al. 2014):
a weight-curve source drives its rig into a dense sequence; the marker layouts give the
landmarks that register the target to the source topology (§3).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..model import MarkerLayout, Performance, Rig
from ..progress import ProgressFn, report


def dense_source(source: Performance, rig: Optional[Rig], name_map=None) -> np.ndarray:
    """(T, V, 3) meshes: a mesh sequence as is, or weight curves driving ``rig``."""
    if source.kind == "meshes":
        return np.asarray(source.data)
    if source.kind == "curves":
        if rig is None:
            raise ValueError(f"transfer: weight curves {source.name!r} need the rig they drive (--source-rig)")
        from ..retarget import drive_rig

        W, _ = drive_rig(source, rig, name_map)
        return rig.evaluate(np.nan_to_num(W))
    raise ValueError("transfer needs a dense source (a mesh sequence, or weight curves with --source-rig); "
                     f"{source.name!r} is {source.kind}: use a marker-based method (lsq, bounded, spacetime, local, geometric)")


def transfer_performance(source: Performance, source_rig: Rig, source_layout: MarkerLayout, target_rig: Rig,
                         target_layout: MarkerLayout, name_map=None, progress: Optional[ProgressFn] = None, **settings):
    """Transfer ``source`` onto ``target_rig``'s face; returns the :class:`TransferResult`.

    Landmarks are the markers both layouts share (source vertex of each marker's largest
    barycentric weight -> the marker's point on the target neutral). The result's meshes have
    the source's topology fitted to the target surface, as in the paper.
    """
    from . import TransferSettings, transfer_sequence

    report(progress, 0.02, "dense source")
    seq = dense_source(source, source_rig, name_map)
    common = [n for n in source_layout.names if n in set(target_layout.names)]
    if len(common) < 4:
        raise ValueError(f"transfer: the layouts share only {len(common)} markers; need >= 4 landmarks")
    src = source_layout.select(common)
    ids = src.vertices[np.arange(len(common)), np.argmax(src.weights, axis=1)]
    pts = target_layout.select(common).points(target_rig.neutral)
    report(progress, 0.1, f"transferring {len(seq)} frames")
    cfg = TransferSettings(**{**settings, "landmarks": (ids, pts)})
    result = transfer_sequence(source_rig.neutral, source_rig.faces, seq, target_rig.neutral, target_rig.faces, cfg)
    report(progress, 1.0, "done")
    return result
