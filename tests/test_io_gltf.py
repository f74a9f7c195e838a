"""glTF writer/reader: exact round trips on the bundled rigs, weight animations, marker
layouts, broken files with errors that name the file and the field, and the files opened by
the Khronos glTF Validator and three.js's GLTFLoader (node, from package.json)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess

import numpy as np
import pytest

from datapaths import PERFORMANCES, RIGS, ROOT
from core.io.gltf import GltfError, read_animation, read_markers, read_rig, vertex_normals, write_rig
from core.io.tabular import estimate_fps
from core.model import MarkerLayout, Performance, Rig
from core.names import canonical

RIG_FILES = sorted(RIGS.glob("*.glb"))


# -- helpers: an independent GLB (un)packer, to make broken files -----------------------


def unpack(path):
    data = path.read_bytes()
    assert data[:4] == b"glTF"
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + jlen])
    blen = struct.unpack_from("<I", data, 20 + jlen)[0]
    return doc, bytearray(data[28 + jlen : 28 + jlen + blen])


def pack(path, doc, blob):
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    blob = bytes(blob) + b"\0" * (-len(blob) % 4)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob))
                     + struct.pack("<II", len(text), 0x4E4F534A) + text
                     + struct.pack("<II", len(blob), 0x004E4942) + blob)
    return path


def assert_same_rig(a: Rig, b: Rig):
    assert a.names == b.names
    assert np.array_equal(a.neutral, b.neutral)
    assert np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.deltas, b.deltas)
    assert (a.uvs is None) == (b.uvs is None)
    if a.uvs is not None:
        assert np.array_equal(a.uvs, b.uvs)
    assert a.extras == b.extras


@pytest.fixture
def small(tiger):
    """The tiger with 3 shapes and deterministic random weights: quick files to break."""
    return tiger.subset(tiger.names[:3])


@pytest.fixture
def small_file(tmp_path, small):
    w = np.random.default_rng(1).random((10, 3))
    return write_rig(tmp_path / "small.glb", small, w)


# -- round trips ------------------------------------------------------------------------


@pytest.mark.parametrize("src", RIG_FILES, ids=lambda p: p.stem)
def test_rig_round_trip_is_exact(tmp_path, rigs, src):
    rig = rigs[src.stem]
    out = write_rig(tmp_path / src.name, rig)
    back = read_rig(out)
    assert_same_rig(rig, back)
    assert back.name == src.stem
    # and a second generation is byte-identical (deterministic writer)
    again = write_rig(tmp_path / "again.glb", back)
    assert again.read_bytes() == out.read_bytes()


def test_extras_survive(ict, tmp_path):
    """ICT's upstreamVertexIndex (14,629 ints) travels in mesh.extras."""
    back = read_rig(write_rig(tmp_path / "ict.glb", ict, normals=False))
    assert back.extras["upstreamVertexIndex"] == ict.extras["upstreamVertexIndex"]
    assert len(back.extras["upstreamVertexIndex"]) == ict.n_vertices
    rig = Rig(ict.neutral, ict.faces, ict.deltas[:1], ict.names[:1], name="x",
              extras={"arr": np.arange(4), "scalar": np.float32(0.5), "nested": {"a": [1, 2]}})
    back = read_rig(write_rig(tmp_path / "x.glb", rig, normals=False))
    assert back.extras == {"arr": [0, 1, 2, 3], "scalar": 0.5, "nested": {"a": [1, 2]}}


def test_embedded_gltf_round_trip(tmp_path, small):
    w = np.random.default_rng(2).random((7, small.n_shapes))
    out = write_rig(tmp_path / "small.gltf", small, w)
    text = out.read_text()
    assert text.lstrip().startswith("{") and "data:application/octet-stream;base64," in text
    assert_same_rig(small, read_rig(out))
    assert np.array_equal(read_animation(out).data, w.astype(np.float32))


