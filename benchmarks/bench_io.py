"""Benchmark: reading and writing the interchange files (the speed asserts the tests had).

Cases (one ``BENCH`` line each, best of ``REPEAT`` runs on each side):

* ``livelink_read_rom_4030rows``: :func:`core.io.livelink.read_livelink` of the bundled
  4,030-row ROM capture; ref = Python's csv module and ``float`` on every cell (the
  reference the tests check every value against, tests/test_io_livelink.py).
* ``livelink_read_1000rows_300loss``: the same on 1,000 ROM rows of which 300 are tracking
  loss rows as the app writes them (timecode, ``0``, nothing else), in three runs like a real
  take's; ref as above.
* ``gltf_write_ict_T300`` / ``gltf_read_ict`` / ``gltf_read_animation_ict_T300``:
  :func:`core.io.gltf.write_rig` of ICT (14,629 vertices, 53 shapes) with 300 frames of
  weights, then ``read_rig`` and ``read_animation`` of that file; ref = the same float32
  arrays to and from one uncompressed ``.npz`` (the bytes without a container: a floor,
  ratio < 1 expected).
* ``objfolder_ict_write`` / ``objfolder_ict_read``: :mod:`core.io.objfolder` of the whole ICT
  rig (neutral + 53 OBJ files); ref = trimesh's OBJ exporter and loader on the same meshes.

Run: ``python benchmarks/bench_io.py``
"""

from __future__ import annotations

import csv
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.io.gltf import read_animation, read_rig, write_rig  # noqa: E402
from core.io.livelink import read_livelink  # noqa: E402
from core.io.objfolder import read_obj_folder, write_obj_folder  # noqa: E402

PERFORMANCES = ROOT / "data" / "performances"
RIGS = ROOT / "data" / "rigs"
ROM = PERFORMANCES / "livelinkface_rom.csv"
REPEAT = 3


def best(f, repeat=REPEAT) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return min(times)


def line(case, ours, ref_s, **kv) -> str:
    extra = " ".join(f"{k}={v}" for k, v in kv.items())
    return f"BENCH {case} ours_s={ours:.4f} ref_s={ref_s:.4f} ratio={ref_s / ours:.3g} {extra}".rstrip()


def csv_reference(path: Path) -> list:
    """Every cell after the timecode as a float, with the csv module (no validation)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return [[float(c) for c in r[1:] if c] for r in rows[1:]]


def loss_take(folder: Path) -> Path:
    """1,000 ROM rows with three runs of loss rows (129, 123 and 48 rows: 300), as
    tests/test_io_livelink.py's real-like take."""
    rows = [ln.split(",") for ln in ROM.read_text().splitlines()[:1001]]
    for a, b in ((100, 229), (400, 522), (700, 746)):
        for i in range(a, b + 1):
            rows[i] = [rows[i][0], "0"]
    p = folder / "real_like.csv"
    p.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return p


def bench_livelink(folder: Path) -> None:
    for case, path, loss in (("livelink_read_rom_4030rows", ROM, 0),
                             ("livelink_read_1000rows_300loss", loss_take(folder), 300)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the loss rows' DataQualityWarning
            perf = read_livelink(path)
            assert (~perf.valid.any(axis=1)).sum() == loss
            ours = best(lambda: read_livelink(path))
        ref = best(lambda: csv_reference(path))
        print(line(case, ours, ref, rows=perf.n_frames, loss_rows=loss, ref="csv-module+float"), flush=True)


def bench_gltf(folder: Path, ict) -> None:
    w = np.random.default_rng(13).random((300, ict.n_shapes))
    write_rig(folder / "warm.glb", ict.subset(ict.names[:1]))  # imports, first-call costs
    path = folder / "ict.glb"
    arrays = {"neutral": ict.neutral.astype(np.float32), "faces": ict.faces.astype(np.uint32),
              "deltas": ict.deltas.astype(np.float32), "weights": w.astype(np.float32),
              "times": (np.arange(300) / 30.0).astype(np.float32)}
    npz = folder / "ict.npz"

    def ref_write():
        np.savez(npz, **arrays)

    def ref_read(keys):
        with np.load(npz) as z:
            return [np.array(z[k]) for k in keys]

    ours = best(lambda: write_rig(path, ict, w))
    ref = best(ref_write)
    mb = path.stat().st_size / 1e6
    print(line("gltf_write_ict_T300", ours, ref, V=ict.n_vertices, K=ict.n_shapes, T=300, glb_mb=f"{mb:.1f}",
               ref="numpy-npz-floor"), flush=True)
    rig = read_rig(path)
    assert rig.n_vertices == ict.n_vertices and rig.names == ict.names
    ours = best(lambda: read_rig(path))
    ref = best(lambda: ref_read(("neutral", "faces", "deltas")))
    print(line("gltf_read_ict", ours, ref, V=ict.n_vertices, K=ict.n_shapes, ref="numpy-npz-floor"), flush=True)
    assert read_animation(path).n_frames == 300
    ours = best(lambda: read_animation(path))
    ref = best(lambda: ref_read(("weights", "times")))
    print(line("gltf_read_animation_ict_T300", ours, ref, K=ict.n_shapes, T=300, ref="numpy-npz-floor"), flush=True)


def bench_objfolder(folder: Path, ict) -> None:
    import trimesh

    meshes = {"neutral": ict.neutral, **{n: ict.neutral + d for n, d in zip(ict.names, ict.deltas)}}
    tm = folder / "trimesh"
    tm.mkdir()

    def ref_write():
        for name, V in meshes.items():
            trimesh.Trimesh(V, ict.faces, process=False).export(tm / f"{name}.obj")

    def ref_read():
        return [trimesh.load(tm / f"{name}.obj", process=False, maintain_order=True) for name in meshes]

    ours_dir = folder / "ours"
    ours = best(lambda: write_obj_folder(ours_dir, ict), repeat=1)
    ref = best(ref_write, repeat=1)
    print(line("objfolder_ict_write", ours, ref, V=ict.n_vertices, files=len(meshes), ref="trimesh-obj-export"), flush=True)
    back = read_obj_folder(ours_dir)
    assert back.n_vertices == ict.n_vertices and back.n_shapes == ict.n_shapes
    ours = best(lambda: read_obj_folder(ours_dir), repeat=1)
    ref = best(ref_read, repeat=1)
    print(line("objfolder_ict_read", ours, ref, V=ict.n_vertices, files=len(meshes), ref="trimesh-obj-load"), flush=True)


def main():
    ict = read_rig(RIGS / "ict_facekit.glb")
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        bench_livelink(folder)
        bench_gltf(folder, ict)
        bench_objfolder(folder, ict)


if __name__ == "__main__":
    main()
