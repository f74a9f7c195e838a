"""Issue 29 case B by geometry (design S): four variants of auto's sparse shape map, on the jaw and the mouth.

The cases are :mod:`scripts.quality_cases`' (S07 take on ICT -> Rocketbox; B: only the non-ARKit
shapes, C: every shape renamed), scored the same way (mean face-vertex error against the truth, mm).
The base is what ``auto`` runs there (:func:`core.stages.methods.dense_shape_map`): the covariance-
aligned source shapes fitted by the target's over the first 1,000 dense-correspondence points, L1
0.3, the curves mapped ``clip(W_source Mᵀ, 0, 1)``. The designs (docs/evaluation.md, "design S"):

1. ``region``   the map fitted per region of the face (a height split at the points, hard or soft;
                or Liu 2011's 12 soft regions of the target rig), each target shape's row taken from
                the regions in proportion to where it moves (its squared displacement per region);
2. ``points``   the points weighted by how much the take moves them (``(e_p / ē)^γ``, ``e_p`` the
                take's mean squared source motion at point p); ``take``: the whole map fitted at
                once on the take's moments, ``min ½ tr((TᵀM − Sᵀ) Q (TᵀM − Sᵀ)ᵀ) + L1``,
                ``Q = (1 − γ) diag(WᵀW/T) + γ WᵀW/T`` (γ 0 is the base exactly), scipy's L-BFGS-B in
                the box;
3. ``jaw``      the jaw as a bone (:func:`core.shape_matching.jaw_rescaled_map`): the source shapes
                that move the chin, and the map's combination for each, fitted by rigid motions;
                the column scaled so the combination turns the jaw by the actor's angle (or, for a
                slide, moves it by the actor's translation times the faces' size ratio);
4. ``resid``    a per-frame correction: the bounded per-frame fit of the source motion at the points
                pulled towards the map, ``min ‖TᵀW − m_t‖² + ρ σ² ‖W − W_map,t‖²`` in the box (the
                difference ``W − W_map`` is the correction, ridge ρ), applied only on the frames
                where the map misses the motion by more than the given percentile.

``--oracle`` adds the bound of any per-shape linear map (the best ``M`` in hindsight, fitted to the
truth on the face) and the source shapes whose column alone, replaced by the hindsight one, helps
most (on the map and on the jaw-rescaled map): analysis only, it uses the truth.

::

    python scripts/sculpt_eval.py [--cases BC] [--oracle]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import quality_cases as qc  # noqa: E402
from core.motion_alignment import apply_alignment, covariance_alignment  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from core.shape_matching import SPARSE_L1, jaw_rescaled_map, jaw_shapes, mapped_weights, shape_map  # noqa: E402
from core.solvers.boxqp import solve_box_sequence  # noqa: E402
from core.stages.methods import AUTO_DENSE_POINTS  # noqa: E402
from core.stages.retarget import masks_at  # noqa: E402

STAGES = ["load", "frames", "shapes", "stabilize", "calibrate", "dense_correspondence"]


def inputs(case: dict) -> dict:
    """The base map's inputs at auto's dense points: source shapes ``Ds`` and neutral ``Ns``, the
    target's (calibrated) ``T`` and neutral ``Nt``, the curves, Liu's masks at the points."""
    pipe = Pipeline(cache=case["cache"], **case["settings"])
    res = pipe.results(STAGES)
    ld, dc, rig = res["load"], res["dense_correspondence"], res["shapes"]["rig"]
    pts = list(dc["source_layout"].names[:AUTO_DENSE_POINTS])
    sl, tl = dc["source_layout"].select(pts), dc["target_layout"].select(pts)
    nt, dt = tl.on_rig(rig)
    warp = res["calibrate"]["target"].warp
    seg = Pipeline(cache=case["cache"], **case["settings"], method="local").results(["segment"])["segment"]
    return dict(Ds=sl.points(ld["source_rig"].deltas), Ns=sl.points(ld["source_rig"].neutral),
                T=warp(nt[None] + dt) - warp(nt)[None], Nt=warp(nt), idx=np.asarray(res["shapes"]["shape_index"]),
                Ws=np.nan_to_num(np.asarray(res["stabilize"]["source"].source_weights, dtype=np.float64)),
                masks=masks_at(tl, seg["masks"]), source_names=list(ld["source_rig"].names))


def score(case, z, W) -> float:
    """Mean face-vertex error (mm) of the solver shapes' curves ``W`` against the truth."""
    full = np.zeros((len(W), case["rig"].n_shapes))
    full[:, z["idx"]] = W
    D = np.asarray(case["rig"].deltas[:, case["face"]], dtype=np.float64).reshape(case["rig"].n_shapes, -1)
    Wt = np.nan_to_num(case["truth"]["weights"])
    e = np.linalg.norm(((full - Wt) @ D).reshape(len(full), -1, 3), axis=2)
    return float(e.mean() * 1e3)


