"""The hard case of the curves issue, where names cannot help: the S07 Live Link take (ICT) onto
Rocketbox solved with only its non-ARKit shapes (visemes and FACS action units), scored against
the Rocketbox head driven by the same ARKit curves (the ground truth of docs/evaluation.md).

    python scripts/evaluate_nonarkit.py [--frames N] [--out docs/evaluation_nonarkit.md]

Writes a markdown table (generated; do not edit by hand): mean and p95 vertex error on the face,
marker error, weight range, shapes above 0.05 per frame, seconds — for the per-marker methods and
for the same methods on dense correspondence with ROM motion matching.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.geometry import face_vertices  # noqa: E402
from core.metrics import vertex_errors  # noqa: E402
from core.names import ARKIT_NAMES, canonical  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.report import ground_truth, method_metrics  # noqa: E402

FILES = dict(source=str(ROOT / "data/performances/livelinkface_take_s07.csv"), source_rig=str(ROOT / "data/rigs/ict_facekit.glb"),
             target_rig=str(ROOT / "data/rigs/rocketbox_female_adult_02.glb"))
DENSE = dict(correspondence="dense", motion_scale="rom")
CONFIGS = [("bounded", dict(method="bounded")), ("local", dict(method="local")), ("spacetime", dict(method="spacetime")),
           ("geometric", dict(method="geometric")),
           ("bounded (dense+rom, ridge 1e-3)", dict(DENSE, method="bounded", ridge=1e-3)),
           ("local (dense+rom)", dict(DENSE, method="local")),
           ("spacetime (dense+rom β=10)", dict(DENSE, method="spacetime", beta=10.0)),
           ("spacetime (dense+rom β=1)", dict(DENSE, method="spacetime", beta=1.0))]


#: the oracle fits every ORACLE_STEP-th frame (it is a bound, not a result: a sample is enough)
ORACLE_STEP = 4


def oracle(rig, truth, face, shapes):
    """Mean and p95 face-vertex error (mm) of the per-frame bounded [0, 1] least-squares fit of the
    true face by ``shapes`` on every face vertex: the best any method could reach with them."""
    from core.solvers.baselines import range_pf

    Wt = truth["weights"]
    frames = np.flatnonzero(np.isfinite(Wt).all(1))[::ORACLE_STEP]
    idx = np.array([rig.names.index(n) for n in shapes])
    D = np.asarray(rig.deltas[:, face], dtype=np.float64)
    Y = np.einsum("tk,kvc->tvc", Wt[frames], D)
    W = np.zeros((len(frames), rig.n_shapes))
    W[:, idx] = range_pf(D[idx], Y, 0.0, 1.0)
    mean, p95, _ = vertex_errors(rig.deltas, W, Wt[frames], face, np.ones(len(frames), bool))
    return float(np.nanmean(mean)), float(p95)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: the whole take)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "evaluation_nonarkit.md"))
    args = ap.parse_args(argv)
    pipe = Pipeline(cache=StageCache(256), **FILES, last_frame=(args.frames - 1) if args.frames else -1)
    rig = pipe.results(["load"])["load"]["target_rig"]
    shapes = [n for n in rig.names if canonical(n) not in ARKIT_NAMES]
    pipe.configure(target_shapes=",".join(shapes))
    base = pipe.results(["load", "frames"])
    truth, face = ground_truth(base["load"], base["frames"]), np.flatnonzero(face_vertices(rig.deltas))
    rows = []
    for label, cfg in CONFIGS:
        pipe.configure(**cfg)
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = method_metrics(pipe, truth, face)
        rows.append((label, r, time.perf_counter() - t))
        print(label, {k: round(float(r[k]), 3) for k in ("mean_mm", "p95_mm", "weight_min", "weight_max")}, flush=True)
    keyable = [x for x in rows if x[1]["weight_min"] >= -0.05 and x[1]["weight_max"] <= 1.05]
    rows.sort(key=lambda x: (x not in keyable, x[1]["mean_mm"]))
    lines = ["# The non-ARKit case", "",
             f"`python scripts/evaluate_nonarkit.py` ({args.frames or 'all'} frames); generated, do not edit by hand. "
             f"S07 (ICT) → Rocketbox with only its {len(shapes)} non-ARKit shapes, scored against the Rocketbox head "
             "driven by the same ARKit curves. Keyable results (weights within −0.05…1.05) first, by mean vertex error. "
             "The curves issue's target is ≤ 0.45 mm with weights inside [0, 1].", "",
             "| method | vertex mm | p95 mm | marker mm | w min | w max | shapes/frame | s |", "|---|---|---|---|---|---|---|---|"]
    for label, r, s in rows:
        lines.append(f"| {label} | {r['mean_mm']:.3f} | {r['p95_mm']:.2f} | {r['marker_mean_mm']:.2f} | {r['weight_min']:.2f} | "
                     f"{r['weight_max']:.2f} | {r['active_per_frame']:.1f} | {s:.1f} |")
    om, op = oracle(rig, truth, face, shapes)
    lines += ["", f"Not a method, the best these shapes can do: the true face fitted per frame by bounded least squares "
              f"on every face vertex (every {ORACLE_STEP}th frame) is {om:.3f} mm mean, {op:.2f} mm p95. The shapes can "
              "express the performance; what is lost is in carrying the ICT take onto Rocketbox through 41 markers or "
              "the dense correspondence (with the ARKit shapes the same methods do better: docs/evaluation.md)."]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
