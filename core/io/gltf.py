"""glTF 2.0 / GLB rigs: mesh + morph targets + ``targetNames`` in, rig + weight animation out.

pygltflib parses the JSON into objects; trimesh does not read morph targets, so accessor
decoding (strides, sparse accessors, normalised integers) is written here against the glTF 2.0
spec §3.6 (accessors), §3.7.2.2 (morph targets) and §3.11 (animations). The GLB container
(§4.4: 12-byte header, JSON chunk, BIN chunk) is split here too rather than by pygltflib,
because pygltflib reports a truncated or foreign file as a bare ``struct.error`` and cannot
say which part of the file is missing.

What :func:`write_rig` writes (and :func:`read_rig` / :func:`read_animation` /
:func:`read_markers` read back):

* one scene, one node (``nodes[0]``, named after the rig) holding one mesh with one triangle
  primitive: ``POSITION`` (float32, min/max), ``NORMAL`` (float32 unit, optional),
  ``TEXCOORD_0`` when the rig has UVs, ``indices`` (uint32), and one morph target per shape
  with ``POSITION`` deltas (float32, min/max) and ``NORMAL`` deltas when normals are written;
* ``mesh.weights`` (zeros) and ``mesh.extras.targetNames`` (the convention three.js and
  Blender read); every other key of ``rig.extras`` goes to ``mesh.extras`` unchanged
  (numpy arrays as JSON lists), e.g. ICT's ``upstreamVertexIndex``;
* with ``weights``: ``animations[0]`` with one LINEAR sampler (input: float32 seconds,
  output: T*K float32 weights, frame-major) and one channel ``{node: 0, path: "weights"}``;
  with reduced keys (:func:`core.controls.reduce_keys`) the sampler holds only the key times,
  LINEAR or CUBICSPLINE (output 3*T*K floats: per key the in-tangents, values and
  out-tangents of all targets). glTF animates a node's morph weights through one sampler, so
  one time grid for all targets: per-curve keys are written on the union of their times
  (:meth:`core.controls.Keys.grid`, which reproduces each curve exactly), or reduced jointly
  (``reduce_keys(..., shared=True)``, the fewest keys of one grid);
* with ``markers``: ``mesh.extras.markerLayout = {"rig", "names", "vertices" (M x 3 ints),
  "weights" (M x 3 barycentric), "extras"}`` so a marker layout travels with its rig. The key
  ``markerLayout`` is reserved: :func:`read_rig` leaves it out of ``Rig.extras``.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from pathlib import Path
from typing import Optional

import numpy as np
import pygltflib

from .. import geometry
from ..model import MarkerLayout, Performance, Rig
from .tabular import estimate_fps

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_NORM = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_INDEX_TYPES = (5121, 5123, 5125)

_GLB_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_FLOAT, _UINT = 5126, 5125

#: mesh.extras keys this module manages; they never end up in ``Rig.extras``
_RESERVED_EXTRAS = ("targetNames", "markerLayout")
#: suffixes :func:`read_rig` reads: glTF, and VRM (0.x and 1.0), which is a GLB by its specification
RIG_SUFFIXES = (".glb", ".gltf", ".vrm")
_MESHOPT = "EXT_meshopt_compression"
_DRACO = "KHR_draco_mesh_compression"


class GltfError(ValueError):
    """A glTF file that cannot be read as a rig; the message names file and field."""


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------


def _split_container(path: Path, data: bytes) -> tuple[bytes, Optional[bytes]]:
    """(JSON bytes, BIN chunk or None) of a GLB (glTF 2.0 §4.4) or a .gltf JSON file."""
    if not data:
        raise GltfError(f"{path}: file is empty (0 bytes), expected a GLB or glTF JSON")
    if data[:4] == _GLB_MAGIC:
        if len(data) < 12:
            raise GltfError(f"{path}: GLB header is {len(data)} bytes, expected 12 (truncated file)")
        _, version, length = struct.unpack_from("<4sII", data)
        if version != 2:
            raise GltfError(f"{path}: GLB header version is {version}, expected 2")
        if length > len(data):
            raise GltfError(f"{path}: GLB header length says {length} bytes but the file has {len(data)} (truncated file)")
        chunks, offset = [], 12
        while offset < length:
            if offset + 8 > length:
                raise GltfError(f"{path}: GLB chunk {len(chunks)} header at byte {offset} is cut off (truncated or corrupt file)")
            clen, ctype = struct.unpack_from("<II", data, offset)
            if offset + 8 + clen > length:
                raise GltfError(
                    f"{path}: GLB chunk {len(chunks)} at byte {offset} says {clen} bytes, only "
                    f"{length - offset - 8} remain (truncated or corrupt file)"
                )
            chunks.append((ctype, data[offset + 8 : offset + 8 + clen]))
            offset += 8 + clen
        if not chunks or chunks[0][0] != _CHUNK_JSON:
            raise GltfError(f"{path}: GLB chunk 0 must be the JSON chunk (type 0x4E4F534A)")
        blob = next((c for t, c in chunks[1:] if t == _CHUNK_BIN), None)
        return chunks[0][1], blob
    if data.lstrip()[:1] != b"{":
        raise GltfError(
            f"{path}: not a glTF file: expected a GLB (starting with b'glTF') or glTF JSON (starting with '{{'), got {data[:8]!r}"
        )
    return data, None


def _load(path: Path):
    """Parse ``path`` into a pygltflib.GLTF2 whose binary blob is the GLB BIN chunk."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise GltfError(f"{path}: is a directory, expected a .glb or .gltf file")
    data = path.read_bytes()
    text, blob = _split_container(path, data)
    part = "GLB JSON chunk" if data[:4] == _GLB_MAGIC else "JSON"
    try:
        text = text.decode("utf-8")
        doc = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GltfError(f"{path}: {part} is not valid UTF-8 JSON ({e}; truncated or corrupt file?)") from None
    if not isinstance(doc, dict):
        raise GltfError(f"{path}: {part} must be a JSON object, got {type(doc).__name__}")
    asset = doc.get("asset")
    version = str(asset.get("version", "")) if isinstance(asset, dict) else ""
    if not version.startswith("2."):
        raise GltfError(f"{path}: asset.version is {version!r}, expected '2.0' (only glTF 2.0 is read)")
    try:
        gltf = pygltflib.GLTF2.gltf_from_json(text)  # pygltflib's own path; from_dict leaves attributes as dicts
    except Exception as e:  # dataclasses_json raises a zoo of types on malformed fields
        raise GltfError(f"{path}: not a readable glTF 2.0 document ({type(e).__name__}: {e})") from None
    if blob is not None:
        gltf.set_binary_blob(blob)
    gltf._face_retarget_buffers = {}  # decoded buffers, so a data: URI is decoded once per read
    return gltf