def test_round_trip_of_float64_rig_is_float32_close(tmp_path):
    """A rig not already float32 comes back within float32 rounding, relative to its size."""
    rng = np.random.default_rng(3)
    V = 40
    neutral = rng.normal(size=(V, 3)) * 0.1
    faces = np.array([rng.choice(V, 3, replace=False) for _ in range(60)])
    deltas = rng.normal(size=(4, V, 3)) * 0.01
    rig = Rig(neutral, faces, deltas, list("abcd"), uvs=rng.random((V, 2)))
    back = read_rig(write_rig(tmp_path / "r.glb", rig))
    tol = 2 * np.finfo(np.float32).eps * rig.size
    assert np.abs(back.neutral - neutral).max() <= tol
    assert np.abs(back.deltas - deltas).max() <= tol
    assert np.abs(back.neutral - neutral).max() > 0  # it really went through float32
    assert np.array_equal(back.faces, faces)


def test_rig_without_shapes(tmp_path, tiger):
    rig = Rig(tiger.neutral, tiger.faces, np.zeros((0, tiger.n_vertices, 3)), [], name="static")
    back = read_rig(write_rig(tmp_path / "static.glb", rig))
    assert back.n_shapes == 0 and np.array_equal(back.neutral, rig.neutral)
    with pytest.raises(ValueError, match="weights: rig 'static' has no shapes"):
        write_rig(tmp_path / "s.glb", rig, np.zeros((3, 0)))


def test_evaluated_mesh_matches_rig(tmp_path, tiger):
    """What a viewer computes from the file, POSITION + sum_k w_k targets[k], is rig.evaluate(w)."""
    w = np.random.default_rng(4).random(tiger.n_shapes)
    back = read_rig(write_rig(tmp_path / "t.glb", tiger))
    assert np.allclose(back.evaluate(w), tiger.evaluate(w), rtol=0, atol=1e-6 * tiger.size)


# -- animation --------------------------------------------------------------------------


def test_animation_round_trip_random(tmp_path, small):
    rng = np.random.default_rng(5)
    w = rng.random((97, small.n_shapes)) * 1.5 - 0.25  # glTF allows weights outside [0, 1]
    out = write_rig(tmp_path / "a.glb", small, w, fps=24.0)
    perf = read_animation(out)
    assert perf.kind == "curves" and perf.names == small.names
    assert np.array_equal(perf.data, w.astype(np.float32).astype(np.float64))
    assert np.abs(perf.data - w).max() <= np.finfo(np.float32).eps * np.abs(w).max()
    assert perf.fps == 24.0
    assert np.array_equal(perf.times, (np.arange(97) / 24.0).astype(np.float32).astype(np.float64))
    assert perf.valid.all()
    assert perf.extras["interpolation"] == "LINEAR"


def test_animation_round_trip_real_livelinkface(tmp_path, rocketbox):
    """A real ARKit capture (4,030 frames) mapped onto Rocketbox's AK_* shapes by ARKit name."""
    csv = PERFORMANCES / "livelinkface_rom.csv"
    header = csv.open().readline().strip().split(",")
    table = np.loadtxt(csv, delimiter=",", skiprows=1, usecols=range(2, len(header)))
    channels = {canonical(n): i for i, n in enumerate(header[2:])}
    w = np.zeros((len(table), rocketbox.n_shapes))
    hit = 0
    for k, n in enumerate(rocketbox.names):
        if canonical(n) in channels:
            w[:, k] = table[:, channels[canonical(n)]]
            hit += 1
    assert hit >= 50 and len(w) == 4030
    out = write_rig(tmp_path / "rb.glb", rocketbox, w, fps=30.0, normals=False)
    perf = read_animation(out)
    assert perf.fps == 30.0 and perf.n_frames == 4030
    assert np.array_equal(perf.data, w.astype(np.float32))
    assert perf.duration == pytest.approx(4029 / 30, rel=1e-6)


def test_animation_from_performance_matches_by_name(tmp_path, small):
    rng = np.random.default_rng(6)
    w = rng.random((12, small.n_shapes))
    rev = list(reversed(small.names)) + ["notInRig"]
    perf = Performance.curves(np.c_[w[:, ::-1], rng.random(12)], rev, fps=60.0, times=np.arange(12) / 60.0 + 2.0)
    back = read_animation(write_rig(tmp_path / "p.glb", small, perf))
    assert np.array_equal(back.data, w.astype(np.float32))
    assert back.times[0] == 0.0 and back.fps == 60.0
    with pytest.raises(ValueError, match=r"weights: .*no channels \['"):
        write_rig(tmp_path / "q.glb", small, perf.select(rev[:2]))


