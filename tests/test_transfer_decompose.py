"""Xu 2014 §3 decomposition: Taubin smoothing, Laplacian coating, Poisson reconstruction,
sequence factorisation -- each against a slow, obviously-correct reference."""


import numpy as np
import pytest
import trimesh

from core.transfer import (PoissonReconstructor, TaubinFilter, factor_sequence, laplacian_coating,
                           laplacian_operator, taubin_smooth)
from core.geometry import vertex_frames, weld_vertices


def _noisy_sphere(subdiv=2, seed=0):
    m = trimesh.creation.icosphere(subdiv)
    rng = np.random.default_rng(seed)
    V = m.vertices * [1.0, 1.2, 0.8] + 0.03 * rng.standard_normal(m.vertices.shape)
    return V, np.asarray(m.faces)


def _dense_taubin(V, F, iterations, lam, mu):
    """Per-iteration dense reference: neighbour sets by a loop over faces."""
    n = len(V)
    nbrs = [set() for _ in range(n)]
    for a, b, c in F:
        for i, j in ((a, b), (b, c), (c, a)):
            nbrs[i].add(j)
            nbrs[j].add(i)
    U = np.zeros((n, n))
    for i in range(n):
        for j in nbrs[i]:
            U[i, j] = 1.0 / len(nbrs[i])
        U[i, i] = -1.0
    x = V.copy()
    for _ in range(iterations):
        x = x + lam * (U @ x)
        x = x + mu * (U @ x)
    return x


def test_taubin_matches_dense_reference_random():
    V, F = _noisy_sphere()
    ours = taubin_smooth(V, F, iterations=7, lam=0.5, mu=-0.53)
    ref = _dense_taubin(V, F, 7, 0.5, -0.53)
    size = np.linalg.norm(np.ptp(V, 0))
    assert np.abs(ours - ref).max() < 1e-12 * size
    assert np.abs(ours - V).max() > 1e-3 * size  # it did smooth


def test_taubin_matches_dense_reference_real(tiger):
    V, F = tiger.neutral, tiger.faces
    ours = taubin_smooth(V, F, iterations=40)
    ref = _dense_taubin(V, F, 40, 0.5, -0.53)
    assert np.abs(ours - ref).max() < 1e-10 * tiger.size


def test_taubin_renumbering_is_bit_identical(tiger):
    """The filter runs on vertices renumbered for locality (reverse Cuthill-McKee) with each row's
    sum in its original order: the very same floats as the products in the mesh's numbering."""
    import scipy.sparse as sp

    from core.geometry import vertex_adjacency

    V, F = tiger.neutral, tiger.faces
    filt = TaubinFilter(F, len(V), 40)
    assert not np.array_equal(filt._order, np.arange(len(V)))  # it did renumber
    A = vertex_adjacency(F, len(V))
    inv = 1.0 / np.asarray(A.sum(axis=1)).ravel()
    U = (sp.diags(inv) @ A - sp.identity(len(V))).tocsr()
    I = sp.identity(len(V), format="csr")
    a, b = (I + 0.5 * U).tocsr(), (I - 0.53 * U).tocsr()
    x = np.concatenate([V, np.random.default_rng(2).standard_normal((len(V), 40))], axis=1)
    y = x.copy()
    for _ in range(40):
        y = b @ (a @ y)
    np.testing.assert_array_equal(filt.apply(x), y)


def test_taubin_sequence_equals_per_frame_and_keeps_input(tiger):
    rng = np.random.default_rng(1)
    seq = tiger.evaluate(rng.random((3, tiger.n_shapes)))
    before = seq.copy()
    filt = TaubinFilter(tiger.faces, tiger.n_vertices, 10)
    batch = filt.apply(seq)
    for t in range(3):
        assert np.allclose(batch[t], filt.apply(seq[t]), atol=1e-12 * tiger.size)
    assert np.array_equal(seq, before)


def test_taubin_does_not_shrink_like_laplacian_smoothing():
    V, F = _noisy_sphere(3)
    r0 = np.linalg.norm(V - V.mean(0), axis=1).mean()
    taubin = taubin_smooth(V, F, 40)
    plain = TaubinFilter(F, len(V), 40, lam=0.5, mu=-0.5)  # |mu| = lam: still allowed
    r_t = np.linalg.norm(taubin - taubin.mean(0), axis=1).mean()
    # plain Laplacian smoothing: 80 steps of lam = 0.5 for comparison
    x = V.copy()
    for _ in range(80):
        x = x + 0.5 * (np.asarray(_umbrella(F, len(V)) @ x))
    r_l = np.linalg.norm(x - x.mean(0), axis=1).mean()
    assert abs(r_t / r0 - 1) < 0.05 and r_l / r0 < 0.9
    assert plain.apply(V).shape == V.shape


