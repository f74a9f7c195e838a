"""The three quality cases of issue 29 ("the best result by default"), and a search over settings.

The S07 Live Link take driving the ICT rig (``source_rig``), retargeted to the Rocketbox head over
the whole take, scored by :mod:`core.report` (:func:`~core.report.ground_truth`,
:func:`~core.report.method_metrics`) against the Rocketbox head driven by the take's curves through
their ARKit names:

* **A** the target's ARKit shapes (``target_shapes="arkit"``): names shared with the source;
* **B** only its non-ARKit shapes (``SR_*``, ``AU_*``, ``AA_VI_*``, ``HB_*``): names reach them only
  through the vocabularies (docs/names.md);
* **C** every shape, renamed ``shape_NNN`` (no name is shared): a renamed copy of the GLB is
  written to a temporary folder with the Rocketbox layout as its sidecar, and scored against the
  truth of the original names (same shape order).

::

    python scripts/quality_cases.py [--cases ABC] [--set method=spacetime --set name_weight=0.1 ...]
    python scripts/quality_cases.py --search [--json out.json]    # the configurations of SEARCH
    python scripts/quality_cases.py --detail ...                  # where the error is
    python scripts/quality_cases.py --oracle [--cases BC]         # where the loss is: solver or motion transfer

One line per case and configuration: mean and p95 face-vertex error (mm), curve RMSE against the
namesakes, the weight range, shapes above 0.05 per frame and the seconds of the run (stages shared
with an earlier configuration are cached: the dense registration is paid once per rig pair and
process, by the first configuration that needs it). ``--detail`` adds the shapes carrying the most
error (RMS weight difference against the truth times the shape's mean face-vertex motion), the
error of the upper and lower face, and the worst frames.

``--oracle`` separates the solver's loss from the motion transfer's: the per-frame bounded solve
(auto's, ridge 1e-2) fitted to the actor's motion as captured, range-of-motion scaled (``rom``) and
aligned by 3x3 maps (``covariance``, and refitted on the take: ``matched``), against the same solve fitted to the *true* target marker
motion (the truth's weights times the calibrated target shapes at the markers: what a perfect
transfer would hand the solver), and to the actor's motion mapped by the best per-marker 3x3 map in
hindsight (least squares onto the true marker motion): how far a per-marker linear map can go.
Uses the truth, so it is an analysis, never a method.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.io.rigs import hidden_names, write_renamed_rig  # noqa: E402
from core.names import ARKIT_NAMES, canonical  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.geometry import face_vertices  # noqa: E402
from core.examples import suggest_poses  # noqa: E402
from core.motion_alignment import apply_alignment, covariance_alignment, matched_alignment  # noqa: E402
from core.metrics import vertex_errors  # noqa: E402
from core.report import ground_truth, method_metrics  # noqa: E402
from core.retarget import target_markers  # noqa: E402
from core.solvers.baselines import range_pf  # noqa: E402
from core.stages.methods import AUTO_RIDGE  # noqa: E402
from core.stages.retarget import rom_scale  # noqa: E402
from core.stages.methods import pose_features  # noqa: E402
from scipy.optimize import lsq_linear  # noqa: E402

TAKE = ROOT / "data/performances/livelinkface_take_s07.csv"
SOURCE_RIG = ROOT / "data/rigs/ict_facekit.glb"
TARGET_RIG = ROOT / "data/rigs/rocketbox_female_adult_02.glb"
#: the vocabularies' prefixes of Rocketbox's non-ARKit shapes (case B)
NON_ARKIT = ("SR_", "AU_", "AA_VI_", "HB_")

D = dict(correspondence="dense")
DR = dict(correspondence="dense", motion_scale="rom")
#: (label, settings, cases) searched by --search; cases "" = all three. Name settings only where a
#: name can be shared (A, B); in C they would change nothing.
SEARCH = [
    ("spacetime (default)", dict(method="spacetime"), ""),
    ("bounded", dict(method="bounded"), ""),
    ("local", dict(method="local"), ""),
    ("spacetime rom", dict(method="spacetime", motion_scale="rom"), ""),
    ("bounded rom", dict(method="bounded", motion_scale="rom"), ""),
    ("bounded dense+rom", dict(DR, method="bounded"), ""),
    ("bounded dense", dict(D, method="bounded"), ""),
    ("spacetime dense+rom β=10", dict(DR, method="spacetime", beta=10.0), ""),
    ("spacetime dense+rom β=1", dict(DR, method="spacetime", beta=1.0), ""),
    ("local dense+rom", dict(DR, method="local"), ""),
    ("bounded dense+rom 3000", dict(DR, method="bounded", dense_points=3000), ""),
    ("bounded dense+rom 10000", dict(DR, method="bounded", dense_points=10000), ""),
    ("bounded dense+rom ridge 1e-4", dict(DR, method="bounded", ridge=1e-4), ""),
    ("bounded dense+rom ridge 1e-2", dict(DR, method="bounded", ridge=1e-2), ""),
    ("spacetime dense+rom 3000 β=10", dict(DR, method="spacetime", beta=10.0, dense_points=3000), ""),
    ("spacetime dense+rom β=10 α=0.001", dict(DR, method="spacetime", beta=10.0, alpha=0.001), ""),
    ("spacetime dense+rom β=10 l1=1e-4", dict(DR, method="spacetime", beta=10.0, l1=1e-4), ""),
] + [(f"spacetime name_weight={nw}", dict(method="spacetime", name_weight=nw), "AB") for nw in (0.01, 0.1, 1.0, 10.0)] + [
    (f"spacetime dense+rom β=10 name_weight={nw}", dict(DR, method="spacetime", beta=10.0, name_weight=nw), "AB")
    for nw in (0.01, 0.1, 1.0, 10.0)] + [
    (f"spacetime dense name_weight={nw}", dict(D, method="spacetime", name_weight=nw), "AB") for nw in (0.01, 0.1, 1.0)] + [
    ("bounded dense+rom ridge 3e-2", dict(DR, method="bounded", ridge=3e-2), ""),
    ("bounded dense+rom ridge 1e-1", dict(DR, method="bounded", ridge=1e-1), ""),
    ("bounded dense+rom symmetry 0.1", dict(DR, method="bounded", symmetry_weight=0.1), ""),
    ("bounded dense+rom personalize", dict(DR, method="bounded", personalize=True), ""),
    ("bounded rom ridge 1e-2", dict(method="bounded", motion_scale="rom", ridge=1e-2), ""),
    ("spacetime dense+rom β=10 α=0.1", dict(DR, method="spacetime", beta=10.0, alpha=0.1), ""),
    ("spacetime dense+rom β=100", dict(DR, method="spacetime", beta=100.0), ""),
    ("spacetime dense+rom β=10 l1=1e-3", dict(DR, method="spacetime", beta=10.0, l1=1e-3), ""),
    ("bounded rom ridge 3e-3", dict(method="bounded", motion_scale="rom", ridge=3e-3), ""),
    ("bounded rom ridge 3e-2", dict(method="bounded", motion_scale="rom", ridge=3e-2), ""),
    ("bounded rom ridge 1e-1", dict(method="bounded", motion_scale="rom", ridge=1e-1), ""),
    ("local rom", dict(method="local", motion_scale="rom"), ""),
    ("spacetime rom β=10", dict(method="spacetime", motion_scale="rom", beta=10.0), ""),
    ("spacetime rom β=10 ridge 1e-2", dict(method="spacetime", motion_scale="rom", beta=10.0, ridge=1e-2), ""),
    ("spacetime rom β=10 ridge 1e-2 α=0", dict(method="spacetime", motion_scale="rom", beta=10.0, ridge=1e-2, alpha=0.0), ""),
    ("bounded dense+rom 3000 ridge 1e-2", dict(DR, method="bounded", dense_points=3000, ridge=1e-2), ""),
    ("bounded rom ridge 1e-2 no calibrate", dict(method="bounded", motion_scale="rom", ridge=1e-2, calibrate=False), ""),
    ("bounded rom ridge 1e-2 rbf 0.01", dict(method="bounded", motion_scale="rom", ridge=1e-2, rbf_smoothing=0.01), ""),
    ("bounded rom ridge 1e-2 rbf 0.1", dict(method="bounded", motion_scale="rom", ridge=1e-2, rbf_smoothing=0.1), ""),
    ("bounded rom ridge 1e-2 gaussian σ=2", dict(method="bounded", motion_scale="rom", ridge=1e-2, weights_filter="gaussian",
                                                 sigma=2.0), ""),
    ("bounded rom ridge 1e-2 symmetry 0.1", dict(method="bounded", motion_scale="rom", ridge=1e-2, symmetry_weight=0.1), ""),
    ("spacetime rom β=1 ridge 1e-2", dict(method="spacetime", motion_scale="rom", beta=1.0, ridge=1e-2), ""),
    ("spacetime rom β=10 ridge 3e-2", dict(method="spacetime", motion_scale="rom", beta=10.0, ridge=3e-2), ""),
] + [(f"spacetime rom β=10 ridge 1e-2 name_weight={nw}", dict(method="spacetime", motion_scale="rom", beta=10.0, ridge=1e-2,
                                                              name_weight=nw), "AB") for nw in (0.003, 0.01, 0.03, 10.0, 100.0)]

COLUMNS = ("mean_mm", "p95_mm", "curve_rmse", "weight_min", "weight_max", "active_per_frame", "seconds")


def build_cases(cases: str, folder: Path, frames: int = 0, cache: StageCache | None = None) -> dict:
    """``{case: {"cache", "settings", "truth", "face", "rig"}}``: the case's pipeline settings, one
    shared cache; the truth, face vertices and rig are always the original rig's."""
    cache = cache if cache is not None else StageCache(512)
    files = dict(source=str(TAKE), source_rig=str(SOURCE_RIG), last_frame=(frames - 1) if frames else -1)
    ref = Pipeline(cache=cache, **files, target_rig=str(TARGET_RIG))
    base = ref.results(["load", "frames"])
    truth, rig = ground_truth(base["load"], base["frames"]), base["load"]["target_rig"]
    face = np.flatnonzero(face_vertices(rig.deltas))
    non_arkit = [n for n in rig.names if n.startswith(NON_ARKIT) and canonical(n) not in ARKIT_NAMES]
    specs = {"A": dict(target_rig=str(TARGET_RIG), target_shapes="arkit"),
             "B": dict(target_rig=str(TARGET_RIG), target_shapes=",".join(non_arkit))}
    if "C" in cases or "D" in cases:
        hidden = write_renamed_rig(TARGET_RIG, folder / "rocketbox_hidden.glb")
        specs["C"] = dict(target_rig=str(hidden), target_shapes="")
        specs["D"] = dict(target_rig=str(hidden), target_shapes=",".join(
            h for h, n in zip(hidden_names(rig.n_shapes), rig.names) if n in set(non_arkit)))
    return {c: {"cache": cache, "settings": dict(files, **specs[c]), "truth": truth, "face": face, "rig": rig}
            for c in cases}


