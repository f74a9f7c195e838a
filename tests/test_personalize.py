"""Ribera 2017 §4 range-of-motion alignment: the pieces (eq. 5-8, §4.2-4.5), the solver against
an independent dense least-squares reference, and the behaviour on real ICT/Live Link data."""

from pathlib import Path

import numpy as np
import pytest

from core import geometry
from core.names import NameMap
from datapaths import face_markers
from core.personalize import (AlignmentProblem, amplitude, blended_similarity, contact_edges, contrast,
                              cross_expression_laplacian, key_expressions, marker_laplacian,
                              marker_triangulation, motion_similarity, personalize, support_masks, trust)

DATA = Path(__file__).resolve().parents[1] / "data"


# -- helpers --------------------------------------------------------------------------------

def rom_weights(rig):
    path = DATA / "performances" / "livelinkface_rom.csv"
    header = open(path).readline().strip().split(",")[2:54]
    W = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=range(2, 54))
    return W @ NameMap.automatic(header, rig.names).matrix(header, rig.names).T


def animface_neutral(name="animface_markers_jaw_60hz.csv"):
    path = DATA / "performances" / name
    header = open(path).readline().strip().split(",")[2:]
    names = [h[:-2] for h in header[::3]]
    X = np.genfromtxt(path, delimiter=",", skip_header=1, max_rows=1)[2:].reshape(-1, 3) * 0.01  # cm -> m
    return names, X


def dense_reference(pr: AlignmentProblem):
    """Minimise E_Align (+ ridge) by numpy.linalg.lstsq on the stacked residuals of eq. 10, 11, 13.

    Built from the energy definitions, not from the normal equations the solver uses.
    """
    K, M, _ = pr.shape
    F = max(pr.weights.shape[1], 1)
    L = pr.mesh_laplacian.toarray()
    G = pr.graph_laplacian
    out = np.zeros((K, M, 3))
    for c in range(3):
        rows, rhs = [], []
        for k in range(K):
            for f in range(pr.weights.shape[1]):
                w = np.sqrt(pr.weights[k, f] / F)
                block = np.zeros((M, K * M))
                u = pr.masks[k]
                block[:, k * M:(k + 1) * M] = w * (np.eye(M) if pr.mask == "target" else np.diag(u))
                rows.append(block)
                rhs.append(w * u * pr.targets[f, :, c])
        sb = np.sqrt(pr.beta / M)
        for k in range(K):
            block = np.zeros((M, K * M))
            block[:, k * M:(k + 1) * M] = sb * L
            rows.append(block)
            rhs.append(sb * L @ pr.initial[k, :, c])
        sg = np.sqrt(pr.gamma / M)
        for k in range(K):
            block = np.zeros((M, K * M))
            for l in range(K):
                block[:, l * M:(l + 1) * M] = sg * G[k, l] * np.eye(M)
            rows.append(block)
            rhs.append(sg * (G[k] @ pr.reference[:, :, c]))
        if pr.ridge:
            rows.append(np.sqrt(pr.ridge) * np.eye(K * M))
            rhs.append(np.sqrt(pr.ridge) * pr.initial[:, :, c].ravel())
        x = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
        out[:, :, c] = x.reshape(K, M)
    return out


@pytest.fixture(scope="module")
def ict_setup(ict):
    idx = face_markers(ict, 60)
    S = ict.deltas[:, idx]
    return idx, S, ict.neutral[idx], rom_weights(ict)


# -- eq. 5-8 --------------------------------------------------------------------------------

def test_similarity_eq5_hand_cases():
    s = np.zeros((3, 2, 3))
    s[0, 0] = [1, 0, 0]
    s[1, 1] = [0, 2, 0]
    s[2] = [[1, 1, 0], [0, 0, 0]]
    a = np.zeros((4, 2, 3))
    a[0, 0] = [5, 0, 0]          # parallel to shape 0, 5x bigger
    a[1, 0] = [-1, 0, 0]         # anti-parallel
    a[2] = np.nan                # a missing frame
    # a[3] stays neutral (zero displacement)
    c = motion_similarity(a, s)
    np.testing.assert_allclose(c[:, 0], [1, 0, 1 / np.sqrt(2)])
    np.testing.assert_allclose(c[:, 1], [-1, 0, -1 / np.sqrt(2)])
    np.testing.assert_array_equal(c[:, 2:], 0)
    rng = np.random.default_rng(0)
    A, S = rng.normal(size=(7, 5, 3)), rng.normal(size=(4, 5, 3))
    np.testing.assert_allclose(motion_similarity(3.7 * A, 0.2 * S), motion_similarity(A, S))  # scale invariant
    ref = np.array([[np.corrcoef(np.r_[A[f].ravel(), -A[f].ravel()], np.r_[S[k].ravel(), -S[k].ravel()])[0, 1]
                     for f in range(7)] for k in range(4)])  # Pearson about the neutral (zero mean)
    np.testing.assert_allclose(motion_similarity(A, S), ref)


