"""core.motion_alignment: the per-point 3x3 map of the actor's motion space onto the character's."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.motion_alignment import (apply_alignment, covariance_alignment, matched_alignment, nearest_shapes,
                                   second_moments)
from core.stages.methods import covariance_inputs
from core.pipeline import Pipeline, StageCache
from tests.datapaths import PERFORMANCES, RIGS

CURVES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"))


def anisotropic_deltas(rng, K=40, M=6, spread=(3.0, 1.0, 0.2)):
    """(K, M, 3) displacements with distinct principal spreads along random axes per point."""
    axes = Rotation.random(M, random_state=rng).as_matrix()  # (M, 3, 3)
    z = rng.standard_normal((K, M, 3)) * np.asarray(spread)
    return np.einsum("mij,kmj->kmi", axes, z)


def test_a_known_rotation_of_the_motion_is_recovered():
    """Source = the target's displacements turned by R_p (< 90 degrees) and scaled by c_p per point:
    A_p = R_pᵀ / c_p, so the mapped source is the target's motion again."""
    rng = np.random.default_rng(0)
    target = anisotropic_deltas(rng)
    M = target.shape[1]
    R = Rotation.from_rotvec(rng.standard_normal((M, 3)) * 0.5 / np.sqrt(3)).as_matrix()  # ~0.5 rad
    c = rng.uniform(0.5, 2.0, M)
    source = np.einsum("mij,kmj->kmi", R * c[:, None, None], target)
    A = covariance_alignment(source, target, eps=0.0)
    np.testing.assert_allclose(A, np.transpose(R, (0, 2, 1)) / c[:, None, None], atol=1e-9)
    np.testing.assert_allclose(apply_alignment(A, source), target, atol=1e-12)
    # with the isotropic regularisation the axes and the rotation are the same, the spreads shrink
    # towards each other: still a pure rotation back (times a scale per axis), still proper
    A = covariance_alignment(source, target)
    assert (np.linalg.det(A) > 0).all()
    U, sv, Vt = np.linalg.svd(A)
    np.testing.assert_allclose(U @ Vt, np.transpose(R, (0, 2, 1)), atol=1e-9)


def test_colours_the_source_second_moments_with_the_targets_and_stays_proper():
    """A C_s Aᵀ = C_t for any two sets of displacements, det A > 0; a uniform scale gives that scale;
    a point neither rig moves gets the identity."""
    rng = np.random.default_rng(1)
    s, t = anisotropic_deltas(rng, K=30), anisotropic_deltas(rng, K=55, spread=(1.0, 0.5, 0.1))
    s[:, 2] = t[:, 2] = 0.0
    for eps in (0.0, 0.1):
        A = covariance_alignment(s, t, eps)
        Cs, Ct = second_moments(s, eps), second_moments(t, eps)
        moving = [0, 1, 3, 4, 5]
        np.testing.assert_allclose(np.einsum("mij,mjk,mlk->mil", A, Cs, A)[moving], Ct[moving], rtol=1e-9, atol=1e-15)
        assert (np.linalg.det(A[moving]) > 0).all()
        np.testing.assert_array_equal(A[2], np.eye(3))
    expected = np.repeat(np.eye(3)[None] / 2.5, 6, axis=0)
    expected[2] = np.eye(3)  # the point that does not move
    np.testing.assert_allclose(covariance_alignment(2.5 * t, t), expected, atol=1e-12)
    with pytest.raises(ValueError, match="same M points"):
        covariance_alignment(s[:, :4], t)
    with pytest.raises(ValueError, match="eps"):
        covariance_alignment(s, t, eps=-1.0)


def test_motion_scale_covariance_maps_the_source_by_the_rigs_alignment():
    """motion_scale = covariance: the calibrate stage's source motion is the stabilised motion mapped
    by covariance_alignment(source rig's shapes at the markers, calibrated target shapes)."""
    pipe = Pipeline(cache=StageCache(), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), method="bounded",
                    last_frame=59, target_shapes="arkit", motion_scale="covariance", **CURVES)
    res = pipe.results(["load", "correspond", "stabilize", "calibrate"])
    cal, st = res["calibrate"], res["stabilize"]["source"]
    Bs = res["correspond"]["source_layout"].select(list(st.names)).points(res["load"]["source_rig"].deltas)
    A = covariance_alignment(Bs, cal["deltas"])
    np.testing.assert_allclose(cal["source_map"], A)
    assert cal["source_scale"] is None
    np.testing.assert_allclose(cal["source"].deltas, np.einsum("mij,tmj->tmi", A, st.deltas), atol=1e-15)
    assert not np.allclose(A, A[:, :1, :1] * np.eye(3))  # a direction change, not only a scale


