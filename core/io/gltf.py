"""glTF 2.0 / GLB rigs: mesh + morph targets + ``targetNames`` in, rig + weight animation out.

pygltflib parses the container; trimesh does not read morph targets, so accessor decoding
(strides, sparse accessors, normalised integers) is written here against the glTF 2.0 spec
§3.6 (accessors) and §3.7.2.2 (morph targets).
"""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np

from ..model import Rig

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}


class GltfError(ValueError):
    """A glTF file that cannot be read as a rig; the message names file and field."""


def _load(path: Path):
    import pygltflib

    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        gltf = pygltflib.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises a zoo of types on corrupt files
        raise GltfError(f"{path}: not a readable glTF 2.0 file ({type(e).__name__}: {e})") from None
    if gltf is None:
        raise GltfError(f"{path}: not a readable glTF 2.0 file")
    return gltf


def _buffer_bytes(gltf, path: Path, index: int) -> bytes:
    buf = gltf.buffers[index]
    if buf.uri is None:
        data = gltf.binary_blob()
        if data is None:
            raise GltfError(f"{path}: buffers[{index}] has no uri and the file has no BIN chunk (truncated GLB?)")
    elif buf.uri.startswith("data:"):
        data = base64.b64decode(buf.uri.split(",", 1)[1])
    else:
        f = path.parent / buf.uri
        if not f.exists():
            raise GltfError(f"{path}: buffers[{index}].uri {buf.uri!r} not found next to the file")
        data = f.read_bytes()
    if len(data) < buf.byteLength:
        raise GltfError(f"{path}: buffers[{index}] holds {len(data)} bytes, byteLength says {buf.byteLength} (truncated file?)")
    return data


def _view(gltf, path, bv_index: int, offset: int, count: int, dtype, ncomp: int, what: str) -> np.ndarray:
    bv = gltf.bufferViews[bv_index]
    data = _buffer_bytes(gltf, path, bv.buffer)
    itemsize = np.dtype(dtype).itemsize * ncomp
    stride = bv.byteStride or itemsize
    start = (bv.byteOffset or 0) + (offset or 0)
    need = start + (count - 1) * stride + itemsize if count else start
    if need > len(data) or need > (bv.byteOffset or 0) + bv.byteLength:
        raise GltfError(f"{path}: {what} reads past the end of bufferViews[{bv_index}] (truncated or corrupt file)")
    raw = np.frombuffer(data, dtype=np.uint8, count=need - start, offset=start)
    if stride == itemsize:
        return raw.view(dtype).reshape(count, ncomp).copy()
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, itemsize), strides=(stride, 1))
    return rows.copy().view(dtype).reshape(count, ncomp)


def read_accessor(gltf, path: Path, index: int, what: str = "accessor") -> np.ndarray:
    """Decode accessor ``index`` to a (count, ncomp) float64/int array (glTF 2.0 §3.6)."""
    if index is None or index >= len(gltf.accessors):
        raise GltfError(f"{path}: {what} refers to accessors[{index}], which does not exist")
    acc = gltf.accessors[index]
    dtype = _COMPONENT.get(acc.componentType)
    if dtype is None:
        raise GltfError(f"{path}: accessors[{index}] ({what}) has unknown componentType {acc.componentType}")
    ncomp = _NCOMP[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, ncomp), dtype=dtype)
    else:
        out = _view(gltf, path, acc.bufferView, acc.byteOffset, acc.count, dtype, ncomp, f"accessors[{index}] ({what})")
    if acc.sparse is not None and acc.sparse.count:
        sp = acc.sparse
        idx = _view(gltf, path, sp.indices.bufferView, sp.indices.byteOffset, sp.count, _COMPONENT[sp.indices.componentType], 1, f"{what} sparse indices")[:, 0]
        vals = _view(gltf, path, sp.values.bufferView, sp.values.byteOffset, sp.count, dtype, ncomp, f"{what} sparse values")
        if idx.size and idx.max() >= acc.count:
            raise GltfError(f"{path}: {what} sparse index {idx.max()} >= count {acc.count}")
        out = out.copy()
        out[idx.astype(np.int64)] = vals
    if acc.normalized and acc.componentType in _NORM:
        return np.maximum(out.astype(np.float64) / _NORM[acc.componentType], -1.0)
    return out.astype(np.float64) if dtype == np.float32 else out.astype(np.int64)


