"""Checks of the arguments the controls take, shared by their modules (validated once, at the boundary).

* shape names: a sequence of distinct names (:func:`as_names`); one name looked up among them,
  exactly or by its canonical ARKit name (:func:`shape_index`, with "did you mean");
* weight curves: a (T, K) float64 array (:func:`as_weights`);
* frame rates: a positive number (:func:`as_fps`).

Each raises ValueError naming the argument and what was expected.
"""

from __future__ import annotations

import difflib
from typing import Sequence

import numpy as np

from ..names import canonical

__all__ = ["as_names", "shape_index", "as_weights", "as_fps"]


def as_names(names, what="names") -> tuple:
    """``names`` as a tuple of str; ValueError (naming ``what``) when one is given twice."""
    names = tuple(str(n) for n in names)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{what}: duplicate names {dup[:5]}")
    return names


def shape_index(name: str, names: Sequence[str], where: str) -> int:
    """Index of ``name`` in ``names``: exact, else by canonical ARKit name when unique.

    Raises ValueError naming ``where``: several shapes share the ARKit name, or none matches
    (with "did you mean")."""
    names = list(names)
    if name in names:
        return names.index(name)
    c = canonical(name)
    hits = [i for i, n in enumerate(names) if canonical(n) == c]
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise ValueError(f"{where}: {name!r} matches several shapes by ARKit name: {[names[i] for i in hits]}; "
                         "use the exact shape name")
    close = difflib.get_close_matches(name, names, n=3)
    raise ValueError(f"{where}: no shape {name!r}" + (f"; did you mean {close}?" if close else ""))


def as_weights(W, name: str = "W") -> np.ndarray:
    """``W`` as a (T, K) float64 array (not copied when it is one); ValueError for another shape."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError(f"{name}: expected (T, K) weights, got shape {W.shape}")
    return W


def as_fps(fps) -> float:
    """``fps`` as a float; ValueError unless a finite positive frame rate."""
    f = float(fps)
    if not (np.isfinite(f) and f > 0):
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    return f