def _item(seq, index, path: Path, field: str):
    if seq is None or not isinstance(index, int) or not 0 <= index < len(seq):
        n = 0 if seq is None else len(seq)
        raise GltfError(f"{path}: {field} refers to index {index}, but the file has {n}")
    return seq[index]


def _buffer_bytes(gltf, path: Path, index: int) -> bytes:
    cache = getattr(gltf, "_face_retarget_buffers", None)
    if cache is not None and index in cache:
        return cache[index]
    buf = _item(gltf.buffers, index, path, "bufferView.buffer (buffers)")
    if buf.uri is None and _ext(buf, _MESHOPT).get("fallback"):
        raise GltfError(f"{path}: buffers[{index}] is the placeholder of {_MESHOPT} compressed data (no bytes of its "
                        "own), and a bufferView reads it directly")
    if buf.uri is None:
        if index != 0:
            raise GltfError(f"{path}: buffers[{index}] has no uri; only buffers[0] can be a GLB's BIN chunk")
        data = gltf.binary_blob()
        if data is None:
            raise GltfError(f"{path}: buffers[{index}] has no uri and the file has no BIN chunk (truncated GLB?)")
    elif buf.uri.startswith("data:"):
        head, _, payload = buf.uri.partition(",")
        if not head.endswith(";base64"):
            raise GltfError(f"{path}: buffers[{index}].uri is a data URI without ';base64'")
        try:
            data = base64.b64decode(payload, validate=True)
        except ValueError as e:
            raise GltfError(f"{path}: buffers[{index}].uri is not valid base64 ({e})") from None
    else:
        f = path.parent / buf.uri
        if not f.exists():
            raise GltfError(f"{path}: buffers[{index}].uri {buf.uri!r} not found next to the file")
        data = f.read_bytes()
    if buf.byteLength is None or len(data) < buf.byteLength:
        raise GltfError(f"{path}: buffers[{index}] holds {len(data)} bytes, byteLength says {buf.byteLength} (truncated file?)")
    if cache is not None:
        cache[index] = data
    return data


def _ext(obj, name: str) -> dict:
    ext = getattr(obj, "extensions", None)
    ext = ext.get(name) if isinstance(ext, dict) else None
    return ext if isinstance(ext, dict) else {}


def _meshopt_view(gltf, path: Path, bv_index: int, ext: dict) -> bytes:
    """The bytes of an EXT_meshopt_compression bufferView, decoded (the extension's spec:
    ``buffer``/``byteOffset``/``byteLength`` of the compressed stream, ``count`` elements of
    ``byteStride`` bytes, ``mode`` ATTRIBUTES/TRIANGLES/INDICES, ``filter``). Decoding is
    meshoptimizer's codec, through the optional ``meshopt`` package (no pure-Python decoder
    exists, and the codec is not one to write again)."""
    cache = getattr(gltf, "_face_retarget_buffers", None)
    key = ("meshopt", bv_index)
    if cache is not None and key in cache:
        return cache[key]
    try:
        import meshopt
    except ImportError:
        raise GltfError(f"{path}: bufferViews[{bv_index}] is compressed with {_MESHOPT}; decoding it needs the optional "
                        "package meshopt (pip install 'face-retarget[meshopt]'), or export the file without meshopt "
                        "compression") from None
    where = f"bufferViews[{bv_index}].extensions.{_MESHOPT}"
    try:
        src_index, count, stride = int(ext["buffer"]), int(ext["count"]), int(ext["byteStride"])
        start, length = int(ext.get("byteOffset", 0)), int(ext["byteLength"])
        mode, filt = str(ext.get("mode", "ATTRIBUTES")), str(ext.get("filter", "NONE"))
    except (KeyError, TypeError, ValueError) as e:
        raise GltfError(f"{path}: {where} lacks or garbles {e}; expected buffer, byteLength, byteStride, count, mode") from None
    src = _buffer_bytes(gltf, path, src_index)
    if start < 0 or start + length > len(src):
        raise GltfError(f"{path}: {where} reads bytes {start}..{start + length} of buffers[{src_index}], "
                        f"which has {len(src)} (truncated file?)")
    try:
        out = meshopt.decode_gltf_buffer(src[start:start + length], count, stride, mode, filt).tobytes()
    except (ValueError, RuntimeError) as e:
        raise GltfError(f"{path}: {where} does not decode ({e}; corrupt file?)") from None
    if cache is not None:
        cache[key] = out
    return out


def _view(gltf, path, bv_index: int, offset: int, count: int, dtype, ncomp: int, what: str) -> np.ndarray:
    bv = _item(gltf.bufferViews, bv_index, path, f"{what}.bufferView (bufferViews)")
    ext = _ext(bv, _MESHOPT)
    if ext:
        data, base = _meshopt_view(gltf, path, bv_index, ext), 0
        if bv.byteLength is None or len(data) < bv.byteLength:
            raise GltfError(f"{path}: bufferViews[{bv_index}] decodes to {len(data)} bytes, byteLength says {bv.byteLength}")
    else:
        data, base = _buffer_bytes(gltf, path, bv.buffer), bv.byteOffset or 0
    itemsize = np.dtype(dtype).itemsize * ncomp
    stride = bv.byteStride or itemsize
    start = base + (offset or 0)
    need = start + (count - 1) * stride + itemsize if count else start
    if bv.byteLength is None or base + bv.byteLength > len(data):
        raise GltfError(f"{path}: bufferViews[{bv_index}] (used by {what}) extends past the end of buffers[{bv.buffer}]")
    if need > base + bv.byteLength:
        raise GltfError(f"{path}: {what} reads past the end of bufferViews[{bv_index}] (truncated or corrupt file)")
    raw = np.frombuffer(data, dtype=np.uint8, count=need - start, offset=start)
    if stride == itemsize:
        return raw.view(dtype).reshape(count, ncomp).copy()
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, itemsize), strides=(stride, 1))
    return rows.copy().view(dtype).reshape(count, ncomp)


