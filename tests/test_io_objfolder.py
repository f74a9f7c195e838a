"""OBJ-folder rigs: round trips on real rigs, vertex order kept at UV seams and for
unreferenced vertices, the parser checked against trimesh, and broken folders."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from core.io.objfolder import ObjFolderError, read_obj_folder, write_obj_folder
from core.model import Rig


def assert_rig_close(a: Rig, b: Rig, rtol=1e-12):
    """b equals a with shapes in sorted-name order, within float64 rounding relative to size."""
    a = a.subset(sorted(a.names))
    assert b.names == a.names
    tol = rtol * a.size
    assert np.abs(a.neutral - b.neutral).max() <= tol
    assert np.abs(a.deltas - b.deltas).max() <= tol
    assert np.array_equal(a.faces, b.faces)
    assert (a.uvs is None) == (b.uvs is None)
    if a.uvs is not None:
        assert np.abs(a.uvs - b.uvs).max() <= 1e-15


def test_tiger_round_trip(tmp_path, tiger):
    folder = write_obj_folder(tmp_path / "tiger", tiger)
    files = sorted(p.name for p in folder.iterdir())
    assert files == sorted(["neutral.obj"] + [n + ".obj" for n in tiger.names])
    back = read_obj_folder(folder)
    assert back.n_shapes == 11 and back.name == "tiger" and back.units == "m"
    assert_rig_close(tiger, back)
    # %.17g: the neutral comes back bit-exact
    assert np.array_equal(back.neutral, tiger.neutral)


def test_ict_subset_round_trip_with_uvs(tmp_path, ict):
    """ICT has UVs (vertices split at seams in the GLB, so one UV per vertex) and 14,629 vertices."""
    rig = ict.subset(ict.names[:3])
    back = read_obj_folder(write_obj_folder(tmp_path / "ict", rig))
    assert_rig_close(rig, back)
    assert back.n_vertices == 14629


@pytest.mark.slow
def test_ict_full_round_trip(tmp_path, ict):
    """All 53 shapes (its time: benchmarks/bench_io.py, objfolder_ict_write / _read)."""
    back = read_obj_folder(write_obj_folder(tmp_path / "ict", ict))
    assert_rig_close(ict, back)


def test_units(tmp_path, tiger):
    folder = write_obj_folder(tmp_path / "cm", tiger, units="cm")
    first = next(l for l in (folder / "neutral.obj").read_text().splitlines() if l.startswith("v "))
    assert np.allclose([float(x) for x in first.split()[1:]], tiger.neutral[0] * 100)
    back = read_obj_folder(folder, units="cm")
    assert back.units == "cm"
    assert_rig_close(tiger, back, rtol=1e-12)
    as_m = read_obj_folder(folder, units="m")
    assert np.allclose(as_m.neutral, tiger.neutral * 100)
    with pytest.raises(ValueError, match="unknown units 'furlong'"):
        read_obj_folder(folder, units="furlong")


def test_parser_matches_trimesh(tmp_path, tiger, ict):
    """On files with no seams and no loose vertices, trimesh's loader is a reference."""
    for rig in (tiger, ict.subset(ict.names[:1])):
        folder = write_obj_folder(tmp_path / rig.name, rig)
        back = read_obj_folder(folder)
        ref = trimesh.load(folder / "neutral.obj", force="mesh", process=False, maintain_order=True)
        assert np.array_equal(back.neutral, ref.vertices)
        assert np.array_equal(back.faces, ref.faces)
        shape = trimesh.load(folder / f"{back.names[0]}.obj", force="mesh", process=False, maintain_order=True)
        assert np.allclose(back.neutral + back.deltas[0], shape.vertices, rtol=0, atol=1e-15 * rig.size)


SEAMS = """# a quad split along a UV seam, a triangle, a vertex on no face, quads and negative indices
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 9 9 9
v 2 0 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 1
f 1/1/1 2/2/1 3/3/1 4/4/1
f 2/5/1 6/1/1 3/3/1
"""


def _shape_text(offset):
    lines = SEAMS.splitlines()
    out = []
    for l in lines:
        if l.startswith("v "):
            x, y, z = (float(t) for t in l.split()[1:])
            out.append(f"v {x} {y} {z + offset}")
        else:
            out.append(l)
    return "\n".join(out) + "\n"


def test_seams_and_loose_vertices_keep_vertex_order(tmp_path):
    folder = tmp_path / "seams"
    folder.mkdir()
    (folder / "neutral.obj").write_text(SEAMS)
    (folder / "up.obj").write_text(_shape_text(0.5))
    # a shape file that only has its v lines (no faces) is fine too
    (folder / "down.obj").write_text("".join(l + "\n" for l in _shape_text(-0.25).splitlines() if l.startswith("v ")))
    with pytest.warns(UserWarning, match=r"neutral\.obj: 1 vertices have several texture coordinates"):
        rig = read_obj_folder(folder)
    assert rig.n_vertices == 6  # v lines in the file, nothing merged, split or dropped
    assert np.array_equal(rig.neutral, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [9, 9, 9], [2, 0, 0]])
    assert np.array_equal(rig.faces, [[0, 1, 2], [0, 2, 3], [1, 5, 2]])  # quad fan-triangulated
    assert rig.uvs is None  # vertex 2 (index 1) has UVs (1,0) and (.5,.5)
    assert rig.names == ("down", "up")
    assert np.allclose(rig.deltas[0], [0, 0, -0.25]) and np.allclose(rig.deltas[1], [0, 0, 0.5])


