"""Issue 29, case B, design V: can the vocabularies steer auto's sparse shape map?

Case B (S07 take on ICT -> Rocketbox with only its non-ARKit shapes, ``SR_*``, ``AU_*``, ``AA_VI_*``,
``HB_*``) and C (every shape renamed: no vocabulary recognises a name, so every design below is
auto's map there by construction), scored as :mod:`scripts.quality_cases` (mean face-vertex error
against the Rocketbox head driven by the take through its ``AK_*`` namesakes, whole take). Every
row maps the source rig's curves through a (K, J) map ``W = clip(W_source Mᵀ, 0, 1)`` fitted over
the first 1,000 dense correspondence points, the target's shapes warped into the actor's
proportions, the source's aligned by the covariance map (auto's
:func:`core.stages.methods.dense_shape_map`); only how M is fitted changes:

* ``auto``                the sparse shape map (l1 0.3), geometry alone;
* ``vocabulary map``      the vocabularies' combinations as the map (the ``names`` method's
                          exclusive :class:`core.names.NameMap`): meaning without geometry;
* ``ceiling …``           oracles (use the truth: analyses, never methods) — the map fitted to each
                          source shape's *true* target, the full rig's ``AK_*`` namesake geometry,
                          with the case's shapes: per shape (l1 0 / 0.1 / 0.3), and over the take
                          (``min Σ_t ‖(W_t Mᵀ − W_t G*ᵀ) T‖²``, the exact box QP on the Kronecker
                          Hessian, B only: the best map of this form); the true sizes with the
                          geometric directions, and the true directions with the geometric sizes;
* ``V2 weighted L1``      :func:`core.shape_matching.shape_map` with ``l1_scale``: the shapes the
                          vocabularies map to source shape j's ARKit name (non-exclusive: every
                          vocabulary's sculpt; exclusive: the names method's one) get f × the L1
                          weight; optionally each column rescaled to auto's column's size on the face;
* ``V3 prior``            ``x0_j = g_j v_j``: the vocabularies' combination for j (averaged over the
                          vocabularies that have it), its gain fitted by geometry, alone, as a
                          quadratic pull ``μ ‖s_j‖² ‖x − x0_j‖²`` on the vocabulary's shapes in the
                          sparse fit, or blended with auto's map;
* ``V4 candidates``       j fitted only by the vocabulary's shapes plus the n target shapes most
                          cosine-similar to it;
* ``auto × 0.8``          not a vocabulary: the geometric map scaled down (how much is size);
* ``ceiling: each column …`` auto's map with each source shape's column taken from the vocabulary
                          map wherever that alone helps (in hindsight: the best per-channel choice).

``--detail`` says where auto's error is: the upper and lower face, the source shapes whose column
costs most (the drop when it alone is replaced by the per-shape ceiling's), and for the shapes the
take moves most the cosine with the true target and the size ratio of the aligned source shape and
of each vocabulary's combination.

::

    python scripts/vocab_map_eval.py [--cases BC] [--detail]
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
from core.metrics import vertex_errors  # noqa: E402
from core.motion_alignment import apply_alignment, covariance_alignment  # noqa: E402
from core.names import NameMap  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from core.shape_matching import SPARSE_L1, mapped_weights, shape_map  # noqa: E402
from core.solvers.boxqp import solve_box_sequence  # noqa: E402
from core.stages.methods import AUTO_DENSE_POINTS  # noqa: E402

STAGES = ["load", "frames", "shapes", "stabilize", "calibrate", "dense_correspondence", "vocabulary"]
VOCAB_PREFIXES = qc.NON_ARKIT  # one vocabulary per prefix in Rocketbox: SR_ SRanipal, AU_ FACS, AA_VI_ visemes, HB_


def case_data(case) -> dict:
    """Auto's inputs to the shape map on a case, the vocabularies' proposals and the truth's map."""
    pipe = Pipeline(cache=case["cache"], **case["settings"])
    res = pipe.results(STAGES)
    ld, sh, dc = res["load"], res["shapes"], res["dense_correspondence"]
    srig, rig, idx = ld["source_rig"], sh["rig"], np.asarray(sh["shape_index"])
    pts = list(dc["source_layout"].names[:AUTO_DENSE_POINTS])
    Ds = dc["source_layout"].select(pts).points(srig.deltas)
    warp = res["calibrate"]["target"].warp

    def warped(r):
        n, d = dc["target_layout"].select(pts).on_rig(r)
        return warp(n[None] + d) - warp(n)[None]

    T, T_full = warped(rig), warped(ld["target_rig"])
    vocabs = res["vocabulary"]["vocabularies"]
    G_all = NameMap.automatic(srig.names, rig.names, vocabularies=vocabs, exclusive=False).matrix(srig.names, rig.names)
    G_one = NameMap.automatic(srig.names, rig.names, vocabularies=vocabs, exclusive=True).matrix(srig.names, rig.names)
    G_true = NameMap.automatic(srig.names, case["rig"].names).matrix(srig.names, case["rig"].names)  # the truth's
    Ws = np.nan_to_num(np.asarray(res["stabilize"]["source"].source_weights, dtype=np.float64))
    Sa = apply_alignment(covariance_alignment(Ds, T), Ds)  # as core.shape_matching.aligned_shape_map
    return dict(case=case, idx=idx, names=list(rig.names), source_names=list(srig.names), Ws=Ws, Sa=Sa, T=T,
                S_true=np.einsum("kj,kmc->jmc", G_true, T_full), G_all=G_all, G_one=G_one)


