"""Xu 2014 eq. 6-7: NNLS weights and greedy basis selection against dense references."""

import numpy as np
import pytest
from scipy.optimize import nnls

from core.transfer import factor_sequence, nnls_gram, select_bases, taubin_smooth


def test_nnls_gram_matches_scipy_on_random_tall_problems():
    rng = np.random.default_rng(0)
    for K in (1, 3, 8, 15):
        B = rng.standard_normal((200, K))
        S = rng.standard_normal((200, 30))  # many columns with negative unconstrained weights
        W = nnls_gram(B.T @ B, B.T @ S)
        for t in range(S.shape[1]):
            ref = nnls(B, S[:, t])[0]
            assert np.abs(W[:, t] - ref).max() < 1e-9 * max(1, np.abs(ref).max())
        assert (W >= 0).all()


def test_nnls_gram_matches_scipy_on_real_rig_deltas(tiger):
    B = tiger.deltas.reshape(tiger.n_shapes, -1).T * 1000.0  # mm, (3V, K)
    rng = np.random.default_rng(1)
    w_true = rng.random((tiger.n_shapes, 12)) - 0.3
    S = B @ w_true + 0.01 * rng.standard_normal((B.shape[0], 12))
    W = nnls_gram(B.T @ B, B.T @ S)
    for t in range(12):
        ref = nnls(B, S[:, t])[0]
        # compare objective values (the minimiser is unique when B has full column rank)
        assert np.linalg.norm(B @ W[:, t] - S[:, t]) <= np.linalg.norm(B @ ref - S[:, t]) * (1 + 1e-9)
        assert np.abs(W[:, t] - ref).max() < 1e-6


def test_nnls_gram_shapes_and_errors():
    G = np.eye(2)
    assert nnls_gram(G, np.array([1.0, -1.0])).tolist() == [1.0, 0.0]
    with pytest.raises(ValueError, match="G, H"):
        nnls_gram(G, np.ones(3))


def _brute_force_step(Y, selected):
    """Exact greedy step by dense scipy NNLS on explicit (3V x k) matrices."""
    best = None
    for j in range(len(Y)):
        if j in selected:
            continue
        B = Y[selected + [j]].T
        if np.linalg.matrix_rank(B) < B.shape[1]:
            continue
        err = sum(nnls(B, Y[t])[1] ** 2 for t in range(len(Y)))
        if best is None or err < best[0]:
            best = (err, j)
    return best


def test_exact_greedy_matches_brute_force_reference():
    rng = np.random.default_rng(2)
    extremes = rng.standard_normal((4, 60))
    Y = rng.random((25, 4)) ** 3 @ extremes + 0.01 * rng.standard_normal((25, 60))
    sel = select_bases(Y @ Y.T, eps=0, max_bases=4, candidates=len(Y))
    chosen = []
    total = (Y ** 2).sum()
    for k in range(4):
        err, j = _brute_force_step(Y, chosen)
        assert sel.frames[k] == j
        assert abs(sel.errors[k + 1] - err / total) < 1e-8
        chosen.append(j)


def test_selection_recovers_generating_extremes_and_stops_at_eps():
    rng = np.random.default_rng(3)
    extremes = rng.standard_normal((3, 90))
    W = rng.random((40, 3)) * 0.8
    W[[5, 17, 30]] = np.eye(3)  # the extremes themselves are frames
    Y = W @ extremes
    sel = select_bases(Y @ Y.T, eps=1e-10, max_bases=10)
    # greedy is not optimal: the first pick is the largest frame, which need not be an
    # extreme; with non-negative weights the three extremes must still all be chosen
    assert sel.n_bases <= 4 and sel.errors[-1] < 1e-10
    assert {5, 17, 30} <= set(sel.frames.tolist())
    rec = sel.weights @ Y[sel.frames]
    assert np.abs(rec - Y).max() < 1e-6
    assert (sel.weights >= 0).all()
    assert np.all(np.diff(sel.errors) <= 1e-12)  # error never increases


def test_selection_on_real_smoothed_sequence(ict):
    rng = np.random.default_rng(4)
    from core.io.livelink import read_livelink
    from core.names import NameMap
    from tests.conftest import PERFORMANCES

    perf = read_livelink(PERFORMANCES / "livelinkface_take_s07.csv")
    G = NameMap.automatic(perf.names, ict.names).matrix(perf.names, ict.names)
    Wsrc = np.nan_to_num(perf.data[:400:10]) @ G.T
    seq = ict.evaluate(Wsrc)
    fac = factor_sequence(seq, 1e-7, base=ict.neutral)
    Q = fac.basis.reshape(fac.rank, -1)
    sel = select_bases(fac.coeffs @ (Q @ Q.T) @ fac.coeffs.T, eps=1e-3, max_bases=20)
    Y = (seq - ict.neutral).reshape(len(seq), -1)
    rec = sel.weights @ Y[sel.frames]
    rel = ((rec - Y) ** 2).sum() / (Y ** 2).sum()
    assert abs(rel - sel.errors[-1]) < 1e-6 and (rel <= 1e-3 or sel.n_bases == 20)
    del rng