def read_rig(path, mesh: int | None = None) -> Rig:
    """Read a blendshape rig from a glTF 2.0 file (``.glb`` or ``.gltf``).

    The rig is the first mesh with morph targets (or ``mesh``); all its triangle primitives
    are merged. Shape names come from ``mesh.extras.targetNames`` (the de-facto convention
    three.js and Blender use), else ``target_<k>``. glTF is metres, +Y up, so no conversion.

    Raises
    ------
    FileNotFoundError, GltfError (a ValueError) naming the file and field.
    """
    path = Path(path)
    gltf = _load(path)
    if not gltf.meshes:
        raise GltfError(f"{path}: no meshes")
    if mesh is None:
        mesh = next((i for i, m in enumerate(gltf.meshes) if any(p.targets for p in m.primitives)), 0)
    m = gltf.meshes[mesh]
    positions, faces, deltas, uvs = [], [], [], []
    offset = 0
    n_targets = None
    for pi, prim in enumerate(m.primitives):
        if prim.mode not in (None, 4):
            continue  # points/lines are not part of a face rig
        what = f"meshes[{mesh}].primitives[{pi}]"
        if prim.attributes.POSITION is None:
            raise GltfError(f"{path}: {what} has no POSITION attribute")
        pos = read_accessor(gltf, path, prim.attributes.POSITION, f"{what}.POSITION")
        V = len(pos)
        if prim.indices is not None:
            idx = read_accessor(gltf, path, prim.indices, f"{what}.indices").reshape(-1)
        else:
            idx = np.arange(V)
        if idx.size % 3:
            raise GltfError(f"{path}: {what}.indices has {idx.size} entries, not a multiple of 3")
        if idx.size and idx.max() >= V:
            raise GltfError(f"{path}: {what}.indices reference vertex {idx.max()} but POSITION has {V}")
        targets = prim.targets or []
        if n_targets is None:
            n_targets = len(targets)
        elif n_targets != len(targets):
            raise GltfError(f"{path}: {what} has {len(targets)} morph targets, the first primitive {n_targets}")
        d = np.zeros((len(targets), V, 3))
        for k, t in enumerate(targets):
            if "POSITION" not in t:
                continue
            dk = read_accessor(gltf, path, t["POSITION"], f"{what}.targets[{k}].POSITION")
            if dk.shape != (V, 3):
                raise GltfError(f"{path}: {what}.targets[{k}].POSITION has {len(dk)} vertices, the mesh has {V}")
            d[k] = dk
        tex = getattr(prim.attributes, "TEXCOORD_0", None)
        uvs.append(read_accessor(gltf, path, tex, f"{what}.TEXCOORD_0") if tex is not None else None)
        positions.append(pos)
        faces.append(idx.reshape(-1, 3) + offset)
        deltas.append(d)
        offset += V
    if not positions:
        raise GltfError(f"{path}: meshes[{mesh}] has no triangle primitives")
    extras = m.extras if isinstance(m.extras, dict) else {}
    names = extras.get("targetNames")
    if names is None:
        names = [f"target_{k}" for k in range(n_targets)]
    if len(names) != n_targets:
        raise GltfError(f"{path}: meshes[{mesh}].extras.targetNames has {len(names)} names for {n_targets} morph targets")
    other = {k: v for k, v in extras.items() if k != "targetNames"}
    return Rig(
        neutral=np.concatenate(positions),
        faces=np.concatenate(faces),
        deltas=np.concatenate(deltas, axis=1),
        names=names,
        uvs=np.concatenate(uvs) if all(u is not None for u in uvs) else None,
        units="m",
        name=path.stem,
        extras=other,
    )
