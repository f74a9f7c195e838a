"""Avatars as real apps write them: several meshes sharing morph names, node transforms, skins,
quantised attributes.

The files are small synthetic replicas of the structure of real avatars (their licences forbid
copying them; see data/SOURCES.md, "Files from elsewhere"):

* Ready Player Me (``avatars/brunette-t.glb`` of met4citizen/TalkingHead, generator "Ready Player
  Me"): meshes in the order EyeLeft, EyeRight, Wolf3D_Head, Wolf3D_Teeth, ..., the first four with
  the same 67 targetNames in ``mesh.extras``; the head skinned; hair and clothes without targets.
  The reader used to take the first mesh with targets, the 120-vertex left eyeball, as the rig.
* VRoid through glTF-Transform (``avatars/vroid.glb`` of the same repository): KHR_mesh_quantization
  (int16 normalised POSITION and targets, dequantised by the node transform) and
  EXT_meshopt_compression (required).

Every expected value is computed here independently of the reader (scipy's rotations, explicit
loops over vertices and joints).
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.io.gltf import GltfError, read_rig

# -- a minimal independent GLB builder ---------------------------------------------------------


class Glb:
    def __init__(self):
        self.doc = {"asset": {"version": "2.0", "generator": "test"}, "buffers": [], "bufferViews": [],
                    "accessors": [], "meshes": [], "nodes": [], "scenes": [{"nodes": []}], "scene": 0}
        self.blob = bytearray()

    def accessor(self, array, type_, component=5126, normalized=False):
        array = np.ascontiguousarray(array)
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": array.nbytes})
        self.blob += array.tobytes()
        acc = {"bufferView": len(self.doc["bufferViews"]) - 1, "componentType": component,
               "count": len(array), "type": type_}
        if normalized:
            acc["normalized"] = True
        if type_ == "VEC3" and component == 5126:
            acc["min"], acc["max"] = array.min(0).tolist(), array.max(0).tolist()
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def mesh(self, name, pos, faces, deltas=(), names=None, quantize=None, extra_attributes=None):
        """``quantize``: None (float32) or a scale s: int16 normalised ``round(x / s * 32767)``."""
        def enc(x):
            if quantize is None:
                return self.accessor(np.asarray(x, np.float32), "VEC3")
            q = np.round(np.asarray(x) / quantize * 32767).astype(np.int16)
            return self.accessor(q, "VEC3", 5122, normalized=True)
        prim = {"attributes": {"POSITION": enc(pos), **(extra_attributes or {})},
                "indices": self.accessor(np.asarray(faces, np.uint32).reshape(-1), "SCALAR", 5125)}
        if len(deltas):
            prim["targets"] = [{"POSITION": enc(d)} for d in deltas]
        m = {"name": name, "primitives": [prim]}
        if names is not None:
            m["extras"] = {"targetNames": list(names)}
        self.doc["meshes"].append(m)
        return len(self.doc["meshes"]) - 1

    def node(self, root=True, **fields):
        self.doc["nodes"].append(fields)
        i = len(self.doc["nodes"]) - 1
        if root:
            self.doc["scenes"][0]["nodes"].append(i)
        return i

    def write(self, path, extensions=None):
        doc = dict(self.doc, buffers=[{"byteLength": len(self.blob)}])
        if extensions:
            doc.update(extensions)
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        blob = bytes(self.blob) + b"\0" * (-len(self.blob) % 4)
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob))
                         + struct.pack("<II", len(text), 0x4E4F534A) + text
                         + struct.pack("<II", len(blob), 0x004E4942) + blob)
        return path


def blob_mesh(n, seed, centre, radius):
    """A closed fan of ``n`` triangles around a point: vertices (n + 2, 3), faces (n, 3)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = np.c_[np.cos(ang), np.sin(ang), 0 * ang] * radius
    pos = np.vstack([[0, 0, radius], rim, [0, 0, -radius]]) + centre + rng.normal(0, radius * 0.01, (n + 2, 3))
    faces = [(0, 1 + k, 1 + (k + 1) % n) for k in range(n)] + [(n + 1, 1 + (k + 1) % n, 1 + k) for k in range(n)]
    return pos, np.array(faces)


