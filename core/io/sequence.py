"""Dense mesh sequences (4D capture, simulation caches): per-frame meshes in and out.

A mesh sequence is a :class:`~core.model.Performance` of kind ``"meshes"``: ``data`` (T, V, 3)
in metres, one shared topology in ``extras["faces"]`` (F, 3), ``valid`` (T,) False for a frame
without data. Three containers are read (:func:`read_mesh_sequence` dispatches):

=====================================  =====================================================
container                              how the frames are laid out
=====================================  =====================================================
folder of OBJ or PLY files             one file per frame, ``frame_0001.obj`` ...; natural sort
                                       order (``f2`` before ``f10``); the last number in a file
                                       name is its frame number, and numbers missing from the
                                       run are frames without data (masked, with a warning)
glTF / GLB                             the mesh's morph targets with a weight animation: frame
                                       ``t = base + sum_k w_tk target_k`` (exporters write one
                                       target per frame, weights one-hot)
USD (``.usd/.usda/.usdc/.usdz``)       a Mesh whose ``points`` are time-sampled
                                       (:func:`core.io.usd.read_mesh_sequence`)
=====================================  =====================================================

Frame rate: the ``fps`` argument, else a folder's sidecar ``sequence.json``
(``{"fps": 60, "units": "mm"}``), else the file's own (glTF key times, USD time codes), else 30.
Every frame must have the first frame's vertex count and faces; the error names the file and
frame that differ. OBJ files are read by :func:`core.io.objfolder.read_obj` (every ``v`` line in
file order: trimesh's OBJ loader can renumber vertices, see that module), PLY files by trimesh.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import trimesh

from ..model import Performance, Rig, unit_scale
from .gltf import read_animation, read_rig, write_rig
from .objfolder import read_obj
from .tabular import DataQualityWarning
from .usd import SUFFIXES as USD_SUFFIXES
from .usd import read_mesh_sequence as read_usd
from .usd import write_mesh_sequence as write_usd

#: per-frame file suffixes a sequence folder may hold
FRAME_SUFFIXES = (".obj", ".ply")
#: the sidecar JSON of a sequence folder
SIDECAR = "sequence.json"
DEFAULT_FPS = 30.0


class SequenceError(ValueError):
    """A mesh sequence that cannot be read; the message names the file or frame and the fix."""


def natural_key(name: str) -> list:
    """Sort key that orders digit runs by value: ``frame_2`` before ``frame_10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _frame_number(stem: str) -> Optional[int]:
    m = re.search(r"(\d+)(?!.*\d)", stem)
    return int(m.group(1)) if m else None


def _sidecar(folder: Path) -> dict:
    f = folder / SIDECAR
    if not f.exists():
        return {}
    try:
        doc = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise SequenceError(f"{f}: not valid JSON ({e})") from None
    if not isinstance(doc, dict):
        raise SequenceError(f"{f}: expected an object like {{\"fps\": 30, \"units\": \"m\"}}, got {type(doc).__name__}")
    fps = doc.get("fps")
    if fps is not None and not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and fps > 0):
        raise SequenceError(f"{f}: field 'fps' must be a positive number, got {fps!r}")
    return doc


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        mesh = trimesh.load(str(path), process=False, force="mesh")
    except Exception as e:  # trimesh raises many types on a malformed file
        raise SequenceError(f"{path}: not a readable PLY file ({type(e).__name__}: {e})") from None
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _read_frame(path: Path) -> tuple[np.ndarray, np.ndarray]:
    if path.suffix.lower() == ".obj":
        positions, faces, _ = read_obj(path)
        return positions, faces
    return _read_ply(path)