def aligned(z):
    return apply_alignment(covariance_alignment(z["Ds"], z["T"]), z["Ds"])


def region_map(z, regions, l1=SPARSE_L1):
    """Design 1: one sparse map per region (points weighted by the region's mask), each target
    shape's row the regions' rows in proportion to its squared motion in each."""
    S, T = aligned(z), z["T"]
    tn = (T ** 2).sum(2)
    M = np.zeros((len(T), len(S)))
    for r in regions:
        w = np.sqrt(r)[None, :, None]
        f = (tn * r[None]).sum(1) / np.maximum(tn.sum(1), 1e-30)
        M += f[:, None] * shape_map(S * w, T * w, ridge=0.0, l1=l1)
    return M


def point_weighted_map(z, gamma, l1=SPARSE_L1):
    """Design 2a: the points weighted by the take's motion there."""
    S, T = aligned(z), z["T"]
    e = (np.einsum("tj,jpc->tpc", z["Ws"][::4], S) ** 2).sum(2).mean(0)
    w = np.sqrt((e / e.mean()) ** gamma)[None, :, None]
    return shape_map(S * w, T * w, ridge=0.0, l1=l1)


def take_map(z, gamma, l1=SPARSE_L1, start=None):
    """Design 2b: the whole map at once on the take's moments (module docstring), in [0, 1]."""
    S, T, Ws = aligned(z), z["T"], z["Ws"]
    K, J = len(T), len(S)
    Tf, Sf = T.reshape(K, -1), S.reshape(J, -1)
    G = Tf @ Tf.T
    Q = Ws.T @ Ws / len(Ws)
    Q = (1 - gamma) * np.diag(np.diag(Q)) + gamma * Q
    B = (Tf @ Sf.T) @ Q
    c = 0.5 * l1 * np.diag(Q) * (Sf ** 2).sum(1)  # the base's L1 (shape_map) weighted as its data term

    def f(x):
        M = x.reshape(K, J)
        GM = G @ M
        return 0.5 * np.sum(GM * (M @ Q)) - np.sum(M * B) + np.sum(M * c[None]), (GM @ Q - B + c[None]).ravel()

    x0 = np.zeros(K * J) if start is None else start.ravel()
    r = minimize(f, x0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * (K * J),
                 options=dict(maxiter=5000, maxfun=20000, ftol=1e-14, gtol=1e-10))
    return r.x.reshape(K, J)


def residual_corrected(z, M0, rho, gate):
    """Design 4: the per-frame box QP pulled towards the map, on the frames whose miss exceeds the
    ``gate`` percentile of the misses."""
    S, T, Ws = aligned(z), z["T"], z["Ws"]
    K = len(T)
    Tf, Sf = T.reshape(K, -1), S.reshape(len(S), -1)
    Wm = mapped_weights(M0, Ws)
    G = Tf @ Tf.T
    s2 = float(np.linalg.eigvalsh(G)[-1])
    m = Ws @ Sf
    miss = np.sqrt(((m - Wm @ Tf).reshape(len(m), -1, 3) ** 2).sum(2).mean(1))
    W = np.clip(solve_box_sequence((G + rho * s2 * np.eye(K))[None], -(m @ Tf.T + rho * s2 * Wm)), 0.0, 1.0)
    return np.where((miss > np.percentile(miss, gate))[:, None], W, Wm)