NAMES = ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "viseme_aa"]


def rpm_like(tmp_path, head_skin=True):
    """EyeLeft first (small, all names, on a translated node), the head (largest, skinned, joints
    at rest = bind pose), teeth (a subset of the names, a rotated and scaled node), hair (no
    targets). Returns the path and, per mesh, what the rig must hold for it."""
    g = Glb()
    rng = np.random.default_rng(0)
    K = len(NAMES)
    eye_p, eye_f = blob_mesh(6, 1, [0, 0, 0], 0.012)
    eye_d = rng.normal(0, 0.002, (K, len(eye_p), 3))
    head_p, head_f = blob_mesh(40, 2, [0, 1.6, 0.1], 0.09)
    head_d = rng.normal(0, 0.005, (K, len(head_p), 3))
    teeth_names = ["viseme_aa", "jawOpen"]  # a subset, in another order
    teeth_p, teeth_f = blob_mesh(8, 3, [0, 0, 0], 0.02)
    teeth_d = rng.normal(0, 0.004, (2, len(teeth_p), 3))
    hair_p, hair_f = blob_mesh(30, 4, [0, 1.7, 0.1], 0.11)

    m_eye = g.mesh("EyeLeft", eye_p, eye_f, eye_d, NAMES)
    m_head = g.mesh("Wolf3D_Head", head_p, head_f, head_d, NAMES,
                    extra_attributes={"JOINTS_0": g.accessor(np.zeros((len(head_p), 4), np.uint8), "VEC4", 5121),
                                      "WEIGHTS_0": g.accessor(np.tile(np.float32([1, 0, 0, 0]), (len(head_p), 1)), "VEC4")})
    m_teeth = g.mesh("Wolf3D_Teeth", teeth_p, teeth_f, teeth_d, teeth_names)
    m_hair = g.mesh("Wolf3D_Hair", hair_p, hair_f)
    # skeleton: Armature (scaled 0.5, as an FBX export might be) > Head joint at (0, 1.5, 0)
    joint_world = np.diag([0.5, 0.5, 0.5, 1.0])
    joint_world[:3, 3] = [0, 0.75, 0]
    ibm = np.linalg.inv(joint_world)  # bind pose = rest pose
    g.doc["skins"] = [{"joints": [1], "inverseBindMatrices": g.accessor(ibm.T.reshape(1, 16).astype(np.float32), "MAT4")}]
    g.node(name="Armature", scale=[0.5, 0.5, 0.5], children=[1])
    g.node(root=False, name="Head", translation=[0, 1.5, 0])
    # the skinned node carries a transform glTF says to ignore (§3.7.3.1)
    g.node(name="Wolf3D_Head", mesh=m_head, skin=0 if head_skin else None, translation=[5, 5, 5])
    eye_t = np.array([0.033, 1.632, 0.113])
    g.node(name="EyeLeft", mesh=m_eye, translation=eye_t.tolist())
    teeth_q = Rotation.from_euler("x", 20, degrees=True)
    g.node(name="Teeth", mesh=m_teeth, translation=[0, 1.565, 0.117], rotation=teeth_q.as_quat().tolist(),
           scale=[1.5, 1.5, 1.5])
    g.node(name="Wolf3D_Hair", mesh=m_hair)
    if not head_skin:
        del g.doc["nodes"][2]["skin"]
    path = g.write(tmp_path / "rpm_like.glb")

    head_expect = (head_p + ([5, 5, 5] if not head_skin else 0), head_d)
    teeth_full = np.zeros((K, len(teeth_p), 3))
    for k, n in enumerate(teeth_names):
        teeth_full[NAMES.index(n)] = teeth_q.apply(teeth_d[k]) * 1.5
    expect = {
        "Wolf3D_Head": head_expect,
        "EyeLeft": (eye_p + eye_t, eye_d),
        "Wolf3D_Teeth": (teeth_q.apply(teeth_p) * 1.5 + [0, 1.565, 0.117], teeth_full),
    }
    faces = {"Wolf3D_Head": head_f, "EyeLeft": eye_f, "Wolf3D_Teeth": teeth_f}
    return path, expect, faces


