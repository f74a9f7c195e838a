"""Mesh-sequence sources (core.io.sequence): OBJ/PLY folders, glTF morph-target frames, and the
errors that name the file and frame that differ."""

import json

import numpy as np
import pytest

from datapaths import RIGS

from core.io import sequence
from core.io.gltf import read_rig
from core.io.performance import read_performance
from core.io.tabular import DataQualityWarning
from core.model import Performance


@pytest.fixture(scope="module")
def take():
    rig = read_rig(RIGS / "jeeliz_tiger.glb")
    W = np.random.default_rng(1).random((12, rig.n_shapes))
    return rig, Performance.meshes(rig.evaluate(W), 30.0, faces=rig.faces, name="take")


def test_natural_order():
    names = ["f10.obj", "f2.obj", "f1.obj", "F3.obj"]
    assert sorted(names, key=sequence.natural_key) == ["f1.obj", "f2.obj", "F3.obj", "f10.obj"]


@pytest.mark.parametrize("fmt", ["obj", "ply"])
def test_folder_round_trip(tmp_path, take, fmt):
    rig, perf = take
    folder = sequence.write_mesh_sequence(tmp_path / "seq", perf, frame_format=fmt)
    back = read_performance(folder)  # a folder is a mesh sequence
    assert back.kind == "meshes" and back.n_frames == 12 and back.fps == 30.0  # from sequence.json
    np.testing.assert_array_equal(back.extras["faces"], rig.faces)
    atol = 0 if fmt == "obj" else 1e-7 * rig.size  # OBJ: 17 digits; trimesh writes PLY as float32
    np.testing.assert_allclose(back.data, perf.data, rtol=0, atol=atol)
    assert back.extras["files"][0] == f"frame_0000.{fmt}"
    assert read_performance(folder, fps=60).fps == 60  # the flag wins over the sidecar


def test_folder_numbering_sidecar_and_gaps(tmp_path, take):
    rig, perf = take
    folder = tmp_path / "cap"
    folder.mkdir()
    faces = "".join(f"f {a} {b} {c}\n" for a, b, c in rig.faces + 1)
    for n in (2, 3, 5, 10):  # frame 4 and 6-9 are missing; natural order puts 10 last
        v = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in (perf.data[n] * 100).tolist())
        (folder / f"shot_{n}.obj").write_text(v + faces)
    (folder / "sequence.json").write_text(json.dumps({"fps": 24, "units": "cm"}))
    with pytest.warns(DataQualityWarning, match=r"5 frame numbers have no file \(4, 6, 7, 8, 9\)"):
        back = sequence.read_mesh_folder(folder)
    assert back.fps == 24 and back.units == "cm" and back.n_frames == 9
    np.testing.assert_array_equal(back.valid, [1, 1, 0, 1, 0, 0, 0, 0, 1])
    np.testing.assert_allclose(back.data[8], perf.data[10], rtol=0, atol=1e-15)
    assert np.isnan(back.data[2]).all()  # a missing frame is masked, never zeroed
    np.testing.assert_array_equal(back.extras["frame_numbers"], np.arange(2, 11))
    np.testing.assert_allclose(back.times, np.arange(9) / 24)


def test_frames_that_differ_are_named(tmp_path, take):
    rig, perf = take
    folder = sequence.write_mesh_sequence(tmp_path / "seq", perf.frames(0, 4))
    f2 = folder / "frame_0002.obj"
    f2.write_text("v 0 0 0\n" + f2.read_text())  # one vertex more (an unreferenced one shifts every index)
    with pytest.raises(sequence.SequenceError, match=r"frame_0002\.obj: frame 2 has 2101 vertices, frame_0000\.obj has 2100"):
        read_performance(folder)
    sequence.write_mesh_sequence(tmp_path / "seq2", perf.frames(0, 3))
    f1 = tmp_path / "seq2" / "frame_0001.obj"
    f1.write_text(f1.read_text().replace("f 1 2 3\n", "f 1 3 2\n", 1) if "f 1 2 3\n" in f1.read_text()
                  else f1.read_text() + "f 1 2 3\n")
    with pytest.raises(sequence.SequenceError, match=r"frame_0001\.obj: frame 1 has other faces than frame_0000\.obj"):
        read_performance(tmp_path / "seq2")
    (tmp_path / "seq2" / "frame_0003.ply").write_bytes(b"ply\n")
    with pytest.raises(sequence.SequenceError, match=r"mixes \.obj and \.ply"):
        read_performance(tmp_path / "seq2")


def test_rig_folder_and_empty_folder_are_refused(tmp_path, take):
    from core.io.objfolder import write_obj_folder

    rig, _ = take
    write_obj_folder(tmp_path / "rig", rig)
    with pytest.raises(sequence.SequenceError, match="neutral.obj, so it is a blendshape rig folder"):
        read_performance(tmp_path / "rig")
    (tmp_path / "empty").mkdir()
    with pytest.raises(sequence.SequenceError, match="no per-frame mesh files"):
        read_performance(tmp_path / "empty")
    with pytest.raises(ValueError, match="a folder is read as a mesh sequence"):
        read_performance(tmp_path / "empty", kind="curves")


def test_gltf_morph_target_frames(tmp_path, take):
    rig, perf = take
    path = sequence.write_mesh_sequence(tmp_path / "seq.glb", perf)
    assert read_performance(path).kind == "curves"  # auto: a glTF animation is weight curves
    back = read_performance(path, kind="meshes")
    assert back.kind == "meshes" and back.n_frames == 12 and back.fps == 30.0
    np.testing.assert_array_equal(back.extras["faces"], rig.faces)
    np.testing.assert_allclose(back.data, perf.data, rtol=0, atol=1e-7 * rig.size)


def test_topology_rig(take):
    rig, perf = take
    masked = Performance.meshes(perf.data, 30, faces=rig.faces, valid=np.r_[False, np.ones(11, bool)])
    topo = sequence.topology_rig(masked)
    np.testing.assert_array_equal(topo.neutral, perf.data[1])  # the first frame with data
    assert topo.n_shapes == 0 and np.array_equal(topo.faces, rig.faces)
    with pytest.raises(ValueError, match=r"has no faces \(extras\['faces'\]\)"):
        sequence.topology_rig(Performance.meshes(perf.data, 30))
