"""Read and write a captured performance in whichever file format it comes in.

:func:`read_performance` dispatches on the suffix and, for ``.csv``, on the header line:

=================  ===========================================  ====================================
format             recognised by                                reader
=================  ===========================================  ====================================
Live Link Face     ``.csv`` whose header starts                 :func:`core.io.livelink.read_livelink`
                   ``Timecode,BlendShapeCount``
marker CSV         ``.csv`` whose header starts ``frame,time_s``  :func:`core.io.markers.read_marker_csv`
TRC                ``.trc``                                     :func:`core.io.markers.read_trc`
C3D                ``.c3d`` (needs ``ezc3d``)                   :func:`core.io.markers.read_c3d`
glTF animation     ``.glb`` / ``.gltf``                         ``core.io.gltf.read_animation``
=================  ===========================================  ====================================

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

from core.io import livelink, markers
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
}
WRITE_FORMATS = {
    ".csv": "Live Link Face CSV for curves, marker CSV for markers",
    ".trc": "TRC for markers",
    ".c3d": "C3D for markers (pip install face-retarget[c3d])",
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


def read_performance(path, **kw) -> Performance:
    """Read a performance from any supported file (see the module table).

    Parameters
    ----------
    path : str or Path
    **kw
        Passed to the format's reader (``allow_missing=`` for Live Link Face, ``units=`` for
        marker CSV/TRC, ...).

    Returns
    -------
    Performance

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Unknown suffix or CSV header (the message lists the supported formats), or the reader's
        own errors.
    ImportError
        ``.glb``/``.gltf`` while ``core.io.gltf.read_animation`` is not available, or ``.c3d``
        without ezc3d.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        header = _first_header(path)
        cells = [c.strip() for c in header.split(",")]
        if cells[:2] == ["Timecode", "BlendShapeCount"]:
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
    if suffix in (".glb", ".gltf"):
        try:
            from core.io.gltf import read_animation
        except ImportError as e:  # another module provides it; say so rather than fail obscurely
            raise ImportError(
                f"{path}: reading a glTF animation needs core.io.gltf.read_animation, which is not "
                f"available in this build ({e})"
            ) from None
        return read_animation(path, **kw)
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
    if suffix in (".glb", ".gltf"):
        raise ValueError(
            f"{path}: writing a glTF animation needs the target rig; use core.io.gltf's writer. "
            f"write_performance supports: {', '.join(WRITE_FORMATS)}"
        )
    raise _unsupported(path, WRITE_FORMATS, "write")