def read_accessor(gltf, path: Path, index: int, what: str = "accessor") -> np.ndarray:
    """Decode accessor ``index`` to a (count, ncomp) float64/int64 array (glTF 2.0 §3.6).

    float32 data comes back as float64 (exactly), normalised integers as float64 in [-1, 1]
    (§3.11 "normalized"), other integers as int64.

    Raises
    ------
    GltfError naming the file, ``what`` (e.g. ``meshes[0].primitives[0].POSITION``) and the
    accessor/bufferView that is missing, unknown or too short.
    """
    acc = _item(gltf.accessors, index, path, f"{what} (accessors)")
    dtype = _COMPONENT.get(acc.componentType)
    if dtype is None:
        raise GltfError(f"{path}: accessors[{index}] ({what}) has unknown componentType {acc.componentType}")
    ncomp = _NCOMP.get(acc.type)
    if ncomp is None:
        raise GltfError(f"{path}: accessors[{index}] ({what}) has unknown type {acc.type!r}, expected one of {sorted(_NCOMP)}")
    if not isinstance(acc.count, int) or acc.count < 0:
        raise GltfError(f"{path}: accessors[{index}] ({what}) has invalid count {acc.count!r}")
    if acc.bufferView is None:
        out = np.zeros((acc.count, ncomp), dtype=dtype)
    else:
        out = _view(gltf, path, acc.bufferView, acc.byteOffset, acc.count, dtype, ncomp, f"accessors[{index}] ({what})")
    if acc.sparse is not None and acc.sparse.count:
        sp = acc.sparse
        itype = _COMPONENT.get(sp.indices.componentType)
        if sp.indices.componentType not in _INDEX_TYPES:
            raise GltfError(f"{path}: accessors[{index}] ({what}).sparse.indices.componentType {sp.indices.componentType} is not an unsigned int type")
        idx = _view(gltf, path, sp.indices.bufferView, sp.indices.byteOffset, sp.count, itype, 1, f"{what} sparse indices")[:, 0]
        vals = _view(gltf, path, sp.values.bufferView, sp.values.byteOffset, sp.count, dtype, ncomp, f"{what} sparse values")
        if idx.size and idx.max() >= acc.count:
            raise GltfError(f"{path}: {what} sparse index {idx.max()} >= count {acc.count}")
        out = out.copy()
        out[idx.astype(np.int64)] = vals
    if acc.normalized and acc.componentType in _NORM:
        return np.maximum(out.astype(np.float64) / _NORM[acc.componentType], -1.0)
    return out.astype(np.float64) if dtype == np.float32 else out.astype(np.int64)


def _mesh_index(gltf, path: Path, mesh: Optional[int]) -> int:
    if not gltf.meshes:
        raise GltfError(f"{path}: meshes: the file has no meshes")
    if mesh is None:
        return next((i for i, m in enumerate(gltf.meshes) if any(p.targets for p in m.primitives)), 0)
    _item(gltf.meshes, mesh, path, "mesh argument (meshes)")
    return mesh


def _mesh_extras(gltf, mesh: int) -> dict:
    extras = gltf.meshes[mesh].extras
    return extras if isinstance(extras, dict) else {}


def _n_targets(gltf, path: Path, mesh: int) -> int:
    counts = {len(p.targets or []) for p in gltf.meshes[mesh].primitives if p.mode in (None, 4)}
    if len(counts) > 1:
        raise GltfError(f"{path}: meshes[{mesh}].primitives have different numbers of morph targets {sorted(counts)}")
    return counts.pop() if counts else 0


def _stored_target_names(gltf, mesh: int):
    """(names, where) as the file stores them, or (None, None): ``mesh.extras.targetNames`` (three.js,
    Blender), else ``primitives[j].extras.targetNames`` (UniVRM since 0.36, so VRM 0.x avatars),
    else ``primitives[j].targets[k].extras.name`` (UniVRM before 0.36)."""
    names = _mesh_extras(gltf, mesh).get("targetNames")
    if names is not None:
        return names, f"meshes[{mesh}].extras.targetNames"
    prims = [(j, p) for j, p in enumerate(gltf.meshes[mesh].primitives) if p.mode in (None, 4) and p.targets]
    for j, p in prims:
        names = p.extras.get("targetNames") if isinstance(p.extras, dict) else None
        if names is not None:
            return names, f"meshes[{mesh}].primitives[{j}].extras.targetNames"
    for j, p in prims:
        old = [t.get("extras", {}).get("name") if isinstance(t, dict) and isinstance(t.get("extras"), dict) else None
               for t in p.targets]
        if all(isinstance(n, str) for n in old):
            return old, f"meshes[{mesh}].primitives[{j}].targets[*].extras.name"
    return None, None


def _target_names(gltf, path: Path, mesh: int, n_targets: int) -> list:
    names, where = _stored_target_names(gltf, mesh)
    if names is None:
        return [f"target_{k}" for k in range(n_targets)]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise GltfError(f"{path}: {where} must be a list of strings")
    if len(names) != n_targets:
        raise GltfError(f"{path}: {where} has {len(names)} names for {n_targets} morph targets")
    return names


