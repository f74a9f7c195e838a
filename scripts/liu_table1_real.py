"""Liu et al. 2011 Table 1 on the bundled captures, through the real pipeline.

Reconstruction error over markers (mm: max / min / avg of each marker's RMS error over the
take) for the global solve (R = 1) and R = 2, 6, 9, 12 regions, with the paper's simplex
constraint, for
  * the AnimFace optical-marker jaw take retargeted to the ICT rig (real capture, head motion
    removed), and
  * ICT driven by a Live Link take (virtual markers) retargeted to the Rocketbox head.

    python scripts/liu_table1_real.py [--out docs/local_table1.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core.pipeline import Pipeline, StageCache  # noqa: E402

CASES = {
    "AnimFace jaw markers -> ICT": dict(source="data/performances/animface_markers_jaw_60hz.csv", target_rig="data/rigs/ict_facekit.glb"),
    "ICT (Live Link s07) -> Rocketbox": dict(source="data/performances/livelinkface_take_s07.csv", source_rig="data/rigs/ict_facekit.glb",
                                              target_rig="data/rigs/rocketbox_female_adult_02.glb"),
}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--regions", type=int, nargs="+", default=[1, 2, 6, 9, 12])
    p.add_argument("--constraint", default="simplex", choices=["simplex", "box"])
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    lines = [f"| case | R | max (mm) | min (mm) | avg (mm) |", "|---|---|---|---|---|"]
    cache = StageCache(64)
    for label, files in CASES.items():
        pipe = Pipeline(cache=cache, method="local", constraint=args.constraint, **{k: str(ROOT / v) for k, v in files.items()})
        for R in args.regions:
            pipe.configure(regions=R)
            ev = pipe.results(["evaluate"])["evaluate"]
            per = ev["marker_error_per_marker_mm"]
            row = f"| {label} | {R if R > 1 else '1 (global)'} | {np.nanmax(per):.2f} | {np.nanmin(per):.2f} | {np.nanmean(per):.2f} |"
            print(row, flush=True)
            lines.append(row)
    text = "\n".join(lines)
    print(text)
    if args.out:
        Path(args.out).write_text(
            "# Liu 2011 Table 1 on the bundled captures\n\nPer-marker RMS reconstruction error over the take, "
            f"{args.constraint} constraint; regenerate with `python scripts/liu_table1_real.py --out {args.out}`.\n\n" + text + "\n")


if __name__ == "__main__":
    main()