def score(d, M) -> float:
    case, W = d["case"], mapped_weights(M, d["Ws"])
    full = np.zeros((len(W), case["rig"].n_shapes))
    full[:, d["idx"]] = W
    Wt = case["truth"]["weights"]
    return float(np.nanmean(vertex_errors(case["rig"].deltas, full, Wt, case["face"], np.isfinite(Wt).all(1))[0]))


def _flat(x):
    return x.reshape(len(x), -1)


def take_weighted_oracle(d) -> np.ndarray:
    """(K, J) the map minimising the take's error against the true targets at the points,
    ``Σ_t ‖W_t (M T − S*)‖²`` = ``tr((MT − S*)ᵀ Q (MT − S*))`` with ``Q = W_sᵀ W_s / T``, within [0, 1]:
    the exact box QP on the Kronecker Hessian ``Q ⊗ T Tᵀ`` (J·K unknowns)."""
    T, S, Ws = _flat(d["T"]), _flat(d["S_true"]), d["Ws"]
    K, J = len(T), len(S)
    Q = Ws.T @ Ws / len(Ws)
    Q[np.diag_indices_from(Q)] += 1e-9 * np.trace(Q)
    H = np.kron(Q, T @ T.T)  # unknowns x[j K + k] = M[k, j]
    H[np.diag_indices_from(H)] += 1e-12 * H.diagonal().max()
    b = (T @ S.T @ Q).T.ravel()
    return solve_box_sequence(H[None], -b[None])[0].reshape(J, K).T


def vocabulary_prior(d) -> np.ndarray:
    """(J, K) ``x0_j = g_j v_j``: the vocabularies' combination for source shape j (the mean over
    the vocabularies proposing it of each one's shapes and gains), its gain fitted to the aligned
    source shape by least squares (>= 0), clipped to [0, 1]; zero where no vocabulary has j."""
    vocab = np.array([next((i for i, p in enumerate(VOCAB_PREFIXES) if n.startswith(p)), -1) for n in d["names"]])
    G = np.clip(d["G_all"], 0, None)
    n_voc = np.array([max(1, len(set(vocab[G[:, j] > 0]))) for j in range(G.shape[1])])
    v = (G / n_voc[None]).T
    tv, s = v @ _flat(d["T"]), _flat(d["Sa"])
    g = np.maximum(0.0, (tv * s).sum(1) / np.maximum((tv ** 2).sum(1), 1e-300))
    return np.clip(g[:, None] * v, 0.0, 1.0)


