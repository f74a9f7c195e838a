"""Measured numbers of docs/controls.md: the production controls on the bundled sample.

The Live Link take ``livelinkface_take_s07.csv`` drives ICT, whose markers are retargeted onto
Rocketbox (the pipeline's defaults; ``--shapes arkit`` restricts the solve to Rocketbox's ARKit
shapes, where the actor's curves are the ground truth by name). Prints markdown tables:

1. symmetry weight: blink RMSE against the actor's namesake curves, L-R asymmetry, curve RMSE
   over all named shapes, marker error (bounded per-frame solve);
2. cancel pairs (blink/wide per eye, jawOpen/mouthClose): rows that fired, passes and marker
   error before / re-solved / clamped, per method;
3. filter responses (formula and measured), the One Euro cutoff against speed;
4. keys before / after reduction (tolerance 0.005).

Run: ``python scripts/controls_report.py`` (about a minute; OPENBLAS_NUM_THREADS=1).
"""

from __future__ import annotations

import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core import controls as C  # noqa: E402

DATA = ROOT / "data"
FILES = dict(source=str(DATA / "performances" / "livelinkface_take_s07.csv"), source_rig=str(DATA / "rigs" / "ict_facekit.glb"),
             target_rig=str(DATA / "rigs" / "rocketbox_female_adult_02.glb"))
FPS = 30.0


def problem(method="bounded", target_shapes="arkit"):
    from core.pipeline import Pipeline, StageCache
    from core.stages.methods import named_target

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pipe = Pipeline(cache=StageCache(), method=method, target_shapes=target_shapes, **FILES)
        r = pipe.results(["stabilize", "personalize", "shapes", "load", "frames", "prior", "segment", "synthesize"])
    st = r["stabilize"]["source"]
    return r, r["personalize"]["deltas"], st.deltas, st.valid, list(r["shapes"]["rig"].names), named_target(r)


def mm(B, W, S, valid, predicted=None):
    from core.metrics import marker_error_mm

    return float(marker_error_mm(B, W, S, valid, predicted=predicted).distances.mean())


def symmetry_table():
    from core.solvers.baselines import range_pf

    r, B, S, valid, names, named = problem()
    iL, iR = names.index("AK_09_EyeBlinkLeft"), names.index("AK_10_EyeBlinkRight")
    pairs = C.pair_indices(C.symmetry_pairs(names), names)
    print(f"\nSymmetry ({len(pairs)} pairs of C.symmetry_pairs), bounded per-frame solve [0, 1], ridge 1e-5, "
          f"{len(names)} ARKit shapes; the actor's own blinks differ by "
          f"{np.sqrt(np.mean((named[:, iL] - named[:, iR]) ** 2)):.4f} RMS\n")
    print("| mu_s | blink RMSE (L, R) | blink L-R RMS | curve RMSE (51 named) | marker error (mm) | time (s) |")
    print("|---|---|---|---|---|---|")
    for mu in (0.0, 1e-3, 1e-2, 0.1, 1.0):
        t = time.perf_counter()
        W = range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5, quadratic=C.symmetry_matrix(pairs, len(names), mu) if mu else None)
        dt = time.perf_counter() - t
        both = np.sqrt(np.mean((W[:, [iL, iR]] - named[:, [iL, iR]]) ** 2))
        asym = np.sqrt(np.mean((W[:, iL] - W[:, iR]) ** 2))
        curve = np.nanmean(np.sqrt(np.nanmean((W - named) ** 2, axis=0)))
        print(f"| {mu:g} | {both:.4f} | {asym:.4f} | {curve:.4f} | {mm(B, W, S, valid):.3f} | {dt:.2f} |")


