"""Check a file when it arrives, and say what is wrong in words for the person who sent it.

:func:`check_upload` reads an uploaded file with the program's own readers (nothing else parses
it) and returns what it is — a take, a rig, a marker layout, a name map or a shot — or raises a
ValueError whose message names the file *as the user called it* (never a server path or a
Python byte string) and says what to do: an empty file, a file that is not what its suffix
says, a rig without blend shapes, a take without frames, a layout for a rig it does not fit.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Optional

from ..controls import validate_table
from ..names import NameMap
from ..shot import Shot
from .layout import read_layout
from .performance import read_performance
from .rigs import load_rig

TAKES = (".csv", ".trc", ".c3d")
RIGS = (".glb", ".gltf", ".vrm", ".usd", ".usda", ".usdc", ".usdz")


def _plain(msg: str, path: Path, name: str) -> str:
    """An error message with the server's path replaced by the name the user gave the file."""
    for p in (str(path), str(path.parent) + "/"):
        msg = msg.replace(p, name if p == str(path) else "")
    return msg


def check_upload(path, name: Optional[str] = None, target_rig=None) -> dict:
    """What an uploaded file is: ``{"kind": "take"|"rig"|"layout"|"name_map"|"shot", "summary": str,
    ...}`` with the object read (``take``, ``rig``, ``layout``, ``name_map``, ``shot``).

    Parameters
    ----------
    path : the stored file
    name : the file's name as uploaded (default: ``path``'s name)
    target_rig : core.model.Rig, optional — a layout is checked against it

    Raises
    ------
    ValueError
        In plain words, naming ``name``.
    """
    path = Path(path)
    name = name or path.name
    suffix = path.suffix.lower()
    if not path.exists() or path.stat().st_size == 0:
        raise ValueError(f"{name} is empty: upload the file again (the upload may have been cut off)")
    try:
        if suffix in TAKES:
            return _take(path, name)
        if suffix in RIGS:
            return _rig(path, name)
        if suffix == ".json":
            return _json(path, name, target_rig)
    except UnicodeDecodeError as e:
        raise ValueError(f"{name} is not UTF-8 text (byte {e.start} is {e.object[e.start:e.start + 1]!r}; "
                         f"{'Latin-1 or Windows-1252' if 0x80 <= e.object[e.start] else 'another encoding'}?): "
                         "save it as UTF-8 and upload it again") from None
    except ValueError as e:
        raise ValueError(_plain(str(e), path, name)) from None
    except (OSError, KeyError, IndexError, TypeError) as e:  # a reader meeting a malformed file
        raise ValueError(f"{name} could not be read as a {'take' if suffix in TAKES else 'rig' if suffix in RIGS else 'file'}: "
                         f"{_plain(str(e), path, name) or type(e).__name__}") from None
    raise ValueError(f"{name}: files of type {suffix or '(no suffix)'} are not something this program reads; upload a take "
                     "(.csv from Live Link Face, a marker .csv/.trc/.c3d), a rig (.glb/.gltf/.vrm/.usd) or a .json shot, "
                     "marker layout or name map")


#: the most columns a take's header may have (a 1,000-marker capture has 3,000 + a few)
MAX_COLUMNS = 20_000
MAX_HEADER_BYTES = 4 * 2**20


def _take(path: Path, name: str) -> dict:
    with open(path, "rb") as fh:
        head = fh.read(4096)
        fh.seek(0)
        first = fh.readline(MAX_HEADER_BYTES + 1)
    if head[:2] in (b"\xff\xfe", b"\xfe\xff") and path.suffix.lower() != ".c3d":
        raise ValueError(f"{name} is UTF-16 text: save it as UTF-8 (a plain .csv) and upload it again")
    n = max(first.count(b","), first.count(b"\t")) + 1  # the header's columns, whichever the separator
    if path.suffix.lower() in (".csv", ".trc") and (len(first) > MAX_HEADER_BYTES or n > MAX_COLUMNS):
        # refused before a reader splits a 10^6-column header (that took the server minutes)
        raise ValueError(f"{name} has {'a first line of more than 4 MB' if len(first) > MAX_HEADER_BYTES else f'{n:,} columns'}"
                         f": a take has at most a few thousand channels (markers x 3); is this the right file?")
    if b"\0" in head:
        raise ValueError(f"{name} is not a text file: a take is a .csv from Live Link Face or a marker capture (.csv/.trc)"
                         if path.suffix.lower() != ".c3d" else f"{name} could not be read as a C3D capture")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        perf = read_performance(path)
    quality = []
    for w in caught:  # passed on, and said in the summary (the page shows it): masked cells are kept
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        if w.category.__name__ == "DataQualityWarning":
            quality.append(str(w.message).replace(str(path), name))
    if perf.n_frames == 0:
        raise ValueError(f"{name} has no frames")
    if not perf.valid.any():
        raise ValueError(f"{name} has {perf.n_frames} frames but no sample with data (every frame lost tracking)")
    kind = {"curves": "weight curves", "markers": "marker trajectories", "meshes": "a mesh sequence"}[perf.kind]
    return {"kind": "take", "take": perf,
            "summary": f"{name}: {kind}, {perf.n_frames} frames at {perf.fps:g} fps ({perf.duration:.1f} s), "
                       f"{len(perf.names)} channels" + "".join(f" — {q.split(': ', 1)[-1]}" for q in quality)}


def _rig(path: Path, name: str) -> dict:
    if path.suffix.lower() in (".glb", ".vrm") and path.read_bytes()[:4] != b"glTF":
        raise ValueError(f"{name} is not a GLB file (it does not start like one): export the rig as binary glTF (.glb)")
    rig = load_rig(path)
    if rig.n_shapes == 0:
        raise ValueError(f"{name} has no blend shapes (morph targets): a rig needs the shapes the weights drive — "
                         "export it with its shape keys / blend shapes")
    return {"kind": "rig", "rig": rig,
            "summary": f"{name}: {rig.n_vertices:,} vertices, {rig.n_shapes} blend shapes"}


def _json(path: Path, name: str, target_rig=None) -> dict:
    try:
        doc = json.loads(path.read_text(encoding="utf-8-sig"))
    except UnicodeDecodeError:
        raise ValueError(f"{name} is not a text (UTF-8) JSON file") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{name} is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{name}: expected a JSON object (a shot, a marker layout or a name map)")
    if "schema_version" in doc:
        shot = Shot.from_dict(doc)
        return {"kind": "shot", "shot": shot, "summary": f"{name}: a shot with {len(shot.files)} files"}
    if doc.get("format") == "face-retarget controls":
        table = validate_table(doc, where=name)
        return {"kind": "controls", "controls": table,
                "summary": f"{name}: controls for {len(table.get('shapes', {}))} shapes"}
    if doc.get("format") == "face-retarget marker layout" or "markers" in doc:
        if target_rig is None:
            raise ValueError(f"{name} is a marker layout: choose the rig it belongs to as the target rig first")
        layout = read_layout(path, rig=target_rig)
        return {"kind": "layout", "layout": layout,
                "summary": f"{name}: {layout.n_markers} markers on {target_rig.name}"}
    try:
        nm = NameMap.from_json(path)
    except ValueError:
        raise ValueError(f"{name} is JSON but not a shot, a marker layout or a name map "
                         "(a name map is {{\"shape\": [\"channel\", ...], ...}})") from None
    return {"kind": "name_map", "name_map": nm, "summary": f"{name}: a name map of {len(nm.entries)} shapes"}
