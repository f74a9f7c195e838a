"""Xu 2014 eq. 9-11: feature-preserving deformation transfer against slow references."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from core.transfer import (DeformationTransfer, deformation_gradients, deformation_transfer, line_edges,
                           line_gradients)
from core.geometry import weld_vertices


def _sphere(subdiv=2):
    m = trimesh.creation.icosphere(subdiv)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _centered(x):
    return x - x.mean(0)


def test_gradients_map_reference_edges_to_deformed_edges():
    V, F = _sphere(1)
    rng = np.random.default_rng(0)
    X = V + 0.1 * rng.standard_normal(V.shape)
    D = deformation_gradients(V, X, F)
    for f in range(0, len(F), 7):
        a, b, c = F[f]
        assert np.allclose(D[f] @ (V[b] - V[a]), X[b] - X[a])
        assert np.allclose(D[f] @ (V[c] - V[a]), X[c] - X[a])


def test_line_gradients_map_edges_including_parallel_case():
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.0]])
    E = np.array([[0, 1], [1, 2]])
    X = np.array([[0, 0, 0], [2, 0, 0], [2, 0.5, 0.5]])  # first edge only scales (parallel)
    D = line_gradients(V, X, E)
    for (a, b), Dl in zip(E, D):
        assert np.allclose(Dl @ (V[b] - V[a]), X[b] - X[a])
    assert np.all(np.isfinite(D))


def test_identity_reproduces_a_different_target(tiger, rocketbox):
    V, F = tiger.neutral, tiger.faces
    rng = np.random.default_rng(1)
    T0 = V * [1.2, 0.9, 1.1] + 0.002 * rng.standard_normal(V.shape)
    edges = line_edges([np.arange(0, 40)])
    x = deformation_transfer(V, T0, F, V, edges, alpha=100)
    assert np.abs(x - T0).max() < 1e-9 * tiger.size


def test_similarity_is_reproduced_on_a_different_target():
    V, F = _sphere(2)
    rng = np.random.default_rng(2)
    T0 = V * [1.0, 1.4, 0.7] + 0.03 * rng.standard_normal(V.shape)
    R = Rotation.random(random_state=3).as_matrix()
    X = 1.7 * V @ R.T + [0.3, -1, 2]
    x = deformation_transfer(V, T0, F, X)  # no feature lines: eq. 10 only
    size = np.linalg.norm(np.ptp(T0, 0))
    assert np.abs(_centered(x) - _centered(1.7 * T0 @ R.T)).max() < 1e-7 * size


def test_affine_on_the_same_mesh_with_feature_lines():
    V, F = _sphere(2)
    A = np.array([[1.2, 0.3, 0], [0, 0.8, 0.1], [0.2, 0, 1.1]])
    edges = line_edges([np.arange(0, 30), np.arange(50, 60)])
    x = deformation_transfer(V, V, F, V @ A.T + 5, edges, alpha=100)
    assert np.abs(_centered(x) - _centered(V @ A.T)).max() < 1e-9


def _dense_reference(S0, T0, F, X, edges, alpha):
    """Eq. 9 built row by row with an independent gradient formula and solved by lstsq.

    On each target triangle the gradient of the positions is J = [x1-x0, x2-x0] pinv([u1, u2]),
    u the target reference edges; the wanted gradient is D [u1, u2] pinv([u1, u2]).
    """
    n = len(S0)
    rows, rhs = [], []
    area = 0.5 * np.linalg.norm(np.cross(T0[F[:, 1]] - T0[F[:, 0]], T0[F[:, 2]] - T0[F[:, 0]]), axis=1)
    a = area / area.mean()
    D = deformation_gradients(S0, X, F)
    for f, (i, j, k) in enumerate(F):
        U = np.stack([T0[j] - T0[i], T0[k] - T0[i]], axis=1)  # (3, 2)
        Pinv = np.linalg.pinv(U)  # (2, 3)
        want = D[f] @ U @ Pinv  # (3, 3)
        # J[c, d] = sum_e (x_e - x_i)[c] Pinv[e, d]
        for d in range(3):
            row = np.zeros(n)
            row[j] += Pinv[0, d]
            row[k] += Pinv[1, d]
            row[i] -= Pinv[0, d] + Pinv[1, d]
            rows.append(np.sqrt(a[f]) * row)
            rhs.append(np.sqrt(a[f]) * want[:, d])
    Dl = line_gradients(S0, X, edges)
    for (p, q), M in zip(edges, Dl):
        e = T0[q] - T0[p]
        w = np.sqrt(alpha / (e @ e))
        row = np.zeros(n)
        row[q], row[p] = w, -w
        rows.append(row)
        rhs.append(w * (M @ e))
    A = np.array(rows)
    b = np.array(rhs)
    return np.linalg.lstsq(A, b, rcond=None)[0]


def test_matches_dense_least_squares_reference():
    V, F = _sphere(1)
    rng = np.random.default_rng(4)
    T0 = V * [1.0, 1.3, 0.8] + 0.05 * rng.standard_normal(V.shape)
    X = V + 0.15 * rng.standard_normal(V.shape)
    edges = line_edges([np.arange(0, 12)])
    ours = DeformationTransfer(V, T0, F, edges, alpha=100).transfer(X)
    ref = _dense_reference(V, T0, F, X, edges, 100)
    assert np.abs(_centered(ours) - _centered(ref)).max() < 1e-8


def test_either_factorisation_gives_the_same_transfer(ict):
    """The eq. 9 system factorised by cholespy's CHOLMOD (default; the naive reference's) or by
    our SparseCholesky (transfer_sequence's: without the GIL): the same meshes to rounding, on
    the ICT head with a feature line."""
    from core.transfer._cholesky import SparseCholesky

    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    S0 = ict.neutral[rep]
    T0 = S0 * [1.15, 0.9, 1.0]
    X = np.stack([(ict.neutral + ict.deltas[ict.index(n)])[rep] for n in ("jawOpen", "mouthSmile_L")])
    edges = line_edges([np.arange(40)])
    ref = DeformationTransfer(S0, T0, Fw, edges, 100).transfer(X)
    ours = DeformationTransfer(S0, T0, Fw, edges, 100, factor=SparseCholesky).transfer(X)
    motion = np.abs(ref - T0).max()
    assert np.abs(ours - ref).max() < 1e-9 * motion


def test_feature_lines_pull_the_line_towards_the_source_motion(ict):
    """Fig. 3: with α = 100 the transferred mouth line follows the source line motion closer."""
    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    S0 = ict.neutral[rep]
    T0 = S0 * [1.15, 0.9, 1.0]
    X = (ict.neutral + ict.deltas[ict.index("jawOpen")] + ict.deltas[ict.index("mouthSmile_L")])[rep]
    from core.geometry import boundary_loops

    mouth = [l for l in boundary_loops(ict.faces) if len(l) == 74][0]
    edges = line_edges([wi[mouth]])
    with_lines = DeformationTransfer(S0, T0, Fw, edges, 100).transfer(X)
    without = DeformationTransfer(S0, T0, Fw, None).transfer(X)
    Dl = line_gradients(S0, X, edges)
    want = np.einsum("eij,ej->ei", Dl, T0[edges[:, 1]] - T0[edges[:, 0]])
    err = lambda x: np.linalg.norm((x[edges[:, 1]] - x[edges[:, 0]]) - want, axis=1).mean()
    assert err(with_lines) < 0.5 * err(without)


def test_validation():
    V, F = _sphere(1)
    with pytest.raises(ValueError, match="target_ref"):
        DeformationTransfer(V, V[:-1], F)
    with pytest.raises(ValueError, match="alpha"):
        DeformationTransfer(V, V, F, alpha=-1)
    with pytest.raises(ValueError, match="deformed"):
        DeformationTransfer(V, V, F).transfer(V[:-1])
