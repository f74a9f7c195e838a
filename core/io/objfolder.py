"""Blendshape rigs as a folder of OBJ files: ``neutral.obj`` plus one OBJ per shape.

Every file holds the same vertices in the same order (the ``v`` lines); a shape's name is its
file stem, its delta is ``shape - neutral``. Faces and texture coordinates are taken from
``neutral.obj``. This is how many rigs are exchanged (ICT FaceKit, FaceWarehouse, exports
from Blender/Maya with "keep vertex order").

Why the OBJ text is parsed here and not by ``trimesh.load(..., process=False,
maintain_order=True)``: that loader (trimesh 5.2) drops vertices no face references, which
renumbers every later vertex, and at UV seams (one ``v`` with several ``vt``) it keeps an
arbitrary one of the UVs. Both silently break the vertex correspondence between the neutral
and the shapes that a blendshape folder depends on. The parser below reads ``v`` lines in
file order, ``vt`` and ``f`` (``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``, negative indices,
polygons fan-triangulated as trimesh does), and ignores everything else (``vn``, groups,
materials). The tests check it against trimesh on files where trimesh is exact.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ..model import Rig, unit_scale

NEUTRAL = "neutral.obj"


class ObjFolderError(ValueError):
    """An OBJ folder that cannot be read as a rig; the message names the file and what is wrong."""


def _vertex_lines(path: Path, text: str, lines: list[str] | None = None) -> np.ndarray:
    """Positions (N, 3) float64 from the ``v`` lines of an OBJ text, in file order."""
    rows = [line[2:] for line in (text.splitlines() if lines is None else lines) if line[:2] in ("v ", "v\t")]
    if not rows:
        return np.zeros((0, 3))
    try:  # numpy's C parser (correctly rounded) when every row has the same columns: x y z [w | r g b]
        out = np.loadtxt(rows, dtype=np.float64, ndmin=2)
        if out.shape[1] >= 3 and len(out) == len(rows):  # loadtxt skips blank rows; those are errors here
            return out[:, :3]
    except ValueError:
        pass
    split = [r.split() for r in rows]
    try:
        return np.array([[float(x) for x in r[:3]] for r in split], dtype=np.float64).reshape(-1, 3)
    except ValueError:
        bad = next(i for i, r in enumerate(rows) if len(r.split()) < 3 or not _floats(r.split()[:3]))
        raise ObjFolderError(f"{path}: vertex {bad + 1} ('v {rows[bad].strip()}') is not three numbers") from None


def _floats(tokens) -> bool:
    try:
        [float(t) for t in tokens]
        return True
    except ValueError:
        return False


_CORNER = {  # corner formats of the fast path: (regex, has texture index)
    "v": (r"(\d+)", False),
    "v/t": (r"(\d+)/(\d+)", True),
    "v/t/n": (r"(\d+)/(\d+)/\d+", True),
    "v//n": (r"(\d+)//\d+", False),
}


def _faces_fast(rows: list[str]):
    """(vertex (F, 3), texcoord (F, 3) or None) 0-based, when every face is a triangle with
    positive indices in one corner format (what exporters write); None otherwise."""
    first = rows[0].split()
    if len(first) != 4:
        return None
    c = first[1]
    fmt = "v" if "/" not in c else "v//n" if "//" in c else "v/t" if c.count("/") == 1 else "v/t/n"
    corner, has_t = _CORNER[fmt]
    pattern = re.compile(rf"^f[ \t]+{corner}[ \t]+{corner}[ \t]+{corner}[ \t]*$", re.M)
    found = pattern.findall("\n".join(rows))
    if len(found) != len(rows):
        return None
    idx = np.array(found, dtype=np.int64).reshape(len(rows), 3, -1) - 1
    return idx[:, :, 0], (idx[:, :, 1] if has_t else None)


def _faces_general(path: Path, lines: list[str], n_vt: int):
    """Any OBJ faces: polygons (fan-triangulated), negative (relative) indices, mixed formats."""
    faces, fvt = [], []
    n_v = 0
    all_t = True
    for lineno, line in enumerate(lines, 1):
        head = line[:2]
        if head in ("v ", "v\t"):
            n_v += 1
            continue
        if head not in ("f ", "f\t"):
            continue
        corners = line.split()[1:]
        if len(corners) < 3:
            raise ObjFolderError(f"{path}:{lineno}: face {line.strip()!r} has fewer than 3 corners")
        vi, ti = [], []
        try:
            for c in corners:
                parts = c.split("/")
                i = int(parts[0])
                vi.append(i - 1 if i > 0 else n_v + i)  # 1-based, or negative = relative
                if len(parts) > 1 and parts[1]:
                    j = int(parts[1])
                    ti.append(j - 1 if j > 0 else n_vt + j)
        except ValueError:
            raise ObjFolderError(f"{path}:{lineno}: face {line.strip()!r} has a non-integer index") from None
        if min(vi) < 0 or max(vi) >= n_v:
            raise ObjFolderError(f"{path}:{lineno}: face {line.strip()!r} indexes a vertex outside 1..{n_v}")
        has_t = len(ti) == len(vi)
        all_t &= has_t
        for k in range(1, len(vi) - 1):  # fan triangulation
            faces.append((vi[0], vi[k], vi[k + 1]))
            fvt.append((ti[0], ti[k], ti[k + 1]) if has_t else (-1, -1, -1))
    faces = np.array(faces, dtype=np.int64).reshape(-1, 3)
    return faces, (np.array(fvt, dtype=np.int64).reshape(-1, 3) if all_t and faces.size else None)


def _texcoords(path: Path, lines: list[str]) -> np.ndarray:
    """(N, 2) texture coordinates from ``vt u [v [w]]`` lines (v defaults to 0)."""
    rows = [line.split()[1:3] for line in lines if line[:3] in ("vt ", "vt\t")]
    try:
        if all(len(r) == 2 for r in rows):
            return np.array(rows, dtype=np.float64).reshape(-1, 2)
        return np.array([(float(r[0]), float(r[1]) if len(r) > 1 else 0.0) for r in rows], dtype=np.float64).reshape(-1, 2)
    except (ValueError, IndexError):
        bad = next(i for i, r in enumerate(rows) if not r or not _floats(r))
        raise ObjFolderError(f"{path}: texture coordinate {bad + 1} ('vt {' '.join(rows[bad])}') is not numbers") from None


def _parse_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(positions (V, 3), faces (F, 3), texcoords (N, 2) or None, face texcoord indices (F, 3) or None).

    Texture coordinates are only returned when every face has them.
    """
    text = _read_text(path)
    lines = text.splitlines()
    positions = _vertex_lines(path, text, lines)
    vt = _texcoords(path, lines)
    rows = [line for line in lines if line[:2] in ("f ", "f\t")]
    fast = _faces_fast(rows) if rows else None
    if fast is not None and fast[0].min() >= 0 and fast[0].max() < len(positions):
        faces, fvt = fast
    else:  # anything unusual, including errors, which the general parser reports by line
        faces, fvt = _faces_general(path, lines, len(vt))
    if not len(vt) or fvt is None:
        return positions, faces, None, None
    if fvt.min() < 0 or fvt.max() >= len(vt):
        raise ObjFolderError(f"{path}: a face indexes a texture coordinate outside 1..{len(vt)}")
    return positions, faces, vt, fvt


