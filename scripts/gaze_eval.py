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
3. ``eyes``   the eyeballs as rigid parts (:mod:`core.eyes`): on each rig the closed part a sphere fits,
              one each side of the mid-plane; each source shape's turn of its eye part about the
              sphere's centre (Kabsch) asks the target's eyeball on that side to turn about the same
              axis — the target eyeball's vertices (warped by the calibrate stage, as the dense points)
              appended to the map's points with weight ``w``, the source's "displacement" there
              ``g r_j × (p − c)``: ``g`` the same angle times a constant, or the *range gain* (the
              target eyeball's largest turn over the source eye part's), ``r_j`` optionally counted by
              its *rigid share* (how much of the part's motion the turn explains). Auto's
              (:func:`core.eyes.gaze_rows`): the range gain × the rigid share, ``w = 1``.

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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import quality_cases as qc  # noqa: E402
import sculpt_eval as se  # noqa: E402
from core.eyes import eye_parts, gaze_rows, part_turns, sphere_fit  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from core.shape_matching import SPARSE_L1, jaw_rescaled_map, mapped_weights, shape_map  # noqa: E402

OUT = 1e3  # the L1 scale that leaves a target shape out of a column


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
            show("base (auto before design E: the map, the jaw as a bone)", M0)
            # where the error is: the target's eyeball vertices
            pipe = Pipeline(cache=case["cache"], **case["settings"])
            res = pipe.results(["load", "calibrate"])
            src = res["load"]["source_rig"]
            size = float(np.sqrt(((Ps - Ps.mean(0)) ** 2).sum(1).mean()))
            eyeball = np.zeros(len(case["rig"].neutral), bool)
            for v in eye_parts(case["rig"]).values():
                eyeball[v] = True
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
            # 3. the eyeballs turned about the actor's axes (core.eyes; auto's rows: range gain × rigid share, w 1)
            tgt_solver = case["rig"].subset([case["rig"].names[k] for k in z["idx"]])  # the original names, same shapes
            eyes_s, eyes_t = eye_parts(src), eye_parts(tgt_solver)
            if not eyes_s or not eyes_t:
                print(f"{c}   no eye part each side on both rigs: design 3 skipped", flush=True)
                continue
            warp = res["calibrate"]["target"].warp
            turns, parts = {}, []
            for side in (1, -1):
                r, share = part_turns(src.neutral[eyes_s[side]], src.deltas[:, eyes_s[side]])
                q, _ = part_turns(tgt_solver.neutral[eyes_t[side]], tgt_solver.deltas[:, eyes_t[side]])
                turns[side] = (r, share, np.linalg.norm(q, axis=1).max() / np.linalg.norm(r, axis=1).max())
                for j in np.argsort(-np.linalg.norm(r, axis=1))[:4]:
                    print(f"{c}   source eye {side:+d}: {z['source_names'][j]} turns {np.round(np.degrees(r[j]), 1)} deg, "
                          f"rigid share {share[j]:.2f}", flush=True)
                print(f"{c}   eye {side:+d}: the rigs' largest turns {np.degrees(np.linalg.norm(q, axis=1).max()):.1f} / "
                      f"{np.degrees(np.linalg.norm(r, axis=1).max()):.1f} deg: range gain {turns[side][2]:.2f}", flush=True)
                Q = tgt_solver.neutral[eyes_t[side]]
                dq = np.asarray(tgt_solver.deltas[:, eyes_t[side]], dtype=np.float64)
                Qw, Tq = (warp(Q), warp(Q[None] + dq) - warp(Q)[None]) if warp is not None else (Q, dq)
                parts.append((side, Qw, sphere_fit(Qw)[0], Tq))

            def rows(gain, w, shared):
                Se = np.concatenate([w * (turns[side][2] if gain == "range" else gain) * np.cross(
                    (turns[side][0] * (turns[side][1][:, None] if shared else 1.0))[:, None, :], (Qw - cen)[None])
                    for side, Qw, cen, _ in parts], 1)
                return Se, np.concatenate([w * Tq for *_, Tq in parts], 1)

            for g, w in ((1, 1.0), (1, 0.5), (2, 0.5), (3, 0.5), (4, 0.5), (5, 0.5), (6, 0.5), (4, 0.3), (4, 0.7)):
                show(f"3 eyes: the same angle × {g}, w {w}", fit(extra=rows(g, w, False)))
            for w in (0.1, 0.3, 0.5):
                show(f"3 eyes: range gain, w {w}", fit(extra=rows("range", w, False)))
            for w in (0.3, 0.5, 1.0, 2.0):
                show(f"3 eyes: range gain × rigid share, w {w}{' (auto)' if w == 1 else ''}", fit(extra=rows("range", w, True)))
            for w in (0.5, 1.0):
                show(f"3 eyes: the same angle × 4 × rigid share, w {w}", fit(extra=rows(4, w, True)))
            auto_rows = gaze_rows(src, tgt_solver, warp)
            show("3 eyes: core.eyes.gaze_rows (what auto adds)", fit(extra=auto_rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