def _umbrella(F, n):
    import scipy.sparse as sp
    from core.geometry import vertex_adjacency

    A = vertex_adjacency(F, n)
    d = np.asarray(A.sum(1)).ravel()
    return sp.diags(1 / d) @ A - sp.identity(n)


def test_taubin_validation():
    V, F = _noisy_sphere(1)
    with pytest.raises(ValueError, match="lam, mu"):
        TaubinFilter(F, len(V), 5, lam=0.5, mu=0.3)
    with pytest.raises(ValueError, match="iterations"):
        TaubinFilter(F, len(V), -1)
    with pytest.raises(ValueError, match="positions"):
        taubin_smooth(V[:, :2], F)


@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_poisson_reconstruction_recovers_unsmoothed_mesh(kind, tiger):
    # eq. 2: S = L^{-1}(L S̄ + ξ) on a real mesh and a random one
    for V, F in ((tiger.neutral, tiger.faces), _noisy_sphere(2, 3)):
        wi, rep, Fw = weld_vertices(V, F)
        S = V[rep]
        Sb = taubin_smooth(S, Fw, 40)
        P = PoissonReconstructor(Fw, len(S), kind, S)
        xi = laplacian_coating(S, Sb, P.L)
        rec = P.reconstruct(Sb, xi, P.component_mean(S - Sb))
        size = np.linalg.norm(np.ptp(S, 0))
        assert np.abs(rec - S).max() < 1e-8 * size
        # without the mean the result differs by one translation per component only
        rec0 = P.reconstruct(Sb, xi)
        off = rec0 - S
        per_component = P.component_mean(off)[P.labels]
        assert np.abs(off - per_component).max() < 1e-8 * size


def test_poisson_two_components_and_batch():
    a = trimesh.creation.icosphere(2)
    b = trimesh.creation.icosphere(1)
    V = np.concatenate([a.vertices, b.vertices * 0.5 + 3])
    F = np.concatenate([a.faces, b.faces + len(a.vertices)])
    rng = np.random.default_rng(4)
    seq = V + 0.02 * rng.standard_normal((3,) + V.shape)
    P = PoissonReconstructor(F, len(V))
    smooth = taubin_smooth(seq, F, 20)
    xi = laplacian_coating(seq, smooth, P.L)
    for t in range(3):
        rec = P.reconstruct(smooth[t], xi[t], P.component_mean(seq[t] - smooth[t]))
        assert np.abs(rec - seq[t]).max() < 1e-9
    # batched (T, V, 3) with one mean for all frames equals per-frame
    m = P.component_mean(seq[0] - smooth[0])
    batch = P.reconstruct(smooth, xi, m)
    assert np.allclose(batch[0], seq[0], atol=1e-9)
    assert np.allclose(batch[1], P.reconstruct(smooth[1], xi[1], m), atol=1e-12)


def test_poisson_matches_dense_pseudoinverse():
    V, F = _noisy_sphere(1, 5)
    P = PoissonReconstructor(F, len(V))
    L = P.L.toarray()
    rng = np.random.default_rng(0)
    xi = L @ rng.standard_normal((len(V), 3))
    ours = P.displacement(xi)
    ref = np.linalg.pinv(L) @ xi  # minimum-norm = zero-mean solution on a connected mesh
    assert np.abs(ours - ref).max() < 1e-9 * np.abs(ref).max()


def test_laplacian_operator_validation():
    V, F = _noisy_sphere(1)
    with pytest.raises(ValueError, match="kind"):
        laplacian_operator(F, len(V), "mean")
    with pytest.raises(ValueError, match="positions"):
        laplacian_operator(F, len(V), "cotangent")


def test_factor_sequence_rig_driven_is_exact_and_reports_residual(ict):
    rng = np.random.default_rng(2)
    W = rng.random((60, ict.n_shapes)) * (rng.random(ict.n_shapes) ** 3)
    seq = ict.evaluate(W)
    fac = factor_sequence(seq, rtol=1e-7, base=ict.neutral)
    assert fac.rank <= ict.n_shapes
    err = np.sqrt(((fac.frames() - seq) ** 2).sum(-1).mean())
    assert err <= 1e-7 * ict.size * 1.01
    # the reported residual is the measured one (to rounding of the ||X||² - ||C||² form)
    assert abs(err - fac.residual_rms) <= 1e-8 * ict.size


