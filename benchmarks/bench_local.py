"""Benchmarks for local retargeting (Liu et al. 2011): the batched regional QP and the
segmentation, each against a reference timed in the same run.

Cases
-----
local_qp_M97_K22_R12_<constraint>
    97 virtual markers on ICT driven by a real Live Link take, the symmetric 22-shape ICT
    rig (scripts/liu_table1.py), 12 regions: 2,000 frames x 12 regions = 24,000 QPs.
    ours: ``LocalProblem.solve`` on all frames (wall seconds). ref: SciPy SLSQP (ftol 1e-12
    on the unit-scaled QP) on ``REF_FRAMES`` frames x 12 regions, scaled to 2,000 frames
    (``ref_scaled_from`` says how many). The paper: 72.3 frames/s (Xeon X5550, n_b = 22,
    n_m = 97). ``obj_gap`` = max over the checked QPs of (ours − ref) / ‖M_k b‖² (≤ 0: ours
    is at least as good).
segment_ict_R12
    ``segment(ict, 12)`` vs a straightforward unvectorised implementation of the same steps
    that dominate the cost: per-vertex PCA in a Python loop (``np.cov`` + ``eigh`` each),
    sign propagation by a Python breadth-first search over adjacency lists, naive Lloyd
    k-means (k-means++ seeding in Python, 30 iterations); split/merge/smoothing are shared.

Run: ``python benchmarks/bench_local.py``.
"""

from __future__ import annotations

import importlib.util
import time
from collections import deque
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 2000
REF_FRAMES = 2


def _liu():
    spec = importlib.util.spec_from_file_location("liu_table1", ROOT / "scripts" / "liu_table1.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def bench_local_qp(setup, constraint: str) -> str:
    from core.segment import marker_weights, segment
    from core.solvers.local import local_precompute
    from core.solvers.reference import solve_qp_scipy

    sym, layout, targets = setup["sym"], setup["layout"], setup["targets"][:FRAMES]
    T = len(targets)
    seg = segment(sym, n_regions=12)
    mw = marker_weights(sym, layout, seg.masks, graph=seg.graph)
    n0, D = layout.on_rig(sym)
    prob = local_precompute(n0, D, mw, constraint)
    prob.solve(targets[:50])  # warm up (imports, BLAS threads)
    t, c = time.perf_counter(), time.process_time()
    U = prob.solve(targets)
    ours, ours_cpu = time.perf_counter() - t, time.process_time() - c
    from core.solvers.qp import max_kkt_violation

    kkt = max_kkt_violation(prob.H, prob.linear_terms(targets).reshape(-1, prob.n_shapes), np.tile(np.arange(12), T),
                        U.reshape(-1, prob.n_shapes), constraint)
    frames = np.linspace(0, T - 1, REF_FRAMES).astype(int)
    K = prob.n_shapes
    f = prob.linear_terms(targets[frames]).reshape(-1, K)
    H = prob.H[np.tile(np.arange(12), len(frames))]
    t = time.perf_counter()
    ref_u = solve_qp_scipy(H, f, constraint, tol=1e-12)
    ref = (time.perf_counter() - t) * T / len(frames)
    u = U[frames].reshape(-1, K)

    def J(x):
        return 0.5 * np.einsum("nk,nkl,nl->n", x, H, x) + np.einsum("nk,nk->n", f, x)

    b2 = np.einsum("rm,tmc->tr", mw**2, (targets[frames] - n0) ** 2).ravel()
    gap = float(np.max((J(u) - J(ref_u)) / b2))
    return (f"BENCH local_qp_M97_K22_R12_{constraint} ours_s={ours:.4f} ref_s={ref:.2f} ratio={ref / ours:.1f} "
            f"fps={T / ours:.0f} fps_cpu={T / ours_cpu:.0f} frames={T} ours_cpu_s={ours_cpu:.4f} ref_scaled_from={len(frames)}frames "
            f"obj_gap={gap:.1e} kkt={kkt:.1e} paper_fps=72.3")


def _reference_segment_core(rig, R=12, seed=0):
    """Unvectorised PCA + Python BFS signs + naive Lloyd (see module docstring)."""
    from core.segment import welded_graph

    g = welded_graph(rig)
    P = rig.neutral[g.first]
    D = rig.deltas[:, g.first]
    n = g.n
    disp = np.sqrt((D**2).sum(2)).max(0)
    moving = disp > 1e-2 * disp.max()
    d = np.zeros((n, 3))
    for v in range(n):  # per-vertex PCA
        if not moving[v]:
            continue
        pts = np.vstack([P[v], P[v] + D[:, v]])
        lam, vec = np.linalg.eigh(np.cov(pts.T, bias=True))
        d[v] = vec[:, 2]
    A = g.adjacency.tolil()
    nbrs = A.rows
    s = np.zeros(n)
    for root in range(n):  # BFS sign propagation
        if s[root]:
            continue
        s[root] = 1
        q = deque([root])
        while q:
            i = q.popleft()
            for j in nbrs[i]:
                if not s[j]:
                    s[j] = s[i] * (1 if d[i] @ d[j] >= 0 else -1)
                    q.append(j)
    X = (d * s[:, None])[moving]
    rng = np.random.default_rng(seed)
    C = [X[rng.integers(len(X))]]
    for _ in range(R - 1):  # k-means++ seeding
        dist = np.min([((X - c) ** 2).sum(1) for c in C], axis=0)
        C.append(X[rng.choice(len(X), p=dist / dist.sum())])
    C = np.array(C)
    for _ in range(30):  # Lloyd
        lab = np.argmin(((X[:, None] - C[None]) ** 2).sum(2), axis=1)
        C = np.array([X[lab == k].mean(0) if (lab == k).any() else C[k] for k in range(R)])
    return lab


def bench_segment(ict) -> str:
    from core.segment import segment

    segment(ict, n_regions=12)  # warm up
    t, c = time.perf_counter(), time.process_time()
    seg = segment(ict, n_regions=12)
    ours, ours_cpu = time.perf_counter() - t, time.process_time() - c
    t = time.perf_counter()
    _reference_segment_core(ict, 12)
    ref = time.perf_counter() - t
    return (f"BENCH segment_ict_R12 ours_s={ours:.3f} ref_s={ref:.3f} ratio={ref / ours:.1f} ours_cpu_s={ours_cpu:.3f} "
            f"V={ict.n_vertices} regions={seg.n_regions} energy_tree={seg.info['energy_tree']:.1f} "
            f"energy_final={seg.info['energy_final']:.1f} ref=unvectorised-pca+python-bfs+naive-lloyd(core-only)")


def main():
    liu = _liu()
    setup = liu.setup("livelinkface_take_s07.csv", n_markers=97, frames=FRAMES)
    for constraint in ("simplex", "box"):
        print(bench_local_qp(setup, constraint), flush=True)
    print(bench_segment(setup["ict"]), flush=True)


if __name__ == "__main__":
    main()
