"""Read and write a captured performance in whichever file format it comes in.

:func:`read_performance` dispatches on the suffix and, for ``.csv``, on the header line:

=================  ===========================================  ====================================
format             recognised by                                reader
=================  ===========================================  ====================================
Live Link Face     ``.csv`` whose header starts                 :func:`core.io.livelink.read_livelink`
                   ``Timecode,BlendShapeCount`` (any case)
marker CSV         ``.csv`` whose header starts ``frame,time_s``  :func:`core.io.markers.read_marker_csv`
TRC                ``.trc``                                     :func:`core.io.markers.read_trc`
C3D                ``.c3d`` (needs ``ezc3d``)                   :func:`core.io.markers.read_c3d`
glTF animation     ``.glb`` / ``.gltf``                         ``core.io.gltf.read_animation``
USD                ``.usd`` / ``.usda`` / ``.usdc`` / ``.usdz``  :func:`core.io.usd.read_performance`
                   (needs ``usd-core``): a SkelAnimation's
                   blend shape weights, else a mesh with
                   time-sampled points
mesh sequence      a folder of per-frame OBJ/PLY files;          :func:`core.io.sequence.read_mesh_sequence`
                   a ``.glb``/``.gltf`` or USD file with
                   ``kind="meshes"``
=================  ===========================================  ====================================

``kind`` says what to read where a file can hold more than one: ``"meshes"`` reads a glTF or
UsdSkel file's animated mesh as a mesh sequence instead of its weight curves. ``fps`` sets the
rate of the formats that may not carry one (mesh folders, glTF, USD).

Units rule for marker CSV files: a file that declares its units in a ``# units: <u>`` comment
line is read in those units; a file without one needs ``units=`` from the caller, except that
files named ``animface_*.csv`` (the bundled AnimFace captures, documented as centimetres in
``data/SOURCES.md``) default to ``"cm"``.

The helpers the readers share (:func:`~core.io.tabular.estimate_fps`,
:class:`~core.io.tabular.DataQualityWarning`, ...) live in :mod:`core.io.tabular`; they are
re-exported here for code that imports them from this module.
"""

from __future__ import annotations

from pathlib import Path

from core.io import gltf, livelink, markers, sequence, usd
from core.io.tabular import (FPS_SNAP_RTOL, STANDARD_FPS, DataQualityWarning, checked_rows, estimate_fps,
                             parse_cells, summarize_rows)
from core.model import Performance

__all__ = [
    "READ_FORMATS", "WRITE_FORMATS", "read_performance", "write_performance",
    # re-exported from core.io.tabular for code that imports them from here
    "DataQualityWarning", "FPS_SNAP_RTOL", "STANDARD_FPS", "checked_rows", "estimate_fps", "parse_cells",
    "summarize_rows",
]

READ_FORMATS = {
    ".csv": "Live Link Face CSV (header 'Timecode,BlendShapeCount,...') or marker CSV (header 'frame,time_s,...')",
    ".trc": "TRC marker trajectories",
    ".c3d": "C3D marker trajectories (pip install face-retarget[c3d])",
    ".glb": "glTF 2.0 binary morph-weight animation",
    ".gltf": "glTF 2.0 morph-weight animation",
    ".usd/.usda/.usdc/.usdz": "USD: UsdSkel blend shape animation, or a mesh with time-sampled points (pip install face-retarget[usd])",
    "folder": "mesh sequence: one OBJ or PLY file per frame (frame_0001.obj ...; fps from sequence.json, default 30)",
}
#: what ``kind=`` may ask for
KINDS = ("auto", "curves", "markers", "meshes")
WRITE_FORMATS = {
    ".csv": "Live Link Face CSV for curves, marker CSV for markers",
    ".trc": "TRC for markers",
    ".c3d": "C3D for markers (pip install face-retarget[c3d])",
    ".usd/.usda/.usdc/.usdz": "USD mesh with time-sampled points, for mesh sequences (pip install face-retarget[usd])",
    "folder": "mesh sequence: one OBJ per frame + sequence.json (a path without a suffix)",
}


def _first_header(path: Path) -> str:
    """First line that is not blank and not a ``#`` comment (BOM stripped)."""
    with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
        for line in f:
            s = line.strip()
            if s and not s.startswith("#"):
                return s
    return ""


def _unsupported(path: Path, table: dict, verb: str) -> ValueError:
    lines = "\n".join(f"  {k}: {v}" for k, v in table.items())
    return ValueError(f"{path}: cannot {verb} suffix {path.suffix or '(none)'!r}; supported formats:\n{lines}")


