"""Evidence for spacetime expression cloning (Seol et al. 2012, §7, Fig. 9–11) on bundled data.

The ICT rig driven by a real Live Link take gives the source markers; they are retargeted to
the Rocketbox head (which has the same ARKit channels, so the same curves give a ground
truth) and to the Jeeliz tiger (no ground truth). Methods: No Const, Range PF
(-0.5 <= w <= 1.5), Prior PF and spacetime, with alpha of Prior PF and of spacetime chosen
as in the paper: so that their weight range matches Range PF's. The pipeline's extra
relative ridge is switched off here so every method is the paper's.

Printed: velocity error ||D(BW)^T - DS^T||^2 (mm^2, Fig. 11 a), marker RMS error (mm), the
weight range, and for Rocketbox the RMS vertex distance (mm) of the retargeted head to the
head driven directly by the same curves.

    python scripts/seol_table.py [--take data/performances/livelinkface_take_s07.csv] [--out docs/spacetime_evidence.md]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core.names import NameMap  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402


def _span(W):
    return float(np.nanmax(W) - np.nanmin(W))


def _match_alpha(pipe, method, target_span, lo=1e-12, hi=1e4, iters=40):
    """Bisect log(alpha) so the weight range of ``method`` equals ``target_span``
    (larger alpha -> smaller range)."""
    pipe.configure(method=method)
    for _ in range(iters):
        mid = np.sqrt(lo * hi)
        pipe.configure(alpha=float(mid))
        span = _span(pipe.results(["solve"])["solve"]["weights"])
        if span > target_span:
            lo = mid
        else:
            hi = mid
    a = float(np.sqrt(lo * hi))
    pipe.configure(alpha=a)
    return a


def run(take: Path, target: str, cache: StageCache) -> list:
    pipe = Pipeline(cache=cache, source=str(take), source_rig=str(ROOT / "data/rigs/ict_facekit.glb"),
                    target_rig=str(ROOT / f"data/rigs/{target}.glb"), ridge=0.0)  # the papers' methods: no extra ridge
    rows = []
    pipe.configure(method="range_pf")
    span = _span(pipe.results(["solve"])["solve"]["weights"])
    plan = [("No Const", "lsq", None), ("Range PF", "range_pf", None), ("Prior PF", "prior_pf", "match"),
            ("Spacetime", "spacetime", "match"), ("Spacetime α=0.01", "spacetime", 0.01)]
    gt = None
    res = pipe.results(["load", "stabilize"])
    rig = res["load"]["target_rig"]
    src = res["load"]["source"]
    names = [n for n in NameMap.automatic(src.names, rig.names).entries]
    if len(names) >= 40:  # a rig with ARKit shapes: the same curves drive it directly
        G = NameMap.automatic(src.names, rig.names).matrix(src.names, rig.names)
        gt = rig.evaluate(np.nan_to_num(src.data) @ G.T)
    for label, method, alpha in plan:
        pipe.configure(method=method)
        if alpha == "match":
            a = _match_alpha(pipe, method, span)
        elif alpha is not None:
            pipe.configure(alpha=alpha)
            a = alpha
        else:
            a = None
        out = pipe.results(["synthesize", "evaluate"])
        W = out["synthesize"]["weights"]  # every shape of the rig (unseen ones at zero)
        ev = out["evaluate"]
        row = {"target": target, "method": label, "alpha": a, "velocity_error_mm2": ev["velocity_error_total_mm2"],
               "marker_rms_mm": ev["marker_rms_mm"], "w_min": float(W.min()), "w_max": float(W.max())}
        if gt is not None:
            row["gt_vertex_rms_mm"] = float(np.sqrt(((rig.evaluate(W) - gt) ** 2).sum(-1).mean()) * 1e3)
        rows.append(row)
        print(row, flush=True)
    return rows


def table(rows) -> str:
    lines = ["| target | method | alpha | velocity error (mm²) | marker RMS (mm) | weight range | vertex RMS to same-curve truth (mm) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        a = "" if r["alpha"] is None else f"{r['alpha']:.3g}"
        gt = f"{r['gt_vertex_rms_mm']:.2f}" if "gt_vertex_rms_mm" in r else "—"
        lines.append(f"| {r['target']} | {r['method']} | {a} | {r['velocity_error_mm2']:.4g} | {r['marker_rms_mm']:.2f} | "
                     f"[{r['w_min']:.2f}, {r['w_max']:.2f}] | {gt} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--take", default=str(ROOT / "data/performances/livelinkface_take_s07.csv"))
    p.add_argument("--targets", nargs="+", default=["rocketbox_female_adult_02", "jeeliz_tiger"])
    p.add_argument("--out", default=None, help="also write the table (markdown) here")
    args = p.parse_args(argv)
    cache = StageCache(256)
    rows = [r for t in args.targets for r in run(Path(args.take), t, cache)]
    text = table(rows)
    print(text)
    if args.out:
        Path(args.out).write_text(
            f"# Spacetime vs per-frame baselines on bundled data\n\nTake: `{Path(args.take).name}` driving ICT; "
            "regenerate with `python scripts/seol_table.py --out docs/spacetime_evidence.md`.\n\n" + text + "\n")


if __name__ == "__main__":
    main()