def test_trust_eq6_hand_case():
    # shape 0 largest; shape 1 correlates 0.6 with it; shape 2 smallest, correlates with both
    e = np.eye(3)
    s = np.zeros((3, 1, 3))
    s[0, 0] = 10 * e[0]
    s[1, 0] = 5 * (0.6 * e[0] + 0.8 * e[1])
    s[2, 0] = 1 * (0.5 * e[0] + np.sqrt(0.75) * e[2])
    c12 = 0.6 * 0.5
    rows = np.array([0.0, 0.6, 0.5 + c12])
    np.testing.assert_allclose(trust(s), 1 - rows / rows.max())
    # order is by displacement, not by input position
    perm = [2, 0, 1]
    np.testing.assert_allclose(trust(s[perm]), (1 - rows / rows.max())[perm])
    # negative correlations do not lower trust
    s2 = np.stack([s[0], -s[0] * 0.5])
    np.testing.assert_allclose(trust(s2), [1, 1])


def test_contrast_eq7_and_blend_eq8():
    c = np.linspace(0, 1, 11)
    r = 15
    np.testing.assert_allclose(contrast(c, r), np.exp(r * c) / (np.exp(r / 2) + np.exp(r * c)))
    assert contrast(0.5) == pytest.approx(0.5)
    assert np.isfinite(contrast(c, 5000)).all()
    rng = np.random.default_rng(1)
    A, S = rng.normal(size=(9, 6, 3)), rng.normal(size=(5, 6, 3))
    cp = np.maximum(motion_similarity(A, S), 0)
    t = trust(S)
    np.testing.assert_allclose(blended_similarity(A, S), (1 - t)[:, None] * cp + t[:, None] * contrast(cp))
    np.testing.assert_allclose(blended_similarity(A, S, trust_values=np.zeros(5)), cp)
    np.testing.assert_allclose(blended_similarity(A, S, trust_values=np.ones(5)), contrast(cp))


def test_key_expressions_three_tap_filter_and_peaks():
    T = 40
    sim = np.zeros((2, T))
    sim[0, 10] = 1.0
    sim[1, 25] = 0.8
    sim[1, 26] = 0.8   # a flat-topped peak
    frames, cum = key_expressions(sim)
    w = np.exp(-0.5)
    np.testing.assert_allclose(cum[9:12], np.array([w, 1, w]) / (1 + 2 * w))
    assert cum[8] == 0 and cum[12] == 0  # the kernel is three frames wide
    assert frames.tolist() == [10, 25]   # find_peaks takes the left of a plateau's middle pair
    frames, _ = key_expressions(sim, valid=np.arange(T) != 10)
    assert frames.tolist() == [25]
    with pytest.raises(ValueError, match="valid"):
        key_expressions(sim, valid=np.ones(3, bool))


def test_masks_amplitude_and_cross_expression_graph():
    rng = np.random.default_rng(2)
    S = rng.normal(size=(5, 7, 3))
    S[3] = 0
    u = support_masks(S)
    np.testing.assert_allclose(u.max(axis=1), [1, 1, 1, 0, 1])
    np.testing.assert_allclose(u[0], np.linalg.norm(S[0], axis=1) / np.linalg.norm(S[0], axis=1).max())
    G = cross_expression_laplacian(S)
    np.testing.assert_allclose(G @ np.ones(5), 0, atol=1e-14)
    C = motion_similarity(S, S)
    for k in (0, 1, 2, 4):
        off = [l for l in range(5) if l != k]
        np.testing.assert_allclose(np.abs(G[k, off]).sum(), 1)
        np.testing.assert_allclose(G[k, off], C[k, off] / np.abs(C[k, off]).sum())
    np.testing.assert_array_equal(G[3], 0)
    # Λ(x)_k = Σ c_kl (x_l − x_k) / Σ|c_kl| on vectors
    X = rng.normal(size=(5, 4))
    k = 1
    off = [l for l in range(5) if l != k]
    want = sum(C[k, l] * (X[l] - X[k]) for l in off) / np.abs(C[k, off]).sum()
    np.testing.assert_allclose((G @ X)[k], want)
    A = np.stack([0.5 * S[0], 2.0 * S[0], -S[0]])
    np.testing.assert_allclose(amplitude(A, S[:1]), [[0.25, 1.0, 0.0]])