def true_poses(case: dict, n: int) -> list:
    """``n`` example poses as an animator would set them, at the frames ``suggest_poses`` proposes:
    the ground-truth weights (all shapes), or for a subset of shapes (case D) their bounded [0, 1]
    least-squares fit of the true face at that frame; named as the case's (hidden) rig names them."""
    if not n:
        return []
    pipe = Pipeline(cache=case["cache"], **case["settings"])
    res = pipe.results(["frames", "stabilize", "shapes"])
    frames = suggest_poses(pose_features(res), n)
    rig, Wt, first = case["rig"], case["truth"]["weights"], res["frames"]["first"]
    shapes = list(res["shapes"]["shape_index"])
    D = rig.deltas[:, case["face"]].reshape(rig.n_shapes, -1)
    names = hidden_names(rig.n_shapes)
    items = []
    for f in frames:
        truth = np.nan_to_num(Wt[f])
        if len(shapes) == rig.n_shapes:
            w = {names[k]: float(truth[k]) for k in range(rig.n_shapes) if truth[k] > 1e-4}
        else:
            x = lsq_linear(D[shapes].T, truth @ D, bounds=(0.0, 1.0)).x
            w = {names[k]: float(v) for k, v in zip(shapes, x) if v > 1e-4}
        items.append({"frame": int(first + f), "weights": w})
    return items