def cancel_table():
    from core.solvers.baselines import prior_pf, range_pf
    from core.solvers.geometric import GeometricSolver
    from core.solvers.local import local_precompute, reconstruct_markers
    from core.solvers.spacetime import SpacetimeSolver

    r, B, S, valid, names, named = problem(method="local")
    prior = problem(method="spacetime")[0]["prior"]["prior"]
    pairs = C.pair_indices(C.suggested_cancel_pairs(names), names)
    print(f"\nCancel pairs {[(names[a], names[b]) for a, b in pairs]}, threshold 0 (w_a w_b = 0)\n")
    print("| method | rows that fired | passes | marker error (mm): none | re-solved | clamped | time (s) |")
    print("|---|---|---|---|---|---|---|")

    def row(name, W0, solve, err):
        t = time.perf_counter()
        W, info = C.cancel_pairs(solve, W0, pairs)
        dt = time.perf_counter() - t
        assert not C.cancel_conflicts(W, pairs).any()
        e0, e1, ec = err(W0), err(W), err(C.cancel_clamp(W0, pairs))
        print(f"| {name} | {info['rows']} | {info['passes']} | {e0:.4f} | {e1:.4f} ({(e1 / e0 - 1) * 100:+.2f} %) | "
              f"{ec:.4f} ({(ec / e0 - 1) * 100:+.2f} %) | {dt:.2f} |")
        return W

    err = lambda W: mm(B, W, S, valid)
    solve = lambda z: range_pf(B, S, 0.0, 1.0, valid, ridge=1e-5, zero=z)
    Wb = solve(None)
    row("bounded", Wb, solve, err)
    solve = lambda z: prior_pf(B, S, 0.01, prior, valid, ridge=1e-5, zero=z)
    row("prior_pf", solve(None), solve, err)
    s = SpacetimeSolver(B, S, alpha=0.01, prior=prior, known={0: Wb[0], len(S) - 1: Wb[-1]}, valid=valid, ridge=1e-5,
                        lower=0.0, upper=1.0)
    Ws0 = s.solve()
    Ws = row("spacetime", Ws0, lambda z: s.solve(zero=z), err)
    e0, e1 = s.energy(Ws0).total, s.energy(Ws).total
    g = GeometricSolver(B, "geometric", rig=r["shapes"]["rig"], mu=0.3, lam=0.6)
    row("geometric", g.solve(S).weights, lambda z: g.solve(S, zero=z).weights, err)
    seg, st = r["segment"], r["stabilize"]["source"]
    prob = local_precompute(np.zeros_like(st.neutral), B, seg["marker_weights"], constraint="simplex")
    U0 = prob.solve(S, valid)
    T, R, K = U0.shape

    def lerr(U):
        P = reconstruct_markers(np.zeros_like(st.neutral), B, U.reshape(T, R, K), seg["marker_masks"])
        return mm(B, np.zeros((T, K)), S, valid, predicted=P)

    row("local (per region)", U0.reshape(T * R, K),
        lambda z: prob.solve(S, valid, zero=z.reshape(T, R, K)).reshape(T * R, K), lerr)
    print(f"\n(spacetime: its own energy rises {(e1 / e0 - 1) * 100:.2f} %; marker error is not what it minimises)")