def test_custom_times_and_fps_estimate(tmp_path, small):
    w = np.random.default_rng(7).random((50, small.n_shapes))
    t = np.arange(50) / 30.0
    t[25:] += 5 / 30.0  # five dropped frames
    perf = read_animation(write_rig(tmp_path / "t.glb", small, w, times=t))
    assert np.array_equal(perf.times, t.astype(np.float32))
    assert perf.fps == 30.0
    assert read_animation(tmp_path / "t.glb", fps=25.0).fps == 25.0


@pytest.mark.parametrize("fps", [24.0, 25.0, 30.0, 60.0, 120.0, 30000 / 1001, 17.3])
def test_estimate_fps(fps):
    """glTF times are float32 seconds; read_animation estimates with snap="whole"."""
    t = (np.arange(4000) / fps).astype(np.float32).astype(np.float64)
    assert estimate_fps(t, snap="whole") == pytest.approx(fps, rel=1e-6)
    jittered = t + np.random.default_rng(8).normal(scale=1e-4 / fps, size=t.size)
    assert estimate_fps(np.sort(jittered), snap="whole") == pytest.approx(fps, rel=1e-3)


def test_cubicspline_and_step_samplers(tmp_path, small):
    """Files from other tools: CUBICSPLINE outputs hold (in-tangent, value, out-tangent) per key."""
    w = np.random.default_rng(9).random((6, 3)).astype(np.float32)
    path = write_rig(tmp_path / "c.glb", small, w)
    doc, blob = unpack(path)
    tangents = np.stack([w * 0 - 7, w, w * 0 + 7], axis=1).astype(np.float32)  # (T, 3, K)
    off = len(blob)
    blob += tangents.tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": off, "byteLength": tangents.nbytes})
    doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": tangents.size, "type": "SCALAR"})
    doc["buffers"][0]["byteLength"] = len(blob)
    doc["animations"][0]["samplers"][0].update(output=len(doc["accessors"]) - 1, interpolation="CUBICSPLINE")
    perf = read_animation(pack(tmp_path / "cs.glb", doc, blob))
    assert np.array_equal(perf.data, w) and perf.extras["interpolation"] == "CUBICSPLINE"


# -- normals and markers ----------------------------------------------------------------


def test_vertex_normals_against_loop(tiger):
    """Area-weighted normals against a plain per-triangle loop."""
    p, f = tiger.neutral, tiger.faces
    ref = np.zeros_like(p)
    for a, b, c in f:
        n = np.cross(p[b] - p[a], p[c] - p[a])
        ref[[a, b, c]] += n
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    got = vertex_normals(p, f)
    assert np.allclose(got, ref, atol=1e-12)
    both = vertex_normals(np.stack([p, p + tiger.deltas[0]]), f)
    assert np.allclose(both[0], ref, atol=1e-12)
    lonely = vertex_normals(np.vstack([p, [[9.0, 9.0, 9.0]]]), f)  # a vertex on no triangle
    assert np.allclose(np.linalg.norm(lonely, axis=1), 1) and np.array_equal(lonely[-1], [0, 0, 1])


def test_written_normals_and_morph_normals(tmp_path, small):
    doc, blob = unpack(write_rig(tmp_path / "n.glb", small))
    prim = doc["meshes"][0]["primitives"][0]

    def acc(i):
        a = doc["accessors"][i]
        bv = doc["bufferViews"][a["bufferView"]]
        return np.frombuffer(bytes(blob), np.float32, a["count"] * 3, bv["byteOffset"]).reshape(-1, 3)

    n0 = acc(prim["attributes"]["NORMAL"])
    assert np.allclose(np.linalg.norm(n0, axis=1), 1, atol=1e-6)
    assert np.allclose(n0, vertex_normals(small.neutral, small.faces), atol=1e-6)
    k = 2
    nk = n0 + acc(prim["targets"][k]["NORMAL"])
    assert np.allclose(nk, vertex_normals(small.neutral + small.deltas[k], small.faces), atol=1e-6)