def hindsight_map(case, z, start):
    """The best per-shape linear map in [0, 1] in hindsight: ``min ‖(W_s Mᵀ − W_true) D‖²`` on the face."""
    D = np.asarray(case["rig"].deltas[:, case["face"]], dtype=np.float64).reshape(case["rig"].n_shapes, -1)
    DB, Ws, Wt = D[z["idx"]], z["Ws"], np.nan_to_num(case["truth"]["weights"])
    G, Q = DB @ DB.T, Ws.T @ Ws
    B = DB @ (D.T @ (Wt.T @ Ws))
    K, J = start.shape

    def f(x):
        M = x.reshape(K, J)
        GM = G @ M
        return 0.5 * np.sum(GM * (M @ Q)) - np.sum(M * B), (GM @ Q - B).ravel()

    r = minimize(f, start.ravel(), jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * (K * J),
                 options=dict(maxiter=3000, ftol=1e-15, gtol=1e-12))
    return r.x.reshape(K, J)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="BC")
    ap.add_argument("--oracle", action="store_true")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases(args.cases.upper(), Path(tmp))
        for c in args.cases.upper():
            case = built[c]
            z = inputs(case)
            Ws = z["Ws"]

            def show(label, M=None, W=None):
                W = mapped_weights(M, Ws) if W is None else W
                print(f"{c} {label:44s} mean_mm={score(case, z, W):.3f}", flush=True)

            M0 = shape_map(aligned(z), z["T"], ridge=0.0, l1=SPARSE_L1)
            show("base (auto's sparse map)", M0)
            y = z["Nt"][:, 1]
            for q in (0.35, 0.5, 0.65):
                thr = np.quantile(y, q)
                for soft in (0.0, 0.01):
                    lo = (y < thr).astype(float) if soft == 0 else 1 / (1 + np.exp((y - thr) / soft))
                    show(f"1 region: height split q{q} soft {soft * 1e3:.0f} mm", region_map(z, [lo, 1 - lo]))
            show("1 region: Liu's 12 soft regions", region_map(z, list(z["masks"])))
            for g in (0.25, 0.5, 1.0):
                show(f"2 points weighted by the take, γ {g}", point_weighted_map(z, g))
            for g in (0.5, 1.0):
                for l1 in (0.3, 1.0):
                    show(f"2 take moments γ {g}, l1 {l1}", take_map(z, g, l1, start=M0))
            M3, scales = jaw_rescaled_map(M0, z["Ns"], z["Ds"], z["Nt"], z["T"])
            jaws = ", ".join(f"{z['source_names'][j]} ×{scales[j]:.2f}" for j in np.flatnonzero(jaw_shapes(z["Ns"], z["Ds"])))
            show(f"3 jaw as a bone ({jaws})", M3)
            for name in ("jawOpen", "jawForward"):
                j = z["source_names"].index(name)
                show(f"3 ... {name} alone", np.where(np.arange(M0.shape[1])[None] == j, M3, M0))
            for rho in (1e-3, 1e-2, 1e-1):
                for gate in (0, 50, 90):
                    show(f"4 residual correction ρ {rho}, frames > p{gate}", W=residual_corrected(z, M0, rho, gate))
            if args.oracle:
                Mh = hindsight_map(case, z, M0)
                show("oracle: best linear map in hindsight", Mh)
                for base, label in ((M0, "the map"), (M3, "the jaw-rescaled map")):
                    J = Mh.shape[1]
                    one = [np.where(np.arange(J)[None] == jj, Mh, base) for jj in range(J)]
                    gain = [score(case, z, mapped_weights(M1, Ws)) for M1 in one]
                    print(f"{c} oracle, one column of {label} in hindsight: " + ", ".join(
                        f"{z['source_names'][jj]} {gain[jj]:.3f}" for jj in np.argsort(gain)[:7]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