def _gain(y, f, t, A):
    n = int(round(FPS / f * np.floor(len(t) / 2 * f / FPS)))
    sl = slice(len(t) // 4, len(t) // 4 + n)
    X = np.c_[np.sin(2 * np.pi * f * t[sl]), np.cos(2 * np.pi * f * t[sl])]
    return float(np.hypot(*np.linalg.lstsq(X, y[sl] - y[sl].mean(), rcond=None)[0]) / A)


def filter_tables():
    from scipy.optimize import brentq

    fs = [0.25, 0.5, 1, 2, 3, 5, 7, 10]
    print("\nMagnitude response at 30 fps\n")
    print("| filter | " + " | ".join(f"{f:g} Hz" for f in fs) + " | -3 dB |")
    print("|---|" + "---|" * (len(fs) + 1))
    for fc in (0.5, 1.0, 2.0):
        f3 = brentq(lambda f: C.lowpass_response(f, FPS, fc) - 2 ** -0.5, 1e-3, 14.9)
        print(f"| One Euro, beta 0, min_cutoff {fc:g} Hz (R1) | " + " | ".join(f"{C.lowpass_response(f, FPS, fc):.3f}" for f in fs)
              + f" | {f3:.2f} Hz |")
    for sg in (1, 2, 4):
        f3 = brentq(lambda f: C.gaussian_response(f, FPS, sg) - 2 ** -0.5, 1e-3, 14.9)
        print(f"| Gaussian, sigma {sg} frames | " + " | ".join(f"{abs(C.gaussian_response(f, FPS, sg)):.3f}" for f in fs)
              + f" | {f3:.2f} Hz |")
    t = np.arange(int(FPS * 200)) / FPS
    for fmin, beta in ((1.0, 0.3), (0.5, 1.0)):
        for A in (0.02, 0.2):
            g = [_gain(C.one_euro((0.5 + A * np.sin(2 * np.pi * f * t))[:, None], FPS, fmin, beta)[:, 0], f, t, A) for f in fs]
            print(f"| One Euro, min_cutoff {fmin:g}, beta {beta:g}, sine amplitude {A:g} (measured) | "
                  + " | ".join(f"{x:.3f}" for x in g) + " | |")
    print("\nOne Euro on a ramp of speed v (R2): steady cutoff and lag\n")
    print("| min_cutoff (Hz) | beta | v (weight/s) | cutoff (Hz) | lag (weight x 1000) | lag (ms) |")
    print("|---|---|---|---|---|---|")
    for fmin, beta in ((1.0, 0.0), (1.0, 0.3), (0.5, 1.0)):
        for v in (0.1, 1.0, 5.0):
            fc, lag = C.one_euro_cutoff(v, FPS, fmin, beta)
            print(f"| {fmin:g} | {beta:g} | {v:g} | {float(fc):.2f} | {float(lag) * 1000:.1f} | {float(lag) / v * 1000:.0f} |")


def keys_table():
    from core.evaluate import jitter

    cases = {}
    for method, shapes in (("bounded", ""), ("bounded", "arkit"), ("spacetime", "arkit")):
        W = problem(method, shapes)[0]["synthesize"]["weights"]
        cases[f"{method}, {'all' if not shapes else 'ARKit'} shapes"] = W
        if method == "bounded" and not shapes:
            cases["bounded, all shapes + One Euro (1 Hz, beta 0.3)"] = C.filter_weights(W, FPS, "one_euro", min_cutoff=1.0, beta=0.3)
            cases["bounded, all shapes + Gaussian (sigma 2)"] = C.filter_weights(W, FPS, "gaussian", sigma=2.0)
    print("\nKeys within 0.005 of the dense curves (2028 frames x 175 Rocketbox shapes = 354,900 samples; shapes the "
          "solve does not use are constant: 2 keys each)\n")
    print("| weights | jitter | LINEAR keys | CUBICSPLINE keys | one grid: LINEAR (union / shared) | one grid: CUBICSPLINE "
          "(union / shared) | time (s) |")
    print("|---|---|---|---|---|---|---|")
    for name, W in cases.items():
        t = time.perf_counter()
        kl, kc = C.reduce_keys(W, FPS, 0.005), C.reduce_keys(W, FPS, 0.005, "CUBICSPLINE")
        sl, sc = C.reduce_keys(W, FPS, 0.005, shared=True), C.reduce_keys(W, FPS, 0.005, "CUBICSPLINE", shared=True)
        dt = time.perf_counter() - t
        for k in (kl, kc, sl, sc):
            assert np.abs(k.evaluate() - W).max() <= 0.005
        n = W.size
        print(f"| {name} | {jitter(W).mean():.4f} | {kl.counts.sum()} ({kl.counts.sum() / n * 100:.1f} %) | "
              f"{kc.counts.sum()} ({kc.counts.sum() / n * 100:.1f} %) | {len(kl.grid()[0])} / {sl.counts[0]} | "
              f"{len(kc.grid()[0])} / {sc.counts[0]} | {dt:.1f} |")


if __name__ == "__main__":
    symmetry_table()
    cancel_table()
    filter_tables()
    keys_table()