def test_markers_travel_with_the_file(tmp_path, tiger):
    rng = np.random.default_rng(10)
    tri = tiger.faces[rng.choice(len(tiger.faces), 6, replace=False)]
    bary = rng.dirichlet(np.ones(3), size=6)
    layout = MarkerLayout([f"m{i}" for i in range(6)], tri, bary, rig="jeeliz_tiger.glb", extras={"source": "test"})
    out = write_rig(tmp_path / "m.glb", tiger, markers=layout)
    back = read_markers(out)
    assert back.names == layout.names and back.rig == layout.rig and back.extras == {"source": "test"}
    assert np.array_equal(back.vertices, layout.vertices) and np.array_equal(back.weights, layout.weights)
    assert "markerLayout" not in read_rig(out).extras
    assert np.allclose(back.points(tiger.neutral), layout.points(tiger.neutral))
    assert read_markers(RIGS / "jeeliz_tiger.glb") is None
    far = MarkerLayout.from_vertices(["x"], [tiger.n_vertices + 3])
    with pytest.raises(ValueError, match="vertices >= 2100"):
        write_rig(tmp_path / "bad.glb", tiger, markers=far)
    doc, blob = unpack(out)
    doc["meshes"][0]["extras"]["markerLayout"]["vertices"][0] = [5000, 5000, 5000]
    bad = pack(tmp_path / "badm.glb", doc, blob)
    with pytest.raises(GltfError, match=r"badm\.glb.*meshes\[0\]\.extras\.markerLayout\.vertices"):
        read_markers(bad)


# -- broken files -----------------------------------------------------------------------