def read_mesh_folder(folder, fps: Optional[float] = None, units: Optional[str] = None) -> Performance:
    """Read a folder of per-frame OBJ or PLY files as a mesh sequence (see the module docstring).

    Parameters
    ----------
    folder : str or Path
    fps : float, optional
        Frame rate; default the sidecar's ``fps``, else 30.
    units : str, optional
        Units of the coordinates; default the sidecar's ``units``, else ``"m"``.

    Returns
    -------
    Performance of kind "meshes", ``extras["faces"]``, ``extras["files"]`` (one name per frame,
    "" for a missing frame), ``extras["frame_numbers"]`` (T,) from the file names.

    Raises
    ------
    FileNotFoundError; SequenceError naming the file: no frames, OBJ and PLY mixed, a rig folder
    (``neutral.obj``), a frame whose vertex count or faces differ from the first frame's, a
    duplicate frame number.
    """
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise SequenceError(f"{folder}: not a folder of per-frame OBJ/PLY files")
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise SequenceError(f"{folder}: no per-frame mesh files ({', '.join(FRAME_SUFFIXES)})")
    if any(p.name.lower() == "neutral.obj" for p in files):
        raise SequenceError(f"{folder}: has neutral.obj, so it is a blendshape rig folder (neutral + one OBJ per shape), "
                            "not a mesh sequence; pass it as a rig (--source-rig / --target-rig)")
    kinds = sorted({p.suffix.lower() for p in files})
    if len(kinds) > 1:
        raise SequenceError(f"{folder}: mixes {' and '.join(kinds)} files; a sequence is one file type")
    side = _sidecar(folder)
    fps = float(fps or side.get("fps") or DEFAULT_FPS)
    units = units or side.get("units") or "m"
    scale = unit_scale(units)

    numbers = [_frame_number(p.stem) for p in files]
    if all(n is not None for n in numbers):
        dup = sorted({n for n in numbers if numbers.count(n) > 1})
        if dup:
            raise SequenceError(f"{folder}: frame numbers {dup[:5]} appear in more than one file name "
                                f"(e.g. {[p.name for p, n in zip(files, numbers) if n == dup[0]]})")
        slots = np.asarray(numbers) - min(numbers)
        T = int(slots.max()) + 1
    else:  # no frame numbers to go by: the natural order is the timeline
        slots, T = np.arange(len(files)), len(files)
        numbers = list(range(len(files)))

    positions, faces = _read_frame(files[0])
    V = len(positions)
    if V == 0 or not faces.size:
        raise SequenceError(f"{files[0]}: the first frame needs vertices and faces, found {V} and {len(faces)}")
    data = np.full((T, V, 3), np.nan)
    valid = np.zeros(T, dtype=bool)
    names = [""] * T
    for i, (p, slot) in enumerate(zip(files, slots)):
        if i:
            positions, f = _read_frame(p)
            if len(positions) != V:
                raise SequenceError(f"{p}: frame {numbers[i]} has {len(positions)} vertices, {files[0].name} has {V}; "
                                    "every frame needs the same vertices in the same order")
            if not np.array_equal(f, faces):
                raise SequenceError(f"{p}: frame {numbers[i]} has other faces than {files[0].name} "
                                    f"({len(f)} vs {len(faces)} triangles); a mesh sequence needs one topology")
        data[slot] = positions * scale
        valid[slot] = True
        names[slot] = p.name
    if not valid.all():
        lost = np.flatnonzero(~valid) + min(numbers)
        warnings.warn(f"{folder}: {len(lost)} frame numbers have no file ({', '.join(map(str, lost[:8]))}"
                      f"{' ...' if len(lost) > 8 else ''}); they are frames without data", DataQualityWarning, stacklevel=2)
    first = min(numbers)
    try:
        return Performance.meshes(data, fps, faces=faces, valid=valid, units=units, name=folder.name,
                                  extras={"files": np.array(names), "frame_numbers": np.arange(first, first + T)})
    except ValueError as e:
        raise SequenceError(f"{folder}: {e}") from None


def read_gltf_sequence(path, fps: Optional[float] = None) -> Performance:
    """A glTF/GLB mesh whose morph targets and weight animation carry the frames:
    ``frame_t = base + sum_k w_tk target_k`` at each key of ``animations[0]`` (the values of
    STEP/LINEAR/CUBICSPLINE keys), with the mesh's triangles as the topology. The mesh is the
    animated one, or the avatar's whole face (:func:`core.io.gltf.read_rig`) when that mesh is one
    of its parts and the animation names all the face's shapes.

    Raises
    ------
    FileNotFoundError; GltfError naming the file and field (no animation, no morph targets, ...).
    """
    path = Path(path)
    curves = read_animation(path, fps=fps)
    # the face (head, eyes, teeth: read_rig's default) when the animated mesh is part of it and the
    # curves name all its shapes (an avatar animates each of those meshes by the same weights)
    rig = read_rig(path)
    parts = [m["mesh"] for m in rig.extras.get("meshes", [])]
    if curves.extras.get("mesh") not in parts or not set(rig.names) <= set(curves.names):
        rig = read_rig(path, mesh=curves.extras.get("mesh"))
    W = curves.select(list(rig.names)).data
    return Performance.meshes(rig.evaluate(np.nan_to_num(W)), curves.fps, faces=rig.faces, valid=curves.valid.all(1),
                              times=curves.times, units=rig.units, name=path.stem,
                              extras={"interpolation": curves.extras.get("interpolation")})