def run(case: dict, settings: dict) -> dict:
    """:func:`core.report.method_metrics` of ``settings`` on a case: a fresh pipeline (every other
    setting its default) on the case's shared cache."""
    pipe = Pipeline(cache=case["cache"], **{**case["settings"], **settings})
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = method_metrics(pipe, case["truth"], case["face"])
    r["seconds"] = time.perf_counter() - t
    return r


def detail(case: dict, r: dict, n: int = 6) -> list:
    """Lines saying where the error is: the shapes whose weight error moves the face most, the
    upper and lower face, the worst frames."""
    rig, face, Wt, W = case["rig"], case["face"], case["truth"]["weights"], r["_weights"]
    ok = np.isfinite(Wt).all(1) & np.isfinite(W).all(1)
    dW = W[ok] - Wt[ok]
    move = np.linalg.norm(rig.deltas[:, face], axis=2).mean(1) * 1e3  # (K,) mm per unit weight
    contrib = np.sqrt((dW ** 2).mean(0)) * move
    top = np.argsort(-contrib)[:n]
    lines = ["  shapes (RMS Δw × mean motion mm): " + ", ".join(f"{rig.names[k]} {contrib[k]:.3f}" for k in top)]
    y = rig.neutral[face, 1]
    upper = y > np.median(y)
    E = np.zeros(len(face))
    idx = np.flatnonzero(ok)[::4]
    for a in range(0, len(idx), 128):
        f = idx[a:a + 128]
        E += np.linalg.norm(np.einsum("tk,kvc->tvc", W[f] - Wt[f], rig.deltas[:, face]), axis=2).sum(0)
    E = E / len(idx) * 1e3
    per = np.nan_to_num(r["_per_frame_mm"], nan=-1)
    worst = np.argsort(-per)[:5]
    lines.append(f"  upper face {E[upper].mean():.3f} mm, lower face {E[~upper].mean():.3f} mm; worst frames "
                 + ", ".join(f"{f}: {per[f]:.2f}" for f in worst))
    return lines


