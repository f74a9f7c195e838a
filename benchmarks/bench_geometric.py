"""Ribera 2017: range-of-motion alignment (§4) and the ℓ1 + geometric-prior solver (§5).

Real data: the ICT FaceKit rig (60 well-spread face vertices as markers) driven by the
Live Link Face range-of-motion take (4,030 frames) with 0.2 mm marker noise.

Cases (one line each):

* ``personalize_K<K>_rom<T>``: the whole of :func:`core.personalize.personalize` (similarity,
  trust, key frames, marker mesh, the (MK × MK) system solved by the Kronecker-sum route);
  reference = the same preprocessing + numpy.linalg.solve of the dense (MK × MK) system.
  ``splu_s`` is SuperLU on the sparse system (the paper's route, §4.6). Paper: 5–23 s.
* ``personalize_residual_K<K>_rom<T>``: the same with ``mask="residual"`` (block-Jacobi PCG).
* ``geometric_l1_ict_K<K>``: :class:`core.solvers.geometric.GeometricSolver` on all frames as the
  pipeline runs it, within [0, 1] (the exact batched box QP); reference = Clarabel per frame on
  eq. 16 in epigraph form, timed on a sample of frames and scaled to all frames. ``unbounded_s``
  is the paper's unbounded form (IRLS + polish) in the same run (``unbounded_ratio`` =
  unbounded_s / ours_s), ``unbounded_out01`` the fraction of its weights outside [0, 1].
  Paper: 105 fps.
* ``geometric_l1_kink_ict_K<K>``: the same within [-0.5, 1.5]: the ℓ1 kink inside the bounds, so
  every shape is split (w = p − n, twice the unknowns).
* ``geometric_l1_unbounded_ict_K<K>``: the unbounded form alone; reference = L-BFGS-B per frame
  on the split w = w⁺ − w⁻ (the case ``geometric_l1_ict_K<K>`` measured before the bounds).

Run: ``python benchmarks/bench_geometric.py``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _setup(M=60, noise=2e-4):
    from core.geometry import vertex_normals, farthest_points
    from core.io.gltf import read_rig
    from core.names import NameMap

    rig = read_rig(ROOT / "data" / "rigs" / "ict_facekit.glb")
    V = rig.neutral
    n = vertex_normals(V, rig.faces)
    cand = np.flatnonzero((V[:, 2] > 0.07) & (n[:, 2] > 0.4) & (V[:, 1] > -0.085) & (V[:, 1] < 0.09))
    P = V[cand]
    idx = cand[farthest_points(P, M, start=int(np.argmax(P[:, 2])))]
    path = ROOT / "data" / "performances" / "livelinkface_rom.csv"
    header = open(path).readline().strip().split(",")[2:54]
    W = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=range(2, 54))
    W = W @ NameMap.automatic(header, rig.names).matrix(header, rig.names).T
    S = rig.deltas[:, idx]
    A = (W @ S.reshape(len(S), -1)).reshape(len(W), M, 3)
    A = A + np.random.default_rng(0).normal(scale=noise, size=A.shape)
    return rig, S, rig.neutral[idx], A


def _best(fn, repeat=3):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_personalize(S, N0, A, mask="target"):
    from core.personalize import personalize

    K, M = S.shape[:2]
    ours_s, res = _best(lambda: personalize(A, S, N0, mask=mask))
    pr = res.problem
    solve_s, _ = _best(lambda: pr.solve("auto"))
    dense_s, x_dense = _best(lambda: pr.solve("dense"), repeat=1)
    splu_s, _ = _best(lambda: pr.solve("splu"), repeat=1)
    ref_s = ours_s - solve_s + dense_s
    err = np.abs(res.deltas - x_dense).max() / np.abs(x_dense).max()
    name = "personalize" if mask == "target" else "personalize_residual"
    print(f"BENCH {name}_K{K}_rom{len(A)} ours_s={ours_s:.4f} ref_s={ref_s:.4f} ratio={ref_s / ours_s:.1f} "
          f"solve_s={solve_s:.4f} dense_solve_s={dense_s:.3f} splu_s={splu_s:.3f} unknowns={K * M} "
          f"key_frames={len(res.key_frames)} max_rel_diff={err:.1e}", flush=True)


def bench_l1(rig, S, A, sample=24):
    from scipy.optimize import minimize

    from core.solvers.geometric import GeometricSolver, geometric_gram

    K = len(S)
    gram_s, Q = _best(lambda: geometric_gram(rig), repeat=1)
    solver = GeometricSolver(S, "geometric", gram=Q)
    ours_s, sol = _best(lambda: solver.solve(A))
    H, c = solver.H, solver.c
    b = solver.rhs(A)
    frames = np.linspace(0, len(A) - 1, sample).astype(int)
    diffs = []
    t = time.perf_counter()
    for f in frames:
        scale = max(np.abs(b[f]).max(), 1e-300)

        def fun(x, bf=b[f], scale=scale):
            w = x[:K] - x[K:]
            gw = 2 * (H @ w - bf)
            return (w @ H @ w - 2 * bf @ w + 2 * c * x.sum()) / scale, np.concatenate([gw + 2 * c, -gw + 2 * c]) / scale

        r = minimize(fun, np.zeros(2 * K), jac=True, method="L-BFGS-B", bounds=[(0, None)] * (2 * K),
                     options=dict(ftol=1e-16, gtol=1e-13, maxiter=50000, maxcor=50))
        diffs.append(np.abs(r.x[:K] - r.x[K:] - sol.weights[f]).max())
    ref_s = (time.perf_counter() - t) / sample * len(A)
    print(f"BENCH geometric_l1_unbounded_ict_K{K} ours_s={ours_s:.4f} ref_s={ref_s:.2f} ratio={ref_s / ours_s:.0f} "
          f"fps={len(A) / ours_s:.0f} frames={len(A)} ref_frames_timed={sample} gram_s={gram_s:.3f} "
          f"polished={sol.polished.mean():.4f} nonzero_per_frame={(sol.weights != 0).sum(1).mean():.1f} "
          f"max_abs_dw_vs_ref={max(diffs):.1e}", flush=True)


def _clarabel(H, c, b, lower, upper):
    """Eq. 16 for one frame within the bounds by Clarabel: min wᵀHw − 2bᵀw + 2c1ᵀt, −t ≤ w ≤ t."""
    import clarabel
    import scipy.sparse as sp

    K = len(b)
    scale = 2 * np.linalg.norm(H, 2)
    I, O = sp.identity(K, format="csc"), sp.csc_matrix((K, K))
    P = sp.block_diag([2 * H / scale, O], format="csc")
    G = sp.vstack([sp.hstack([I, -I]), sp.hstack([-I, -I]), sp.hstack([I, O]), sp.hstack([-I, O])], format="csc")
    h = np.concatenate([np.zeros(2 * K), upper, -lower])
    st = clarabel.DefaultSettings()
    st.verbose = False
    st.tol_gap_abs = st.tol_gap_rel = st.tol_feas = 1e-12
    q = np.concatenate([-2 * b, 2 * c * np.ones(K)]) / scale
    return np.asarray(clarabel.DefaultSolver(P, q, G, h, [clarabel.NonnegativeConeT(4 * K)], st).solve().x)[:K]


def bench_bounded(rig, S, A, lower, upper, name, sample=24):
    from core.solvers.geometric import GeometricSolver, geometric_gram

    K = len(S)
    Q = geometric_gram(rig)
    lo, hi = np.full(K, lower), np.full(K, upper)
    solver = GeometricSolver(S, "geometric", gram=Q, lower=lo, upper=hi)
    ours_s, sol = _best(lambda: solver.solve(A))
    free = GeometricSolver(S, "geometric", gram=Q)
    unb_s, unb = _best(lambda: free.solve(A))
    b = solver.rhs(A)
    frames = np.linspace(0, len(A) - 1, sample).astype(int)
    t = time.perf_counter()
    ref = np.stack([_clarabel(solver.H, solver.c, b[f], lo, hi) for f in frames])
    ref_s = (time.perf_counter() - t) / sample * len(A)
    e, er = solver.energy(A[frames], sol.weights[frames]), solver.energy(A[frames], ref)
    W, U = sol.weights, unb.weights
    print(f"BENCH {name}_ict_K{K} ours_s={ours_s:.4f} ref_s={ref_s:.2f} ratio={ref_s / ours_s:.0f} "
          f"fps={len(A) / ours_s:.0f} frames={len(A)} ref_frames_timed={sample} bounds=[{lower:g},{upper:g}] "
          f"unbounded_s={unb_s:.4f} unbounded_ratio={unb_s / ours_s:.2f} "
          f"unbounded_out01={((U < 0) | (U > 1)).mean():.4f} out_of_bounds={((W < lo) | (W > hi)).sum()} "
          f"polished={sol.polished.mean():.4f} kkt={sol.extras['kkt']:.1e} nonzero_per_frame={(W != 0).sum(1).mean():.1f} "
          f"max_rel_energy_vs_ref={((e - er) / er).max():.1e} max_abs_dw_vs_ref={np.abs(W[frames] - ref).max():.1e} "
          f"fallback={sol.extras['boxqp']['fallback']}", flush=True)


def main():
    rig, S, N0, A = _setup()
    bench_personalize(S, N0, A, "target")
    bench_personalize(S, N0, A, "residual")
    bench_bounded(rig, S, A, 0.0, 1.0, "geometric_l1")
    bench_bounded(rig, S, A, -0.5, 1.5, "geometric_l1_kink")
    bench_l1(rig, S, A)


if __name__ == "__main__":
    main()
