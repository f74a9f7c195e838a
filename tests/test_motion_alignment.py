"""core.motion_alignment: the per-point 3x3 map of the actor's motion space onto the character's."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.motion_alignment import apply_alignment, covariance_alignment, second_moments
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
    """auto derives motion_scale = covariance when a source rig's shapes are there to learn from, rom
    for a capture without one (no warning: the user did not ask for covariance); the key carries it."""
    pipe = Pipeline(cache=StageCache(), target_rig=str(RIGS / "jeeliz_tiger.glb"), last_frame=29, **CURVES)
    assert pipe.view("calibrate").motion_scale == "covariance"
    key = pipe.key("calibrate")
    pipe.configure(method="bounded", motion_scale="covariance")
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
