"""Ribera et al. 2017, Fig. 12-style comparison on the bundled data.

The "actor" is one ARKit rig driven by Live Link Face curves, the target another ARKit rig;
both are driven by the same curves, so the target's true weights are known. For each
direction (ICT -> Rocketbox, Rocketbox -> ICT):

1. actor markers = the bundled layout's 41 AnimFace markers on the source rig, driven by the
   range-of-motion take (training) and by an acting take (test);
2. actor blendshapes: **RBF** = the target's marker blendshapes warped into the actor's
   proportions (Seol 2012 §3.2, ``core.calibrate.calibrate_deltas``), or **aligned** =
   :func:`core.personalize.personalize` started from them (paper settings, and the
   extension settings of docs/geometric.md);
3. retarget the acting take with eq. 16 and ℓ1 only (prior "none", λ = 0.6 for cm, as in §6.1)
   and, as extra rows, with the geometric prior (μ = 0.3);
4. error against the same-curve ground truth: target mesh from the solved weights vs the
   target mesh from the true weights (mean / 95th percentile vertex distance in mm over the
   face region the markers cover) and the mean |weight error|.

Run: ``python scripts/ribera_fig12.py`` (about a minute). Prints a markdown table.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RIGS = {"ict": "ict_facekit", "rocketbox": "rocketbox_female_adult_02"}
TRAIN = "livelinkface_rom.csv"
TEST = "livelinkface_take_s07.csv"


def _arkit_subset(rig):
    """Rocketbox carries 175 shapes; keep the ARKit ones (the curves' ground truth lives there)."""
    from core.names import ARKIT_NAMES, canonical, split_base

    keep = [n for n in rig.names if canonical(n) in ARKIT_NAMES or split_base(n)]
    return rig.subset(keep)


def _load():
    from core.io.gltf import read_rig
    from core.io.layout import read_layout
    from core.io.performance import read_performance

    rigs, layouts = {}, {}
    for key, stem in RIGS.items():
        rig = _arkit_subset(read_rig(ROOT / "data" / "rigs" / f"{stem}.glb"))
        rigs[key] = rig
        layouts[key] = read_layout(ROOT / "data" / "layouts" / f"{stem}.json", rig)
    takes = {n: read_performance(ROOT / "data" / "performances" / n) for n in (TRAIN, TEST)}
    return rigs, layouts, takes


def _weights(curves, rig):
    from core.names import NameMap

    G = NameMap.automatic(curves.names, rig.names).matrix(curves.names, rig.names)
    return np.nan_to_num(np.where(curves.valid, curves.data, np.nan)) @ G.T


def _face_region(rig, layout):
    """Vertices within 1.5 cm of the markers' convex region: where marker-based errors mean something."""
    from scipy.spatial import cKDTree

    n0 = layout.points(rig.neutral)
    d, _ = cKDTree(n0).query(rig.neutral)
    return d < 0.015


def run_direction(src, dst, rigs, layouts, takes, extension):
    from core.calibrate import calibrate_deltas
    from core.personalize import personalize
    from core.solvers.geometric import GeometricSolver, geometric_gram

    rs, rt = rigs[src], rigs[dst]
    ls, lt = layouts[src], layouts[dst]
    names = [n for n in ls.names if n in lt.names]
    ls, lt = ls.select(names), lt.select(names)
    actor_neutral = ls.points(rs.neutral)
    train = ls.points(rs.evaluate(_weights(takes[TRAIN], rs))) - actor_neutral
    test_w_src = _weights(takes[TEST], rs)
    test = ls.points(rs.evaluate(test_w_src)) - actor_neutral
    true_w = _weights(takes[TEST], rt)
    tn, td = lt.on_rig(rt)
    rbf, _ = calibrate_deltas(tn, td, actor_neutral)
    variants = {"RBF": rbf}
    t = time.perf_counter()
    variants["aligned (paper)"] = personalize(train, rbf, actor_neutral, names=names, rig_deltas=td).deltas
    t_align = time.perf_counter() - t
    variants["aligned (extensions)"] = personalize(train, rbf, actor_neutral, names=names, rig_deltas=td,
                                                   **extension).deltas
    region = _face_region(rt, lt)
    true_mesh = rt.evaluate(true_w)[:, region]
    rest = np.linalg.norm(true_mesh - rt.neutral[region], axis=2) * 1e3
    active = rest.mean(axis=1) > 1.0  # frames whose true expression moves the region > 1 mm on average
    Q = geometric_gram(rt)

    def row(label, how, W):
        err = np.linalg.norm(rt.evaluate(W)[:, region] - true_mesh, axis=2) * 1e3
        return (f"{src} -> {dst}", label, how, err.mean(), err[active].mean(), np.percentile(err, 95),
                np.abs(W - true_w).mean())

    rows = [row("(neutral pose: all weights 0)", "-", np.zeros_like(true_w))]
    for prior in ("none", "geometric"):
        for label, P in variants.items():
            sol = GeometricSolver(P, prior, gram=Q if prior == "geometric" else None).solve(test)
            rows.append(row(label, "ℓ1" if prior == "none" else "ℓ1 + geometric", sol.weights))
    return rows, t_align, int(active.sum())


def main():
    try:
        rigs, layouts, takes = _load()
    except (FileNotFoundError, ImportError) as e:
        print(f"cannot run: {e}\nneeds data/layouts/{{ict_facekit,rocketbox_female_adult_02}}.json, "
              "core.io.layout, core.io.performance and core.calibrate")
        return 1
    extension = dict(mask="residual", exclusive=True, peak_power=4, beta=1e-4, gamma=1e-3)
    print(f"training: {TRAIN} ({takes[TRAIN].n_frames} frames); test: {TEST} ({takes[TEST].n_frames} frames); "
          f"extension settings: {extension}\n")
    print("| direction | actor blendshapes | retarget | mesh error mean (mm) | on active frames (mm) | p95 (mm) | mean abs weight error |")
    print("|---|---|---|---|---|---|---|")
    notes = []
    for src, dst in (("ict", "rocketbox"), ("rocketbox", "ict")):
        rows, t_align, n_active = run_direction(src, dst, rigs, layouts, takes, extension)
        for r in rows:
            print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]:.2f} | {r[4]:.2f} | {r[5]:.2f} | {r[6]:.3f} |")
        notes.append(f"{src} -> {dst}: alignment (paper settings) {t_align:.2f} s; {n_active} active frames")
    print("\n" + "\n".join(notes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
