"""The bundled evaluation suite: every bundled capture x every bundled rig, every method.

    python scripts/evaluate_suite.py --out docs/evaluation.md [--json docs/evaluation.json] [--last-frame N]

Weight-curve captures (Live Link Face) drive the ICT head (their source rig); marker captures are
solved directly. Per pair, the methods are the solve methods with the 41-marker layouts, and the
advanced configurations (dense correspondence + range-of-motion matching; the name-aware prior
where names match). Ground truth (the target driven by the same curves through their ARKit names)
exists for the Live Link captures onto targets with ARKit shapes (ICT, Rocketbox); elsewhere the
table has marker and velocity error only. Writes a Markdown table (best first per pair) and the
full JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.pipeline import StageCache  # noqa: E402
from core.report import evaluate_methods, ranking, to_json  # noqa: E402

PERF = ROOT / "data" / "performances"
RIGS = ROOT / "data" / "rigs"
BASIC = ["auto", "lsq", "bounded", "range_pf", "prior_pf", "spacetime", "local", "geometric", "names"]
#: advanced configurations: (label, settings, methods)
ADVANCED = [
    ("dense+rom", {"correspondence": "dense", "motion_scale": "rom", "ridge": 1e-3}, ["bounded", "local"]),
    ("dense+rom β=10", {"correspondence": "dense", "motion_scale": "rom", "beta": 10.0}, ["spacetime"]),
    ("dense+names", {"correspondence": "dense", "name_weight": 0.01, "alpha": 0.01}, ["spacetime"]),
]
SHOWN = [("mean_mm", "vertex mm", "{:.3f}"), ("p95_mm", "p95 mm", "{:.2f}"), ("curve_rmse", "curve RMSE", "{:.3f}"),
         ("marker_mean_mm", "marker mm", "{:.2f}"), ("velocity_error_mm_per_frame", "velocity", "{:.4f}"),
         ("weight_min", "w min", "{:.2f}"), ("weight_max", "w max", "{:.2f}"), ("active_per_frame", "shapes/frame", "{:.1f}"),
         ("seconds", "s", "{:.1f}")]


def pairs():
    takes = sorted(PERF.glob("*.csv"))
    rigs = sorted(RIGS.glob("*.glb"))
    for take in takes:
        curves = take.name.startswith("livelinkface")
        for rig in rigs:
            yield take, rig, ({"source_rig": str(RIGS / "ict_facekit.glb")} if curves else {}), curves


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "evaluation.md"))
    ap.add_argument("--json", default=str(ROOT / "docs" / "evaluation.json"))
    ap.add_argument("--last-frame", type=int, default=-1, help="evaluate frames 0..N of every take (-1: whole takes)")
    ap.add_argument("--from-json", help="write the Markdown of an earlier run's JSON (no computing)")
    args = ap.parse_args(argv)
    if args.from_json:
        results = json.loads(Path(args.from_json).read_text())
        for res in results:
            res["order"] = ranking({"methods": res["methods"], "ground_truth": res["ground_truth"]})
        write_markdown(results, args.out, args.last_frame)
        return 0
    cache = StageCache(max_entries=256)
    results = []
    t0 = time.perf_counter()
    for take, rig, extra, curves in pairs():
        base = {"source": str(take), "target_rig": str(rig), "last_frame": args.last_frame, **extra}
        if rig.stem == "rocketbox_female_adult_02" or rig.stem == "ict_facekit":
            base["target_shapes"] = "arkit"
        rows = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rep = evaluate_methods(base, [m for m in BASIC if curves or m != "names"], cache=cache)
            truth = rep["ground_truth"]
            for m, r in to_json(rep)["methods"].items():
                rows[m] = r
            for label, settings, methods in ADVANCED:
                if "name_weight" in settings and not truth:
                    continue
                adv = evaluate_methods({**base, **settings}, methods, cache=cache)
                for m, r in to_json(adv)["methods"].items():
                    rows[f"{m} ({label})"] = r
        order = ranking({"methods": rows, "ground_truth": truth})
        results.append({"take": take.name, "rig": rig.name, "ground_truth": truth, "order": order, "methods": rows})
        print(f"{take.name} -> {rig.name}: best {order[0]} ({time.perf_counter() - t0:.0f} s)", flush=True)
    Path(args.json).write_text(json.dumps(results, indent=1, allow_nan=True) + "\n")
    write_markdown(results, args.out, args.last_frame)
    print(f"wrote {args.out} and {args.json} in {time.perf_counter() - t0:.0f} s")
    return 0


#: where scripts/example_poses_eval.py's section starts (kept when the suite rewrites the file)
EXAMPLE_POSES = "<!-- example poses: scripts/example_poses_eval.py -->"


def write_markdown(results, out, last_frame):
    lines = ["# Evaluation suite", "",
             f"`python scripts/evaluate_suite.py` (frames: {'all' if last_frame < 0 else f'0–{last_frame}'}); "
             "generated by the script, do not edit by hand. Methods best first: by mean vertex error against the "
             "ground truth where there is one (a Live Link take onto a target with ARKit shapes: the target driven by "
             "the same curves), else by marker error. `names` copies the curves by name, so against a name-driven "
             "truth it is exact by construction: it is the baseline the geometric methods are compared with, not a "
             "competitor. Methods whose weights leave −0.05…1.05 are ranked after the keyable ones. Targets with "
             "ARKit shapes are solved on those (`--target-shapes arkit`).", ""]
    for res in results:
        lines += [f"## {res['take']} → {res['rig']}" + ("" if res["ground_truth"] else " (no ground truth)"), "",
                  "| method | " + " | ".join(label for _, label, _ in SHOWN) + " |",
                  "|---|" + "---|" * len(SHOWN)]
        for m in res["order"]:
            r = res["methods"][m]
            if "error" in r:
                lines.append(f"| {m} | failed: {r['error'][:80]} |" + " |" * (len(SHOWN) - 1))
                continue
            cells = " | ".join("—" if r.get(k) is None else fmt.format(r[k]) for k, _, fmt in SHOWN)
            lines.append(f"| {m} | {cells} |")
        lines.append("")
    text = "\n".join(lines) + "\n"
    old = Path(out).read_text() if Path(out).exists() else ""
    if EXAMPLE_POSES in old:  # the section scripts/example_poses_eval.py writes stays
        text += old[old.index(EXAMPLE_POSES):]
    Path(out).write_text(text)


if __name__ == "__main__":
    sys.exit(main())
