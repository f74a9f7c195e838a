"""The registration table of docs/transfer.md: ``register`` (ICT -> Rocketbox, tiger,
triceratops, the layouts' shared markers as landmarks), its time and quality measures.

    python scripts/xu_register_table.py [target,target,...]
"""

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.geometry import weld_vertices  # noqa: E402
from core.io.gltf import read_rig  # noqa: E402
from core.io.layout import read_layout  # noqa: E402
from core.transfer import register  # noqa: E402
from core.transfer.performance import shared_landmarks  # noqa: E402


def main(targets=("rocketbox_female_adult_02", "jeeliz_tiger", "jeeliz_triceratops")):
    D = ROOT / "data"
    ict = read_rig(D / "rigs" / "ict_facekit.glb")
    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    li = read_layout(D / "layouts" / "ict_facekit.json", ict)
    for name in targets:
        t = read_rig(D / "rigs" / f"{name}.glb")
        ids, pts = shared_landmarks(li, read_layout(D / "layouts" / f"{name}.json", t), t.neutral)
        t0 = time.perf_counter()
        r = register(ict.neutral[rep], Fw, t.neutral, t.faces, wi[ids], pts).report
        print(f"{name:28s} time {time.perf_counter() - t0:5.1f}s crop={r['crop']} landmarks "
              f"{r['landmark_residual_mm_mean']:.3f}/{r['landmark_residual_mm_max']:.3f} mm surface median/p95 "
              f"{r['surface_distance_mm_median']:.4f}/{r['surface_distance_mm_p95']:.3f} mm projected "
              f"{r['projected_fraction']:.3f}/{r['crop_projected_fraction']:.3f} folded "
              f"{r['flipped_triangles']}/{r['flipped_triangles_crop']}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1].split(",")) if len(sys.argv) > 1 else main()