def test_auto_aligns_with_a_source_rig_and_scales_a_capture_without_one():
    """auto derives motion_scale = matched when a source rig's shapes are there to learn from, rom
    for a capture without one (no warning: the user did not ask for an alignment); the key carries it."""
    pipe = Pipeline(cache=StageCache(), target_rig=str(RIGS / "jeeliz_tiger.glb"), last_frame=29, **CURVES)
    assert pipe.view("calibrate").motion_scale == "matched"
    key = pipe.key("calibrate")
    pipe.configure(method="bounded", motion_scale="matched")
    assert pipe.key("calibrate") == key  # the same computation, chosen or set
    pipe.configure(motion_scale="rom")
    assert pipe.key("calibrate") != key
    capture = Pipeline(cache=StageCache(), source=str(PERFORMANCES / "animface_markers_jaw_60hz.csv"),
                       target_rig=str(RIGS / "jeeliz_tiger.glb"), last_frame=29)
    assert capture.view("calibrate").motion_scale == "rom"
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        cal = capture.results(["calibrate"])["calibrate"]
    np.testing.assert_allclose(cal["source_map"], cal["source_scale"][:, None, None] * np.eye(3))
    capture.configure(method="bounded", motion_scale="covariance")
    with pytest.warns(UserWarning, match="needs the source rig"):
        assert capture.results(["calibrate"])["calibrate"]["source_scale"] is not None


def test_nearest_shapes_is_relative_to_the_source_shapes_size():
    """One point, 1-D in x: source 1 is nearest to the target shape of its own size, not the
    smaller one a scale-blind match would take (same direction)."""
    src = np.array([[[1.0, 0, 0]], [[0, 2.0, 0]]])
    tgt = np.array([[[0, 0.5, 0]], [[0.9, 0, 0]], [[0, 1.9, 0]], [[0, 0, 3.0]]])
    np.testing.assert_array_equal(nearest_shapes(src, tgt), [1, 2])


def synthetic_pair(rng, J=30, M=7, distractors=6, angle=0.3):
    """A source rig and a target rig that differ by a known per-point map, names hidden: the
    target's shapes are the source's mapped by A_true(p) = c_p R_p S_p (a turn of about ``angle``
    rad, a stretch of 0.8-1.25 per axis, a scale of 0.5-2), shuffled among extra target shapes that
    match no source shape; weight curves as a take's (mostly small)."""
    src = anisotropic_deltas(rng, K=J, M=M)
    R = Rotation.from_rotvec(rng.standard_normal((M, 3)) * angle / np.sqrt(3)).as_matrix()
    S = np.stack([np.diag(rng.uniform(0.8, 1.25, 3)) for _ in range(M)])
    A_true = rng.uniform(0.5, 2.0, M)[:, None, None] * np.einsum("mij,mjk->mik", R, S)
    extra = apply_alignment(A_true, anisotropic_deltas(rng, K=distractors, M=M))
    target = np.concatenate([apply_alignment(A_true, src), extra])[rng.permutation(J + distractors)]
    W = rng.uniform(0, 1, (200, J)) ** 3
    return src, target, W, A_true


def test_matched_alignment_recovers_a_known_per_point_map():
    """Without a prior the matched pairs' take-weighted fit is the true map exactly (each source shape
    finds its mapped self among the shuffled target shapes and the distractors); with the default
    prior it stays closer to the truth than the covariance map it starts from."""
    for seed in range(6):
        rng = np.random.default_rng(seed)
        src, target, W, A_true = synthetic_pair(rng)
        A0 = covariance_alignment(src, target)
        exact = matched_alignment(src, target, W, prior=0.0, cap=np.inf)
        np.testing.assert_allclose(exact, A_true, atol=1e-9 * np.abs(A_true).max())
        pulled = matched_alignment(src, target, W)

        def err(A):
            return (np.linalg.norm(A - A_true, axis=(1, 2)) / np.linalg.norm(A_true, axis=(1, 2))).mean()

        assert err(pulled) < 0.9 * err(A0), (seed, err(pulled), err(A0))
        np.testing.assert_allclose(matched_alignment(src, target, W, initial=A0), pulled)


