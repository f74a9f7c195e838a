"""Issue 29, cases B and C, design 2: the shape-to-shape correspondence recovered from geometry
(:mod:`core.shape_matching`) used as pseudo-names or as a whole-take map, against ``auto``.

The cases are :mod:`scripts.quality_cases`' (S07 take on ICT -> Rocketbox; B: only the non-ARKit
shapes, C: every shape renamed), scored the same way (:mod:`core.report`: face-vertex error
against Rocketbox driven by the take's curves through their ARKit names). Every variant works on
what ``auto`` sees: the 41 markers, the actor's range of motion matched to the character's
(``motion_scale = rom``), the solver's shapes, bounds [0, 1], ridge 1e-2:

* ``bounded (auto before)``     the per-frame bounded solve of the source's motion as it is;
* ``auto``                      the default: the same on the motion re-sculpted in the character's style
                                (:func:`core.shape_matching.restyled_motion`, β 0.5);
* ``pull nw=…``                 the whole take at once (spacetime, β 10) pulled towards the sure
                                pairs' pseudo-name curves, name weight ``nw × confidence``;
* ``pull nw=… others 0``        the same with the unmatched shapes held at zero (as auto does with
                                real names, case A);
* ``map``                       ``clip(W_source Mᵀ)``, M the per-shape bounded fit;
* ``blend a``                   ``(1 − a) auto + a map``;
* ``bounded matched only``      auto's per-frame solve on the assigned shapes only.

``--pair tiger`` runs the variants on ICT -> jeeliz tiger and triceratops (11 shapes of their own
names, no ground truth: the marker fit and the weight range are printed, to see nothing breaks).

::

    python scripts/shape_matching_eval.py [--cases BC] [--pair rocketbox|tiger] [--frames N]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import quality_cases as qc  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.metrics import vertex_errors  # noqa: E402
from core.shape_matching import match_shapes, pseudo_names, shape_map  # noqa: E402
from core.solvers import baselines  # noqa: E402
from core.solvers.spacetime import SpacetimeSolver  # noqa: E402
from core.stages.methods import AUTO_RIDGE  # noqa: E402

STAGES = ["load", "frames", "correspond", "shapes", "stabilize", "calibrate", "personalize", "synthesize"]


def inputs_of(pipe) -> dict:
    """What auto's solve sees, plus the source rig's shapes at the same markers in the character's
    range: ``Ds (J, M, 3)``, ``B (K, M, 3)``, ``S (T, M, 3)``, ``Ws (T, J)``, auto's weights ``W0``."""
    res = pipe.results(STAGES[:-1])
    t = time.perf_counter()
    res = pipe.results(STAGES)
    seconds = time.perf_counter() - t
    names = res["stabilize"]["names"]
    rig = res["load"]["source_rig"]
    Ds = res["correspond"]["source_layout"].select(list(names)).points(rig.deltas)
    Ds = Ds * res["calibrate"]["source_scale"][None, :, None]
    src = res["calibrate"]["source"]
    W0 = np.asarray(res["synthesize"]["weights"])[:, res["shapes"]["shape_index"]]
    return {"Ds": Ds, "B": np.asarray(res["personalize"]["deltas"]), "S": src.deltas, "valid": src.valid,
            "Ws": np.nan_to_num(np.asarray(src.source_weights)), "W0": W0, "auto_seconds": seconds,
            "idx": res["shapes"]["shape_index"],
            "source_names": rig.names, "target_names": res["shapes"]["rig"].names}