@pytest.mark.parametrize("head_skin", [True, False])
def test_ready_player_me_like_avatar_is_the_head_with_teeth_and_eyes(tmp_path, head_skin):
    path, expect, faces = rpm_like(tmp_path, head_skin)
    rig = read_rig(path)
    spans = rig.extras["meshes"]
    assert [s["name"] for s in spans] == ["Wolf3D_Head", "EyeLeft", "Wolf3D_Teeth"]  # the head first, no hair
    assert list(rig.names) == NAMES
    assert rig.n_vertices == sum(len(p) for p, _ in expect.values())
    for s in spans:
        a, b = s["vertices"]
        pos, d = expect[s["name"]]
        np.testing.assert_allclose(rig.neutral[a:b], pos, atol=1e-6)
        np.testing.assert_allclose(rig.deltas[:, a:b], d, atol=1e-6)
        inside = (rig.faces >= a) & (rig.faces < b)
        rows = inside.all(1)
        np.testing.assert_array_equal(rig.faces[rows] - a, faces[s["name"]])
    assert ((rig.faces >= 0).all() and not ((rig.faces < spans[0]["vertices"][1]).any(1)
                                           & (rig.faces >= spans[0]["vertices"][1]).any(1)).any())
    # teeth have no eyeBlink target: zero there
    a, b = spans[2]["vertices"]
    assert not rig.deltas[NAMES.index("eyeBlinkLeft"), a:b].any()


def test_explicit_mesh_is_read_alone(tmp_path):
    path, expect, _ = rpm_like(tmp_path)
    eye = read_rig(path, mesh=0)
    assert "meshes" not in eye.extras and eye.n_vertices == len(expect["EyeLeft"][0])
    np.testing.assert_allclose(eye.neutral, expect["EyeLeft"][0], atol=1e-6)


def test_meshes_with_other_names_are_left_out(tmp_path):
    """A mesh whose targets are not all the head's (a VRoid body with its own shapes) is not merged."""
    g = Glb()
    p, f = blob_mesh(20, 0, [0, 1.6, 0], 0.1)
    q, h = blob_mesh(6, 1, [0, 1.0, 0], 0.05)
    g.node(mesh=g.mesh("Face", p, f, np.ones((2, len(p), 3)) * 0.01, ["A", "B"]))
    g.node(mesh=g.mesh("Body", q, h, np.ones((2, len(q), 3)) * 0.01, ["A", "Breathe"]))
    rig = read_rig(g.write(tmp_path / "v.glb"))
    assert rig.n_vertices == len(p) and list(rig.names) == ["A", "B"] and "meshes" not in rig.extras


def test_two_joint_skin_is_blended_per_vertex(tmp_path):
    """Joints at rest away from the bind pose: each vertex placed by sum_j w_j world_j inverseBind_j."""
    g = Glb()
    p, f = blob_mesh(10, 5, [0, 1.6, 0], 0.1)
    d = np.random.default_rng(6).normal(0, 0.01, (1, len(p), 3))
    w = np.random.default_rng(7).random((len(p), 2))
    w /= w.sum(1, keepdims=True)
    joints = np.zeros((len(p), 4), np.uint16)
    joints[:, 1] = 1
    weights = np.zeros((len(p), 4), np.float32)
    weights[:, :2] = w
    m = g.mesh("Head", p, f, d, ["jawOpen"], extra_attributes={
        "JOINTS_0": g.accessor(joints, "VEC4", 5123), "WEIGHTS_0": g.accessor(weights, "VEC4")})
    r0, r1 = Rotation.from_euler("y", 10, degrees=True), Rotation.from_euler("z", -15, degrees=True)
    g.node(name="J0", rotation=r0.as_quat().tolist(), translation=[0.1, 0, 0])
    g.node(name="J1", rotation=r1.as_quat().tolist(), translation=[0, 0.2, 0])
    g.doc["skins"] = [{"joints": [0, 1]}]  # no inverseBindMatrices: identity
    g.node(mesh=m, skin=0)
    weights = weights[:, :2].astype(np.float64)
    weights /= weights.sum(1, keepdims=True)
    rig = read_rig(g.write(tmp_path / "s.glb"))
    want_p, want_d = np.zeros_like(p), np.zeros_like(d[0])
    for v in range(len(p)):
        for wj, (rot, t) in zip(weights[v], [(r0, [0.1, 0, 0]), (r1, [0, 0.2, 0])]):
            want_p[v] += wj * (rot.apply(p[v]) + t)
            want_d[v] += wj * rot.apply(d[0, v])
    np.testing.assert_allclose(rig.neutral, want_p, atol=1e-6)
    np.testing.assert_allclose(rig.deltas[0], want_d, atol=1e-6)