# -- §4.4 marker mesh on real markers --------------------------------------------------------

def test_contact_edges_animface_names():
    names, _ = animface_neutral()
    pairs = {(names[a], names[b]) for a, b in contact_edges(names)}
    assert pairs == {("Leye_Up", "Leye_Down"), ("Reye_Up", "Reye_Down"), ("Mouth_Up", "Mouth_Down"),
                     ("Mouth_UpL1", "Mouth_DownL"), ("Mouth_UpR1", "Mouth_DownR")}
    assert contact_edges(["Lcheek_Up", "Lcheek_Down", "Leyebrow_Up", "Leyebrow_Down"]).shape == (0, 2)


def test_marker_triangulation_real_animface():
    names, X = animface_neutral()
    F = marker_triangulation(X)
    M = len(X)
    assert set(F.ravel()) == set(range(M))                 # every marker in the mesh
    E = geometry.edges(F)
    assert M - len(E) + len(F) == 1                        # a disk: Euler characteristic 1
    assert len(geometry.boundary_loops(F)) == 1
    assert (geometry.face_normals(X, F)[:, 2] > 0).all()   # facing the camera (+Z)
    # no slivers left on the rim
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", b - a, c - a)
                                       / np.linalg.norm(b - a, axis=1) / np.linalg.norm(c - a, axis=1), -1, 1)))
    assert ang.min() > 5
    L = marker_laplacian(X, F, contact_edges(names))
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0, atol=1e-12 * abs(L).max())
    up, down = names.index("Mouth_Up"), names.index("Mouth_Down")
    assert L[up, down] < 0  # the contact edge couples the lips
    with pytest.raises(ValueError, match="points"):
        marker_triangulation(X[:2])


# -- the solver ------------------------------------------------------------------------------

def _random_problem(rng, K=4, M=9, T=30, mask="target"):
    P0 = np.column_stack([rng.uniform(-0.05, 0.05, M), rng.uniform(-0.05, 0.05, M), rng.uniform(0, 0.01, M)])
    S = rng.normal(scale=0.005, size=(K, M, 3))
    A = rng.normal(scale=0.005, size=(T, M, 3))
    return personalize(A, S, P0, mask=mask, rig_deltas=S * 1.3 + rng.normal(scale=1e-3, size=S.shape))


@pytest.mark.parametrize("mask", ["target", "residual"])
def test_solver_matches_dense_lstsq_random(mask):
    res = _random_problem(np.random.default_rng(4), mask=mask)
    pr = res.problem
    ref = dense_reference(pr)
    scale = np.abs(ref).max()
    for method in ("auto", "kron", "pcg", "splu", "dense") if mask == "target" else ("auto", "pcg", "splu", "dense"):
        np.testing.assert_allclose(pr.solve(method), ref, atol=1e-8 * scale, err_msg=method)
    np.testing.assert_allclose(res.deltas, ref, atol=1e-8 * scale)
    if mask == "residual":
        with pytest.raises(ValueError, match="kron"):
            pr.solve("kron")


@pytest.mark.parametrize("mask", ["target", "residual"])
def test_solver_matches_dense_lstsq_real_ict(ict_setup, mask):
    idx, S, N0, W = ict_setup
    m = np.arange(0, 60, 2)            # 30 markers
    k = np.arange(0, 53, 5)            # 11 shapes
    Sk, Wk = S[k][:, m], W[::8][:, k]
    A = (Wk @ Sk.reshape(len(k), -1)).reshape(len(Wk), len(m), 3)
    A = A + np.random.default_rng(5).normal(scale=2e-4, size=A.shape)
    g = 1.2 * Sk
    res = personalize(A, g, N0[m], rig_deltas=Sk, mask=mask, peak_power=2.0)
    ref = dense_reference(res.problem)
    np.testing.assert_allclose(res.deltas, ref, atol=1e-7 * np.abs(ref).max())
    # a minimum of the energy: no coordinate perturbation lowers it
    e0 = res.problem.energies(res.deltas)["total"]
    rng = np.random.default_rng(6)
    for _ in range(5):
        d = rng.normal(scale=1e-4, size=res.deltas.shape)
        assert res.problem.energies(res.deltas + d)["total"] > e0
    assert res.energies["aligned"]["total"] <= res.energies["initial"]["total"]