def prior_map(d, x0, mu, l1_scale) -> np.ndarray:
    """(K, J) the sparse fit pulled towards ``x0`` on the vocabulary's shapes:
    ``min ‖Tᵀx − s_j‖² + μ ‖s_j‖² Σ_{k∈V_j} (x_k − x0_jk)² + l1 ‖s_j‖² Σ_k c_jk x_k`` in [0, 1], one
    exact box QP per source shape (its own Hessian)."""
    T, S = _flat(d["T"]), _flat(d["Sa"])
    V = (x0 > 0) | (d["G_all"].T > 0)
    G = T @ T.T
    G[np.diag_indices_from(G)] += 1e-9 * np.linalg.eigvalsh(G)[-1]
    s2 = (S ** 2).sum(1)
    H = np.stack([G + np.diag(mu * s2[j] * V[j]) for j in range(len(S))])
    rhs = S @ T.T - 0.5 * SPARSE_L1 * s2[:, None] * l1_scale + mu * s2[:, None] * V * x0
    return np.clip(solve_box_sequence(H, -rhs, idx=np.arange(len(S))), 0.0, 1.0).T


def rows(d, has_truth_qp: bool):
    """(label, map) of every design (module docstring)."""
    Sa, T = d["Sa"], d["T"]
    sparse = lambda S, c=None, l1=SPARSE_L1: shape_map(S, T, ridge=0.0, l1=l1, l1_scale=c)  # noqa: E731
    auto = sparse(Sa)
    yield "auto (geometry alone)", auto
    yield "vocabulary map (names method's combinations)", d["G_one"]
    for l1 in (0.0, 0.1, 0.3):
        yield f"ceiling: true targets per shape, l1 {l1}", (shape_map(d["S_true"], T, ridge=1e-4) if l1 == 0 else
                                                            sparse(d["S_true"], l1=l1))
    if has_truth_qp:
        yield "ceiling: true targets over the take", take_weighted_oracle(d)
    ns, nt = np.linalg.norm(_flat(Sa), axis=1), np.linalg.norm(_flat(d["S_true"]), axis=1)
    yield "ceiling: true sizes, geometric directions", sparse(Sa * (nt / np.maximum(ns, 1e-300))[:, None, None])
    yield "ceiling: true directions, geometric sizes", sparse(d["S_true"] * (ns / np.maximum(nt, 1e-300))[:, None, None])
    V = d["G_all"].T > 0  # (J, K) every vocabulary's shapes for source shape j
    if V.any():
        yield ("ceiling: true sizes, directions ½ geometry + ½ the vocabularies' that agree (cos ≥ 0.7), "
               "their L1 × 0.1"), sparse(blended_targets(d, nt), np.where(V, 0.1, 1.0))
    size = np.linalg.norm(auto.T @ _flat(T), axis=1)
    for which in ("all", "one"):
        Vw = d["G_all" if which == "all" else "G_one"].T > 0
        for f in (0.0, 0.1, 0.3):
            M = sparse(Sa, np.where(Vw, f, 1.0))
            yield f"V2 weighted L1, {which} vocabularies' shapes × {f}", M
            if f == 0.1:
                rescale = size / np.maximum(np.linalg.norm(M.T @ _flat(T), axis=1), 1e-300)
                yield f"V2 weighted L1, {which} × {f}, columns at auto's size", np.clip(M * rescale[None], 0, 1)
    x0 = vocabulary_prior(d)
    has = x0.any(1)
    yield "V3 x0 alone (auto's column where no vocabulary)", np.where(has[None], x0.T, auto)
    for a in (0.25, 0.5):
        yield f"V3 {a} x0 + {1 - a} auto", a * np.where(has[None], x0.T, auto) + (1 - a) * auto
    for mu in (0.03, 0.3, 3.0):
        for f in (0.0, 1.0):
            yield f"V3 pull μ {mu} towards x0, vocabulary's L1 × {f}", prior_map(d, x0, mu, np.where(V, f, 1.0))
    cosine = _flat(Sa) @ _flat(T).T / np.maximum(np.linalg.norm(_flat(Sa), axis=1)[:, None]
                                                   * np.linalg.norm(_flat(T), axis=1)[None], 1e-300)
    for n in (0, 4, 8):
        cand = V.copy()
        if n:
            np.put_along_axis(cand, np.argsort(-cosine, axis=1)[:, :n], True, axis=1)
        cand[~V.any(1)] = True  # no vocabulary for j: every shape a candidate
        yield f"V4 candidates: vocabulary + top {n} by cosine", sparse(Sa, np.where(cand, 1.0, 1e6))
    yield "auto × 0.8 (size, no vocabulary)", 0.8 * auto
    yield "ceiling: each column auto's or the vocabulary map's, the better", hindsight_choice(d, auto)