def line(case: str, label: str, r: dict) -> str:
    cr = r["curve_rmse"] if r["curve_rmse"] is not None else float("nan")
    return (f"{case} {label:42s} mean_mm={r['mean_mm']:.3f} p95_mm={r['p95_mm']:.3f} curve_rmse={cr:.3f} "
            f"w=[{r['weight_min']:.3f}, {r['weight_max']:.3f}] active={r['active_per_frame']:.1f} "
            f"seconds={r['seconds']:.1f}")


def parse_value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v.lower(), v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="ABC", help="which cases (letters), default ABC")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a pipeline setting (repeat)")
    ap.add_argument("--search", action="store_true", help="run the configurations of SEARCH instead of --set")
    ap.add_argument("--only", default="", help="with --search: only labels matching this regular expression")
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: the whole take)")
    ap.add_argument("--detail", action="store_true", help="also say which shapes, regions and frames carry the error")
    ap.add_argument("--json", help="write every result (metrics and per-shape curve RMSE) to this file")
    ap.add_argument("--oracle", action="store_true", help="the solve fitted to the true target marker motion "
                                                            "and to the actor's motion under several maps (an analysis)")
    ap.add_argument("--poses", default="", help="cases C and D (names hidden; D: only the non-ARKit shapes) with this "
                                                "many true example poses at the suggested frames, e.g. 0,2,4,8,16")
    args = ap.parse_args(argv)
    if args.poses:
        return poses_table([int(n) for n in args.poses.split(",")], args.frames)
    cases = "".join(c for c in args.cases.upper() if c in "ABC")
    if args.oracle:
        return oracle_table(cases, args.frames)
    if args.search:
        configs = [(lbl, cfg, cs or "ABC") for lbl, cfg, cs in SEARCH if re.search(args.only, lbl)]
    else:
        cfg = dict(kv.split("=", 1) for kv in args.set)
        cfg = {k: parse_value(v) for k, v in cfg.items()}
        configs = [(" ".join(f"{k}={v}" for k, v in cfg.items()) or "defaults", cfg, "ABC")]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        built = build_cases(cases, Path(tmp), args.frames)
        for label, cfg, cs in configs:
            for c in cases:
                if c not in cs:
                    continue
                try:
                    r = run(built[c], cfg)
                except Exception as e:  # noqa: BLE001 - one configuration failing is a line, not the end
                    print(f"{c} {label:42s} error {type(e).__name__}: {e}", flush=True)
                    out.append({"case": c, "label": label, "settings": cfg, "error": f"{type(e).__name__}: {e}"})
                    continue
                print(line(c, label, r), flush=True)
                if args.detail:
                    print("\n".join(detail(built[c], r)), flush=True)
                out.append({"case": c, "label": label, "settings": cfg,
                            **{k: v for k, v in r.items() if not k.startswith("_") and k != "curve_rmse_per_shape"},
                            "curve_rmse_per_shape": r.get("curve_rmse_per_shape")})
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1, allow_nan=True) + "\n")
    return 0