def test_factor_sequence_full_rank_random():
    rng = np.random.default_rng(3)
    seq = rng.standard_normal((8, 50, 3))
    fac = factor_sequence(seq, rtol=1e-9)
    assert fac.rank == 7  # 8 frames minus the base
    assert np.abs(fac.frames() - seq).max() < 1e-8
    with pytest.raises(ValueError, match="sequence"):
        factor_sequence(seq[0])


def test_smoothing_the_factored_basis_equals_smoothing_frames(tiger):
    rng = np.random.default_rng(5)
    seq = tiger.evaluate(rng.random((20, tiger.n_shapes)))
    fac = factor_sequence(seq, 1e-9, base=tiger.neutral)
    filt = TaubinFilter(tiger.faces, tiger.n_vertices, 40)
    smooth = fac.map_basis(filt.apply)
    assert np.abs(smooth.frames() - filt.apply(seq)).max() < 1e-8 * tiger.size


def test_local_frames_orthonormal_right_handed(tiger):
    F = np.stack(vertex_frames(tiger.neutral, tiger.faces), axis=-1)  # columns [t, b, n]
    I = np.einsum("vji,vjk->vik", F, F)
    assert np.abs(I - np.eye(3)).max() < 1e-9
    assert np.allclose(np.linalg.det(F), 1.0)
    t, b, n = vertex_frames(tiger.neutral.astype(np.float32), tiger.faces)
    dev = np.abs(np.stack([t, b, n], -1) - F).max(axis=(1, 2))
    # float32 frames: rotations to ~1e-6, worse only where the tangent edge is near the normal
    assert t.dtype == np.float32 and np.percentile(dev, 99) < 1e-5 and dev.max() < 1e-3


def test_screened_poisson_returns_prior_and_matches_dense_solve(tiger):
    wi, rep, Fw = weld_vertices(tiger.neutral, tiger.faces)
    S = tiger.neutral[rep]
    Sb = taubin_smooth(S, Fw, 40)
    P = PoissonReconstructor(Fw, len(S), screening=0.01)
    y0 = S - Sb
    assert np.abs(P.displacement(P.L @ y0, prior=y0) - y0).max() < 1e-10 * tiger.size
    rng = np.random.default_rng(0)
    c = rng.standard_normal((len(S), 3)) * 1e-3
    dense = np.linalg.solve(P.L.toarray() + P.eps * np.eye(len(S)), c + P.eps * y0)
    assert np.abs(P.displacement(c, prior=y0) - dense).max() < 1e-9 * np.abs(dense).max()
    with pytest.raises(ValueError, match="screening"):
        PoissonReconstructor(Fw, len(S), screening=-1)


@pytest.mark.parametrize("screening", [0.0, 0.05])
def test_poisson_block_solve_matches_dense(screening, tiger):
    """(V, m) right-hand sides at once (any m, in blocks of columns) = dense solves column by column."""
    wi, rep, Fw = weld_vertices(tiger.neutral, tiger.faces)
    V = len(rep)
    P = PoissonReconstructor(Fw, V, screening=screening)
    rng = np.random.default_rng(1)
    L = P.L.toarray()
    B = L @ rng.standard_normal((V, 37))  # orthogonal to the constants, as L^+ needs
    ours = P.solve(B)
    if screening:
        ref = np.linalg.solve(L + P.eps * np.eye(V), B)
        assert P._pinned is None  # the plain factorisation is never built when screened
    else:
        # zero mean on every component: with E the (V, C) component indicators, L x = B and
        # E^T x = 0 is (L + E E^T) x = B (B ⊥ range E), a non-singular dense system
        E = (P.labels[:, None] == np.arange(P.labels.max() + 1)).astype(float)
        assert E.shape[1] > 1  # the tiger has several components (eyes, teeth): gauge per component
        ref = np.linalg.solve(L + E @ E.T, B)
    assert ours.shape == (V, 37)
    assert np.abs(ours - ref).max() < 1e-9 * np.abs(ref).max()
    assert np.allclose(P.solve(np.asfortranarray(B[:, :5])), ours[:, :5], atol=1e-12 * np.abs(ref).max())
    with pytest.raises(ValueError, match="B"):
        P.solve(B[:-1])
    # any block size gives the same columns (the blocks only group the triangular solves)
    assert np.abs(P.solve(B, block=5) - ours).max() < 1e-12 * np.abs(ref).max()
    # the float32 solve of the detail stage: screened in single precision (to ~1e-6 here,
    # condition ~200), the plain Laplacian always in float64
    single = P.solve(B, dtype=np.float32)
    if screening:
        assert single.dtype == np.float32
        assert 1e-12 < np.abs(single - ref).max() / np.abs(ref).max() < 1e-5
    else:
        assert single.dtype == np.float64 and np.array_equal(single, ours)