def read_mesh_sequence(path, fps: Optional[float] = None, units: Optional[str] = None) -> Performance:
    """A mesh sequence from a folder of OBJ/PLY frames, a glTF/GLB or a USD file (see the
    module table); ``fps`` overrides the rate the files give, ``units`` a folder's units."""
    path = Path(path)
    if path.is_dir():
        return read_mesh_folder(path, fps=fps, units=units)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return read_gltf_sequence(path, fps=fps)
    if suffix in USD_SUFFIXES:
        return read_usd(path, fps=fps)
    raise SequenceError(f"{path}: a mesh sequence is a folder of OBJ/PLY frames, a .glb/.gltf with morph-target frames, "
                        f"or a USD file ({', '.join(USD_SUFFIXES)}); got {suffix or 'no suffix'!r}")


def topology_rig(perf: Performance) -> Rig:
    """The sequence's own face as a rig without shapes: its first frame with data as the neutral
    and ``extras["faces"]`` (what the dense stages and marker layouts on a sequence work on).

    Raises
    ------
    ValueError
        Not a mesh sequence, no faces, or no frame with data.
    """
    if perf.kind != "meshes":
        raise ValueError(f"performance {perf.name!r} is {perf.kind}, not a mesh sequence")
    faces = perf.extras.get("faces")
    if faces is None:
        raise ValueError(f"mesh sequence {perf.name!r} has no faces (extras['faces']); read it with "
                         "core.io.sequence.read_mesh_sequence, or give the source rig whose topology it has")
    ok = np.flatnonzero(perf.valid)
    if not len(ok):
        raise ValueError(f"mesh sequence {perf.name!r} has no frame with data")
    neutral = perf.data[ok[0]]
    return Rig(neutral, faces, np.zeros((0,) + neutral.shape), [], None, perf.units, perf.name)


def write_mesh_sequence(path, perf: Performance, frame_format: str = "obj", prefix: str = "frame_") -> Path:
    """Write a mesh sequence as per-frame files in a folder (``path`` without a suffix, or an existing
    folder), a GLB/glTF (one morph target per frame, one-hot LINEAR keys), or USD (time-sampled
    points, :func:`core.io.usd.write_mesh_sequence`).

    A folder gets ``<prefix><n:04d>.<frame_format>`` for each frame with data (frames without
    data leave a gap in the numbering, which :func:`read_mesh_folder` reads back as such) and
    ``sequence.json`` with the fps; OBJ coordinates have 17 significant digits.

    Raises
    ------
    ValueError
        Not a mesh sequence, no faces, or an unknown ``frame_format`` / suffix.
    """
    path = Path(path)
    topo = topology_rig(perf)  # validates kind and faces
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        ok = np.flatnonzero(perf.valid)
        names = [f"{prefix}{i:04d}" for i in ok]
        rig = Rig(topo.neutral, topo.faces, perf.data[ok] - topo.neutral, names, None, perf.units, perf.name)
        return write_rig(path, rig, weights=np.eye(len(ok)), times=perf.times[ok] - perf.times[0], normals=False)
    if suffix in USD_SUFFIXES:
        return write_usd(path, perf)
    if suffix and not path.is_dir():
        raise ValueError(f"path: {path}: a sequence is written to a folder, a .glb/.gltf or a USD file")
    if frame_format not in ("obj", "ply"):
        raise ValueError(f"frame_format: expected 'obj' or 'ply', got {frame_format!r}")
    path.mkdir(parents=True, exist_ok=True)
    faces = topo.faces
    obj_faces = ("f %d %d %d\n" * len(faces)) % tuple((faces + 1).ravel())
    for i in np.flatnonzero(perf.valid):
        f = path / f"{prefix}{i:04d}.{frame_format}"
        if frame_format == "obj":
            v = ("v %.17g %.17g %.17g\n" * len(perf.data[i])) % tuple(perf.data[i].ravel())
            f.write_text(f"# face-retarget mesh sequence {perf.name!r}, frame {i}\n" + v + obj_faces)
        else:
            trimesh.Trimesh(perf.data[i], faces, process=False).export(str(f))
    (path / SIDECAR).write_text(json.dumps({"fps": perf.fps, "units": "m"}) + "\n")
    return path
