"""Issue 29, cases B and C, design D: the two rigs' shapes compared over dense correspondence (the
whole face) instead of the 41 markers — namesakes recovered, and the sparse shape map auto uses.

The cases are :mod:`scripts.quality_cases`' (S07 take on ICT -> Rocketbox; B: only the non-ARKit
shapes, C: every shape renamed), scored the same way. For each case and each number of dense
points (the first N of the rig pair's farthest-point order):

* ``namesakes``   how many of the 53 source shapes :func:`core.shape_matching.match_shapes` pairs
                  with their true namesake (C only: B has none), over the markers and the points;
* ``map l1=…``    ``clip(W_source Mᵀ, 0, 1)``, M :func:`core.shape_matching.aligned_shape_map`
                  (covariance-aligned source shapes, sparse fit) with the target's shapes warped
                  by the calibrate stage's RBF (``auto``'s :func:`core.stages.methods.dense_shape_map`);
* ``auto``        the default, as ``face-retarget retarget`` runs it.

``--pair tiger`` runs auto on ICT -> jeeliz tiger and triceratops (11 shapes, no ground truth): the
weight range, the marker fit and the strongest pairs, to see nothing breaks.

::

    python scripts/dense_matching_eval.py [--cases BC] [--points 1000,2000,5000] [--l1 0.2,0.3,0.4] [--pair tiger]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import quality_cases as qc  # noqa: E402
from core.motion_alignment import apply_alignment, covariance_alignment  # noqa: E402
from core.names import NameMap  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.metrics import vertex_errors  # noqa: E402
from core.shape_matching import aligned_shape_map, mapped_weights, match_shapes  # noqa: E402

STAGES = ["load", "frames", "correspond", "shapes", "stabilize", "calibrate", "dense_correspondence"]


def namesakes(match, G) -> int:
    """Pairs of ``match`` whose target shape is the source shape's namesake (``G`` (K, J) != 0)."""
    return int(sum(G[k, j] != 0 for j, k in zip(match.source, match.target)))


def mm(case, idx, W) -> float:
    full = np.zeros((len(W), case["rig"].n_shapes))
    full[:, idx] = W
    Wt = case["truth"]["weights"]
    return float(np.nanmean(vertex_errors(case["rig"].deltas, full, Wt, case["face"], np.isfinite(Wt).all(1))[0]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="BC")
    ap.add_argument("--points", default="1000,2000,5000")
    ap.add_argument("--l1", default="0.2,0.3,0.4")
    ap.add_argument("--pair", default="rocketbox", choices=["rocketbox", "tiger"])
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.pair == "tiger":
        for target in ("jeeliz_tiger", "jeeliz_triceratops"):
            pipe = Pipeline(cache=StageCache(64), source=str(qc.TAKE), source_rig=str(qc.SOURCE_RIG),
                            target_rig=str(ROOT / f"data/rigs/{target}.glb"))
            res = pipe.results(["solve", "evaluate"])
            W, info = np.asarray(res["solve"]["weights"]), res["solve"]["info"]
            print(f"{target}: {info['auto']}\n  w=[{np.nanmin(W):.3f}, {np.nanmax(W):.3f}] "
                  f"marker error median {np.nanmedian(res['evaluate']['marker_error_mm']):.2f} mm; "
                  + ", ".join(f"{a}→{b}" for a, b in list(info.get("shape_matches", {}).items())[:8]), flush=True)
        return 0
    points = [int(n) for n in args.points.split(",")]
    l1s = [float(v) for v in args.l1.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases(args.cases.upper(), Path(tmp))
        for c in args.cases.upper():
            case = built[c]
            pipe = Pipeline(cache=case["cache"], **case["settings"])
            res = pipe.results(STAGES)
            ld, sh, cal, dc = res["load"], res["shapes"], res["calibrate"], res["dense_correspondence"]
            srig, rig, idx = ld["source_rig"], sh["rig"], np.asarray(sh["shape_index"])
            G = NameMap.automatic(srig.names, case["rig"].names).matrix(srig.names, case["rig"].names)[idx]
            Ws = np.nan_to_num(np.asarray(res["stabilize"]["source"].source_weights, dtype=np.float64))
            names = list(res["stabilize"]["names"])
            Dm = res["correspond"]["source_layout"].select(names).points(srig.deltas)
            if c == "C":
                m = match_shapes(apply_alignment(cal["source_map"], Dm), np.asarray(cal["deltas"]))
                print(f"{c} markers: namesakes {namesakes(m, G)} of {len(Ws.T)} ({int(m.sure.sum())} sure)", flush=True)
            warp = cal["target"].warp
            for n in points:
                pts = list(dc["source_layout"].names[:n])
                Ds = dc["source_layout"].select(pts).points(srig.deltas)
                nt, dt = dc["target_layout"].select(pts).on_rig(rig)
                T = warp(nt[None] + dt) - warp(nt)[None]
                if c == "C":
                    m = match_shapes(apply_alignment(covariance_alignment(Ds, T), Ds), T)
                    print(f"{c} {n} points: namesakes {namesakes(m, G)} ({int(m.sure.sum())} sure)", flush=True)
                for l1 in l1s:
                    M = aligned_shape_map(Ds, T, l1=l1)
                    W = mapped_weights(M, Ws)
                    print(f"{c} {n} points map l1={l1}: mean_mm={mm(case, idx, W):.3f} w=[{W.min():.3f}, {W.max():.3f}] "
                          f"shapes per source shape {(M > 0.01).sum(0).mean():.1f}", flush=True)
            r = qc.run(case, {})
            print(qc.line(c, "auto", r), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