def _per_vertex_uvs(path: Path, V: int, faces: np.ndarray, texcoords, fvt) -> np.ndarray | None:
    """One UV per vertex when every corner of a vertex uses the same UV, else None (with a warning)."""
    if texcoords is None:
        return None
    uv = np.zeros((V, 2))
    v, t = faces.reshape(-1), fvt.reshape(-1)
    uv[v] = texcoords[t]  # last corner wins; checked below
    seams = np.flatnonzero(np.abs(uv[v] - texcoords[t]).max(axis=1) > 0)
    if seams.size:
        n = len(np.unique(v[seams]))
        warnings.warn(
            f"{path}: {n} vertices have several texture coordinates (UV seams); a Rig holds one UV per "
            f"vertex, so the UVs are dropped (split the vertices at the seams to keep them)",
            stacklevel=3,
        )
        return None
    return uv


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        raise ObjFolderError(f"{path}: not a text OBJ file (not UTF-8)") from None


def read_obj(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One OBJ file as ``(positions (V, 3), faces (F, 3), uvs (V, 2) or None)``, vertex order kept.

    The parser of this module (every ``v`` line in file order, polygons fan-triangulated, one UV
    per vertex or none); :mod:`core.io.sequence` reads per-frame OBJ files with it.

    Raises
    ------
    FileNotFoundError; ObjFolderError naming the file (and line) that cannot be parsed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    positions, faces, texcoords, fvt = _parse_obj(path)
    return positions, faces, _per_vertex_uvs(path, len(positions), faces, texcoords, fvt)


def read_obj_folder(folder, units: str = "m") -> Rig:
    """Read a rig from ``folder/neutral.obj`` and one ``<shape name>.obj`` per shape.

    ``deltas[k] = positions(<name_k>.obj) - positions(neutral.obj)`` (the delta blendshape
    model, Seol et al. 2012 eq. 1), shapes ordered by file name (sorted, case-sensitive).
    Vertex order is the order of ``v`` lines, kept as is: nothing is merged, split or
    dropped. UVs come from ``neutral.obj`` when each vertex has one.

    Parameters
    ----------
    folder : str or Path
    units : str
        Units of the OBJ coordinates (``"m"``, ``"cm"``, ``"mm"``, ...); converted to metres.

    Returns
    -------
    Rig with neutral (V, 3), faces (F, 3), deltas (K, V, 3), ``name`` the folder name.

    Raises
    ------
    FileNotFoundError
        ``folder`` does not exist.
    ObjFolderError (a ValueError)
        No OBJ files, no ``neutral.obj``, ``neutral.obj`` without faces, a shape whose vertex
        count differs from ``neutral.obj`` (names that file), unparsable lines (file:line).
    """
    folder = Path(folder)
    scale = unit_scale(units)
    if not folder.exists():
        raise FileNotFoundError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise ObjFolderError(f"{folder}: not a folder (expected a folder with neutral.obj and one OBJ per shape)")
    objs = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".obj" and p.is_file())
    if not objs:
        raise ObjFolderError(f"{folder}: no OBJ files (expected neutral.obj and one OBJ per shape)")
    neutral_path = folder / NEUTRAL
    if neutral_path not in objs:
        raise ObjFolderError(f"{neutral_path}: missing; the folder has {len(objs)} other OBJ files ({objs[0].name}, ...)")
    positions, faces, texcoords, fvt = _parse_obj(neutral_path)
    V = len(positions)
    if V == 0 or not faces.size:
        raise ObjFolderError(f"{neutral_path}: needs vertices ('v' lines) and triangles ('f' lines), found {V} and {len(faces)}")
    uvs = _per_vertex_uvs(neutral_path, V, faces, texcoords, fvt)
    shapes = [p for p in objs if p != neutral_path]
    deltas = np.empty((len(shapes), V, 3))
    for k, p in enumerate(shapes):
        pk = _vertex_lines(p, _read_text(p))
        if len(pk) != V:
            raise ObjFolderError(f"{p}: has {len(pk)} vertices ('v' lines), {NEUTRAL} has {V}; every shape needs the neutral's vertices in the same order")
        deltas[k] = pk - positions
    try:
        return Rig(positions * scale, faces, deltas * scale, [p.stem for p in shapes], uvs, units, folder.name)
    except ValueError as e:
        raise ObjFolderError(f"{folder}: {e}") from None