def oracle_table(cases: str, frames: int = 0) -> int:
    """Mean face-vertex error (mm) of auto's per-frame bounded solve fitted to the actor's motion
    under each map, and to the true target marker motion (see the module docstring)."""
    print("| case | captured | rom | covariance | matched | best 3×3 map in hindsight | true target marker motion |\n"
          "|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        built = build_cases(cases, Path(tmp), frames)
        for c in cases:
            case = built[c]
            pipe = Pipeline(cache=case["cache"], **case["settings"], method="bounded", ridge=AUTO_RIDGE)
            res = pipe.results(["load", "correspond", "stabilize", "calibrate"])
            ld, cor, st, cal = res["load"], res["correspond"], res["stabilize"], res["calibrate"]
            names, src = list(st["names"]), st["source"]
            B, S, valid = cal["deltas"], src.deltas, src.valid
            idx = np.asarray(pipe.results(["shapes"])["shapes"]["shape_index"])
            Wt = case["truth"]["weights"]
            ok = np.isfinite(Wt).all(1)
            full = target_markers(ld["target_rig"], cor["target_layout"], names, src.neutral).calibrated
            true = np.einsum("tk,kmc->tmc", np.nan_to_num(Wt), full)
            Bs = cor["source_layout"].select(names).points(ld["source_rig"].deltas)
            use = ok[:, None] & valid
            hindsight = np.stack([np.linalg.lstsq(S[use[:, m], m], true[use[:, m], m], rcond=None)[0].T
                                  for m in range(len(names))])
            fits = {"captured": S, "rom": S * rom_scale(B, src, ld["source_rig"], cor["source_layout"], names)[None, :, None],
                    "covariance": apply_alignment(covariance_alignment(Bs, B), S),
                    "matched": apply_alignment(matched_alignment(Bs, B, src.source_weights), S),
                    "hindsight": apply_alignment(hindsight, S), "true": true}
            row = []
            for label, motion in fits.items():
                W = np.zeros((len(S), case["rig"].n_shapes))
                W[:, idx] = range_pf(B, motion, 0.0, 1.0, valid, ridge=AUTO_RIDGE)
                mean = vertex_errors(case["rig"].deltas, W, Wt, case["face"], ok)[0]
                row.append(f"{np.nanmean(mean):.3f}")
            print(f"| {c} | " + " | ".join(row) + " |", flush=True)
    return 0


def poses_table(counts: list, frames: int = 0) -> int:
    """The default (auto) with 0, 2, 4 ... true example poses on the hidden-name cases."""
    print("| case | " + " | ".join(f"{n} poses" for n in counts) + " |\n|---|" + "---|" * len(counts))
    with tempfile.TemporaryDirectory() as tmp:
        built = build_cases("CD", Path(tmp), frames)
        for c, label in (("C", "names hidden, all shapes"), ("D", "names hidden, non-ARKit shapes")):
            row = []
            for n in counts:
                r = run(built[c], {"example_poses": true_poses(built[c], n)})
                row.append(f"{r['mean_mm']:.3f} mm (w {r['weight_min']:.2f}…{r['weight_max']:.2f})")
            print(f"| {label} | " + " | ".join(row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
