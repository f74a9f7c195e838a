"""Issue 29, example poses on top of auto's shape map (design E, the posed path): can 2 poses be no worse than 0?

Cases C and D of :mod:`scripts.quality_cases` (names hidden; D only the non-ARKit shapes), the true
example poses at the frames ``suggest_poses`` proposes (:func:`quality_cases.true_poses`), scored as
there (mean face-vertex error, whole take, mm). ``auto`` with poses today solves frame by frame on the
covariance map and then learns from the poses (:func:`core.examples.learn_from_poses`); here the base
is auto's shape map (its 0-pose result) instead, corrected by

* ``learn_from_poses`` as auto runs it (linear + RBF, ridge 1e-2), and its linear / RBF parts, ridge 1 / 10;
* ``src-linear``: the correction regressed on the source's curves (the map's input) instead of its
  output, ``W = X + W_s W_sPᵀ (W_sP W_sPᵀ + r s² I)⁻¹ (P − X_P)`` (``s²`` the posed curves' mean
  square: ``r`` relative), i.e. the map itself corrected towards the poses, regularised towards
  auto's; ``r`` fixed, or chosen by leave-one-out over the poses (each pose predicted from the
  others, error in the character's face: ``dᵀ (D Dᵀ) d``; grid 1e-3 … 1e4);
* ``choose_by_loo`` (what ``auto`` runs since, :func:`core.examples.choose_by_loo`): none, src-linear at
  each ridge, or ``learn_from_poses``, by leave-one-out over the poses with the one-standard-error rule,
  each pose keyed at its own frame. (*auto today* is then that same rule, through the pipeline.)

::

    python scripts/posed_base_eval.py [--poses 2,4,8,16]
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
from core.examples import choose_by_loo, learn_from_poses  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from core.stages.methods import example_poses, pose_features  # noqa: E402

RIDGES = (1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0, 1e4)


def score(case, idx, W) -> float:
    full = np.zeros((len(W), case["rig"].n_shapes))
    full[:, idx] = W
    D = np.asarray(case["rig"].deltas[:, case["face"]], dtype=np.float64).reshape(case["rig"].n_shapes, -1)
    e = np.linalg.norm(((full - np.nan_to_num(case["truth"]["weights"])) @ D).reshape(len(W), -1, 3), axis=2)
    return float(e.mean() * 1e3)


def src_linear(X, Fs, poses, ridge):
    """The correction regressed on the source's curves (module docstring), unclipped."""
    fr = np.array(sorted(poses))
    P, A = np.stack([poses[f] for f in fr]), Fs[fr]
    s2 = np.trace(A @ A.T) / len(fr)
    return X + (Fs @ A.T) @ np.linalg.solve(A @ A.T + ridge * s2 * np.eye(len(fr)), P - X[fr])


def loo_ridge(X, Fs, poses, G):
    """The ridge of :data:`RIDGES` whose corrections from all poses but one predict the held-out
    pose best (summed over the poses, in the face: ``dᵀ G d``); the largest with one pose."""
    fr = sorted(poses)
    if len(fr) < 2:
        return RIDGES[-1]
    errs = []
    for r in RIDGES:
        e = 0.0
        for h in fr:
            rest = [f for f in fr if f != h]
            rows = [h] + rest
            pred = np.clip(src_linear(X[rows], Fs[rows], {i + 1: poses[f] for i, f in enumerate(rest)}, r)[0], 0, 1)
            d = pred - poses[h]
            e += d @ G @ d
        errs.append(e)
    return RIDGES[int(np.argmin(errs))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", default="2,4,8,16")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases("CD", Path(tmp))
        for c in "CD":
            case = built[c]
            res = Pipeline(cache=case["cache"], **case["settings"]).results(["load", "frames", "shapes", "stabilize", "solve"])
            idx, X = np.asarray(res["shapes"]["shape_index"]), np.asarray(res["solve"]["weights"])
            F = pose_features(res)
            Dr = np.asarray(res["shapes"]["rig"].deltas, dtype=np.float64).reshape(len(idx), -1)
            G = Dr @ Dr.T
            print(f"{c} 0 poses (auto's map) {score(case, idx, X):.4f}", flush=True)
            for n in (int(x) for x in args.poses.split(",")):
                items = qc.true_poses(case, n)
                poses = example_poses(res, items)
                now = Pipeline(cache=case["cache"], **case["settings"], example_poses=items).results(["solve"])["solve"]
                row = [f"auto today {score(case, idx, np.asarray(now['weights'])):.4f}"]
                for design, ridge in (("linear+rbf", 1e-2), ("linear+rbf", 1.0), ("rbf", 1e-2), ("linear", 1.0), ("linear", 10.0)):
                    row.append(f"map+{design} r{ridge:g} {score(case, idx, learn_from_poses(X, F, poses, design=design, ridge=ridge)):.4f}")
                for ridge in (1e-2, 1.0):
                    row.append(f"map+src-linear r{ridge:g} {score(case, idx, np.clip(src_linear(X, F, poses, ridge), 0, 1)):.4f}")
                r = loo_ridge(X, F, poses, G)
                row.append(f"map+src-linear LOO (r {r:g}) {score(case, idx, np.clip(src_linear(X, F, poses, r), 0, 1)):.4f}")
                W, label, _ = choose_by_loo(X, F, poses, gram=G)
                row.append(f"map+LOO one-SE choice ({label}) {score(case, idx, W):.4f}")
                print(f"{c} {n} poses: " + "; ".join(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
