"""Spacetime expression cloning (Seol et al. 2012): our solver vs the literal Kronecker system.

Cases (one ``BENCH`` line each):

* ``spacetime_T{10..1500}_M54_K50``: Table I of the paper (54 markers, 50 shapes; ``paper_s`` is
  the paper's Matlab time on a 2.8 GHz Xeon). ICT FaceKit, 54 well-spread marker vertices, its
  first 50 shapes driven by the real Live Link take ``livelinkface_take_s07.csv`` (scaled 1.1x,
  0.3 mm noise), alpha = 0.01 (cm scale), neutral boundary frames. ``ours`` = build + solve
  (:func:`solve_spacetime`: PCA prior, diagonalisation, solve); ``ref`` =
  :func:`spacetime_reference` (``scipy.sparse.kron`` + ``spsolve``). ``maxrel`` = max |W - W_ref| /
  max |W_ref|; ``kkt_*`` = max |dE/dW| on the free weights relative to ||B^T B|| (backward
  error). The ICT subset is ill-conditioned (cond B ~ 3e4, and the time Laplacian adds ~T^2),
  so two backward-stable solvers differ by up to ~1e-5 relative at T = 1500 while both KKT
  residuals sit at rounding level.
* ``spacetime_edit_window12``: a pose edit at frame 500 of the T=1000 solve, window 494..505;
  ours = ``SpacetimeSolver.edit``; ref = the Kronecker system on the 12-frame window.
* ``spacetime_T36000_K175``: Rocketbox (175 shapes, 54 marker vertices), curves = the longest
  Live Link take (``livelinkface_rom.csv``) repeated to 36,000 frames. The reference is the
  Kronecker solve on a 200-frame prefix, extrapolated linearly in T (``ref_kind``), since the
  full system (6.3 M unknowns) is out of reach. ``peak_mb`` = tracemalloc peak during our solve.

* ``spacetime_bounded_T1000_K52_M41``: the bounded solver (:mod:`core.solvers.bounded_spacetime`)
  on the bundled ICT -> Rocketbox sample as the pipeline builds it: Rocketbox's 52 ARKit shapes
  (the tongue moves no marker), its 41 layout markers calibrated to the actor, the Live Link take
  driving ICT (first 1,000 frames), alpha = 0.01, relative ridge 1e-5, bounds [0, 1], neutral
  boundary frames. ``ours`` = build + solve; ``ref`` = Clarabel (interior point) on the literal
  Kronecker QP (:func:`bounded_spacetime_reference`, gap/feasibility tolerance 1e-9; its time
  excludes assembling the system, ``ref_build_s``). ``kkt`` / ``kkt_ref`` = relative KKT
  residual of each answer by the same measure (:meth:`SpacetimeSolver.kkt_residual`; ours is
  required to be <= 1e-9; the reference's weights within 1e-6 of a bound are snapped onto it
  first, since an interior-point method never reaches the bound), ``active`` = weights on a bound, ``maxdiff`` = max |W - W_ref|,
  ``dE`` = (E_ref - E_ours) / E_ours of the clipped reference (>= 0: ours is not worse).

BLAS runs single-threaded here (``blas_threads=1``): on this shared 2-core machine OpenBLAS
threads under oversubscription made the small (T x 3M) @ (3M x K) products 10-20x slower.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np

from core.io.gltf import read_rig
from core.names import NameMap
from core.solvers.reference import spacetime_reference
from core.solvers.spacetime import SpacetimeSolver, solve_spacetime

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
TABLE_I = {10: 0.22, 50: 1.32, 100: 2.76, 500: 15.21, 1000: 31.65, 1500: 47.38}


@contextlib.contextmanager
def blas_threads(n: int):
    """Set OpenBLAS threads of numpy's and scipy's bundled OpenBLAS, restoring them after."""
    import numpy
    import scipy

    libs = []
    for pkg in (numpy, scipy):
        for so in glob.glob(os.path.join(os.path.dirname(pkg.__file__), "..", pkg.__name__ + ".libs", "*openblas*.so*")):
            try:
                lib = ctypes.CDLL(so)
            except OSError:
                continue
            for get, set_ in (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                              ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                              ("openblas_get_num_threads", "openblas_set_num_threads")):
                if hasattr(lib, get) and hasattr(lib, set_):
                    libs.append((getattr(lib, set_), getattr(lib, get)()))
                    getattr(lib, set_)(n)
                    break
    try:
        yield
    finally:
        for set_, old in libs:
            set_(old)


def spread_markers(rig, n=54):
    """``n`` well-spread vertices among those the shapes move (farthest-point sampling)."""
    mag = np.linalg.norm(rig.deltas, axis=2).max(0)
    moving = np.flatnonzero(mag > 0.05 * mag.max())
    P = rig.neutral[moving]
    pick = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[pick[0]], axis=1)
    for _ in range(n - 1):
        pick.append(int(d.argmax()))
        d = np.minimum(d, np.linalg.norm(P - P[pick[-1]], axis=1))
    return moving[pick]


def curves(rig, name):
    path = DATA / "performances" / name
    src = path.read_text().split("\n", 1)[0].split(",")[2:54]
    C = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(2, 54))
    return C @ NameMap.automatic(src, rig.names).matrix(src, rig.names).T


def best(f, repeat):
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t)
    return min(ts), out


def line(case, ours, ref, **extra):
    kv = " ".join(f"{k}={v}" for k, v in extra.items())
    print(f"BENCH {case} ours_s={ours:.6f} ref_s={ref:.6f} ratio={ref / ours:.1f} {kv}".rstrip(), flush=True)


def rocketbox_arkit(T: int):
    """(B (52, 41, 3), S (T, 41, 3)): the pipeline's marker problem with all 52 ARKit shapes."""
    import warnings

    from core.pipeline import Pipeline, StageCache
    from core.retarget import target_markers
    from core.stages import solver_shapes

    pipe = Pipeline(cache=StageCache(), method="spacetime", target_shapes="arkit",
                    source=str(DATA / "performances" / "livelinkface_take_s07.csv"),
                    source_rig=str(DATA / "rigs" / "ict_facekit.glb"),
                    target_rig=str(DATA / "rigs" / "rocketbox_female_adult_02.glb"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = pipe.results(["load", "stabilize"])
    ld, st = res["load"], res["stabilize"]
    rig = ld["target_rig"]
    sub = rig.subset([rig.names[i] for i in solver_shapes(rig, "arkit")])
    tm = target_markers(sub, ld["target_layout"], st["names"], st["source"].neutral, True, 0.0)
    return np.asarray(tm.calibrated), np.asarray(st["source"].deltas[:T])


def bounded_case():
    from core.solvers.reference import bounded_spacetime_reference, kronecker_system

    B, S = rocketbox_arkit(1000)
    kw = dict(alpha=0.01, ridge=1e-5, lower=0.0, upper=1.0)
    SpacetimeSolver(B, S, **kw).solve()  # warm-up (imports, first-call allocations)
    ours, W = best(lambda: SpacetimeSolver(B, S, **kw).solve(), 7)
    s = SpacetimeSolver(B, S, **kw)
    s.solve()
    t = time.perf_counter()
    kronecker_system(B, S, 0.01, 0.0, None, None, ridge=s.ridge_)
    build = time.perf_counter() - t
    R, info = bounded_spacetime_reference(B, S, 0.01, 0.0, None, None, lower=0.0, upper=1.0, tol=1e-9,
                                          ridge=s.ridge_)
    Rc = np.clip(R, 0.0, 1.0)
    # an interior-point answer approaches a bound without reaching it: snap what is within 1e-6
    Rs = np.where(Rc <= 1e-6, 0.0, np.where(Rc >= 1.0 - 1e-6, 1.0, Rc))
    e, er = s.energy(W).total, s.energy(Rc).total
    line(f"spacetime_bounded_T{len(S)}_K{B.shape[0]}_M{B.shape[1]}", ours, info["seconds"],
         kkt=f"{s.kkt_residual(W):.0e}", active=s.info_["active"], kkt_ref=f"{s.kkt_residual(Rs):.0e}",
         maxdiff=f"{np.abs(W - R).max():.1e}", dE=f"{(er - e) / e:.1e}", inner_solves=s.info_["iterations"],
         ref_kind=f"clarabel_{info['status']}_{info['iterations']}it", ref_build_s=f"{build:.2f}", blas_threads=1)


def main():
    rng = np.random.default_rng(0)
    with blas_threads(1):
        ict = read_rig(DATA / "rigs" / "ict_facekit.glb")
        B = ict.deltas[:50][:, spread_markers(ict)]  # (50, 54, 3)
        Wt = curves(ict, "livelinkface_take_s07.csv")[:, :50]
        S_all = 1.1 * np.einsum("tk,kmc->tmc", Wt, B) + rng.normal(size=(len(Wt),) + B.shape[1:]) * 3e-4
        for T, paper in TABLE_I.items():
            S = S_all[:T]
            ours, W = best(lambda: solve_spacetime(B, S, alpha=0.01), 7 if T <= 1000 else 3)
            ref, R = best(lambda: spacetime_reference(B, S, 0.01, 0.0, None, None), 3 if T <= 100 else 1)
            err = np.abs(W - R).max() / np.abs(R).max()
            s = SpacetimeSolver(B, S, alpha=0.01)
            line(f"spacetime_T{T}_M54_K50", ours, ref, paper_s=paper, maxrel=f"{err:.1e}",
                 kkt_ours=f"{s.kkt_residual(W):.0e}", kkt_ref=f"{s.kkt_residual(R):.0e}", blas_threads=1)

        # editing: one pose at frame 500 propagated through 494..505
        S = S_all[:1000]
        solver = SpacetimeSolver(B, S, alpha=0.01)
        W = solver.solve()
        pose = np.clip(W[500] + 0.3, 0, 1)
        a, b = 494, 505
        ours, W2 = best(lambda: solver.edit(W, 500, pose, window=(a, b)), 50)
        ref, R = best(lambda: spacetime_reference(B, S[a:b + 1], 0.01, 0.0, None,
                                                  {0: W[a], 500 - a: pose, b - a: W[b]}, boundary="none"), 5)
        err = np.abs(W2[a:b + 1] - R).max() / np.abs(R).max()
        line("spacetime_edit_window12", ours, ref, maxrel=f"{err:.1e}", blas_threads=1)

        bounded_case()

        # 36,000 frames x 175 shapes (Rocketbox)
        rb = read_rig(DATA / "rigs" / "rocketbox_female_adult_02.glb")
        B = rb.deltas[:, spread_markers(rb)]  # (175, 54, 3)
        take = curves(rb, "livelinkface_rom.csv")
        Wt = np.tile(take, (-(-36000 // len(take)), 1))[:36000]
        S = np.einsum("tk,kmc->tmc", Wt, B) + rng.normal(size=(36000,) + B.shape[1:]) * 3e-4
        tracemalloc.start()
        t = time.perf_counter()
        W = solve_spacetime(B, S, alpha=0.01)
        first = time.perf_counter() - t
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        ours, W = best(lambda: solve_spacetime(B, S, alpha=0.01), 2)
        ours = min(ours, first)
        n = 200
        solver = SpacetimeSolver(B, S[:n], alpha=0.01)
        ref_n, R = best(lambda: spacetime_reference(B, S[:n], 0.01, 0.0, None, None, ridge=solver.ridge_), 1)
        err = np.abs(solver.solve() - R).max() / np.abs(R).max()
        line("spacetime_T36000_K175", ours, ref_n * 36000 / n, peak_mb=f"{peak / 2**20:.0f}",
             ref_kind=f"kron_spsolve_T{n}_x{36000 // n}_linear", ref_prefix_s=f"{ref_n:.2f}",
             prefix_maxrel=f"{err:.1e}", blas_threads=1)


if __name__ == "__main__":
    main()
