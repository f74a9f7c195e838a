"""Issue 29 case B, the eyes (design E): the side of a shape, its direction, and gaze as the eyeballs' turn.

The cases are :mod:`scripts.quality_cases`' (S07 take on ICT -> Rocketbox; B: only the non-ARKit
shapes, C: every shape renamed), scored the same way (mean face-vertex error against the truth, mm),
over auto's map today (:func:`core.stages.methods.dense_shape_map`: the covariance-aligned source
shapes fitted by the target's over the first 1,000 dense-correspondence points, L1 0.3, then the jaw
mapped as a bone). Every design changes only how that map ``M`` is fitted (docs/evaluation.md, "design E"):

1. ``side``   a source shape moving one side of the face (more than ``one`` of its squared motion on
              one side of the mid-plane ``x = mid``, the points within 2 % of the face's size of it
              left out) may not use a target shape whose motion is mostly (more than ``1 − other``)
              on the other side: its L1 weight is multiplied by 1,000 (``shape_map(l1_scale=)``);
2. ``dir``    a target shape whose motion, over the points where the source shape moves most (more
              than 0.3 of its largest motion), has a cosine below ``c`` with the source shape's is
              left out the same way;
3. ``eyes``   the eyeballs as rigid parts: the closed mesh components a sphere fits, one each side
              of the mid-plane, on each rig; each source shape's turn of its eye sphere about the
              sphere's centre (Kabsch) asks the target's eyeball on that side to turn by ``g`` times
              that angle about the same axis — the target eyeball's vertices (warped by the calibrate
              stage, as the dense points) appended to the map's points with weight ``w``, the
              source's "displacement" there ``g r_j × (p − c)``.

It also prints the share of the error on the target's eyeball vertices. ::

    python scripts/gaze_eval.py [--cases BC]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import quality_cases as qc  # noqa: E402
import sculpt_eval as se  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from core.shape_matching import SPARSE_L1, jaw_rescaled_map, mapped_weights, shape_map  # noqa: E402

OUT = 1e3  # the L1 scale that leaves a target shape out of a column


def components(rig) -> np.ndarray:
    """(V,) the connected component of each vertex (the triangles' edges)."""
    F, V = np.asarray(rig.faces), len(rig.neutral)
    A = sp.coo_matrix((np.ones(F.size), (F.ravel(), np.roll(F, 1, 1).ravel())), (V, V))
    return connected_components(A, directed=False)[1]


def sphere_fit(P) -> tuple:
    """(centre (3,), radius, RMS radial residual) of the least-squares sphere through the points."""
    A = np.c_[2 * P, np.ones(len(P))]
    x = np.linalg.lstsq(A, (P ** 2).sum(1), rcond=None)[0]
    c = x[:3]
    r = np.linalg.norm(P - c, axis=1)
    return c, float(np.sqrt(x[3] + c @ c)), float(r.std())


def eye_spheres(rig, size) -> dict:
    """``{+1: vertex mask, -1: vertex mask}``: per side of x = 0, the component (not the largest)
    that some shape moves and a sphere fits within 3 % of its radius, 0.05–0.5 × the face's size;
    the largest such on each side. Empty when a side has none."""
    lab = components(rig)
    main = np.bincount(lab).argmax()
    moved = np.linalg.norm(rig.deltas, axis=2).max(0) > 1e-5
    found = {}
    for c in np.unique(lab):
        sel = lab == c
        if c == main or sel.sum() < 20 or not moved[sel].any():
            continue
        centre, radius, resid = sphere_fit(rig.neutral[sel])
        if resid < 0.03 * radius and 0.05 * size < radius < 0.5 * size:
            side = int(np.sign(centre[0]))
            if side and (side not in found or sel.sum() > found[side].sum()):
                found[side] = sel
    return found


def side_fraction(P, d, mid, band):
    """(…,) the share of the squared motion ``d`` (…, M, 3) on the +x side of x = mid (points
    within ``band`` of it left out)."""
    e = (d ** 2).sum(-1)
    ep, en = e[..., P[:, 0] > mid + band].sum(-1), e[..., P[:, 0] < mid - band].sum(-1)
    return ep / np.maximum(ep + en, 1e-30)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="BC")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases(args.cases.upper(), Path(tmp))
        for c in args.cases.upper():
            case = built[c]
            z = se.inputs(case)
            Ws, S, T = z["Ws"], se.aligned(z), z["T"]
            Ps, Pt = z["Ns"], z["Nt"]

            def fit(scale=None, extra=None):
                Sx, Tx = (S, T) if extra is None else (np.concatenate([S, extra[0]], 1), np.concatenate([T, extra[1]], 1))
                M = shape_map(Sx, Tx, ridge=0.0, l1=SPARSE_L1, l1_scale=scale)
                return jaw_rescaled_map(M, Ps, z["Ds"], Pt, T)[0]

            def show(label, M):
                print(f"{c} {label:52s} mean_mm={se.score(case, z, mapped_weights(M, Ws)):.4f}", flush=True)

            M0 = fit()
            show("base (auto today: the map, the jaw as a bone)", M0)
            # where the error is: the target's eyeball vertices
            pipe = Pipeline(cache=case["cache"], **case["settings"])
            res = pipe.results(["load", "calibrate"])
            src, tgt = res["load"]["source_rig"], res["load"]["target_rig"]
            size = float(np.sqrt(((Ps - Ps.mean(0)) ** 2).sum(1).mean()))
            eyes_s = eye_spheres(src, size)
            eyes_t = eye_spheres(case["rig"], float(np.sqrt(((Pt - Pt.mean(0)) ** 2).sum(1).mean())))
            eyeball = np.zeros(len(case["rig"].neutral), bool)
            for m in eyes_t.values():
                eyeball |= m
            on_eye = eyeball[case["face"]]
            full = np.zeros((len(Ws), case["rig"].n_shapes))
            full[:, z["idx"]] = mapped_weights(M0, Ws)
            D = np.asarray(case["rig"].deltas[:, case["face"]], dtype=np.float64)
            e = np.linalg.norm(np.einsum("tk,kvc->tvc", full - np.nan_to_num(case["truth"]["weights"]), D), axis=2)
            print(f"{c}   eyeball vertices {on_eye.sum()} of {len(on_eye)} face vertices: error there "
                  f"{e[:, on_eye].mean() * 1e3:.3f} mm, elsewhere {e[:, ~on_eye].mean() * 1e3:.3f}, "
                  f"{e[:, on_eye].sum() / e.sum():.0%} of the total", flush=True)
            # 1. the side rule
            band = 0.02 * size
            mid_s = 0.5 * (Ps[:, 0].min() + Ps[:, 0].max())
            mid_t = 0.5 * (Pt[:, 0].min() + Pt[:, 0].max())
            fs, ft = side_fraction(Ps, z["Ds"], mid_s, band), side_fraction(Pt, T, mid_t, band)
            for one, other in ((0.9, 0.1), (0.9, 0.25), (0.9, 0.4), (0.8, 0.1)):
                sc = np.ones((len(fs), len(ft)))
                for j in range(len(fs)):
                    if fs[j] > one:
                        sc[j, ft < other] = OUT
                    elif fs[j] < 1 - one:
                        sc[j, ft > 1 - other] = OUT
                show(f"1 side: one side > {one}, other side's share < {other} out", fit(sc))
            # 2. direction agreement where the source shape moves most
            m = np.linalg.norm(S, axis=2)
            for cmin in (0.0, -0.2, 0.2):
                sc = np.ones((len(S), len(T)))
                for j in range(len(S)):
                    sel = m[j] > 0.3 * m[j].max() if m[j].max() > 0 else np.zeros(len(m[j]), bool)
                    a, b = S[j, sel].ravel(), T[:, sel].reshape(len(T), -1)
                    cos = b @ a / np.maximum(np.linalg.norm(b, axis=1) * np.linalg.norm(a), 1e-30)
                    sc[j, cos < cmin] = OUT
                show(f"2 direction: cosine < {cmin} where the source moves out", fit(sc))
            # 3. the eyeballs turned by the actor's eye sphere's angle times g
            if set(eyes_s) != {-1, 1} or set(eyes_t) != {-1, 1}:
                print(f"{c}   no eye sphere each side on both rigs: design 3 skipped", flush=True)
                continue
            warp = res["calibrate"]["target"].warp
            rot = {}
            for side, sel in eyes_s.items():
                P = src.neutral[sel]
                centre = sphere_fit(P)[0]
                rot[side] = np.array([Rotation.align_vectors(P + d - centre, P - centre)[0].as_rotvec()
                                      if np.abs(d).max() > 0 else np.zeros(3) for d in src.deltas[:, sel]])
                for j in np.argsort(-np.linalg.norm(rot[side], axis=1))[:4]:
                    print(f"{c}   source eye {side:+d}: {z['source_names'][j]} turns "
                          f"{np.round(np.degrees(rot[side][j]), 1)} deg", flush=True)
            tparts = []
            for side, sel in eyes_t.items():
                Q = case["rig"].neutral[sel]
                dq = np.asarray(case["rig"].deltas[z["idx"]][:, sel], dtype=np.float64)
                Qw = warp(Q) if warp is not None else Q
                Tq = (warp(Q[None] + dq) - Qw[None]) if warp is not None else dq
                tparts.append((side, Qw, sphere_fit(Qw)[0], Tq))
            for g, w in ((1, 1.2), (1, 0.5), (2, 0.5), (3, 0.5), (4, 0.5), (5, 0.5), (6, 0.5), (4, 0.3), (4, 0.7), (7.5, 0.3)):
                Se = np.concatenate([g * w * np.cross(rot[side][:, None, :], (Qw - cen)[None]) for side, Qw, cen, _ in tparts], 1)
                Te = np.concatenate([w * Tq for *_, Tq in tparts], 1)
                show(f"3 eyes: g {g}, w {w}", fit(extra=(Se, Te)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
