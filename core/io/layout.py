"""Marker layouts as JSON: where each named marker sits on a rig.

Format (version 1)::

    {"format": "face-retarget marker layout", "version": 1,
     "rig": "ict_facekit.glb",
     "markers": {"ForeHead_M": {"vertex": 1234},
                 "Chin_L2": {"face": 17, "vertices": [3, 4, 5], "barycentric": [0.2, 0.3, 0.5]}},
     "notes": "..."}

A marker is either on a vertex or a barycentric point on a triangle. A face marker keeps its
triangle's vertex ids so the file is self-contained; ``"face"`` alone (without ``"vertices"``)
is accepted and resolved against the rig, and ``"vertices"`` alone (face index unknown) too.
Markers keep the file's order.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Optional, Union

import numpy as np

import core
from ..model import MarkerLayout, Rig

FORMAT = "face-retarget marker layout"
VERSION = 1
#: |sum of barycentric weights - 1| allowed in a file (they are written with 12 digits)
BARY_TOL = 1e-6


class LayoutError(ValueError):
    """A layout file that cannot be read; the message names the file, the marker and the field."""


class LayoutRigMismatch(UserWarning):
    """The layout names a different rig than the one it is being used with."""


def _rig_file(rig: Rig) -> str:
    return f"{rig.name}.glb"


def _same_rig(declared: str, rig: Rig) -> bool:
    return Path(declared).stem == rig.name


def read_layout(path, rig: Optional[Rig] = None, strict_rig: bool = False) -> MarkerLayout:
    """Read a marker layout JSON file.

    Parameters
    ----------
    path : str or Path
    rig : Rig, optional
        When given, every vertex and face index is range-checked against it, face markers
        without ``"vertices"`` are resolved from ``rig.faces``, and a stored ``"vertices"`` list
        must match the rig's triangle. A file naming another rig (``"rig"`` stem differs from
        ``rig.name``) warns with :class:`LayoutRigMismatch`, or raises when ``strict_rig``.
    strict_rig : bool
        Raise instead of warn when the file names another rig.

    Returns
    -------
    MarkerLayout
        ``vertices`` (M, 3) int and ``weights`` (M, 3); a vertex marker is ``(v, v, v)``,
        ``(1, 0, 0)``. ``extras`` holds ``notes`` and, per marker, the face index
        (``extras["faces"]``: (M,) int, -1 for vertex markers).

    Raises
    ------
    FileNotFoundError
    LayoutError (a ValueError)
        Malformed JSON, wrong ``format``/``version``, a missing field, a negative or
        out-of-range index, barycentric weights that are negative or do not sum to 1,
        duplicate marker names, or (``strict_rig``) a layout made for another rig.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"layout {path}: no such file")
    text = path.read_text(encoding="utf-8")
    where = f"layout {path.name}"
    try:
        # object_pairs_hook sees every key, so duplicate marker names are not silently merged
        doc = json.loads(text, object_pairs_hook=_pairs)
    except json.JSONDecodeError as e:
        raise LayoutError(f"{where}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    except _Duplicate as e:
        raise LayoutError(f"{where}: duplicate key {e.args[0]!r} (marker names must be unique)") from None
    if not isinstance(doc, dict):
        raise LayoutError(f"{where}: expected a JSON object at the top level, got {type(doc).__name__}")
    if doc.get("format") != FORMAT:
        raise LayoutError(f"{where}: field 'format' must be {FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != VERSION:
        raise LayoutError(f"{where}: field 'version' must be {VERSION}, got {doc.get('version')!r}")
    for key in ("rig", "markers"):
        if key not in doc:
            raise LayoutError(f"{where}: missing field {key!r}")
    declared = doc["rig"]
    if not isinstance(declared, str) or not declared:
        raise LayoutError(f"{where}: field 'rig' must be the rig file name, got {declared!r}")
    markers = doc["markers"]
    if not isinstance(markers, dict) or not markers:
        raise LayoutError(f"{where}: field 'markers' must be a non-empty object of name -> placement")
    if rig is not None and not _same_rig(declared, rig):
        msg = f"{where} was made for rig {declared!r}, not {rig.name!r}"
        if strict_rig:
            raise LayoutError(msg)
        warnings.warn(msg + "; indices are only range-checked", LayoutRigMismatch, stacklevel=2)
    rig_label = rig.name if rig is not None else declared
    V = rig.n_vertices if rig is not None else None
    names, verts, weights, faces = [], [], [], []
    for name, m in markers.items():
        at = f"{where} marker {name!r}"
        if not isinstance(m, dict):
            raise LayoutError(f"{at}: expected an object with 'vertex' or 'face', got {m!r}")
        if "vertex" in m:
            v = _index(m["vertex"], f"{at}: 'vertex'")
            if V is not None and v >= V:
                raise LayoutError(f"{at}: vertex {v} out of range for rig {rig_label} ({V} vertices)")
            names.append(name)
            verts.append((v, v, v))
            weights.append((1.0, 0.0, 0.0))
            faces.append(-1)
            continue
        if "face" not in m and "vertices" not in m:
            raise LayoutError(f"{at}: needs 'vertex' or 'face' (with 'barycentric'), got keys {sorted(m)}")
        fi = _index(m["face"], f"{at}: 'face'") if "face" in m else -1
        if rig is not None and fi >= len(rig.faces):
            raise LayoutError(f"{at}: face {fi} out of range for rig {rig_label} ({len(rig.faces)} faces)")
        if "barycentric" not in m:
            raise LayoutError(f"{at}: a face marker needs 'barycentric' [a, b, c]")
        bary = m["barycentric"]
        if not (isinstance(bary, list) and len(bary) == 3 and all(_is_number(b) for b in bary)):
            raise LayoutError(f"{at}: 'barycentric' must be 3 numbers, got {bary!r}")
        bary = np.asarray(bary, dtype=np.float64)
        if (bary < -BARY_TOL).any() or abs(bary.sum() - 1) > BARY_TOL:
            raise LayoutError(f"{at}: 'barycentric' {bary.tolist()} must be >= 0 and sum to 1 (sum {bary.sum():.9g})")
        if "vertices" in m:
            tri = m["vertices"]
            if not (isinstance(tri, list) and len(tri) == 3):
                raise LayoutError(f"{at}: 'vertices' must be the face's 3 vertex indices, got {tri!r}")
            tri = tuple(_index(t, f"{at}: 'vertices'") for t in tri)
            if V is not None and max(tri) >= V:
                raise LayoutError(f"{at}: vertex {max(tri)} out of range for rig {rig_label} ({V} vertices)")
            if fi >= 0 and rig is not None and _same_rig(declared, rig) and tuple(rig.faces[fi]) != tri:
                raise LayoutError(f"{at}: 'vertices' {list(tri)} are not face {fi} of rig {rig_label} ({rig.faces[fi].tolist()})")
        elif rig is not None:
            tri = tuple(int(t) for t in rig.faces[fi])
        else:
            raise LayoutError(f"{at}: face marker without 'vertices' needs the rig to resolve face {fi}; pass rig=")
        names.append(name)
        verts.append(tri)
        weights.append(tuple(np.clip(bary, 0, None) / np.clip(bary, 0, None).sum()))
        faces.append(fi)
    notes = doc.get("notes", "")
    if not isinstance(notes, str):
        raise LayoutError(f"{where}: field 'notes' must be a string")
    return MarkerLayout(names, np.array(verts, dtype=np.int64), np.array(weights), declared,
                        {"notes": notes, "faces": np.array(faces, dtype=np.int64), "source": str(path)})


def write_layout(path, layout: MarkerLayout, rig_file: Optional[str] = None, notes: Optional[str] = None) -> Path:
    """Write ``layout`` as layout JSON (inverse of :func:`read_layout`).

    A marker whose three vertices are equal with weight (1, 0, 0) is written as ``{"vertex": v}``;
    any other as ``{"face": f, "vertices": [a, b, c], "barycentric": [...]}`` where ``f`` comes from
    ``layout.extras["faces"]`` (-1 when unknown: such a file is still self-contained).

    Parameters
    ----------
    path : str or Path
    layout : MarkerLayout
    rig_file : str, optional
        Rig file name recorded in the file; defaults to ``layout.rig``.
    notes : str, optional
        Defaults to ``layout.extras.get("notes", "")``.

    Raises
    ------
    ValueError when no rig file name is known.
    """
    rig_file = rig_file or layout.rig
    if not rig_file:
        raise ValueError("write_layout: rig_file is required (the layout does not name its rig)")
    faces = np.asarray(layout.extras.get("faces", np.full(layout.n_markers, -1)), dtype=np.int64)
    if faces.shape != (layout.n_markers,):
        raise ValueError(f"write_layout: layout.extras['faces'] must have shape ({layout.n_markers},), got {faces.shape}")
    markers = {}
    for i, name in enumerate(layout.names):
        v, w = layout.vertices[i], layout.weights[i]
        if (v == v[0]).all() or np.isclose(w.max(), 1.0, atol=1e-12):
            markers[name] = {"vertex": int(v[np.argmax(w)])}
        else:
            m = {"face": int(faces[i])} if faces[i] >= 0 else {}  # face unknown: the vertices say it all
            m.update({"vertices": [int(x) for x in v], "barycentric": [round(float(x), 12) for x in w]})
            markers[name] = m
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "rig": Path(rig_file).name,
        "markers": markers,
        "notes": layout.extras.get("notes", "") if notes is None else notes,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return path


def layouts_dir() -> Path:
    """The bundled layouts folder: ``<repo>/data/layouts`` next to the ``core`` package."""
    return Path(core.__file__).resolve().parents[1] / "data" / "layouts"


def sidecar_layout_path(rig_path) -> Path:
    """Where a rig's own layout lives: ``<rig>.layout.json`` beside the rig file (an uploaded or
    user rig keeps its layout there, next to it)."""
    p = Path(rig_path)
    return p.with_name(p.stem + ".layout.json") if not p.is_dir() else p / "layout.json"


def default_layout_path(rig_path) -> Optional[Path]:
    """The layout a rig falls back to when none is chosen: its sidecar ``<rig>.layout.json``
    (:func:`sidecar_layout_path`) when it exists, else the bundled ``data/layouts/<rig stem>.json``,
    else None."""
    side = sidecar_layout_path(rig_path)
    if side.exists():
        return side
    p = layouts_dir() / f"{Path(rig_path).stem}.json"
    return p if p.exists() else None


# -- helpers ----------------------------------------------------------------------------------
class _Duplicate(Exception):
    pass


def _pairs(pairs):
    seen = {}
    for k, v in pairs:
        if k in seen:
            raise _Duplicate(k)
        seen[k] = v
    return seen


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)


def _index(x, what: str) -> int:
    if isinstance(x, bool) or not isinstance(x, int):
        raise LayoutError(f"{what} must be an integer index, got {x!r}")
    if x < 0:
        raise LayoutError(f"{what} must be >= 0, got {x}")
    return int(x)