def test_quantized_mesh_is_dequantized_by_its_node(tmp_path):
    """KHR_mesh_quantization as glTF-Transform / gltfpack write it: int16 normalised POSITION and
    targets in [-1, 1], the node's scale and translation bringing them back to metres."""
    p, f = blob_mesh(30, 8, [0, 0, 0], 0.08)
    d = np.random.default_rng(9).normal(0, 0.004, (3, len(p), 3))
    s, t = 0.1, np.array([0.0, 1.6, 0.1])
    g = Glb()
    g.node(mesh=g.mesh("Face", p / s, f, d / s, ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"], quantize=1.0),
           scale=[s, s, s], translation=t.tolist())
    path = g.write(tmp_path / "q.glb", {"extensionsUsed": ["KHR_mesh_quantization"],
                                        "extensionsRequired": ["KHR_mesh_quantization"]})
    rig = read_rig(path)
    step = s / 32767  # one quantisation step, in metres
    np.testing.assert_allclose(rig.neutral, p + t, atol=step)
    np.testing.assert_allclose(rig.deltas, d, atol=step)
    assert list(rig.names) == ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"]


# -- EXT_meshopt_compression, as glTF-Transform writes it (TalkingHead's vroid.glb) -------------


def meshopt_file(tmp_path):
    """A quantised face whose POSITION, target and index bufferViews are meshopt-compressed into
    buffers[0]; buffers[1] is the fallback placeholder with no bytes, as in vroid.glb."""
    import meshopt

    p, f = blob_mesh(24, 11, [0, 0, 0], 0.9)
    d = np.random.default_rng(12).normal(0, 0.05, (2, len(p), 3))
    g = Glb()
    fallback = 0

    def compressed(raw, mode, type_, component, count, normalized=False, stride=None):
        nonlocal fallback
        data = meshopt.encode_gltf_buffer(raw, mode)
        g.blob += b"\0" * (-len(g.blob) % 4)
        ext = {"buffer": 0, "byteOffset": len(g.blob), "byteLength": len(data), "mode": mode,
               "byteStride": raw.itemsize * (raw.shape[1] if raw.ndim > 1 else 1), "count": len(raw)}
        g.blob += data
        bv = {"buffer": 1, "byteOffset": fallback, "byteLength": raw.nbytes,
              "extensions": {"EXT_meshopt_compression": ext}}
        if stride:
            bv["byteStride"] = stride
        fallback += raw.nbytes + (-raw.nbytes % 4)
        g.doc["bufferViews"].append(bv)
        acc = {"bufferView": len(g.doc["bufferViews"]) - 1, "componentType": component, "count": count, "type": type_}
        if normalized:
            acc["normalized"] = True
        g.doc["accessors"].append(acc)
        return len(g.doc["accessors"]) - 1

    def vec3(x):  # int16 normalised, padded to 8-byte rows (meshopt rows are multiples of 4 bytes)
        q = np.zeros((len(x), 4), np.int16)
        q[:, :3] = np.round(x * 32767)
        return compressed(q, "ATTRIBUTES", "VEC3", 5122, len(x), normalized=True, stride=8)

    prim = {"attributes": {"POSITION": vec3(p)},
            "indices": compressed(f.astype(np.uint32).reshape(-1), "TRIANGLES", "SCALAR", 5125, f.size),
            "targets": [{"POSITION": vec3(dk)} for dk in d]}
    g.doc["meshes"].append({"name": "Face", "primitives": [prim], "extras": {"targetNames": ["jawOpen", "eyeBlinkLeft"]}})
    s = 0.1
    g.node(mesh=0, scale=[s, s, s])
    doc_ext = {"extensionsUsed": ["EXT_meshopt_compression", "KHR_mesh_quantization"],
               "extensionsRequired": ["EXT_meshopt_compression", "KHR_mesh_quantization"]}
    path = g.write(tmp_path / "meshopt.glb", doc_ext)
    raw = json.loads(path.read_bytes()[20:20 + struct.unpack_from("<I", path.read_bytes(), 12)[0]])
    raw["buffers"] = [raw["buffers"][0], {"byteLength": fallback, "extensions": {"EXT_meshopt_compression": {"fallback": True}}}]
    text = json.dumps(raw).encode()
    text += b" " * (-len(text) % 4)
    blob = bytes(g.blob) + b"\0" * (-len(g.blob) % 4)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob))
                     + struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob)
    return path, p * s, f, d * s, s / 32767