def _node_matrix(node) -> np.ndarray:
    """The node's local 4x4 transform (glTF 2.0 §3.5.3: ``matrix``, column-major, or T * R * S)."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T
    M = np.eye(4)
    if node.scale is not None:
        M = np.diag([*map(float, node.scale), 1.0])
    if node.rotation is not None:
        x, y, z, w = map(float, node.rotation)
        n = np.sqrt(x * x + y * y + z * z + w * w) or 1.0
        x, y, z, w = x / n, y / n, z / n, w / n
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        M = np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]) @ M
    if node.translation is not None:
        M[:3, 3] = np.asarray(node.translation, dtype=np.float64)
    return M


def _world_matrices(gltf) -> dict:
    """{node index: world 4x4} for every node reachable from a root (a node no node lists as child)."""
    nodes = gltf.nodes or []
    children = {c for n in nodes for c in (n.children or []) if isinstance(c, int)}
    out, stack = {}, [(i, np.eye(4)) for i in range(len(nodes)) if i not in children]
    while stack:
        i, parent = stack.pop()
        if i in out or not 0 <= i < len(nodes):
            continue  # a cycle or a bad child index: the node is placed once, where first reached
        out[i] = parent @ _node_matrix(nodes[i])
        stack.extend((c, out[i]) for c in (nodes[i].children or []) if isinstance(c, int))
    return out


def _placement(gltf, path: Path, mesh: int, worlds: dict, node: Optional[int] = None):
    """How mesh ``mesh`` sits in the scene, on ``node`` (default: the first node in the scene
    that holds it): (node index or None, 4x4 or None for skinned).

    A mesh on a node without a skin is placed by the node's world matrix (glTF 2.0 §3.5.3);
    a skinned mesh ignores its node's transform (§3.7.3.1) and is placed by its joints at
    rest, which :func:`_read_mesh` applies per vertex. A mesh no node uses is left as it is.
    """
    if node is None:
        node = next((i for i, n in enumerate(gltf.nodes or []) if n.mesh == mesh and i in worlds), None)
    if node is None:
        return None, np.eye(4)
    return node, (None if gltf.nodes[node].skin is not None else worlds[node])


def _skin_matrices(gltf, path: Path, node: int, worlds: dict) -> np.ndarray:
    """(J, 4, 4) ``world(joint_j) @ inverseBind_j`` of the node's skin: its joints at rest."""
    skin = _item(gltf.skins, gltf.nodes[node].skin, path, f"nodes[{node}].skin (skins)")
    J = len(skin.joints or [])
    if skin.inverseBindMatrices is None:
        ibm = np.broadcast_to(np.eye(4), (J, 4, 4))
    else:
        ibm = read_accessor(gltf, path, skin.inverseBindMatrices, f"skins[{gltf.nodes[node].skin}].inverseBindMatrices")
        if ibm.shape != (J, 16):
            raise GltfError(f"{path}: skins[{gltf.nodes[node].skin}].inverseBindMatrices has {len(ibm)} MAT4, "
                            f"the skin has {J} joints")
        ibm = ibm.reshape(J, 4, 4).transpose(0, 2, 1)
    return np.stack([worlds.get(j, np.eye(4)) @ ibm[k] for k, j in enumerate(skin.joints or [])]) if J else np.eye(4)[None]


def _read_mesh(gltf, path: Path, mesh: int, n_targets: int, worlds: dict, node: Optional[int] = None):
    """(positions (V, 3), faces (F, 3), deltas (K, V, 3), uvs (V, 2) or None) of ``meshes[mesh]``'s
    triangle primitives, placed in the scene (:func:`_placement`, on ``node``): ``p' = A p + t``
    and ``d' = A d`` (a delta moves with the linear part only); a skinned mesh by linear blend
    skinning at rest, ``A = sum_j w_j world(joint_j) inverseBind_j`` per vertex. A mirroring
    placement (``det A < 0``, e.g. one eye mesh on two nodes, one scaled by -1) reverses the
    winding (§3.7.4), so the faces keep facing out.

    Quantised attributes (KHR_mesh_quantization: int8/int16 POSITION and targets, normalised or
    not) are read as numbers; the transform that dequantises them is the node's (or the skin's),
    which the placement applies.
    """
    m = gltf.meshes[mesh]
    node, world = _placement(gltf, path, mesh, worlds, node)
    skins = _skin_matrices(gltf, path, node, worlds) if node is not None and world is None else None
    positions, faces, deltas, uvs = [], [], [], []
    offset = 0
    for pi, prim in enumerate(m.primitives):
        if prim.mode not in (None, 4):
            continue  # points/lines/strips are not part of a face rig
        what = f"meshes[{mesh}].primitives[{pi}]"
        if prim.attributes.POSITION is None:
            raise GltfError(f"{path}: {what} has no POSITION attribute")
        pos_acc = _item(gltf.accessors, prim.attributes.POSITION, path, f"{what}.attributes.POSITION (accessors)")
        if pos_acc.bufferView is None and _ext(prim, _DRACO):
            raise GltfError(f"{path}: {what} is Draco-compressed ({_DRACO}), which this reader does not decode; "
                            "export the avatar without Draco mesh compression")
        pos = read_accessor(gltf, path, prim.attributes.POSITION, f"{what}.attributes.POSITION").astype(np.float64)
        if pos.shape[1] != 3:
            raise GltfError(f"{path}: {what}.attributes.POSITION must be a VEC3 accessor, got {pos.shape[1]} components")
        V = len(pos)
        if prim.indices is not None:
            idx = read_accessor(gltf, path, prim.indices, f"{what}.indices")
            if idx.shape[1] != 1 or gltf.accessors[prim.indices].componentType not in _INDEX_TYPES:
                raise GltfError(f"{path}: {what}.indices must be an unsigned-int SCALAR accessor")
            idx = idx.reshape(-1)
        else:
            idx = np.arange(V)
        if idx.size % 3:
            raise GltfError(f"{path}: {what}.indices has {idx.size} entries, not a multiple of 3")
        if idx.size and idx.max() >= V:
            raise GltfError(f"{path}: {what}.indices reference vertex {idx.max()} but POSITION has {V} vertices")
        d = np.zeros((n_targets, V, 3))
        for k, t in enumerate(prim.targets or []):
            if not isinstance(t, dict) or "POSITION" not in t:
                continue  # a target may move only normals; its position delta is zero
            dk = read_accessor(gltf, path, t["POSITION"], f"{what}.targets[{k}].POSITION")
            if dk.shape != (V, 3):
                raise GltfError(f"{path}: {what}.targets[{k}].POSITION has {len(dk)} vertices, POSITION has {V}")
            d[k] = dk
        tri = idx.reshape(-1, 3)
        if skins is not None:
            A = _blend_skin(gltf, path, prim, what, skins, V)
            pos = np.einsum("vij,vj->vi", A[:, :3, :3], pos) + A[:, :3, 3]
            d = np.einsum("vij,kvj->kvi", A[:, :3, :3], d)
            flip = np.linalg.det(A[0, :3, :3]) < 0 if V else False
        else:
            if world is not None and not np.array_equal(world, np.eye(4)):
                pos = pos @ world[:3, :3].T + world[:3, 3]
                d = d @ world[:3, :3].T
            flip = world is not None and np.linalg.det(world[:3, :3]) < 0
        if flip:
            tri = tri[:, ::-1]
        tex = getattr(prim.attributes, "TEXCOORD_0", None)
        uv = read_accessor(gltf, path, tex, f"{what}.attributes.TEXCOORD_0") if tex is not None else None
        if uv is not None and uv.shape != (V, 2):
            raise GltfError(f"{path}: {what}.attributes.TEXCOORD_0 has shape {uv.shape}, expected ({V}, 2)")
        uvs.append(None if uv is None else uv.astype(np.float64))
        positions.append(pos)
        faces.append(tri + offset)
        deltas.append(d)
        offset += V
    if not positions:
        raise GltfError(f"{path}: meshes[{mesh}] has no triangle primitives")
    return (np.concatenate(positions), np.concatenate(faces), np.concatenate(deltas, axis=1),
            np.concatenate(uvs) if all(u is not None for u in uvs) else None)


