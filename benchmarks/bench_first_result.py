"""The first result a user waits for: the default method (auto) on the sample from the command
line, against the plain ``--method bounded`` run, measured in the same run (issue 30: at most 2x).

Each is a fresh process (``python -m core.cli retarget``: imports, reading the rigs, the solve,
writing the CSV), best of 3, so the time is what a user waits for at the prompt.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
ARGS = ["--source", str(DATA / "performances/livelinkface_take_s07.csv"), "--source-rig", str(DATA / "rigs/ict_facekit.glb"),
        "--target-rig", str(DATA / "rigs/rocketbox_female_adult_02.glb"), "--target-shapes", "arkit", "--quiet"]


def cli_seconds(extra, out: Path, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "core.cli", "retarget", *ARGS, *extra, "--weights-csv", str(out)],
                       cwd=ROOT, check=True, capture_output=True)
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        ours = cli_seconds([], Path(tmp) / "auto.csv")
        ref = cli_seconds(["--method", "bounded"], Path(tmp) / "bounded.csv")
    print(f"BENCH first_result_auto_s07 ours_s={ours:.2f} ref_s={ref:.2f} ratio={ref / ours:.2f} "
          f"ref_kind=cli_method_bounded budget_ratio=0.5 frames=2028")


if __name__ == "__main__":
    main()
