"""PCA prior (Seol et al. 2012, §5, eq. 3): checked against the covariance matrix directly."""

import json

import numpy as np
import pytest

from core.model import flatten
from core.prior import PCAPrior, alpha_for_units
from datapaths import LAYOUTS


def _ict_marker_deltas(ict):
    layout = LAYOUTS / "ict_facekit.json"
    vid = [m["vertex"] for m in json.loads(layout.read_text())["markers"].values()]
    return ict.deltas[:, vid]


@pytest.fixture(scope="module")
def random_basis():
    rng = np.random.default_rng(3)
    return rng.normal(size=(12, 7, 3)) * 0.01


def _pinv_energy(X, W, basis):
    """Reference: E_prior = x^T Sigma^+ x, x = B w - mean, Sigma the sample covariance."""
    flat = flatten(X)
    cov = np.cov(flat.T)  # (3M, 3M), normalised by N - 1
    x = W @ flatten(basis) - flat.mean(0)
    return np.einsum("ti,ij,tj->t", x, np.linalg.pinv(cov, rcond=1e-10, hermitian=True), x)


@pytest.mark.parametrize("source", ["random", "ict"])
def test_pca_matches_covariance_and_energy(source, random_basis, ict):
    X = random_basis if source == "random" else _ict_marker_deltas(ict)
    prior = PCAPrior().fit(X)
    flat = flatten(X)
    ev = np.linalg.eigvalsh(np.cov(flat.T))[::-1]
    h = np.linalg.matrix_rank(flat - flat.mean(0))
    assert prior.n_components_ == h  # zero eigenvalues dropped (K shapes, centred: rank <= K - 1)
    assert h <= len(X) - 1
    np.testing.assert_allclose(prior.eigenvalues_, ev[:h], rtol=1e-8)
    E = prior.components_
    np.testing.assert_allclose(E @ E.T, np.eye(h), atol=1e-12)
    # the quadratic form equals v^T Lambda^-1 v and the covariance pseudo-inverse form
    rng = np.random.default_rng(0)
    W = rng.normal(size=(20, len(X)))
    lit = prior.energy(W)
    quad = np.einsum("tk,kl,tl->t", W, prior.P_, W) - 2 * W @ prior.q_ + prior.c_
    np.testing.assert_allclose(quad, lit, rtol=1e-9)
    np.testing.assert_allclose(lit, _pinv_energy(X, W, X), rtol=1e-6)
    # each training shape is a plausible face: its energy is small compared to random weights
    assert prior.energy(np.eye(len(X))).mean() < 0.1 * lit.mean()


def test_signs_fixed_and_repeatable(random_basis):
    a = PCAPrior().fit(random_basis)
    b = PCAPrior().fit(random_basis[::-1].copy())  # same data, other order
    big = np.abs(a.components_).argmax(1)
    assert (a.components_[np.arange(a.n_components_), big] > 0).all()
    np.testing.assert_allclose(np.abs(a.components_ @ b.components_.T).diagonal(), 1, atol=1e-8)
    np.testing.assert_allclose(a.components_, b.components_, atol=1e-8)


def test_scale_free(random_basis):
    """E_prior does not change when all lengths are scaled (Lambda scales with length^2)."""
    a = PCAPrior().fit(random_basis)
    b = PCAPrior().fit(random_basis * 100.0)
    np.testing.assert_allclose(b.P_, a.P_, rtol=1e-9)
    np.testing.assert_allclose(b.q_, a.q_, rtol=1e-9, atol=1e-12 * np.abs(a.q_).max())
    assert alpha_for_units(0.01, "cm") == pytest.approx(1e-6)
    assert alpha_for_units(0.01, "m") == 0.01
    assert alpha_for_units(2.0, "mm") == pytest.approx(2e-6)