def _blend_skin(gltf, path: Path, prim, what: str, skins: np.ndarray, V: int) -> np.ndarray:
    """(V, 4, 4) per-vertex ``sum_j w_j M_j`` from JOINTS_0/WEIGHTS_0 (one M for all when the
    joints at rest all agree, as in most exports, where it is the identity)."""
    if np.allclose(skins, skins[0], atol=1e-9):
        return np.broadcast_to(skins[0], (V, 4, 4))
    ja, wa = getattr(prim.attributes, "JOINTS_0", None), getattr(prim.attributes, "WEIGHTS_0", None)
    if ja is None or wa is None:
        raise GltfError(f"{path}: {what} is skinned but has no JOINTS_0/WEIGHTS_0")
    joints = read_accessor(gltf, path, ja, f"{what}.attributes.JOINTS_0")
    weights = read_accessor(gltf, path, wa, f"{what}.attributes.WEIGHTS_0").astype(np.float64)
    if joints.shape != (V, 4) or weights.shape != (V, 4) or joints.max(initial=0) >= len(skins):
        raise GltfError(f"{path}: {what}.attributes.JOINTS_0/WEIGHTS_0 must be ({V}, 4) with joints below {len(skins)}")
    total = weights.sum(axis=1, keepdims=True)
    weights = np.where(total > 0, weights / np.where(total > 0, total, 1), 0.25)
    return np.einsum("vk,vkij->vij", weights, skins[joints])


def _mesh_size(gltf, mesh: int) -> int:
    return sum(gltf.accessors[p.attributes.POSITION].count for p in gltf.meshes[mesh].primitives
               if p.mode in (None, 4) and p.attributes.POSITION is not None
               and isinstance(p.attributes.POSITION, int) and 0 <= p.attributes.POSITION < len(gltf.accessors or []))


def _target_count(gltf, mesh: int) -> int:
    return max((len(p.targets or []) for p in gltf.meshes[mesh].primitives), default=0)


def _face_meshes(gltf, path: Path, worlds: dict) -> list:
    """``[(mesh, node or None), ...]`` that make the face rig when no ``mesh`` is given: the mesh
    with the most morph targets, the largest of those (the head: not a body mesh with a breathing
    shape of its own, not an eye with the head's names), then every other placed mesh with named targets
    all of which the head also has (teeth, eyes, lashes of a Ready Player Me or VRoid avatar: one
    weight moves them together), once per node that holds it (one eye mesh on two nodes is two eyes)."""
    morphs = [i for i, m in enumerate(gltf.meshes) if any(p.targets for p in m.primitives)]
    placed = [(n.mesh, i) for i, n in enumerate(gltf.nodes or [])
              if i in worlds and isinstance(n.mesh, int) and n.mesh in morphs]
    if not placed:  # meshes no scene node holds: the largest, where it is
        if not morphs:
            return [(0, None)]
        return [(max(morphs, key=lambda i: (_target_count(gltf, i), _mesh_size(gltf, i), -i)), None)]
    head = max(placed, key=lambda mn: (_target_count(gltf, mn[0]), _mesh_size(gltf, mn[0]), -mn[0], -mn[1]))
    names = _stored_target_names(gltf, head[0])[0]
    if not isinstance(names, list):
        return [head]
    group = [head]
    for m, n in placed:
        other = _stored_target_names(gltf, m)[0]
        if m != head[0] and isinstance(other, list) and other and len(set(other)) == len(other) and set(other) <= set(names):
            group.append((m, n))
    return group


def read_rig(path, mesh: int | None = None) -> Rig:
    """Read a blendshape rig from a glTF 2.0 file (``.glb`` or ``.gltf``).

    The rig is ``meshes[mesh]``, or by default the face: the mesh with the most morph targets
    (the largest of those) and every other mesh whose named targets all appear in its names (a Ready Player Me avatar's
    ``Wolf3D_Head`` with ``Wolf3D_Teeth``, ``EyeLeft`` and ``EyeRight``, which share the 67 names),
    merged, each target of a smaller mesh added to its namesake (zero where it has none). All
    triangle primitives of a mesh are merged. Shape names come from ``mesh.extras.targetNames``
    (the de-facto convention three.js and Blender use), else a primitive's ``extras.targetNames``
    (UniVRM's, so VRM 0.x avatars) or its targets' ``extras.name`` (UniVRM before 0.36), else
    ``target_<k>``. Meshes are placed
    as the scene places them (node world matrices; a skinned mesh by its joints at rest), which
    also dequantises KHR_mesh_quantization attributes. glTF is metres, +Y up, so no unit
    conversion. ``mesh.extras`` of the (first) mesh other than ``targetNames`` and
    ``markerLayout`` become ``Rig.extras``; with several meshes ``Rig.extras["meshes"]`` lists
    each one's ``{"mesh", "node", "name", "vertices": [first, stop)}`` (a mesh on two nodes, such as
    one eye mesh placed twice, is there twice).

    Parameters
    ----------
    path : str or Path
    mesh : int, optional
        Index into ``meshes``: that mesh alone.

    Returns
    -------
    Rig with neutral (V, 3), faces (F, 3), deltas (K, V, 3) as float64 copies of the file's
    values (float32 in the file round-trips exactly).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    GltfError (a ValueError)
        Naming the file and the field: truncated GLB, not glTF, a compression extension this
        reader does not decode, a morph target whose vertex count differs from POSITION, a
        ``targetNames`` count mismatch, indices out of range ...
    """
    path = Path(path)
    gltf = _load(path)
    worlds = _world_matrices(gltf)
    if mesh is None:
        if not gltf.meshes:
            raise GltfError(f"{path}: meshes: the file has no meshes")
        group = _face_meshes(gltf, path, worlds)
    else:
        group = [(_mesh_index(gltf, path, mesh), None)]
    head, head_node = group[0]
    n_targets = _n_targets(gltf, path, head)
    names = _target_names(gltf, path, head, n_targets)
    neutral, faces, deltas, uvs = _read_mesh(gltf, path, head, n_targets, worlds, head_node)
    other = {k: v for k, v in _mesh_extras(gltf, head).items() if k not in _RESERVED_EXTRAS}
    if len(group) > 1:
        parts, spans = [(neutral, faces, deltas, uvs)], [(head, head_node, 0, len(neutral))]
        at = {n: k for k, n in enumerate(names)}
        V = len(neutral)
        for i, node in group[1:]:
            k_i = _n_targets(gltf, path, i)
            p, f, d, u = _read_mesh(gltf, path, i, k_i, worlds, node)
            full = np.zeros((n_targets, len(p), 3))
            full[[at[n] for n in _target_names(gltf, path, i, k_i)]] = d
            parts.append((p, f + V, full, u))
            spans.append((i, node, V, V + len(p)))
            V += len(p)
        neutral = np.concatenate([q[0] for q in parts])
        faces = np.concatenate([q[1] for q in parts])
        deltas = np.concatenate([q[2] for q in parts], axis=1)
        uvs = np.concatenate([q[3] for q in parts]) if all(q[3] is not None for q in parts) else None
        other["meshes"] = [{"mesh": int(i), "node": int(n), "name": gltf.meshes[i].name or f"mesh_{i}", "vertices": [a, b]}
                           for i, n, a, b in spans]
    try:
        return Rig(neutral=neutral, faces=faces, deltas=deltas, names=names, uvs=uvs, units="m",
                   name=path.stem, extras=other)
    except ValueError as e:  # NaN positions, duplicate names ...
        raise GltfError(f"{path}: meshes[{head}]: {e}") from None