def test_personalize_real_rom_similarity_follows_the_driving_curves(ict_setup):
    """Fig. 7 on real data: a shape's similarity over the ROM rises and falls with its own curve."""
    idx, S, N0, W = ict_setup
    A = (W @ S.reshape(len(S), -1)).reshape(len(W), -1, 3)
    A = A + np.random.default_rng(0).normal(scale=2e-4, size=A.shape)  # ~0.2 mm capture noise
    res = personalize(A, S, N0)
    big = np.linalg.norm(S, axis=(1, 2)) > 5e-3
    corr = np.array([np.corrcoef(res.blended_similarity[k], W[:, k])[0, 1] for k in np.flatnonzero(big)])
    assert np.median(corr) > 0.5
    assert (corr > 0.25).mean() >= 0.75
    assert 20 < len(res.key_frames) < len(W) / 4
    assert res.deltas.shape == S.shape and np.isfinite(res.deltas).all()


def test_paper_defaults_shrink_shapes_on_a_mixed_rom(ict_setup):
    """Characterises the limitation of §6.3 on a real, mixed ARKit ROM: the amplitude-blind
    correlation averages ramps and co-activated shapes into E_Match, so the paper's settings
    under-estimate the actor's blendshapes (docs/geometric.md has the numbers)."""
    idx, S, N0, W = ict_setup
    A = (W @ S.reshape(len(S), -1)).reshape(len(W), -1, 3)
    res = personalize(A, S, N0)
    big = np.linalg.norm(S, axis=(1, 2)) > 5e-3
    gain = np.einsum("kmc,kmc->k", res.deltas, S) / np.einsum("kmc,kmc->k", S, S)
    assert np.median(gain[big]) < 0.9


def test_personalization_recovers_actor_shapes_from_a_held_rom(ict_setup):
    """Actor = ICT with every shape rescaled (0.6-1.6); ROM = each expression ramped up, held,
    released, with 0.2 mm noise; initial guess = ICT's own shapes. Aligned shapes are much
    closer to the actor's than the initial guess (extension settings; see docs)."""
    idx, S, N0, _ = ict_setup
    K = len(S)
    rng = np.random.default_rng(0)
    gain = rng.uniform(0.6, 1.6, K)
    P_true = S * gain[:, None, None]
    seg = np.concatenate([np.linspace(0, 1, 10), np.ones(10), np.linspace(1, 0, 10), np.zeros(5)])
    W = np.zeros((K * len(seg), K))
    for k in range(K):
        W[k * len(seg):(k + 1) * len(seg), k] = seg
    A = (W @ P_true.reshape(K, -1)).reshape(len(W), -1, 3) + rng.normal(scale=2e-4, size=(len(W), len(idx), 3))
    res = personalize(A, S, N0, mask="residual", exclusive=True, peak_power=4, beta=1e-6, gamma=1e-6)
    e0 = np.linalg.norm(S - P_true, axis=(1, 2))
    e1 = np.linalg.norm(res.deltas - P_true, axis=(1, 2))
    assert np.linalg.norm(e1) < 0.5 * np.linalg.norm(e0)
    big = np.linalg.norm(S, axis=(1, 2)) > 5e-3
    assert (e1 < e0)[big].mean() >= 0.6
    # raising β blends back towards the initial guess's local shape (§6.3, Fig. 16): E_Mesh of
    # the minimiser can only fall as its weight grows
    mesh = [personalize(A, S, N0, mask="residual", exclusive=True, peak_power=4, beta=b, gamma=1e-6)
            .energies["aligned"]["mesh"] for b in (1e-6, 1e-3, 1.0)]
    assert mesh[0] > mesh[1] > mesh[2]


def test_missing_frames_and_validation(ict_setup):
    idx, S, N0, W = ict_setup
    A = (W[:400] @ S.reshape(len(S), -1)).reshape(400, -1, 3)
    A[50:60, 3] = np.nan
    res = personalize(A, S, N0)
    assert res.extras["n_invalid_frames"] == 10
    assert not np.isin(res.key_frames, np.arange(50, 60)).any()
    assert (res.blended_similarity[:, 50:60] == 0).all()
    assert np.isnan(A[50, 3]).all()  # input untouched
    with pytest.raises(ValueError, match="initial_guess"):
        personalize(A, S[:, :5], N0)
    with pytest.raises(ValueError, match="neutral"):
        personalize(A, S, N0[:5])
    with pytest.raises(ValueError, match="key_frames"):
        personalize(A, S, N0, key_frames=[55])
    with pytest.raises(ValueError, match="names"):
        personalize(A, S, N0, names=["a"])
    with pytest.raises(ValueError, match="no frame"):
        personalize(np.full((3, len(N0), 3), np.nan), S, N0)
    with pytest.raises(ValueError, match="mask"):
        personalize(A, S, N0, mask="both")