def test_matched_alignment_is_weighted_by_the_take():
    """Pairs the take never uses do not move the map: a source shape whose curve is zero is paired
    with a wrong shape (its partner is taken out of the target rig) and the map stays the true one."""
    rng = np.random.default_rng(7)
    src, target, W, A_true = synthetic_pair(rng, distractors=0)
    W[:, 3] = 0.0
    mapped3 = apply_alignment(A_true, src[3:4])[0]
    target = target[~np.all(np.isclose(target, mapped3), axis=(1, 2))]
    assert len(target) == len(src) - 1
    np.testing.assert_allclose(matched_alignment(src, target, W, prior=0.0, cap=np.inf), A_true,
                               atol=1e-9 * np.abs(A_true).max())
    W[:, 3] = 0.5  # used: the wrong pair now moves the map
    assert not np.allclose(matched_alignment(src, target, W, prior=0.0, cap=np.inf), A_true, atol=1e-3)


def test_matched_alignment_caps_the_map_where_the_take_barely_moves():
    """A point the take barely moves (its source shapes tiny there) whose partners move it a lot:
    uncapped the refit multiplies its motion ~1000-fold; capped, no singular value of the map
    exceeds κ times the covariance map's largest."""
    rng = np.random.default_rng(3)
    src, target, W, A_true = synthetic_pair(rng, distractors=0)
    src[:, 0] *= 1e-3  # point 0: the source barely moves it, the target as before
    A0 = covariance_alignment(src, target)
    free = matched_alignment(src, target, W, prior=0.0, cap=np.inf)
    capped = matched_alignment(src, target, W, prior=0.0, cap=1.5)
    s0, sfree, scap = (np.linalg.norm(A, ord=2, axis=(1, 2)) for A in (A0, free, capped))
    assert sfree[0] > 100 * np.linalg.norm(A_true[0], ord=2)
    assert np.all(scap <= 1.5 * s0 * (1 + 1e-12))
    assert scap[0] < sfree[0]


def test_matched_alignment_rejects_bad_input():
    rng = np.random.default_rng(1)
    src, target, W, _ = synthetic_pair(rng)
    with pytest.raises(ValueError, match="source_weights"):
        matched_alignment(src, target, W[:, :-1])
    with pytest.raises(ValueError, match="prior"):
        matched_alignment(src, target, W, prior=-1.0)
    with pytest.raises(ValueError, match="cap"):
        matched_alignment(src, target, W, cap=0.0)
    with pytest.raises(ValueError, match="same M points"):
        matched_alignment(src[:, :3], target, W)


def test_motion_scale_matched_maps_the_source_by_the_take_refit():
    """motion_scale = matched: the calibrate stage's source motion is the stabilised motion mapped by
    matched_alignment(source rig's shapes, calibrated target shapes, the take's curves); with example
    poses auto's solve goes back to the covariance map (covariance_inputs)."""
    pipe = Pipeline(cache=StageCache(), target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), method="bounded",
                    last_frame=59, target_shapes="arkit", motion_scale="matched", **CURVES)
    res = pipe.results(["load", "frames", "correspond", "stabilize", "shapes", "personalize", "calibrate"])
    cal, st = res["calibrate"], res["stabilize"]["source"]
    Bs = res["correspond"]["source_layout"].select(list(st.names)).points(res["load"]["source_rig"].deltas)
    A = matched_alignment(Bs, cal["deltas"], st.source_weights)
    assert cal["alignment"] == "matched"
    np.testing.assert_allclose(cal["source_map"], A)
    np.testing.assert_allclose(cal["source"].deltas, np.einsum("mij,tmj->tmi", A, st.deltas), atol=1e-15)
    np.testing.assert_allclose(cal["covariance_map"], covariance_alignment(Bs, cal["deltas"]))
    assert not np.allclose(A, cal["covariance_map"])
    back = covariance_inputs(res)["calibrate"]
    pipe.configure(motion_scale="covariance")
    cov = pipe.results(["calibrate"])["calibrate"]
    assert back["alignment"] == cov["alignment"] == "covariance"
    np.testing.assert_allclose(back["source"].deltas, cov["source"].deltas, atol=1e-15)
    np.testing.assert_allclose(back["source_map"], cov["source_map"])
    assert covariance_inputs({**res, "calibrate": cov}) is not None
    assert covariance_inputs({**res, "calibrate": cov})["calibrate"] is cov