def read_markers(path, mesh: int | None = None) -> Optional[MarkerLayout]:
    """The marker layout stored by :func:`write_rig` in ``mesh.extras.markerLayout``.

    Returns None when the file has none. Raises GltfError naming the file and the field
    when the layout is malformed or indexes vertices the mesh does not have.
    """
    path = Path(path)
    gltf = _load(path)
    mesh = _mesh_index(gltf, path, mesh)
    doc = _mesh_extras(gltf, mesh).get("markerLayout")
    if doc is None:
        return None
    field = f"meshes[{mesh}].extras.markerLayout"
    if not isinstance(doc, dict) or not {"names", "vertices", "weights"} <= set(doc):
        raise GltfError(f"{path}: {field} must be an object with names, vertices, weights")
    try:
        layout = MarkerLayout(doc["names"], np.asarray(doc["vertices"], dtype=np.int64).reshape(-1, 3),
                              np.asarray(doc["weights"], dtype=np.float64).reshape(-1, 3),
                              str(doc.get("rig", "")), dict(doc.get("extras") or {}))
    except (ValueError, TypeError) as e:
        raise GltfError(f"{path}: {field}: {e}") from None
    V = sum(gltf.accessors[p.attributes.POSITION].count for p in gltf.meshes[mesh].primitives
            if p.mode in (None, 4) and p.attributes.POSITION is not None)
    if layout.n_markers and layout.vertices.max() >= V:
        raise GltfError(f"{path}: {field}.vertices index vertex {layout.vertices.max()} but the mesh has {V}")
    return layout


