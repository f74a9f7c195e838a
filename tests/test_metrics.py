"""core.metrics: the marker and velocity errors computed from one shared residual are the
numbers of the two functions called apart (missing samples and a prediction included), and the
velocity error matches its definition on a hand-sized case."""

import numpy as np
import pytest

from core.metrics import marker_and_velocity_error, marker_error_mm, velocity_error


def _case(seed=0, T=30, K=6, M=5):
    r = np.random.default_rng(seed)
    B, W, S = r.normal(size=(K, M, 3)), r.normal(size=(T, K)), r.normal(size=(T, M, 3))
    S[4, 2] = np.nan
    S[10] = np.nan
    return B, W, S


def test_one_residual_gives_both_errors_exactly():
    B, W, S = _case()
    valid = np.isfinite(S).all(-1)
    for predicted in (None, np.einsum("tk,kmc->tmc", W, B) * 0.9):
        me, ve = marker_and_velocity_error(B, W, S, valid, predicted)
        for got, want in zip(me, marker_error_mm(B, W, S, valid, predicted)):
            assert np.array_equal(got, want, equal_nan=True)
        for got, want in zip(ve, velocity_error(B, W, S, valid, predicted)):
            assert np.array_equal(got, want, equal_nan=True)


def test_velocity_error_is_its_definition():
    B, W, S = _case(1)
    valid = np.isfinite(S).all(-1)
    _, ve = marker_and_velocity_error(B, W, S, valid)
    X = np.einsum("tk,kmc->tmc", W, B) - np.nan_to_num(S)
    want = [0.0] + [sum(float(np.sum((X[t, m] - X[t - 1, m]) ** 2)) for m in range(S.shape[1])
                        if valid[t, m] and valid[t - 1, m]) * 1e6 for t in range(1, len(S))]
    assert np.allclose(ve.per_frame, want, rtol=1e-12, atol=0)
    assert np.isclose(ve.total, sum(want), rtol=1e-12)


def _marker_error_by_norm(B, W, S, valid):
    """The marker error as it was first written (np.linalg.norm over x, y, z; masks applied even
    where every sample is valid): the faster code must give these numbers bit for bit."""
    X = (W @ B.reshape(len(B), -1) - np.where(valid[..., None], S, 0.0).reshape(len(S), -1)).reshape(S.shape)
    d = np.where(valid, np.linalg.norm(X, axis=2) * 1e3, np.nan)
    d2 = np.where(valid, d, 0.0) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame, per_marker = np.sqrt(d2.sum(1) / valid.sum(1)), np.sqrt(d2.sum(0) / valid.sum(0))
    return d, per_frame, per_marker, float(np.sqrt(d2.sum() / valid.sum())), float(np.nanmax(d))


def test_marker_error_is_the_norm_bit_for_bit():
    for seed, holes in ((2, True), (3, False)):
        B, W, S = _case(seed, T=200, K=7, M=40)
        if not holes:
            S = np.nan_to_num(S)
        S *= 1e-3  # metres, as the solvers pass them
        valid = np.isfinite(S).all(-1)
        got = marker_error_mm(B * 1e-3, W, S, valid)
        want = _marker_error_by_norm(B * 1e-3, W, S, valid)
        for g, w in zip(got, want):
            assert np.array_equal(g, w, equal_nan=True)


def _evaluations_agree(ev, ref, rtol):
    assert ev.keys() == ref.keys()
    for k in ref:
        got, want = np.asarray(ev[k], dtype=np.float64), np.asarray(ref[k], dtype=np.float64)
        assert np.array_equal(np.isnan(got), np.isnan(want)), k
        np.testing.assert_allclose(got, want, rtol=rtol, atol=0, err_msg=k)


def test_errors_from_the_take_products_are_the_residuals():
    """evaluate with the take's products (the errors summed in weight space, expanded as
    w^T G w - 2 w^T (S B)_t + ||s_t||^2) gives the residual's numbers to rounding: frames left out
    (non-finite weights, frame_valid False) in the middle and at the ends, every frame left out,
    and a product that cannot apply (a missing sample) is None."""
    from core.evaluate import evaluate
    from core.metrics import error_products

    r = np.random.default_rng(3)
    T, K, M = 40, 6, 9
    B, S = r.normal(size=(K, M, 3)), r.normal(size=(T, M, 3))
    W = r.normal(size=(T, K)) + 0.3
    W[7] = np.nan
    P = error_products(B, S)
    assert P is not None
    for fv in (None, np.arange(T) % 5 != 2, np.arange(T) > 0, np.zeros(T, dtype=bool)):
        ref = evaluate(B, W, S, frame_valid=fv)
        ev = evaluate(B, W, S, frame_valid=fv, products=P)
        assert (ev["n_valid_frames"] > 0) == (fv is None or fv.any())
        _evaluations_agree(ev, ref, 1e-11)
    with pytest.raises(ValueError, match="products: made for S"):
        evaluate(B, W[:-1], S[:-1], products=P)
    S[4, 2] = np.nan
    assert error_products(B, S) is None


def test_a_low_rank_take_is_factorised_to_rounding_and_scored_through_its_factors():
    """A take of rank 12 (a source rig's shapes driven by curves, as dense correspondence's face
    points are) gets factors S = A V with r = 12 and ||S - A V|| at rounding, and the errors
    through them are the residual's; a full-rank take and a small one get none (the plain W^T S)."""
    from core.evaluate import evaluate
    from core.metrics import error_products

    r = np.random.default_rng(5)
    T, K, M = 600, 8, 600
    B = r.normal(size=(K, M, 3))
    S = (r.normal(size=(T, 12)) @ r.normal(size=(12, 3 * M))).reshape(T, M, 3)
    W = r.normal(size=(T, K))
    W[1:] = 0.9 * W[:-1] + 0.1 * W[1:]
    P = error_products(B, S)
    A, V = P.low_rank
    assert A.shape == (T, 12) and V.shape == (12, 3 * M)
    assert np.linalg.norm(A @ V - S.reshape(T, -1)) <= 1e-13 * np.linalg.norm(S)
    fv = np.arange(T) % 7 != 3
    _evaluations_agree(evaluate(B, W, S, frame_valid=fv, products=P), evaluate(B, W, S, frame_valid=fv), 1e-10)
    S100 = r.normal(size=(T, 100)) @ r.normal(size=(100, 3 * M))  # above the first sketch: the second finds it
    assert error_products(B, S100.reshape(T, M, 3)).low_rank[0].shape == (T, 100)
    assert error_products(B, r.normal(size=(T, M, 3))).low_rank is None
    assert error_products(B[:, :50], S[:100, :50]).low_rank is None
