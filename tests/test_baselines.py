"""core.solvers.baselines: prior_pf given the data term's products (``data_gram``, what the
pipeline's ``gram`` stage keeps across setting changes) gives the numbers it computes itself."""

import numpy as np

from core.solvers.baselines import data_gram, prior_pf


def _case(seed, holes):
    r = np.random.default_rng(seed)
    K, M, T = 7, 12, 60
    B = r.normal(size=(K, M, 3)) * 1e-2
    S = np.einsum("tk,kmc->tmc", r.uniform(0, 1, (T, K)), B) + r.normal(size=(T, M, 3)) * 1e-4
    if holes:
        S[5, 3] = np.nan
        S[20:23, 0] = np.nan
    return B, S, np.isfinite(S).all(-1)


def test_prior_pf_with_the_gram_is_bit_identical():
    for seed, holes in ((0, False), (1, True)):
        B, S, valid = _case(seed, holes)
        gram = data_gram(B, S, valid)
        assert np.array_equal(gram["frames"], np.flatnonzero(valid.all(1)))
        Q = np.zeros((7, 7))
        Q[0, 0] = Q[1, 1] = 1e-3
        Q[0, 1] = Q[1, 0] = -1e-3
        zero = np.zeros((len(S), 7), bool)
        zero[::7, 2] = True
        for kw in ({}, {"ridge": 1e-3}, {"ridge": 1e-3, "quadratic": Q, "zero": zero}):
            want = prior_pf(B, S, 0.05, None, valid, **kw)
            got = prior_pf(B, S, 0.05, None, valid, gram=gram, **kw)
            assert np.array_equal(got, want)


def test_prior_pf_with_a_gram_of_every_frame_reads_no_frame_of_the_take():
    """With the gram of a take whose frames all have every marker, prior_pf solves from the gram
    alone (a dense alpha change makes no pass over the (T, 3M) take): the take's numbers are not
    read, and the result is the one it computes from the take."""
    B, S, valid = _case(2, False)
    gram = data_gram(B, S, valid)
    want = prior_pf(B, S, 0.05, None, valid, ridge=1e-3)
    blind = np.full_like(S, np.nan)  # what is not read cannot change the result
    assert np.array_equal(prior_pf(B, blind, 0.05, None, None, ridge=1e-3, gram=gram), want)