def read_animation(path, animation: int = 0, fps: Optional[float] = None) -> Performance:
    """Morph-weight curves of ``animations[animation]`` as a ``Performance`` of kind "curves".

    The channel whose ``target.path`` is ``"weights"`` and whose node holds a mesh with morph
    targets is read (glTF 2.0 §3.11). Its sampler's input gives ``times`` (seconds, as in the
    file); its output holds T*K weights, frame-major, for LINEAR and STEP, or 3*T*K
    (in-tangent, value, out-tangent) for CUBICSPLINE, of which the values are kept. Channel
    names are the mesh's target names (as :func:`read_rig` reads them).

    Parameters
    ----------
    path : str or Path
    animation : int
        Index into ``animations``.
    fps : float, optional
        Frame rate to record; by default estimated from the times
        (:func:`core.io.tabular.estimate_fps` with ``snap="whole"``); 30 when the animation has
        a single key.

    Returns
    -------
    Performance, kind "curves", data (T, K) float64 (float32 in the file round-trips
    exactly), ``extras["interpolation"]`` the sampler interpolation; for CUBICSPLINE also
    ``extras["in_tangents"]`` and ``extras["out_tangents"]`` (T, K) float64 (per second, as in
    the file), so the curves can be evaluated between keys (:func:`core.controls.evaluate_sampler`).

    Raises
    ------
    FileNotFoundError; GltfError naming the file and the field (no animation, no weights
    channel, output count not T*K, times not increasing, ...).
    """
    path = Path(path)
    gltf = _load(path)
    anims = gltf.animations or []
    anim = _item(anims, animation, path, "animation argument (animations)")
    where = f"animations[{animation}]"
    for ci, ch in enumerate(anim.channels or []):
        tgt = ch.target
        if tgt is None or tgt.path != "weights" or tgt.node is None:
            continue
        node = _item(gltf.nodes, tgt.node, path, f"{where}.channels[{ci}].target.node (nodes)")
        if node.mesh is None:
            raise GltfError(f"{path}: {where}.channels[{ci}] animates weights of nodes[{tgt.node}], which has no mesh")
        mesh = node.mesh
        _item(gltf.meshes, mesh, path, f"nodes[{tgt.node}].mesh (meshes)")
        K = _n_targets(gltf, path, mesh)
        if K == 0:
            raise GltfError(f"{path}: {where}.channels[{ci}] animates weights of meshes[{mesh}], which has no morph targets")
        names = _target_names(gltf, path, mesh, K)
        sampler = _item(anim.samplers, ch.sampler, path, f"{where}.channels[{ci}].sampler ({where}.samplers)")
        sw = f"{where}.samplers[{ch.sampler}]"
        times = read_accessor(gltf, path, sampler.input, f"{sw}.input")
        if times.shape[1] != 1 or times.dtype != np.float64:
            raise GltfError(f"{path}: {sw}.input must be a float SCALAR accessor (seconds)")
        times = times[:, 0]
        if not np.isfinite(times).all() or (np.diff(times) <= 0).any():
            raise GltfError(f"{path}: {sw}.input times must be finite and strictly increasing")
        values = read_accessor(gltf, path, sampler.output, f"{sw}.output").reshape(-1)
        T = len(times)
        interp = sampler.interpolation or "LINEAR"
        per_key = 3 if interp == "CUBICSPLINE" else 1
        if values.size != per_key * T * K:
            raise GltfError(
                f"{path}: {sw}.output has {values.size} values, expected {per_key}*{T} keys*{K} targets = {per_key * T * K} ({interp})"
            )
        data = values.reshape(T, per_key, K)[:, per_key // 2, :].astype(np.float64)
        extras = {"interpolation": interp, "node": int(tgt.node), "mesh": int(mesh)}
        if interp == "CUBICSPLINE":
            tan = values.reshape(T, 3, K).astype(np.float64)
            extras["in_tangents"], extras["out_tangents"] = tan[:, 0].copy(), tan[:, 2].copy()
        if fps is None:
            fps = estimate_fps(times, f"{path}: {sw}.input", snap="whole") if T > 1 else 30.0
        name = anim.name or path.stem
        try:
            return Performance.curves(data, names, fps, times=times, name=name, extras=extras)
        except ValueError as e:
            raise GltfError(f"{path}: {sw}: {e}") from None
    raise GltfError(f"{path}: {where} has no channel with target.path 'weights' on a node with a mesh")


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The ``NORMAL`` glTF stores: :func:`core.geometry.vertex_normals` with a +Z fallback.

    Unit area-weighted vertex normals of (V, 3) or (S, V, 3) positions, float64; a vertex on
    no (or only degenerate) triangles gets +Z, since glTF requires unit normals.
    """
    return geometry.vertex_normals(np.asarray(positions, dtype=np.float64), faces, fallback=(0.0, 0.0, 1.0))


class _Bin:
    """Accumulates the binary buffer, its bufferViews and accessors (glTF 2.0 §3.6)."""

    def __init__(self):
        self.parts: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, type_: str, component: int, target: Optional[int] = None,
            minmax: bool = False) -> int:
        """Append ``array`` (already of the stored dtype) and return its accessor index."""
        raw = np.ascontiguousarray(array).tobytes()
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.parts.append(raw)
        pad = (-len(raw)) % 4  # every accessor starts 4-byte aligned (§3.6.2.4)
        if pad:
            self.parts.append(b"\0" * pad)
        self.length += len(raw) + pad
        self.views.append(view)
        count = len(array) if array.ndim > 1 or type_ != "SCALAR" else array.size
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(count), "type": type_}
        if minmax:
            a = np.asarray(array).reshape(int(count), -1)
            # float32 -> Python float is exact, so the validator's float32 comparison matches
            acc["min"] = [float(x) for x in a.min(0)] if count else []
            acc["max"] = [float(x) for x in a.max(0)] if count else []
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.parts)


def _jsonable(value, where: str):
    """numpy arrays/scalars -> lists/Python numbers for JSON; TypeError naming ``where``."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, where) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (str, bool, int, float)):
        if isinstance(value, float) and not np.isfinite(value):
            raise ValueError(f"{where}: {value} cannot be stored in glTF JSON")
        return value
    raise TypeError(f"{where}: {type(value).__name__} cannot be stored in glTF JSON extras")


def _tangents(tangents, interpolation: str, shape) -> Optional[np.ndarray]:
    """(T, 3, K) float32 sampler output of CUBICSPLINE keys (in-tangent, value slot, out-tangent)."""
    if interpolation == "LINEAR":
        if tangents is not None:
            raise ValueError("tangents: only for interpolation='CUBICSPLINE'")
        return None
    if interpolation != "CUBICSPLINE":
        raise ValueError(f"interpolation: expected 'LINEAR' or 'CUBICSPLINE', got {interpolation!r}")
    if tangents is None or len(tangents) != 2:
        raise ValueError("tangents: CUBICSPLINE needs (in_tangents, out_tangents), each (T, K) per second")
    out = np.empty((shape[0], 3, shape[1]), np.float32)
    for slot, (name, t) in zip((0, 2), zip(("in_tangents", "out_tangents"), tangents)):
        a = np.asarray(t, dtype=np.float64)
        if a.shape != shape:
            raise ValueError(f"tangents: {name} must be {shape} (like the weights), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"tangents: {name} contains NaN/inf")
        out[:, slot] = a
    return out


def _animation_inputs(rig: Rig, weights, fps, times) -> tuple[np.ndarray, np.ndarray]:
    """Validated (weights (T, K) float32, times (T,) float32) for the animation."""
    if isinstance(weights, Performance):
        if weights.kind != "curves":
            raise ValueError(f"weights: a Performance of kind 'curves' is needed, got {weights.kind!r}")
        missing = [n for n in rig.names if n not in weights.names]
        if missing:
            raise ValueError(f"weights: performance {weights.name!r} has no channels {missing} of rig {rig.name!r}")
        if times is None:
            times = weights.times - weights.times[0] if len(weights.times) else weights.times
        weights = weights.select(rig.names).data
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != rig.n_shapes:
        raise ValueError(f"weights: expected shape (T, K) with K={rig.n_shapes} (shapes of rig {rig.name!r}), got {w.shape}")
    if len(w) == 0:
        raise ValueError("weights: need at least one frame")
    if rig.n_shapes == 0:
        raise ValueError(f"weights: rig {rig.name!r} has no shapes to animate")
    if not np.isfinite(w).all():
        bad = np.argwhere(~np.isfinite(w))[0]
        raise ValueError(f"weights: NaN/inf at frame {bad[0]}, shape {rig.names[bad[1]]!r}; fill or drop missing samples first")
    if times is None:
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps: must be positive, got {fps}")
        t = np.arange(len(w)) / float(fps)
    else:
        t = np.asarray(times, dtype=np.float64)
        if t.shape != (len(w),):
            raise ValueError(f"times: expected shape ({len(w)},) to match weights, got {t.shape}")
    t32 = t.astype(np.float32)
    if not np.isfinite(t32).all() or t32[0] < 0 or (np.diff(t32) <= 0).any():
        raise ValueError("times: glTF needs finite seconds >= 0, strictly increasing (also after rounding to float32)")
    return w.astype(np.float32), t32


def write_rig(path, rig: Rig, weights=None, fps: float = 30.0, times=None,
              markers: Optional[MarkerLayout] = None, *, normals: bool = True, interpolation: str = "LINEAR",
              tangents=None) -> Path:
    """Write ``rig`` (and optionally a morph-weight animation) as glTF 2.0.

    The mesh is ``neutral + sum_k w_k deltas[k]`` (glTF 2.0 §3.7.2.2), the layout is given
    in the module docstring. Positions, deltas, UVs, weights and times are stored as float32
    (glTF has no float64); indices as uint32.

    Parameters
    ----------
    path : str or Path
        ``.glb`` writes a binary GLB; ``.gltf`` a JSON file with the buffer embedded as a
        base64 data URI. Written to a temporary file and moved into place.
    rig : Rig
    weights : (T, K) array or Performance of kind "curves", optional
        Weights per frame in ``rig.names`` order (a Performance is matched by channel name;
        its times are used, shifted to start at 0, unless ``times`` is given). Adds
        ``animations[0]`` with a LINEAR sampler targeting ``nodes[0]`` weights.
    fps : float
        Frame rate for the default times ``t = arange(T) / fps``.
    times : (T,) float, optional
        Key times in seconds, >= 0 and strictly increasing.
    markers : MarkerLayout, optional
        Stored in ``mesh.extras.markerLayout``; read back with :func:`read_markers`.
    normals : bool
        Write ``NORMAL`` (unit, area-weighted, see :func:`vertex_normals`) and per-target
        ``NORMAL`` deltas so viewers shade morphed shapes correctly.
    interpolation : {"LINEAR", "CUBICSPLINE"}
        The sampler's interpolation. Reduced keys: ``F, t, V, A, Bt = keys.grid()`` then
        ``write_rig(path, rig, V, times=t, interpolation=keys.interpolation, tangents=(A, Bt))``
        (:meth:`core.controls.Keys.grid`).
    tangents : (in_tangents, out_tangents), each (T, K) float per second, CUBICSPLINE only
        glTF 2.0 Appendix C: on ``[t_k, t_k+1]`` the value is the cubic Hermite of the two
        values, key k's out-tangent and key k+1's in-tangent, times ``t_k+1 - t_k``.

    Returns
    -------
    Path written.

    Raises
    ------
    ValueError
        Naming the argument: unknown suffix, weights not (T, K) or not finite, times not
        increasing, markers indexing vertices the rig lacks, extras not JSON-storable.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise ValueError(f"path: {path} must end in .glb or .gltf")
    if not isinstance(rig, Rig):
        raise TypeError(f"rig: expected a core.model.Rig, got {type(rig).__name__}")
    anim = None if weights is None else _animation_inputs(rig, weights, fps, times)
    cubic = None if anim is None else _tangents(tangents, interpolation, anim[0].shape)
    if markers is not None:
        if not isinstance(markers, MarkerLayout):
            raise TypeError(f"markers: expected a MarkerLayout, got {type(markers).__name__}")
        markers.check(rig)

    b = _Bin()
    attributes = {"POSITION": b.add(rig.neutral.astype(np.float32), "VEC3", _FLOAT, _ARRAY_BUFFER, minmax=True)}
    if normals:
        shapes = np.concatenate([rig.neutral[None], rig.neutral + rig.deltas]) if rig.n_shapes else rig.neutral[None]
        vn = vertex_normals(shapes, rig.faces)
        attributes["NORMAL"] = b.add(vn[0].astype(np.float32), "VEC3", _FLOAT, _ARRAY_BUFFER)
    if rig.uvs is not None:
        attributes["TEXCOORD_0"] = b.add(rig.uvs.astype(np.float32), "VEC2", _FLOAT, _ARRAY_BUFFER)
    prim = {"attributes": attributes, "mode": 4,
            "indices": b.add(rig.faces.reshape(-1).astype(np.uint32), "SCALAR", _UINT, _ELEMENT_ARRAY_BUFFER)}
    targets = []
    for k in range(rig.n_shapes):
        t = {"POSITION": b.add(rig.deltas[k].astype(np.float32), "VEC3", _FLOAT, _ARRAY_BUFFER, minmax=True)}
        if normals:
            t["NORMAL"] = b.add((vn[k + 1] - vn[0]).astype(np.float32), "VEC3", _FLOAT, _ARRAY_BUFFER)
        targets.append(t)
    if targets:
        prim["targets"] = targets

    extras = _jsonable({k: v for k, v in rig.extras.items() if k not in _RESERVED_EXTRAS}, "rig.extras")
    extras["targetNames"] = list(rig.names)
    if markers is not None:
        extras["markerLayout"] = {
            "rig": markers.rig, "names": list(markers.names), "vertices": markers.vertices.tolist(),
            "weights": markers.weights.tolist(), "extras": _jsonable(dict(markers.extras), "markers.extras"),
        }
    mesh = {"name": rig.name, "primitives": [prim], "extras": extras}
    if rig.n_shapes:
        mesh["weights"] = [0.0] * rig.n_shapes
    doc = {
        "asset": {"version": "2.0", "generator": "face-retarget core.io.gltf"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": rig.name, "mesh": 0}],
        "meshes": [mesh],
    }
    if anim is not None:
        w32, t32 = anim
        inp = b.add(t32, "SCALAR", _FLOAT, minmax=True)
        if cubic is not None:
            cubic[:, 1] = w32
            w32 = cubic
        out = b.add(w32.reshape(-1), "SCALAR", _FLOAT)
        doc["animations"] = [{
            "name": "weights",
            "samplers": [{"input": inp, "output": out, "interpolation": interpolation}],
            "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
        }]
    blob = b.blob()
    buffer = {"byteLength": len(blob)}
    if suffix == ".gltf":
        buffer["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode("ascii")
    doc["buffers"] = [buffer]
    doc["bufferViews"] = b.views
    doc["accessors"] = b.accessors
    text = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")

    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            if suffix == ".gltf":
                f.write(text)
            else:  # GLB container, glTF 2.0 §4.4: header, JSON chunk (space-padded), BIN chunk (zero-padded)
                text += b" " * ((-len(text)) % 4)
                blob += b"\0" * ((-len(blob)) % 4)
                f.write(struct.pack("<4sII", _GLB_MAGIC, 2, 12 + 8 + len(text) + 8 + len(blob)))
                f.write(struct.pack("<II", len(text), _CHUNK_JSON))
                f.write(text)
                f.write(struct.pack("<II", len(blob), _CHUNK_BIN))
                f.write(blob)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