def _format(positions: np.ndarray) -> str:
    # %.17g round-trips float64 exactly; one formatting call for the whole block is ~3x
    # faster than np.savetxt's per-row loop
    return ("v %.17g %.17g %.17g\n" * len(positions)) % tuple(positions.ravel())


def write_obj_folder(folder, rig: Rig, units: str = "m", overwrite: bool = False) -> Path:
    """Write ``rig`` as ``folder/neutral.obj`` and ``folder/<name>.obj`` per shape.

    Each shape file holds ``neutral + deltas[k]`` and the neutral's faces, so any OBJ viewer
    opens it; ``neutral.obj`` also holds ``vt`` (one per vertex) when the rig has UVs.
    Coordinates are written with 17 significant digits (float64 round-trips exactly).

    Parameters
    ----------
    folder : str or Path
        Created if missing.
    rig : Rig
    units : str
        Units to write in (positions are divided by metres-per-unit).
    overwrite : bool
        When False, a folder that already has OBJ files is refused. When True, OBJ files that
        are not part of this rig are removed, so the folder reads back as ``rig``.

    Returns
    -------
    Path of the folder.

    Raises
    ------
    FileExistsError
        OBJ files present and ``overwrite`` is False.
    ValueError
        A shape name that is not a usable file name (empty, has a path separator, or is
        ``neutral``, or two names differ only in case).
    """
    folder = Path(folder)
    scale = unit_scale(units)
    if not isinstance(rig, Rig):
        raise TypeError(f"rig: expected a core.model.Rig, got {type(rig).__name__}")
    stems = [n for n in rig.names]
    for n in stems:
        if not n or n.strip() != n or any(c in n for c in '/\\:*?"<>|\0') or n in (".", "..") or n.lower() == "neutral":
            raise ValueError(f"rig {rig.name!r}: shape name {n!r} cannot be an OBJ file name (nor be 'neutral')")
    lower = [n.lower() for n in stems]
    if len(set(lower)) != len(lower):
        dup = sorted({n for n in stems if lower.count(n.lower()) > 1})
        raise ValueError(f"rig {rig.name!r}: shape names {dup} differ only in case; they would collide on some file systems")
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {NEUTRAL} | {n + ".obj" for n in stems}
    existing = [p for p in folder.iterdir() if p.suffix.lower() == ".obj"]
    if existing and not overwrite:
        raise FileExistsError(f"{folder}: already has {len(existing)} OBJ files; pass overwrite=True to replace them")

    f = rig.faces + 1
    if rig.uvs is not None:
        uv = ("vt %.17g %.17g\n" * rig.n_vertices) % tuple(rig.uvs.ravel())
        faces = ("f %d/%d %d/%d %d/%d\n" * len(f)) % tuple(np.repeat(f, 2, axis=1).ravel())
    else:
        uv = ""
        faces = ("f %d %d %d\n" * len(f)) % tuple(f.ravel())
    plain = ("f %d %d %d\n" * len(f)) % tuple(f.ravel())
    header = f"# face-retarget rig {rig.name!r}, units {units}, {rig.n_vertices} vertices\n"
    (folder / NEUTRAL).write_text(header + "o neutral\n" + _format(rig.neutral / scale) + uv + faces)
    for k, name in enumerate(stems):
        (folder / f"{name}.obj").write_text(header + f"o {name}\n" + _format((rig.neutral + rig.deltas[k]) / scale) + plain)
    for p in existing:
        if p.name not in wanted:
            p.unlink()
    return folder