def test_factor_sequence_truncates_like_the_svd():
    """Eckart–Young: one pass of the float64 Gram picks the best rank-k subspace, so rank and
    residual equal those of the truncated SVD with the same tolerance (np.linalg.svd reference)."""
    rng = np.random.default_rng(9)
    T, V = 40, 300
    U = np.linalg.qr(rng.standard_normal((T, 12)))[0]
    W = np.linalg.qr(rng.standard_normal((3 * V, 12)))[0]
    X = (U * np.geomspace(1.0, 1e-7, 12)) @ W.T  # singular values over 7 decades
    base = rng.standard_normal((V, 3))
    seq = base + X.reshape(T, V, 3)
    size = np.linalg.norm(np.ptp(base, 0))
    s = np.linalg.svd(X, compute_uv=False)
    for rtol in (1e-4, 1e-6, 1e-8):
        tol2 = (rtol * size) ** 2 * T * V
        tail = np.concatenate([np.cumsum((s ** 2)[::-1])[::-1], [0.0]])
        k = int(np.argmax(tail <= tol2))
        fac = factor_sequence(seq, rtol, base=base)
        assert fac.rank == k, (rtol, fac.rank, k)
        assert abs(fac.residual_rms - np.sqrt(tail[k] / (T * V))) < 1e-6 * np.sqrt(tail[k] / (T * V)) + 1e-15
        Q = fac.basis.reshape(k, -1)
        assert np.abs(Q @ Q.T - np.eye(k)).max() < 1e-12
    capped = factor_sequence(seq, 1e-12, max_rank=5, base=base)
    assert capped.rank == 5 and capped.residual_rms > 0
    with pytest.raises(ValueError, match="NaN"):
        factor_sequence(np.where(np.arange(T)[:, None, None] == 3, np.nan, seq), 1e-6)


def test_cholesky_factor_matches_dense_solves_in_any_block():
    """CholeskyFactor (CHOLMOD through cholespy) against np.linalg.solve: a random sparse SPD
    matrix, one vector and 37 columns solved in blocks that do not divide them."""
    import scipy.sparse as sp

    from core.transfer._mesh import CholeskyFactor

    rng = np.random.default_rng(3)
    n = 200
    R = sp.random(n, n, density=0.02, random_state=4)
    A = (R @ R.T + sp.identity(n)).tocsr()  # SPD, cond ~ 1 + |R|^2
    ch = CholeskyFactor(A)
    B = rng.standard_normal((n, 37))
    ref = np.linalg.solve(A.toarray(), B)
    for block in (None, 5, 37, 64):
        assert np.abs(ch.solve(B, block) - ref).max() < 1e-10 * np.abs(ref).max()
    assert np.abs(ch.solve(B[:, 3]) - ref[:, 3]).max() < 1e-10 * np.abs(ref).max()
    assert np.abs(ch.solve(np.asfortranarray(B)) - ref).max() < 1e-10 * np.abs(ref).max()
    with pytest.raises(ValueError, match="b"):
        ch.solve(B[:-1])
    with pytest.raises(ValueError, match="square"):
        CholeskyFactor(sp.csr_matrix((3, 4)))
    with pytest.raises(ValueError, match="positive definite"):  # singular: SuperLU raised here too
        CholeskyFactor(sp.csr_matrix(np.array([[1.0, 1, 0], [1, 1, 0], [0, 0, 1]])))