def test_uvs_in_a_different_order_from_vertices(tmp_path):
    folder = tmp_path / "uv"
    folder.mkdir()
    (folder / "neutral.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"
                                        "vt 0.9 0.9\nvt 0.1 0.2\nvt 0.3 0.4\nvt 0.5 0.6\n"
                                        "f 1/2 2/3 3/4\nf -3/-2 -1/-4 -2/-1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rig = read_obj_folder(folder)
    assert np.array_equal(rig.faces, [[0, 1, 2], [1, 3, 2]])
    assert np.allclose(rig.uvs, [[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [0.9, 0.9]])
    assert rig.n_shapes == 0


def make_folder(tmp_path, rig, name="rig"):
    return write_obj_folder(tmp_path / name, rig.subset(rig.names[:3]))


def test_shape_with_different_vertex_count(tmp_path, tiger):
    folder = make_folder(tmp_path, tiger)
    victim = folder / f"{sorted(tiger.names[:3])[1]}.obj"
    lines = victim.read_text().splitlines()
    drop = next(i for i, l in enumerate(lines) if l.startswith("v "))
    victim.write_text("\n".join(lines[:drop] + lines[drop + 1 :]) + "\n")
    with pytest.raises(ObjFolderError) as info:
        read_obj_folder(folder)
    msg = str(info.value)
    assert str(victim) in msg and "2099 vertices" in msg and "neutral.obj has 2100" in msg


def test_empty_missing_and_bad_folders(tmp_path, tiger):
    with pytest.raises(FileNotFoundError, match="nope: no such folder"):
        read_obj_folder(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no objs here")
    with pytest.raises(ObjFolderError, match=r"empty: no OBJ files \(expected neutral\.obj"):
        read_obj_folder(empty)
    folder = make_folder(tmp_path, tiger)
    (folder / "neutral.obj").unlink()
    with pytest.raises(ObjFolderError, match=r"neutral\.obj: missing; the folder has 3 other OBJ files"):
        read_obj_folder(folder)
    with pytest.raises(ObjFolderError, match="not a folder"):
        read_obj_folder(folder / f"{tiger.names[0]}.obj")


def test_bad_lines_named_with_file_and_line(tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    neutral = folder / "neutral.obj"
    neutral.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(ObjFolderError, match=r"neutral\.obj:4: face 'f 1 2 4' indexes a vertex outside 1\.\.3"):
        read_obj_folder(folder)
    neutral.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ObjFolderError, match=r"neutral\.obj: needs vertices .* found 3 and 0"):
        read_obj_folder(folder)
    neutral.write_text("v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ObjFolderError, match=r"neutral\.obj: vertex 2 \('v 1 zero 0'\) is not three numbers"):
        read_obj_folder(folder)
    neutral.write_text("v 0 0 0\nv \nv 0 1 0\nf 1 2 3\n")  # a blank v line is not skipped
    with pytest.raises(ObjFolderError, match=r"neutral\.obj: vertex 2 \('v '\) is not three numbers"):
        read_obj_folder(folder)
    neutral.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n")
    with pytest.raises(ObjFolderError, match=r"neutral\.obj:4: .*non-integer index"):
        read_obj_folder(folder)
    neutral.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ObjFolderError, match=r"neutral\.obj: not a text OBJ file"):
        read_obj_folder(folder)
    neutral.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (folder / "s.obj").write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ObjFolderError, match=r"bad: .*NaN"):
        read_obj_folder(folder)


def test_write_refuses_and_overwrites(tmp_path, tiger):
    rig = tiger.subset(tiger.names[:3])
    folder = write_obj_folder(tmp_path / "w", rig)
    with pytest.raises(FileExistsError, match="already has 4 OBJ files; pass overwrite=True"):
        write_obj_folder(folder, rig)
    (folder / "stale.obj").write_text((folder / "neutral.obj").read_text())
    (folder / "keep.txt").write_text("not an obj")
    two = tiger.subset(tiger.names[3:5])
    write_obj_folder(folder, two, overwrite=True)
    assert_rig_close(two, read_obj_folder(folder))
    assert (folder / "keep.txt").exists()
    for bad in ["a/b", "", "neutral", "x:y"]:
        r = Rig(rig.neutral, rig.faces, rig.deltas[:1], [bad])
        with pytest.raises(ValueError, match="cannot be an OBJ file name"):
            write_obj_folder(tmp_path / "n", r)
    r = Rig(rig.neutral, rig.faces, rig.deltas[:2], ["Smile", "smile"])
    with pytest.raises(ValueError, match="differ only in case"):
        write_obj_folder(tmp_path / "c", r)