def test_meshopt_compressed_rig_is_decoded(tmp_path):
    path, pos, faces, deltas, step = meshopt_file(tmp_path)
    rig = read_rig(path)

    def rotated(tri):  # the triangle codec may start a triangle at another corner (same winding)
        k = np.argmin(tri, axis=1)
        return np.stack([np.roll(t, -i) for t, i in zip(tri, k)])
    np.testing.assert_array_equal(rotated(rig.faces), rotated(faces))
    np.testing.assert_allclose(rig.neutral, pos, atol=step)
    np.testing.assert_allclose(rig.deltas, deltas, atol=step)


def test_meshopt_without_the_package_names_the_extra(tmp_path, monkeypatch):
    import sys

    path = meshopt_file(tmp_path)[0]
    monkeypatch.setitem(sys.modules, "meshopt", None)  # as if not installed
    with pytest.raises(GltfError, match=r"EXT_meshopt_compression.*face-retarget\[meshopt\]"):
        read_rig(path)


def test_meshopt_corrupt_stream_is_named(tmp_path):
    path = meshopt_file(tmp_path)[0]
    data = bytearray(path.read_bytes())
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + jlen])
    ext = doc["bufferViews"][0]["extensions"]["EXT_meshopt_compression"]
    at = 28 + jlen + ext["byteOffset"]
    data[at:at + ext["byteLength"]] = b"\xff" * ext["byteLength"]
    path.write_bytes(bytes(data))
    with pytest.raises(GltfError, match=r"bufferViews\[0\]\.extensions\.EXT_meshopt_compression does not decode"):
        read_rig(path)


def test_buffer_without_uri_other_than_the_first(tmp_path):
    """Only buffers[0] of a GLB is its BIN chunk; the compressed file's old reading of buffers[1] as
    the BIN chunk gave 'truncated file?'. A plain second buffer without uri is now named as such."""
    g = Glb()
    p, f = blob_mesh(6, 0, [0, 0, 0], 0.1)
    g.node(mesh=g.mesh("Face", p, f, np.ones((1, len(p), 3)) * 0.01, ["jawOpen"]))
    path = g.write(tmp_path / "b.glb")
    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + jlen])
    doc["buffers"].append({"byteLength": 4})
    doc["bufferViews"][0]["buffer"] = 1
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob = data[28 + jlen:]
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob))
                     + struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob)
    with pytest.raises(GltfError, match=r"buffers\[1\] has no uri; only buffers\[0\] can be a GLB's BIN chunk"):
        read_rig(path)


