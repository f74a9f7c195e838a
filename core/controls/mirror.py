"""Mirroring: a take, its weight curves, its markers or a pose edit with left and right swapped.

Which name is the mirror of which comes from :func:`core.controls.sides.mirror_map` (or from
given pairs). Weight curves swap columns (:func:`mirror_weights`); marker trajectories swap
markers and reflect in the midline plane (:func:`mirror_markers`); a whole take
(:func:`mirror_performance`) does either, and negates Live Link Face's head and eye yaw and roll;
a spacetime pose edit moves to the other side (:func:`mirror_edit`). Mesh sequences are
refused: they need the mesh's left/right vertex map.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Optional, Sequence

import numpy as np

from ..model import Performance
from .inputs import as_names, as_weights, shape_index
from .pairs import pair_indices
from .sides import mirror_map

__all__ = ["mirror_weights", "mirror_markers", "mirror_performance", "mirror_edit"]


def mirror_weights(W, names: Sequence[str], pairs=None) -> np.ndarray:
    """Left/right swapped weight curves: ``W'[:, k] = W[:, m[k]]`` (:func:`mirror_map`, or the
    given name ``pairs``); shapes without a mirror (jawOpen) keep their curve."""
    W = as_weights(W)
    names = as_names(names)
    if W.shape[1] != len(names):
        raise ValueError(f"W: expected {len(names)} columns (one per name), got {W.shape[1]}")
    m = _perm(names, pairs)
    return W[:, m].copy()


def _perm(names, pairs):
    if pairs is None:
        return mirror_map(names)
    m = np.arange(len(names))
    for a, b in pair_indices(pairs, names):
        if m[a] != a or m[b] != b:
            raise ValueError(f"pairs: shape {names[a] if m[a] != a else names[b]!r} is in two mirror pairs")
        m[a], m[b] = b, a
    return m


def mirror_markers(positions, names: Sequence[str], center: Optional[float] = None, axis: int = 0) -> np.ndarray:
    """Marker trajectories mirrored left/right: each marker takes its mirror's trajectory
    (names paired by :func:`mirror_map`, as the bundled layouts name them: ``Leye_Up`` /
    ``Reye_Up``, ``Mouth_UpL1`` / ``Mouth_UpR1``, ``Chin_L2`` / ``Chin_R2``), reflected in the
    plane ``x[axis] = center``.

    The faces look down +Z with +Y up, so left/right is ``axis = 0`` (x). Mirror stabilised
    markers (head frame), or captures whose head faces +Z.

    Parameters
    ----------
    positions : (T, M, 3) or (M, 3) float, NaN = missing (stays missing)
    names : M marker names
    center : float, optional
        The mirror plane; default the mean ``x[axis]`` of the markers without a mirror (the
        midline: ``ForeHead_M``, ``NoseTop``, ``Chin``), over all valid samples, else of all markers.
    axis : int

    Returns
    -------
    Same shape as ``positions``.
    """
    P = np.asarray(positions, dtype=np.float64)
    one = P.ndim == 2
    if one:
        P = P[None]
    names = as_names(names)
    if P.ndim != 3 or P.shape[1:] != (len(names), 3):
        raise ValueError(f"positions: expected (T, {len(names)}, 3) or ({len(names)}, 3), got {np.shape(positions)}")
    if axis not in (0, 1, 2):
        raise ValueError(f"axis: expected 0, 1 or 2, got {axis}")
    m = mirror_map(names)
    if center is None:
        mid = m == np.arange(len(names))
        x = P[:, mid, axis] if mid.any() else P[:, :, axis]
        if not np.isfinite(x).any():
            x = P[:, :, axis]
        center = float(np.nanmean(x)) if np.isfinite(x).any() else 0.0
    out = P[:, m].copy()
    out[..., axis] = 2.0 * float(center) - out[..., axis]
    return out[0] if one else out


#: Live Link Face rotation extras (yaw, pitch, roll): mirrored, yaw and roll change sign
_ROT_SWAP = {"eye_rotation_left": "eye_rotation_right", "eye_rotation_right": "eye_rotation_left"}


def mirror_performance(perf, center: Optional[float] = None):
    """A :class:`core.model.Performance` mirrored left/right.

    Curves: :func:`mirror_weights` by channel name (and Live Link Face's rotation extras: left
    and right eye swapped, yaw and roll negated, pitch kept: a reflection in the x = 0 plane
    reverses rotations about y and z). Markers: :func:`mirror_markers`. Mesh sequences are refused
    (they need a vertex correspondence of the mesh with its mirror image).
    """
    if not isinstance(perf, Performance):
        raise TypeError(f"perf: expected a core.model.Performance, got {type(perf).__name__}")
    if perf.kind == "meshes":
        raise ValueError(f"{perf.name}: mirroring a mesh sequence needs the mesh's left/right vertex map; "
                         "mirror the weight curves or markers instead")
    m = mirror_map(perf.names)
    extras = dict(perf.extras)
    if perf.kind == "curves":
        data = perf.data[:, m]
        for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
            if key in perf.extras:
                r = np.asarray(perf.extras[_ROT_SWAP.get(key, key)], dtype=np.float64).copy()
                if r.ndim == 2 and r.shape[1] == 3:
                    r[:, 0] *= -1.0
                    r[:, 2] *= -1.0
                r.setflags(write=False)
                extras[key] = r
    else:
        data = mirror_markers(perf.data, perf.names, center)
    return replace(perf, data=data, valid=perf.valid[:, m], extras=extras, name=f"{perf.name}_mirrored")


def mirror_edit(edit: dict, names: Sequence[str], keep: bool = False) -> dict:
    """A spacetime edit ``{frame, weights: {shape: value}, window}`` moved to the other side.

    ``keep=False``: every shape is replaced by its mirror (an edit of ``eyeBlinkLeft`` becomes
    one of ``eyeBlinkRight``; midline shapes keep theirs). ``keep=True``: the edit plus its
    mirror (both eyes), the edit's own values winning where it sets both sides.

    Raises
    ------
    ValueError
        Not an edit dict, or a shape name not in ``names`` (with "did you mean").
    """
    if not isinstance(edit, dict) or "frame" not in edit or not isinstance(edit.get("weights"), dict):
        raise ValueError(f"edit: expected {{'frame': int, 'weights': {{shape: value}}, 'window': [a, b] or None}}, got {edit!r}")
    names = as_names(names)
    m = mirror_map(names)
    out = {}
    for shape, v in edit["weights"].items():
        k = shape_index(str(shape), names, "edit.weights")
        out[names[m[k]]] = v
    if keep:
        mine = {names[shape_index(str(s), names, "edit.weights")]: v for s, v in edit["weights"].items()}
        out.update(mine)
    res = copy.deepcopy(edit)
    res["weights"] = out
    return res