def test_sparse_cholesky_matches_dense_solves_in_both_precisions():
    """SparseCholesky (ours: METIS ordering, up-looking factorisation, GIL-free block solves)
    against np.linalg.solve and np.linalg.cholesky: a random sparse SPD matrix with a
    disconnected part, one vector and 37 columns in blocks that do not divide them, in place."""
    import scipy.sparse as sp

    from core.transfer._cholesky import SparseCholesky

    rng = np.random.default_rng(5)
    n = 240
    R = sp.random(n, n, density=0.015, random_state=6)
    A = (R @ R.T + sp.identity(n)).tocsr()
    A = sp.block_diag([A, sp.diags(rng.uniform(1, 2, 7))]).tocsr()  # isolated vertices too
    n = A.shape[0]
    B = rng.standard_normal((n, 37))
    ref = np.linalg.solve(A.toarray(), B)
    ch = SparseCholesky(A)
    # the factor is the dense Cholesky factor of the ordered matrix, entry for entry
    L = sp.csc_matrix((ch.Lx, ch.Li, ch.Lp), shape=(n, n)).toarray()
    np.testing.assert_allclose(L, np.linalg.cholesky(A.toarray()[np.ix_(ch.perm, ch.perm)]), atol=1e-12)
    assert sorted(ch.perm) == list(range(n))
    for block in (None, 1, 5, 37, 64):
        assert np.abs(ch.solve(B, block) - ref).max() < 1e-10 * np.abs(ref).max()
    assert np.abs(ch.solve(B[:, 3]) - ref[:, 3]).max() < 1e-10 * np.abs(ref).max()
    inplace = B.copy()
    assert ch.solve(inplace, 8, out=inplace) is inplace
    assert np.abs(inplace - ref).max() < 1e-10 * np.abs(ref).max()
    # single precision (the float32 detail stage): to float32 rounding times the condition
    # number, and clearly not the float64 answer bit for bit
    x32 = SparseCholesky(A, np.float32).solve(B.astype(np.float32), 16)
    assert x32.dtype == np.float32
    rel = np.abs(x32 - ref).max() / np.abs(ref).max()
    assert 1e-12 < rel < 1e-5 * np.linalg.cond(A.toarray())
    with pytest.raises(ValueError, match="dtype"):
        SparseCholesky(A, np.float16)
    with pytest.raises(ValueError, match="square"):
        SparseCholesky(sp.csr_matrix((3, 4)))
    with pytest.raises(ValueError, match="positive definite"):
        SparseCholesky(sp.csr_matrix(np.array([[1.0, 1, 0], [1, 1, 0], [0, 0, 1]])))
    with pytest.raises(ValueError, match="b"):
        ch.solve(B[:-1])
    with pytest.raises(ValueError, match="out"):
        ch.solve(B, out=np.empty((n, 37), np.float32))


def test_screened_poisson_solve_is_the_sparse_solve(tiger):
    """The detail stage's screened Poisson solve (SparseCholesky) against scipy's sparse LU of
    the same operator, on a real mesh, in float64 and float32."""
    from scipy.sparse.linalg import splu

    V = len(tiger.neutral)
    P = PoissonReconstructor(tiger.faces, V, screening=0.01)
    rng = np.random.default_rng(7)
    B = rng.standard_normal((V, 6))
    ref = splu(P._A.tocsc()).solve(B)
    assert np.abs(P.solve(B) - ref).max() < 1e-10 * np.abs(ref).max()
    x32 = P.solve(B.astype(np.float32), dtype=np.float32)
    assert x32.dtype == np.float32 and np.abs(x32 - ref).max() < 1e-4 * np.abs(ref).max()


def test_taubin_on_two_cores_is_bit_identical_to_one(tiger, monkeypatch):
    """The column blocks of the filter run on the cores the process may use (the compiled CSR
    product releases the GIL); the blocks are independent, so the floats are the same."""
    from core.transfer import decompose

    filt = TaubinFilter(tiger.faces, tiger.n_vertices, 40)
    x = np.random.default_rng(3).standard_normal((tiger.n_vertices, 3 * 26))  # several blocks
    monkeypatch.setattr(decompose, "free_cores", lambda: 1)
    one = filt.apply(x)
    monkeypatch.setattr(decompose, "free_cores", lambda: 2)
    two = filt.apply(x)
    np.testing.assert_array_equal(one, two)
    assert np.abs(one - x).max() > 1e-3 * np.abs(x).max()  # it did smooth


def test_poisson_reconstructor_pickles_without_its_lock():
    """The lock that keeps threads from factorising twice does not make it unpicklable."""
    import pickle

    from core.transfer import PoissonReconstructor

    box = trimesh.creation.box()
    P = PoissonReconstructor(np.asarray(box.faces), len(box.vertices), screening=0.01)
    Q = pickle.loads(pickle.dumps(P))
    b = np.random.default_rng(0).random((len(box.vertices), 3))
    np.testing.assert_array_equal(Q.solve(b), P.solve(b))
