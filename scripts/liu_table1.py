"""Liu et al. 2011, Table 1 on our data: marker reconstruction error, global vs local.

Setting (the paper's situation rebuilt from what data/ has):

* **Truth**: the full ICT FaceKit rig (53 shapes, left/right split) driven by a real Live
  Link Face take (ARKit curves, mapped by canonical names). Its asymmetries are real.
* **Markers**: ``n_markers`` vertices spread over the front of the face by farthest-point
  sampling (until data/layouts/ exists); virtual markers = those vertices on the driven
  ICT mesh, in metres.
* **Rig to solve with**: a *symmetric* 22-shape ICT rig, like the paper's rig of 22
  scanned, mostly symmetric expressions: every left/right pair summed into one shape
  (eyeLook* dropped: markers do not see the eyes), plus jawOpen, jawForward, mouthFunnel,
  mouthPucker, mouthRollLower, mouthRollUpper. A global solve cannot make an asymmetric
  face from it; local solves can, which is the paper's claim.
* Error as in the paper: per marker, the mean distance over frames between the marker and
  its reconstruction (eq. 3 evaluated at the marker); max / min / avg over markers, mm.

Run: ``python scripts/liu_table1.py [--take livelinkface_take_s07.csv] [--frames 600]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.io.gltf import read_rig  # noqa: E402
from core.model import MarkerLayout, Rig  # noqa: E402
from core.names import NameMap  # noqa: E402
from core.segment import marker_weights, segment  # noqa: E402
from core.solvers.local import local_precompute, masks_at, reconstruct_markers  # noqa: E402

DATA = ROOT / "data"
SYM_EXTRA = ("jawOpen", "jawForward", "mouthFunnel", "mouthPucker", "mouthRollLower", "mouthRollUpper")


def symmetric_rig(rig: Rig) -> Rig:
    """The 22-shape symmetric rig described in the module docstring."""
    names, deltas = [], []
    for n in rig.names:
        if n.endswith("_L") and not n.startswith("eyeLook"):
            names.append(n[:-2])
            deltas.append(rig.deltas[rig.index(n)] + rig.deltas[rig.index(n[:-2] + "_R")])
    for n in SYM_EXTRA:
        names.append(n)
        deltas.append(rig.deltas[rig.index(n)])
    return Rig(rig.neutral, rig.faces, np.array(deltas), names, rig.uvs, rig.units, rig.name + "_sym22")


def face_markers(rig: Rig, n_markers: int = 97, seed: int = 0) -> MarkerLayout:
    """Farthest-point sample of front-facing skin vertices that move > 1 mm in some shape."""
    from core.geometry import vertex_normals

    nrm = vertex_normals(rig.neutral, rig.faces)
    disp = np.linalg.norm(rig.deltas, axis=2).max(0)
    P = rig.neutral
    ok = (nrm[:, 2] > 0.35) & (disp > 1e-3) & (P[:, 2] > P[:, 2].max() - 0.09) & (P[:, 1] > P[:, 1].min() + 0.12)
    cand = np.flatnonzero(ok)
    # drop seam duplicates so a position is sampled once
    _, first = np.unique(P[cand], axis=0, return_index=True)
    cand = cand[np.sort(first)]
    rng = np.random.default_rng(seed)
    chosen = [int(cand[rng.integers(len(cand))])]
    dmin = np.linalg.norm(P[cand] - P[chosen[0]], axis=1)
    for _ in range(n_markers - 1):
        j = int(np.argmax(dmin))
        chosen.append(int(cand[j]))
        dmin = np.minimum(dmin, np.linalg.norm(P[cand] - P[cand[j]], axis=1))
    return MarkerLayout.from_vertices([f"m{i:03d}" for i in range(n_markers)], chosen, rig="ict_facekit.glb")


def read_livelink(path: Path):
    """(weights (T, C), channel names) of a Live Link Face CSV (the 52 ARKit channels)."""
    with open(path) as fh:
        header = fh.readline().strip().split(",")
    cols = [i for i, h in enumerate(header) if h not in ("Timecode", "BlendShapeCount")][:52]
    W = np.loadtxt(path, delimiter=",", skiprows=1, usecols=cols)
    return W, [header[i] for i in cols]


def setup(take: str = "livelinkface_take_s07.csv", n_markers: int = 97, frames=None):
    ict = read_rig(DATA / "rigs" / "ict_facekit.glb")
    W, chans = read_livelink(DATA / "performances" / take)
    if frames:
        W = W[:frames]
    G = NameMap.automatic(chans, ict.names).matrix(chans, ict.names)
    Wt = W @ G.T  # (T, 53) ICT weights
    layout = face_markers(ict, n_markers)
    n0, D = layout.on_rig(ict)
    targets = n0[None] + np.einsum("tk,kmc->tmc", Wt, D)
    sym = symmetric_rig(ict)
    return {"ict": ict, "sym": sym, "layout": layout, "weights": Wt, "targets": targets}


def errors_mm(setup_, R: int, constraint: str = "simplex", seg_kw=None):
    """(max, min, avg) over markers of the per-marker mean error (mm), and solve seconds."""
    sym, layout, targets = setup_["sym"], setup_["layout"], setup_["targets"]
    n0, D = layout.on_rig(sym)
    if R == 1:
        mw, mm = None, np.ones((1, layout.n_markers))
    else:
        seg = segment(sym, n_regions=R, **(seg_kw or {}))
        mw = marker_weights(sym, layout, seg.masks, graph=seg.graph)
        mm = masks_at(layout, seg.masks)
    t = time.perf_counter()
    U = local_precompute(n0, D, mw, constraint).solve(targets)
    secs = time.perf_counter() - t
    rec = reconstruct_markers(n0, D, U, mm)
    per_marker = np.linalg.norm(rec - targets, axis=2).mean(0) * 1000
    return per_marker.max(), per_marker.min(), per_marker.mean(), secs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--take", default="livelinkface_take_s07.csv")
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0 = all)")
    ap.add_argument("--markers", type=int, default=97)
    ap.add_argument("--constraint", default="both", choices=("simplex", "box", "both"))
    ap.add_argument("--position-weight", type=float, default=0.0)
    ap.add_argument("--still-tol", type=float, default=1e-2)
    ap.add_argument("--seeds", type=int, default=3, help="k-means seeds to average over")
    args = ap.parse_args(argv)
    s = setup(args.take, args.markers, args.frames or None)
    T = len(s["targets"])
    print(f"# ICT (53 shapes) driven by {args.take} ({T} frames) -> {args.markers} virtual markers; "
          f"solved with the symmetric 22-shape ICT rig; errors in mm (per-marker mean over frames)")
    print(f"# mean over k-means seeds 0..{args.seeds - 1}; 'Avg. range' = min..max of Avg. over the seeds")
    for c in (("simplex", "box") if args.constraint == "both" else (args.constraint,)):
        print(f"\n## constraint = {c}")
        print(f"{'Group':>6} {'Max.':>6} {'Min.':>6} {'Avg.':>6} {'Avg. range':>12} {'solve_s':>8}")
        for R in (1, 2, 6, 9, 12):
            rows = []
            for seed in range(1 if R == 1 else args.seeds):
                seg_kw = {"position_weight": args.position_weight, "still_tol": args.still_tol, "seed": seed}
                rows.append(errors_mm(s, R, c, seg_kw))
            mx, mn, avg, secs = np.mean(rows, axis=0)
            lo, hi = min(r[2] for r in rows), max(r[2] for r in rows)
            print(f"{'Global' if R == 1 else R:>6} {mx:6.2f} {mn:6.2f} {avg:6.2f} {f'{lo:.2f}..{hi:.2f}':>12} {secs:8.3f}")


if __name__ == "__main__":
    main()