def read_performance(path, kind: str = "auto", fps=None, **kw) -> Performance:
    """Read a performance from any supported file or folder (see the module table).

    Parameters
    ----------
    path : str or Path
        A file, or a folder of per-frame meshes.
    kind : {"auto", "curves", "markers", "meshes"}
        What to read; ``"auto"`` = what the format holds (weight curves for a glTF animation,
        a UsdSkel file's curves, else its time-sampled mesh). ``"meshes"`` reads a glTF/UsdSkel
        file's animated mesh as a mesh sequence. A kind the file cannot give is an error.
    fps : float, optional
        Frame rate for mesh folders, glTF and USD (their own rate, or 30 for a folder without
        ``sequence.json``, otherwise); the other formats carry their own clock.
    **kw
        Passed to the format's reader (``allow_missing=`` for Live Link Face, ``units=`` for
        marker CSV/TRC and mesh folders, ...).

    Returns
    -------
    Performance

    Raises
    ------
    FileNotFoundError
        No such file or folder.
    ValueError
        Unknown suffix or CSV header (the message lists the supported formats), a ``kind`` the
        file does not hold, ``fps`` for a format with its own clock, or the reader's own errors.
    ImportError
        ``.c3d`` without ezc3d, USD without usd-core.
    """
    path = Path(path)
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    if path.is_dir():
        if kind not in ("auto", "meshes"):
            raise ValueError(f"{path}: a folder is read as a mesh sequence (one OBJ/PLY per frame), not as {kind}")
        return sequence.read_mesh_folder(path, fps=fps, **kw)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix in usd.SUFFIXES:
        if kind == "markers":
            raise ValueError(f"{path}: a USD file holds blend shape curves or a mesh sequence, not markers")
        return usd.read_performance(path, kind=kind, fps=fps)
    if suffix in (".glb", ".gltf"):
        if kind == "markers":
            raise ValueError(f"{path}: a glTF file holds weight curves or a mesh sequence, not markers")
        if kind == "meshes":
            return sequence.read_gltf_sequence(path, fps=fps)
        if not hasattr(gltf, "read_animation"):  # another module provides it; say so rather than fail obscurely
            raise ImportError(f"{path}: reading a glTF animation needs core.io.gltf.read_animation, which is not "
                              "available in this build")
        return gltf.read_animation(path, **({"fps": fps} if fps else {}), **kw)
    if fps:
        raise ValueError(f"{path}: fps cannot be set for {suffix or 'this'} files: their times come from the file")
    perf = _read_clocked(path, suffix, kw)
    if kind not in ("auto", perf.kind):
        raise ValueError(f"{path}: holds {perf.kind}, not {kind}")
    return perf


def _read_clocked(path: Path, suffix: str, kw: dict) -> Performance:
    """CSV, TRC and C3D: the formats with their own times."""
    if suffix == ".csv":
        header = _first_header(path)
        cells = [c.strip() for c in header.split(",")]
        if livelink.is_livelink_header(cells):
            return livelink.read_livelink(path, **kw)
        if [c.lower() for c in cells[:2]] == ["frame", "time_s"]:
            if kw.get("units") is None and markers.declared_units(path) is None and path.name.lower().startswith("animface_"):
                kw["units"] = "cm"  # bundled AnimFace captures: centimetres per data/SOURCES.md
            return markers.read_marker_csv(path, **kw)
        raise ValueError(
            f"{path}: unrecognised CSV header {header[:80]!r}; expected a Live Link Face CSV "
            f"(header 'Timecode,BlendShapeCount,...') or a marker CSV (header 'frame,time_s,<name>_X,...'). "
            f"Supported formats: {', '.join(READ_FORMATS)}"
        )
    if suffix == ".trc":
        return markers.read_trc(path, **kw)
    if suffix == ".c3d":
        return markers.read_c3d(path, **kw)
    raise _unsupported(path, READ_FORMATS, "read")


def write_performance(path, perf: Performance, **kw) -> None:
    """Write ``perf`` in the format named by the suffix of ``path``.

    ``.csv``: curves as Live Link Face CSV (:func:`core.io.livelink.write_livelink`), markers as
    marker CSV (:func:`core.io.markers.write_marker_csv`); ``.trc`` / ``.c3d``: markers. glTF
    animations need a rig to write against: use ``core.io.gltf`` directly.

    Raises
    ------
    TypeError
        ``perf`` is not a Performance.
    ValueError
        Unknown suffix (the message lists the supported ones), or a kind the format cannot hold.
    """
    path = Path(path)
    if not isinstance(perf, Performance):
        raise TypeError(f"perf: expected a core.model.Performance, got {type(perf).__name__}")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        if perf.kind == "curves":
            return livelink.write_livelink(path, perf, **kw)
        if perf.kind == "markers":
            return markers.write_marker_csv(path, perf, **kw)
        raise ValueError(f"{path}: a {perf.kind!r} performance cannot be written as CSV; expected curves or markers")
    if suffix in (".trc", ".c3d"):
        if perf.kind != "markers":
            raise ValueError(f"{path}: {suffix} holds marker trajectories; got a {perf.kind!r} performance")
        return (markers.write_trc if suffix == ".trc" else markers.write_c3d)(path, perf, **kw)
    if perf.kind == "meshes" and (suffix in usd.SUFFIXES or suffix in (".glb", ".gltf") or not suffix):
        return sequence.write_mesh_sequence(path, perf, **kw)
    if suffix in (".glb", ".gltf") or suffix in usd.SUFFIXES:
        raise ValueError(
            f"{path}: writing a {'USD' if suffix in usd.SUFFIXES else 'glTF'} animation needs the target rig; use "
            f"core.io.{'usd' if suffix in usd.SUFFIXES else 'gltf'}.write_rig. "
            f"write_performance supports: {', '.join(WRITE_FORMATS)}"
        )
    raise _unsupported(path, WRITE_FORMATS, "write")