def expect(path, *fields, fn=read_rig, exc=GltfError):
    with pytest.raises(exc) as info:
        fn(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for f in fields:
        assert f in msg, f"{f!r} not in {msg!r}"
    return msg


def test_truncated_glb_at_many_points(tmp_path, small_file):
    data = small_file.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    cuts = [0, 3, 8, 12, 16, 20, 20 + jlen // 2, 20 + jlen, 24 + jlen, 28 + jlen + 100, len(data) // 2, len(data) - 1]
    for cut in cuts:
        p = tmp_path / f"cut{cut}.glb"
        p.write_bytes(data[:cut])
        if cut == 0:
            expect(p, "file is empty")
        elif cut < 4:
            expect(p, "not a glTF file")
        elif cut < 12:
            expect(p, "GLB header is", "truncated")
        else:
            expect(p, "GLB header length", "truncated")
        with pytest.raises(GltfError):
            read_animation(p)


def test_truncated_glb_with_consistent_header(tmp_path, small_file):
    """A file cut short whose header length was 'fixed' up: the chunk lengths catch it."""
    data = small_file.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    for cut, field in [(16, "GLB chunk 0 header"), (20 + jlen // 2, "GLB chunk 0 at byte 12"),
                       (28 + jlen + 100, "GLB chunk 1 at byte")]:
        p = tmp_path / f"fix{cut}.glb"
        p.write_bytes(data[:8] + struct.pack("<I", cut) + data[12:cut])
        expect(p, field, "truncated")
    # BIN chunk itself shortened consistently: then buffers[0].byteLength catches it
    doc, blob = unpack(small_file)
    p = tmp_path / "short_bin.glb"
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    short = bytes(blob[:400])
    p.write_bytes(struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(short)) + struct.pack("<II", len(text), 0x4E4F534A)
                  + text + struct.pack("<II", len(short), 0x004E4942) + short)
    expect(p, "buffers[0] holds 400 bytes", "byteLength")


def test_corrupt_json_chunk(tmp_path, small_file):
    data = bytearray(small_file.read_bytes())
    data[20] = ord("x")  # the JSON's opening brace
    p = tmp_path / "json.glb"
    p.write_bytes(bytes(data))
    expect(p, "GLB JSON chunk", "not valid UTF-8 JSON")


def test_morph_target_vertex_count_mismatch(tmp_path, small_file, small):
    doc, blob = unpack(small_file)
    t1 = doc["meshes"][0]["primitives"][0]["targets"][1]["POSITION"]
    doc["accessors"].append(dict(doc["accessors"][t1], count=small.n_vertices - 5))
    doc["meshes"][0]["primitives"][0]["targets"][1]["POSITION"] = len(doc["accessors"]) - 1
    p = pack(tmp_path / "morph.glb", doc, blob)
    expect(p, "meshes[0].primitives[0].targets[1].POSITION", f"{small.n_vertices - 5} vertices", f"POSITION has {small.n_vertices}")


def test_target_names_count_mismatch(tmp_path, small_file):
    doc, blob = unpack(small_file)
    doc["meshes"][0]["extras"]["targetNames"].pop()
    p = pack(tmp_path / "names.glb", doc, blob)
    expect(p, "meshes[0].extras.targetNames", "2 names for 3 morph targets")
    expect(p, "meshes[0].extras.targetNames", fn=read_animation)
    doc["meshes"][0]["extras"]["targetNames"] = "abc"
    expect(pack(tmp_path / "names2.glb", doc, blob), "targetNames must be a list of strings")


def test_indices_out_of_range(tmp_path, small_file, small):
    doc, blob = unpack(small_file)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    off = doc["bufferViews"][acc["bufferView"]]["byteOffset"] + 4 * 7
    blob[off : off + 4] = struct.pack("<I", small.n_vertices + 10)
    p = pack(tmp_path / "idx.glb", doc, blob)
    expect(p, "meshes[0].primitives[0].indices", f"vertex {small.n_vertices + 10}", f"POSITION has {small.n_vertices}")


def test_missing_and_foreign_files(tmp_path):
    expect(tmp_path / "nope.glb", "no such file", exc=FileNotFoundError)
    png = tmp_path / "image.glb"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    expect(png, "not a glTF file", "GLB")
    txt = tmp_path / "notes.gltf"
    txt.write_text("hello, this is not glTF\n")
    expect(txt, "not a glTF file")
    other = tmp_path / "other.gltf"
    other.write_text(json.dumps({"foo": 1}))
    expect(other, "asset.version")
    odd = tmp_path / "odd.gltf"
    odd.write_text(json.dumps({"asset": "2.0"}))
    expect(odd, "asset.version")
    v1 = tmp_path / "v1.gltf"
    v1.write_text(json.dumps({"asset": {"version": "1.0"}}))
    expect(v1, "asset.version is '1.0'")
    arr = tmp_path / "list.gltf"
    arr.write_text("[1, 2]")
    expect(arr, "not a glTF file")
    expect(tmp_path, "is a directory")
    glb1 = tmp_path / "v1.glb"
    glb1.write_bytes(b"glTF" + struct.pack("<II", 1, 12))
    expect(glb1, "GLB header version is 1")


def test_bad_references(tmp_path, small_file):
    doc, blob = unpack(small_file)
    prim = doc["meshes"][0]["primitives"][0]
    for label, edit, fields in [
        ("acc", lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(POSITION=999), ["attributes.POSITION", "index 999"]),
        ("bv", lambda d: d["accessors"][prim["attributes"]["POSITION"]].update(bufferView=999), ["bufferView", "index 999"]),
        ("type", lambda d: d["accessors"][prim["attributes"]["POSITION"]].update(type="VEC7"), ["accessors[0]", "unknown type 'VEC7'"]),
        ("ctype", lambda d: d["accessors"][prim["attributes"]["POSITION"]].update(componentType=1234), ["accessors[0]", "componentType 1234"]),
        ("long", lambda d: d["accessors"][prim["attributes"]["POSITION"]].update(count=10**6), ["accessors[0]", "reads past the end of bufferViews[0]"]),
        ("mesh", lambda d: d.update(meshes=[]), ["meshes", "no meshes"]),
        ("nopos", lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop("POSITION"), ["primitives[0] has no POSITION"]),
        ("uri", lambda d: d["buffers"][0].update(uri="missing.bin"), ["buffers[0].uri 'missing.bin' not found"]),
        ("b64", lambda d: d["buffers"][0].update(uri="data:application/octet-stream;base64,@@@@"), ["buffers[0].uri", "base64"]),
    ]:
        d = json.loads(json.dumps(doc))
        edit(d)
        expect(pack(tmp_path / f"{label}.glb", d, blob), *fields)


def test_nan_positions_named(tmp_path, small_file):
    doc, blob = unpack(small_file)
    off = doc["bufferViews"][doc["accessors"][0]["bufferView"]]["byteOffset"]
    blob[off : off + 4] = struct.pack("<f", float("nan"))
    expect(pack(tmp_path / "nan.glb", doc, blob), "meshes[0]", "NaN")


def test_bad_animations(tmp_path, small_file, small):
    expect(RIGS / "jeeliz_tiger.glb", "animation argument (animations)", "the file has 0", fn=read_animation)
    doc, blob = unpack(small_file)
    d = json.loads(json.dumps(doc))
    d["animations"][0]["channels"][0]["target"]["path"] = "rotation"
    expect(pack(tmp_path / "nochan.glb", d, blob), "animations[0] has no channel with target.path 'weights'", fn=read_animation)
    d = json.loads(json.dumps(doc))
    out = d["animations"][0]["samplers"][0]["output"]
    d["accessors"][out]["count"] -= 1
    expect(pack(tmp_path / "count.glb", d, blob), "animations[0].samplers[0].output", "expected 1*10 keys*3 targets = 30",
           fn=read_animation)
    d = json.loads(json.dumps(doc))
    inp = d["animations"][0]["samplers"][0]["input"]
    off = d["bufferViews"][d["accessors"][inp]["bufferView"]]["byteOffset"]
    blob2 = bytearray(blob)
    blob2[off + 8 : off + 12] = struct.pack("<f", 0.0)  # third key back at t=0
    expect(pack(tmp_path / "times.glb", d, blob2), "animations[0].samplers[0].input", "strictly increasing", fn=read_animation)


def test_write_rejects_bad_arguments(tmp_path, small):
    with pytest.raises(ValueError, match=r"path: .*\.obj must end in \.glb or \.gltf"):
        write_rig(tmp_path / "x.obj", small)
    with pytest.raises(ValueError, match=r"weights: expected shape \(T, K\) with K=3"):
        write_rig(tmp_path / "x.glb", small, np.zeros((5, 4)))
    w = np.zeros((5, 3))
    w[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"weights: NaN/inf at frame 2, shape '"):
        write_rig(tmp_path / "x.glb", small, w)
    with pytest.raises(ValueError, match="times: glTF needs"):
        write_rig(tmp_path / "x.glb", small, np.zeros((3, 3)), times=[0.0, 0.2, 0.1])
    with pytest.raises(ValueError, match="times: glTF needs"):
        write_rig(tmp_path / "x.glb", small, np.zeros((3, 3)), times=[-1.0, 0.2, 0.3])
    with pytest.raises(ValueError, match="times: glTF needs"):  # distinct in float64, equal in float32
        write_rig(tmp_path / "x.glb", small, np.zeros((2, 3)), times=[100.0, 100.0 + 1e-9])
    with pytest.raises(ValueError, match=r"times: expected shape \(3,\)"):
        write_rig(tmp_path / "x.glb", small, np.zeros((3, 3)), times=[0.0, 0.1])
    with pytest.raises(ValueError, match="fps: must be positive"):
        write_rig(tmp_path / "x.glb", small, np.zeros((3, 3)), fps=0)
    bad = Rig(small.neutral, small.faces, small.deltas, small.names, extras={"obj": object()})
    with pytest.raises(TypeError, match="rig.extras.obj"):
        write_rig(tmp_path / "x.glb", bad)
    assert not list(tmp_path.iterdir())  # nothing half-written left behind


# -- real tools: Khronos glTF Validator and three.js GLTFLoader (node) -------------------


def run_node_check(path, *flags):
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not installed: install Node.js (>= 18), then run `npm ci` at the repository root")
    for pkg in ("gltf-validator", "three"):
        if not (ROOT / "node_modules" / pkg / "package.json").exists():
            pytest.fail(f"node_modules/{pkg} is missing: run `npm ci` at the repository root ({ROOT})")
    proc = subprocess.run([node, str(ROOT / "tests" / "gltf_validate.mjs"), str(path), *flags],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, f"gltf_validate.mjs failed ({proc.returncode}): {proc.stderr}"
    report = json.loads(proc.stdout)
    v = report["validator"]
    for m in v["messages"]:
        print(f"validator {['error', 'warning', 'info', 'hint'][m['severity']]}: {m['code']} {m['pointer']}: {m['message']}")
    return report


@pytest.fixture(scope="module")
def ict_animated(tmp_path_factory, rigs):
    ict = rigs["ict_facekit"]
    w = np.random.default_rng(11).random((90, ict.n_shapes))
    layout = MarkerLayout.from_vertices(["a", "b"], [0, 100], rig="ict_facekit.glb")
    return write_rig(tmp_path_factory.mktemp("ict") / "ict_anim.glb", ict, w, fps=30.0, markers=layout), ict


def test_validator_and_threejs_open_ict_with_animation(ict_animated):
    path, ict = ict_animated
    report = run_node_check(path)
    v = report["validator"]
    assert v["numErrors"] == 0, v["messages"]
    assert v["numWarnings"] == 0, v["messages"]
    # the one info the ICT file gets: TEXCOORD_0 without a material that samples a texture
    assert {m["code"] for m in v["messages"]} <= {"UNUSED_OBJECT"}
    (mesh,) = report["three"]["meshes"]
    assert mesh["vertices"] == ict.n_vertices
    assert mesh["morphTargets"] == ict.n_shapes == mesh["morphNormals"]
    assert mesh["targetNames"] == list(ict.names)
    assert mesh["hasNormals"] and mesh["morphTargetInfluences"] == [0.0] * ict.n_shapes
    (anim,) = report["three"]["animations"]
    (track,) = anim["tracks"]
    assert track["name"].endswith(".morphTargetInfluences")
    assert track["times"] == 90 and track["values"] == 90 * ict.n_shapes
    assert anim["duration"] == pytest.approx(89 / 30, rel=1e-6)


def test_validator_on_embedded_gltf_without_uvs_or_normals(tmp_path, tiger):
    w = np.random.default_rng(12).random((5, tiger.n_shapes))
    report = run_node_check(write_rig(tmp_path / "tiger.gltf", tiger, w, normals=False))
    assert report["validator"]["numErrors"] == 0 and report["validator"]["numWarnings"] == 0
    assert report["three"]["meshes"][0]["morphTargets"] == tiger.n_shapes
    assert not report["three"]["meshes"][0]["hasNormals"]


def test_validator_catches_a_broken_file(tmp_path, small_file, small):
    """The check can fail: an out-of-range index is an error for the validator too."""
    doc, blob = unpack(small_file)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    off = doc["bufferViews"][acc["bufferView"]]["byteOffset"]
    blob[off : off + 4] = struct.pack("<I", small.n_vertices + 10)
    report = run_node_check(pack(tmp_path / "broken.glb", doc, blob), "--no-three")
    assert report["validator"]["numErrors"] >= 1
    assert "ACCESSOR_INDEX_OOB" in {m["code"] for m in report["validator"]["messages"]}


def test_missing_node_modules_fails_with_npm_ci_hint(tmp_path, monkeypatch, small_file):
    """Without node_modules the check fails (never skips) and says what to run."""
    import test_io_gltf as me

    real_script = ROOT / "tests" / "gltf_validate.mjs"
    monkeypatch.setattr(me, "ROOT", tmp_path)
    with pytest.raises(pytest.fail.Exception, match="run `npm ci`"):
        run_node_check(small_file)
    # the script on its own, away from any node_modules: exit code 3 and the same hint
    script = tmp_path / "gltf_validate.mjs"
    shutil.copy(real_script, script)
    proc = subprocess.run([shutil.which("node") or "node", str(script), str(small_file)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3 and "npm ci" in proc.stderr