def test_draco_compressed_primitive_is_refused_by_name(tmp_path):
    """Ready Player Me and Avaturn serve Draco-compressed avatars on request: POSITION then has no
    bufferView (its data is in the Draco stream), which read as all-zero vertices."""
    g = Glb()
    p, f = blob_mesh(6, 0, [0, 0, 0], 0.1)
    g.node(mesh=g.mesh("Wolf3D_Head", p, f, np.ones((1, len(p), 3)) * 0.01, ["jawOpen"]))
    prim = g.doc["meshes"][0]["primitives"][0]
    del g.doc["accessors"][prim["attributes"]["POSITION"]]["bufferView"]
    prim["extensions"] = {"KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0}}}
    path = g.write(tmp_path / "draco.glb", {"extensionsUsed": ["KHR_draco_mesh_compression"],
                                            "extensionsRequired": ["KHR_draco_mesh_compression"]})
    with pytest.raises(GltfError, match=r"meshes\[0\]\.primitives\[0\] is Draco-compressed"):
        read_rig(path)


@pytest.mark.parametrize("where", ["primitive", "target"])
def test_vrm0_target_names_on_primitives(tmp_path, where):
    """UniVRM (VRM 0.x) stores the names in ``primitives[j].extras.targetNames`` (since 0.36; before:
    ``targets[k].extras.name``), every primitive of the face repeating them; they used to read as
    target_0, target_1 ..., so no ARKit name of a Perfect Sync avatar was seen."""
    g = Glb()
    p, f = blob_mesh(12, 0, [0, 1.5, 0], 0.1)
    q, h = blob_mesh(5, 1, [0, 1.5, 0.1], 0.02)
    names = ["Fcl_MTH_A", "jawOpen", "eyeBlinkLeft"]
    m = g.mesh("Face", p, f, np.ones((3, len(p), 3)) * 0.01)
    prim2 = dict(g.doc["meshes"][g.mesh("x", q, h, np.ones((3, len(q), 3)) * 0.01)]["primitives"][0])
    g.doc["meshes"].pop()
    g.doc["meshes"][m]["primitives"].append(prim2)  # a second material's primitive, same targets
    for prim in g.doc["meshes"][m]["primitives"]:
        if where == "primitive":
            prim["extras"] = {"targetNames": names}
        else:
            for t, n in zip(prim["targets"], names):
                t["extras"] = {"name": n}
    g.node(mesh=m)
    rig = read_rig(g.write(tmp_path / "vrm0.glb"))
    assert list(rig.names) == names and rig.n_vertices == len(p) + len(q)


@pytest.mark.parametrize("index_type,base", [(5121, False), (5123, False), (5125, True)])
def test_sparse_morph_targets(tmp_path, index_type, base):
    """Blender's glTF exporter writes shape keys as sparse accessors by default (only the moved
    vertices; no bufferView, so the rest is zero), indices as the smallest unsigned type; another
    writer may give a dense base that the sparse values override."""
    p, f = blob_mesh(40, 3, [0, 1.6, 0], 0.1)
    V = len(p)
    rng = np.random.default_rng(4)
    dense = np.zeros((2, V, 3))
    g = Glb()
    m = g.mesh("Face", p, f, np.zeros((2, V, 3)), ["jawOpen", "mouthSmileLeft"])
    itype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[index_type]
    for k, t in enumerate(g.doc["meshes"][m]["primitives"][0]["targets"]):
        moved = np.sort(rng.choice(V, 9, replace=False))
        vals = rng.normal(0, 0.01, (9, 3)).astype(np.float32)
        acc = g.doc["accessors"][t["POSITION"]]
        if base:
            b = rng.normal(0, 0.001, (V, 3)).astype(np.float32)
            acc["bufferView"] = g.doc["accessors"][g.accessor(b, "VEC3")]["bufferView"]
            dense[k] = b
        else:
            del acc["bufferView"]
        dense[k, moved] = vals
        iv = g.doc["accessors"][g.accessor(moved.astype(itype), "SCALAR", index_type)]["bufferView"]
        vv = g.doc["accessors"][g.accessor(vals, "VEC3")]["bufferView"]
        acc["sparse"] = {"count": 9, "indices": {"bufferView": iv, "componentType": index_type},
                         "values": {"bufferView": vv}}
    rig = read_rig(g.write(tmp_path / "sparse.glb"))
    np.testing.assert_array_equal(rig.deltas, dense.astype(np.float32).astype(np.float64))


def test_sparse_index_out_of_range_is_named(tmp_path):
    p, f = blob_mesh(6, 3, [0, 0, 0], 0.1)
    g = Glb()
    m = g.mesh("Face", p, f, np.zeros((1, len(p), 3)), ["jawOpen"])
    acc = g.doc["accessors"][g.doc["meshes"][m]["primitives"][0]["targets"][0]["POSITION"]]
    del acc["bufferView"]
    iv = g.doc["accessors"][g.accessor(np.array([2, 99], np.uint16), "SCALAR", 5123)]["bufferView"]
    vv = g.doc["accessors"][g.accessor(np.ones((2, 3), np.float32), "VEC3")]["bufferView"]
    acc["sparse"] = {"count": 2, "indices": {"bufferView": iv, "componentType": 5123}, "values": {"bufferView": vv}}
    with pytest.raises(GltfError, match=r"targets\[0\]\.POSITION sparse index 99 >= count 8"):
        read_rig(g.write(tmp_path / "bad_sparse.glb"))


def test_one_eye_mesh_on_two_nodes_mirrored(tmp_path):
    """Blender exports linked-duplicate eyes as one mesh on two nodes; a mirrored one (scale -1 in
    x) must keep its triangles facing out (glTF reverses the winding when the determinant is < 0)."""
    g = Glb()
    head_p, head_f = blob_mesh(30, 0, [0, 1.6, 0], 0.09)
    eye_p, eye_f = blob_mesh(6, 1, [0, 0, 0.01], 0.012)
    eye_p[:, 0] += 0.004  # not symmetric in x, so the mirror shows
    eye_d = np.random.default_rng(2).normal(0, 0.002, (1, len(eye_p), 3))
    g.node(name="Head", mesh=g.mesh("Head", head_p, head_f, np.ones((2, len(head_p), 3)) * 0.01, ["eyeLookInLeft", "jawOpen"]))
    eye = g.mesh("Eye", eye_p, eye_f, eye_d, ["eyeLookInLeft"])
    g.node(name="EyeLeft", mesh=eye, translation=[0.03, 1.63, 0.08])
    g.node(name="EyeRight", mesh=eye, translation=[-0.03, 1.63, 0.08], scale=[-1, 1, 1])
    rig = read_rig(g.write(tmp_path / "eyes.glb"))
    spans = rig.extras["meshes"]
    assert [(s["name"], s["node"]) for s in spans] == [("Head", 0), ("Eye", 1), ("Eye", 2)]
    (a1, b1), (a2, b2) = spans[1]["vertices"], spans[2]["vertices"]
    mirror = np.array([-1.0, 1, 1])
    np.testing.assert_allclose(rig.neutral[a1:b1], eye_p + [0.03, 1.63, 0.08], atol=1e-6)
    np.testing.assert_allclose(rig.neutral[a2:b2], eye_p * mirror + [-0.03, 1.63, 0.08], atol=1e-6)
    np.testing.assert_allclose(rig.deltas[0, a2:b2], eye_d[0] * mirror, atol=1e-7)
    assert not rig.deltas[1, a1:].any()  # the eyes have no jawOpen

    def outward(a, b):  # every triangle's normal points away from its mesh's centre
        tri = rig.faces[((rig.faces >= a) & (rig.faces < b)).all(1)]
        P = rig.neutral[tri]
        n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        return np.einsum("ij,ij->i", n, P.mean(1) - rig.neutral[a:b].mean(0)) > 0
    assert outward(a1, b1).all() and outward(a2, b2).all()


def test_animated_avatar_as_a_mesh_sequence_is_the_whole_face(tmp_path):
    """A Ready Player Me-like avatar whose weight animation's first channel is on the EyeLeft node
    (exporters write one channel per mesh node): read as a mesh sequence it is the face (head,
    eyes, teeth), each frame ``neutral + sum_k w_tk delta_k``, not the eyeball."""
    from core.io.sequence import read_gltf_sequence

    path, expect, _ = rpm_like(tmp_path)
    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    g = Glb()
    g.doc = json.loads(data[20:20 + jlen])
    g.blob = bytearray(data[28 + jlen:])
    T, K = 5, len(NAMES)
    W = np.random.default_rng(5).random((T, K)).astype(np.float32)
    times = g.accessor((np.arange(T) / 30).astype(np.float32), "SCALAR")
    g.doc["accessors"][times]["min"], g.doc["accessors"][times]["max"] = [0.0], [float((T - 1) / 30)]
    out = g.accessor(W.reshape(-1), "SCALAR")
    eye_node = next(i for i, n in enumerate(g.doc["nodes"]) if n.get("name") == "EyeLeft")
    head_node = next(i for i, n in enumerate(g.doc["nodes"]) if n.get("name") == "Wolf3D_Head")
    g.doc["animations"] = [{"samplers": [{"input": times, "output": out}],
                            "channels": [{"sampler": 0, "target": {"node": eye_node, "path": "weights"}},
                                         {"sampler": 0, "target": {"node": head_node, "path": "weights"}}]}]
    seq = read_gltf_sequence(g.write(tmp_path / "animated.glb"))
    rig = read_rig(path)
    assert seq.kind == "meshes" and seq.data.shape == (T, rig.n_vertices, 3)
    want = rig.neutral + np.einsum("tk,kvi->tvi", W.astype(np.float64), rig.deltas)
    np.testing.assert_allclose(seq.data, want, atol=1e-6)


def test_face_is_the_mesh_with_most_targets_not_the_biggest(tmp_path):
    """A full-body avatar whose body mesh (larger) carries one shape of its own (a breathing
    shape) and whose face mesh carries the expressions: the face is the rig."""
    g = Glb()
    body_p, body_f = blob_mesh(200, 0, [0, 1.0, 0], 0.5)
    face_p, face_f = blob_mesh(40, 1, [0, 1.6, 0.1], 0.1)
    g.node(name="Body", mesh=g.mesh("Body", body_p, body_f, np.ones((1, len(body_p), 3)) * 0.01, ["Breathe"]))
    g.node(name="Face", mesh=g.mesh("Face", face_p, face_f, np.ones((3, len(face_p), 3)) * 0.01,
                                    ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"]))
    rig = read_rig(g.write(tmp_path / "body.glb"))
    assert list(rig.names) == ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"] and rig.n_vertices == len(face_p)


def test_vrm_file_is_read_as_a_rig(tmp_path):
    """A VRM (VRoid Studio, VRM 0.x / 1.0) is a GLB named .vrm: the CLI, load_rig and the page's
    upload check read it; one with no morph targets (the VRM 1.0 specification's expression
    samples animate textures only) is refused in plain words."""
    from core.cli import main
    from core.io.check import check_upload
    from core.io.rigs import load_rig

    path, expect, _ = rpm_like(tmp_path)
    vrm = tmp_path / "avatar.vrm"
    vrm.write_bytes(path.read_bytes())
    rig = load_rig(vrm)
    assert rig.n_vertices == sum(len(p) for p, _ in expect.values())
    assert check_upload(vrm)["kind"] == "rig"
    assert main(["info", str(vrm)]) == 0
    g = Glb()
    p, f = blob_mesh(4, 0, [0, 0, 0], 0.1)
    g.node(mesh=g.mesh("Quad", p, f))
    bare = g.write(tmp_path / "bare.vrm", {"extensionsUsed": ["VRMC_vrm"]})
    with pytest.raises(ValueError, match=r"bare\.vrm has no blend shapes"):
        check_upload(bare)
    (tmp_path / "fake.vrm").write_bytes(b"PK\x03\x04 not a glb")
    with pytest.raises(ValueError, match=r"fake\.vrm is not a GLB file"):
        check_upload(tmp_path / "fake.vrm")