def vocabulary_combinations(d) -> list:
    """Per source shape j, ``[(vocabulary prefix, (M, 3) displacement)]``: each vocabulary's
    combination of the case's shapes for j's ARKit name (the non-exclusive map's gains)."""
    out = []
    for j in range(d["G_all"].shape[1]):
        row = []
        for p in VOCAB_PREFIXES:
            g = np.array([d["G_all"][k, j] if n.startswith(p) else 0.0 for k, n in enumerate(d["names"])])
            if (g > 0).any():
                row.append((p, np.einsum("k,kmc->mc", np.clip(g, 0, None), d["T"])))
        out.append(row)
    return out


def _cos(a, b) -> float:
    return float(a.ravel() @ b.ravel() / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


def blended_targets(d, sizes, tau: float = 0.7, beta: float = 0.5) -> np.ndarray:
    """(J, M, 3) each aligned source shape's direction moved half-way (β) towards the mean direction
    of the vocabularies' combinations that agree with it (cosine ≥ τ), at the given sizes."""
    out = []
    for j, row in enumerate(vocabulary_combinations(d)):
        s = d["Sa"][j] / max(np.linalg.norm(d["Sa"][j]), 1e-300)
        good = [v / np.linalg.norm(v) * _cos(v, s) for _, v in row if _cos(v, s) >= tau]
        u = s if not good else (1 - beta) * s + beta * sum(good) / np.linalg.norm(sum(good))
        out.append(sizes[j] * u / max(np.linalg.norm(u), 1e-300))
    return np.stack(out)


def cosines(d, n: int = 30) -> str:
    """Per source shape (the n the take moves most), the cosine with the true target at the points
    and the size ratio of the aligned source shape and of each vocabulary's combination; the means."""
    use = np.abs(d["Ws"]).mean(0) * np.linalg.norm(_flat(d["S_true"]), axis=1)
    combos, lines, means = vocabulary_combinations(d), [], {}
    for j in np.argsort(-use)[:n]:
        t = d["S_true"][j]
        nt = max(np.linalg.norm(t), 1e-300)
        parts = [("geometry", d["Sa"][j])] + combos[j]
        for p, v in parts:
            means.setdefault(p, []).append(_cos(v, t))
        lines.append(f"    {d['source_names'][j]:18s} " + "  ".join(
            f"{p} cos {_cos(v, t):.2f} size {np.linalg.norm(v) / nt:.2f}" for p, v in parts))
    sizes = [np.linalg.norm(v) / max(np.linalg.norm(d["S_true"][j]), 1e-300) for j, row in enumerate(combos) for _, v in row]
    geo = np.linalg.norm(_flat(d["Sa"]), axis=1) / np.maximum(np.linalg.norm(_flat(d["S_true"]), axis=1), 1e-300)
    ok = np.linalg.norm(_flat(d["S_true"]), axis=1) > 0
    lines.append("    mean cosine with the true target: " + ", ".join(f"{p} {np.mean(c):.2f}" for p, c in means.items())
                 + f"; median size / true: geometry {np.median(geo[ok]):.2f}"
                 + (f", vocabularies {np.median(sizes):.2f}" if sizes else ""))
    return "\n".join(lines)


def hindsight_choice(d, auto) -> np.ndarray:
    """(K, J) auto's map with each source shape's column replaced by the vocabulary map's (the names
    method's) wherever that alone lowers the error against the truth: the best a per-channel choice
    between meaning and geometry could do (an oracle: it reads the truth)."""
    base, M = score(d, auto), auto.copy()
    for j in range(auto.shape[1]):
        trial = auto.copy()
        trial[:, j] = d["G_one"][:, j]
        if score(d, trial) < base:
            M[:, j] = d["G_one"][:, j]
    return M


def detail(d, M, n: int = 6) -> str:
    """Where ``M``'s error is: the upper / lower face, and the source shapes whose column costs most
    (the error drop when it alone is replaced by the per-shape ceiling's, l1 0.1)."""
    case = d["case"]
    ceiling = shape_map(d["S_true"], d["T"], ridge=0.0, l1=0.1)
    base = score(d, M)
    gain = []
    for j in range(M.shape[1]):
        Mj = M.copy()
        Mj[:, j] = ceiling[:, j]
        gain.append(base - score(d, Mj))
    top = np.argsort(gain)[::-1][:n]
    W = np.zeros((len(d["Ws"]), case["rig"].n_shapes))
    W[:, d["idx"]] = mapped_weights(M, d["Ws"])
    Wt = case["truth"]["weights"]
    ok = np.flatnonzero(np.isfinite(Wt).all(1))[::4]
    face = case["face"]
    E = np.zeros(len(face))
    for a in range(0, len(ok), 128):
        f = ok[a:a + 128]
        E += np.linalg.norm(np.einsum("tk,kvc->tvc", W[f] - Wt[f], case["rig"].deltas[:, face]), axis=2).sum(0)
    E = E / len(ok) * 1e3
    y = case["rig"].neutral[face, 1]
    upper = y > np.median(y)
    lines = [f"    upper face {E[upper].mean():.3f} mm, lower {E[~upper].mean():.3f}; columns costing most: "
             + ", ".join(f"{d['source_names'][j]} {gain[j]:.3f}" for j in top)]
    weighted = shape_map(d["Sa"], d["T"], ridge=0.0, l1=SPARSE_L1, l1_scale=np.where(d["G_all"].T > 0, 0.1, 1.0))
    column = lambda X, j: ", ".join(f"{d['names'][k]} {X[k, j]:.2f}" for k in np.argsort(-X[:, j])[:4]  # noqa: E731
                                    if X[k, j] > 0.02) or "(nothing)"
    for j in top[:4]:
        lines.append(f"    {d['source_names'][j]}: auto {column(M, j)}; true-target fit {column(ceiling, j)}; "
                     f"V2 all × 0.1 {column(weighted, j)}")
    gaze = [j for j, n in enumerate(d["source_names"]) if n.startswith("eyeLook")]
    if gaze and d["G_one"].any():
        Mg = M.copy()
        Mg[:, gaze] = d["G_one"][:, gaze]
        lines.append(f"    every eyeLook* column from the vocabulary map: {score(d, Mg):.3f} mm")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="BC")
    ap.add_argument("--detail", action="store_true", help="where auto's error is")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    cases = "".join(c for c in args.cases.upper() if c in "BC")
    with tempfile.TemporaryDirectory() as tmp:
        built = qc.build_cases(cases, Path(tmp))
        data = {c: case_data(built[c]) for c in cases}
        results = {c: {} for c in cases}
        for c in cases:
            for label, M in rows(data[c], has_truth_qp=(c == "B")):  # C's Kronecker Hessian: 8,745² (0.6 GB)
                results[c][label] = score(data[c], M)
                print(f"{c} {label:62s} {results[c][label]:.3f} mm", flush=True)
                if args.detail and label.startswith("auto ("):
                    print(detail(data[c], M) + "\n" + cosines(data[c]), flush=True)
    labels = list(dict.fromkeys(lbl for c in cases for lbl in results[c]))
    print("\n| design | " + " | ".join(cases) + " |\n|---|" + "---|" * len(cases))
    for lbl in labels:
        print(f"| {lbl} | " + " | ".join(f"{results[c][lbl]:.3f}" if lbl in results[c] else "—" for c in cases) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