def test_subset_and_examples(random_basis):
    """Fig. 13 subsets and example animations; positions with a neutral equal deltas."""
    B = random_basis
    sub = [0, 2, 5, 7]
    a = PCAPrior().fit(B, subset=sub)
    b = PCAPrior().fit(B[sub], basis=B)
    assert a.n_samples_ == 4 and a.n_components_ == 3
    np.testing.assert_allclose(a.P_, b.P_, rtol=1e-10)
    mask = np.zeros(len(B), bool)
    mask[sub] = True
    np.testing.assert_allclose(PCAPrior().fit(B, subset=mask).P_, a.P_, rtol=1e-10)
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=B.shape[1:])
    ex = np.einsum("tk,kmc->tmc", rng.uniform(0, 1, (30, len(B))), B)
    c = PCAPrior().fit(ex + neutral, neutral_markers=neutral, basis=B)
    d = PCAPrior().fit(ex, basis=B)
    np.testing.assert_allclose(c.P_, d.P_, rtol=1e-8)
    np.testing.assert_allclose(c.q_, d.q_, rtol=1e-8)
    np.testing.assert_allclose(c.mean_, ex.mean(0), atol=1e-12)
    # quadratic for another basis == energy with that basis
    W = rng.normal(size=(5, len(B)))
    P, q, cc = d.quadratic(B[::-1])
    np.testing.assert_allclose(np.einsum("tk,kl,tl->t", W, P, W) - 2 * W @ q + cc, d.energy(W, basis=B[::-1]), rtol=1e-9)


def test_errors(random_basis):
    with pytest.raises(ValueError, match=r"\(N, M, 3\)"):
        PCAPrior().fit(np.zeros((4, 5)))
    bad = random_basis.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        PCAPrior().fit(bad)
    with pytest.raises(ValueError, match="at least 2"):
        PCAPrior().fit(random_basis, subset=[3])
    with pytest.raises(ValueError, match="do not vary"):
        PCAPrior().fit(np.repeat(random_basis[:1], 3, axis=0))
    with pytest.raises(ValueError, match="needs basis"):
        PCAPrior().fit(random_basis, neutral_markers=np.zeros((7, 3)))
    with pytest.raises(ValueError, match="neutral_markers"):
        PCAPrior().fit(random_basis, neutral_markers=np.zeros((6, 3)), basis=random_basis)
    with pytest.raises(RuntimeError, match="not fitted"):
        PCAPrior().energy(np.zeros(3))
    with pytest.raises(ValueError, match="alpha"):
        alpha_for_units(-1.0)
    with pytest.raises(ValueError, match="units"):
        alpha_for_units(1.0, "furlong")


def test_the_quadratic_of_the_priors_own_basis_is_the_fitted_one_and_a_refit_replaces_it():
    """quadratic() of the fitted basis (given as (K, M, 3) or as the (3M, K) matrix) returns the
    fitted P_, q_, c_ (the solvers ask for it at every solve); another basis is computed; a new
    fit's quadratic is the new basis's."""
    r = np.random.default_rng(3)
    X = r.normal(size=(9, 6, 3))
    p = PCAPrior().fit(X)
    R, m = p._factor(X)
    for basis in (X, flatten(X).T.copy()):
        P, q, c = p.quadratic(basis)
        np.testing.assert_allclose(P, R.T @ R, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(q, R.T @ m, rtol=1e-12, atol=1e-14)
        P[0, 0] = 1e9  # a copy: the prior's own is untouched
    assert p.P_[0, 0] != 1e9
    Y = X + r.normal(size=X.shape) * 0.1
    R2, m2 = p._factor(Y)
    np.testing.assert_allclose(p.quadratic(Y)[0], R2.T @ R2, rtol=1e-12, atol=1e-14)
    p.fit(Y)
    R3, _ = p._factor(Y)
    np.testing.assert_allclose(p.P_, R3.T @ R3, rtol=1e-12, atol=1e-14)
    assert not np.allclose(p.quadratic(X)[0], p.P_)