def variants(x: dict):
    """Yield ``(label, weights (T, K), seconds)`` of each design on the solve's inputs ``x``."""
    Ds, B, S, valid, Ws = x["Ds"], x["B"], x["S"], x["valid"], x["Ws"]
    K = len(B)
    t = time.perf_counter()
    Wb = baselines.range_pf(B, S, 0.0, 1.0, valid, ridge=AUTO_RIDGE)
    yield "bounded (auto before)", Wb, time.perf_counter() - t
    yield "auto (restyled)", x["W0"], x["auto_seconds"]
    t = time.perf_counter()
    m = match_shapes(Ds, B)
    named, conf = pseudo_names(m, Ws, K)
    t_match = time.perf_counter() - t
    x["match"] = m
    for nw in (0.1, 1.0, 30.0):
        for held in (False, True):
            t = time.perf_counter()
            solver = SpacetimeSolver(B, S, alpha=0.0, beta=10.0, valid=valid, ridge=AUTO_RIDGE, lower=0.0, upper=1.0,
                                     name_target=named, name_weight=nw * conf)
            W = solver.solve(zero=(conf == 0) if held else None)
            yield f"pull nw={nw}{' others 0' if held else ''}", W, t_match + time.perf_counter() - t
    t = time.perf_counter()
    M = shape_map(Ds, B, 0.0, 1.0, ridge=AUTO_RIDGE)
    Wm = np.clip(Ws @ M.T, 0.0, 1.0)
    t_map = time.perf_counter() - t
    yield "map clip(M w)", Wm, t_map
    for a in (0.25, 0.5):
        yield f"blend {a}", (1 - a) * Wb + a * Wm, t_map
    t = time.perf_counter()
    keep = np.zeros(K, bool)
    keep[m.target] = True
    W = baselines.range_pf(B, S, 0.0, 1.0, valid, ridge=AUTO_RIDGE, zero=~keep)
    yield "bounded matched only", W, t_match + time.perf_counter() - t


def marker_mm(x, W) -> float:
    """Mean marker distance (mm) between the fit ``B W`` and the source motion."""
    fit = np.einsum("tk,kmc->tmc", W, x["B"])
    d = np.linalg.norm(fit - x["S"], axis=2)[x["valid"]]
    return float(d.mean() * 1e3)


def scored(case, x, W) -> str:
    rig, Wt = case["rig"], case["truth"]["weights"]
    full = np.zeros((len(W), rig.n_shapes))
    full[:, x["idx"]] = W
    ok = np.isfinite(Wt).all(1)
    mean, p95, _ = vertex_errors(rig.deltas, full, Wt, case["face"], ok)
    named = case["truth"]["named"]
    rmse = np.sqrt(np.nanmean((full[ok][:, named] - Wt[ok][:, named]) ** 2, axis=0)).mean()
    return f"mean_mm={np.nanmean(mean):.3f} p95_mm={p95:.3f} curve_rmse={rmse:.3f}"


def line(case_label, label, W, seconds, extra) -> str:
    return (f"{case_label} {label:26s} {extra} w=[{W.min():.3f}, {W.max():.3f}] "
            f"active={(W > 0.05).sum(1).mean():.1f} seconds={seconds:.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="BC")
    ap.add_argument("--pair", default="rocketbox", choices=["rocketbox", "tiger"])
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: the whole take)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    if args.pair == "tiger":
        for target in ("jeeliz_tiger", "jeeliz_triceratops"):
            pipe = Pipeline(cache=StageCache(64), source=str(qc.TAKE), source_rig=str(qc.SOURCE_RIG),
                            target_rig=str(ROOT / f"data/rigs/{target}.glb"),
                            last_frame=(args.frames - 1) if args.frames else -1)
            x = inputs_of(pipe)
            for label, W, sec in variants(x):
                print(line(target, label, W, sec, f"marker_mm={marker_mm(x, W):.3f}"), flush=True)
            m = x["match"]
            print(f"{target} sure pairs: " + ", ".join(f"{x['source_names'][j]}→{x['target_names'][k]} {a:.2f}"
                                                      for j, k, a, s in zip(m.source, m.target, m.affinity, m.sure)
                                                      if s), flush=True)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases(args.cases.upper(), Path(tmp), args.frames)
        for c in args.cases.upper():
            case = built[c]
            x = inputs_of(Pipeline(cache=case["cache"], **case["settings"]))
            for label, W, sec in variants(x):
                print(line(c, label, W, sec, scored(case, x, W)), flush=True)
            m = x["match"]
            print(f"{c} {int(m.sure.sum())} sure pairs of {len(m.source)}; e.g. "
                  + ", ".join(f"{x['source_names'][j]}→{x['target_names'][k]}"
                              for j, k in zip(m.source[m.sure][:6], m.target[m.sure][:6])), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
