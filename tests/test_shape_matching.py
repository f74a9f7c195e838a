"""Shape-to-shape correspondence from geometry (core.shape_matching), and auto without shared names
(the source's motion re-sculpted in the character's style, before the take-fitted map replaced it)."""

import warnings

import numpy as np
import pytest
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from core.shape_matching import match_shapes, motion_affinity, pseudo_names, restyled_motion, shape_map
from core.solvers.baselines import range_pf
from core.stages.methods import restyled_inputs
from datapaths import PERFORMANCES, RIGS


def _localised_shapes(rng, K, M):
    """(K, M, 3): each shape moves a random patch of the M points (a bump around a centre)."""
    pts = rng.uniform(-1, 1, (M, 3))
    centres = pts[rng.choice(M, K, replace=False)]
    fall = np.exp(-np.linalg.norm(pts[None] - centres[:, None], axis=2) ** 2 / 0.15)  # (K, M)
    dirs = rng.normal(size=(K, 1, 3))
    return fall[..., None] * dirs / np.linalg.norm(dirs, axis=2, keepdims=True)


def _resculpted(rng, target, perm, degrees=50.0):
    """The target's shapes permuted, each re-sculpted: its motion turned by a rotation of
    ``degrees`` about a random axis, and scaled by 0.5…2."""
    out = []
    for k in perm:
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(np.deg2rad(degrees) * axis / np.linalg.norm(axis)).as_matrix()
        out.append(rng.uniform(0.5, 2.0) * target[k] @ R.T)
    return np.stack(out)


def test_single_shape_affinity_by_hand():
    # one point moving along x against one along y: direction cos 0, magnitude pattern cos 1
    s = np.array([[[1.0, 0, 0], [0, 0, 0]]])
    t = np.array([[[0, 2.0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 1.0]]])
    A = motion_affinity(s, t, mix=0.5)
    assert A[0, 0] == pytest.approx(0.5)   # 0.5·0 + 0.5·1
    assert A[0, 1] == pytest.approx(0.0)   # another point: nothing shared
    assert motion_affinity(s, t, mix=1.0)[0, 0] == pytest.approx(0.0)
    assert motion_affinity(s, s, mix=0.3)[0, 0] == pytest.approx(1.0)


def test_matching_recovers_permutation_of_resculpted_shapes():
    rng = np.random.default_rng(7)
    K, M = 12, 200
    target = _localised_shapes(rng, K, M)
    perm = rng.permutation(K)
    source = _resculpted(rng, target, perm)
    m = match_shapes(source, target)
    assert np.array_equal(m.source, np.arange(K))
    assert np.array_equal(m.target, perm)  # source shape j is target shape perm[j]
    # every pair is sure with the magnitude pattern; by direction alone (turned 50°) most are not
    assert m.mutual.all() and (m.confidence > 0).all()
    assert match_shapes(source, target, mix=1.0).sure.sum() < K // 2
    # the gain undoes the scale: g = ||s_j|| / ||t_k||
    for j, k, g in zip(m.source, m.target, m.gain):
        assert g == pytest.approx(np.linalg.norm(source[j]) / np.linalg.norm(target[k]))


def test_unsure_pairs_do_not_pull():
    rng = np.random.default_rng(3)
    target = _localised_shapes(rng, 6, 150)
    # a source shape that resembles none of the target's (moves everything a little, at random)
    odd = rng.normal(size=(1, 150, 3)) * 0.1
    source = np.concatenate([target[:3], odd])
    m = match_shapes(source, target)
    assert m.sure[:3].all() and not m.sure[3]
    W, conf = pseudo_names(m, rng.uniform(0, 1, (20, 4)), 6)
    k_odd = m.target[3]
    assert np.isnan(W[:, k_odd]).all() and conf[k_odd] == 0
    assert np.isfinite(W[:, m.target[:3]]).all() and (conf[m.target[:3]] > 0).all()


def test_pseudo_names_scale_by_gain_within_bounds():
    rng = np.random.default_rng(1)
    target = _localised_shapes(rng, 5, 120)
    source = 3.0 * target[[2, 0, 1]]
    m = match_shapes(source, target)
    Ws = rng.uniform(0, 1, (30, 3))
    W, conf = pseudo_names(m, Ws, 5, lower=0.0, upper=np.array([1, 1, 2.5, 1, 1.0]))
    np.testing.assert_allclose(W[:, 2], np.clip(3.0 * Ws[:, 0], 0, 2.5))
    np.testing.assert_allclose(W[:, 0], np.clip(3.0 * Ws[:, 1], 0, 1))
    assert np.isnan(W[:, [3, 4]]).all() and (conf[[3, 4]] == 0).all()


@pytest.mark.parametrize("ridge", [0.0, 1e-2])
def test_shape_map_against_bvls(ridge):
    """The per-shape fit against SciPy's bounded least squares on the ridge-augmented system."""
    rng = np.random.default_rng(5)
    target = rng.normal(size=(8, 15, 3))
    source = rng.normal(size=(4, 15, 3))
    M = shape_map(source, target, 0.0, 1.0, ridge=ridge)
    assert M.shape == (8, 4) and (M >= 0).all() and (M <= 1).all()
    T = target.reshape(8, -1).T
    smax = np.linalg.norm(T, 2)
    A = np.vstack([T, np.sqrt(ridge) * smax * np.eye(8)])
    for j in range(4):
        ref = lsq_linear(A, np.concatenate([source[j].ravel(), np.zeros(8)]), bounds=(0, 1), method="bvls",
                         tol=1e-12).x
        np.testing.assert_allclose(M[:, j], ref, atol=1e-7)


def test_boundary_errors_name_the_argument():
    with pytest.raises(ValueError, match="source"):
        motion_affinity(np.zeros((2, 5)), np.zeros((2, 5, 3)))
    with pytest.raises(ValueError, match="same points"):
        match_shapes(np.zeros((2, 4, 3)), np.zeros((2, 5, 3)))
    with pytest.raises(ValueError, match="mix"):
        motion_affinity(np.zeros((2, 5, 3)), np.zeros((2, 5, 3)), mix=2.0)


def test_restyled_motion_moves_sure_shapes_towards_their_match():
    rng = np.random.default_rng(11)
    target = _localised_shapes(rng, 6, 120)
    perm = rng.permutation(6)
    source = _resculpted(rng, target, perm, degrees=30.0)
    odd = rng.normal(size=(1, 120, 3)) * 0.1  # matches nothing: keeps its motion
    source = np.concatenate([source, odd])
    m = match_shapes(source, target)
    assert sorted(m.source[m.sure]) == list(range(6)) and np.array_equal(m.target[m.sure][np.argsort(m.source[m.sure])], perm)
    W = rng.uniform(0, 1, (25, 7))
    W[3] = np.nan  # a frame without data stays without data
    motion = np.einsum("tj,jmc->tmc", W, source)
    np.testing.assert_array_equal(np.nan_to_num(restyled_motion(m, source, target, np.nan_to_num(W), beta=0.0)), 0.0)
    full = motion + restyled_motion(m, source, target, W, beta=1.0)
    # beta = 1: each sure source shape is its match, scaled by the gain (the same overall size)
    g = np.linalg.norm(source[:6].reshape(6, -1), axis=1) / np.linalg.norm(target[perm].reshape(6, -1), axis=1)
    expected = np.einsum("tj,jmc->tmc", W[:, :6] * g, target[perm]) + np.einsum("tj,jmc->tmc", W[:, 6:], odd)
    ok = np.isfinite(W).all(1)
    np.testing.assert_allclose(full[ok], expected.reshape(full.shape)[ok], atol=1e-12)
    assert np.isnan(full[3]).all()
    half = motion + restyled_motion(m, source, target, W, beta=0.5)
    np.testing.assert_allclose(half[ok], 0.5 * (motion[ok] + full[ok]), atol=1e-12)
    with pytest.raises(ValueError, match="beta"):
        restyled_motion(m, source, target, W, beta=1.5)


@pytest.mark.slow
def test_auto_without_names_aligns_on_the_take_and_beats_plain_geometry(hidden_rocketbox):
    """S07 on Rocketbox with every shape renamed, 300 frames: auto says it aligns the actor's motion
    by the map fitted on the take to the character's nearest shapes (motion_scale = matched, which
    replaced the re-sculpt: core.motion_alignment), stays in [0, 1], and its face error is below
    the plain per-frame solve it ran before (bounded, rom, ridge 1e-2) and the re-sculpted one."""
    from core.geometry import face_vertices
    from core.pipeline import Pipeline, StageCache
    from core.metrics import vertex_errors
    from core.report import ground_truth

    files = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
                 last_frame=299)
    cache = StageCache()
    base = Pipeline(cache=cache, target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), **files).results(["load", "frames"])
    rig = base["load"]["target_rig"]
    Wt = ground_truth(base["load"], base["frames"])["weights"]
    face = np.flatnonzero(face_vertices(rig.deltas))
    ok = np.isfinite(Wt).all(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        auto = Pipeline(cache=cache, target_rig=str(hidden_rocketbox), **files).results(["solve", "synthesize"])
        plain = Pipeline(cache=cache, target_rig=str(hidden_rocketbox), method="bounded", motion_scale="rom",
                         ridge=1e-2, **files).results(["synthesize"])
        pipe = Pipeline(cache=cache, target_rig=str(hidden_rocketbox), method="bounded", motion_scale="covariance",
                        ridge=1e-2, **files)
        inputs = pipe.results(["load", "frames", "correspond", "stabilize", "shapes", "personalize", "calibrate"])
        restyled = restyled_inputs(inputs)[0]["calibrate"]["source"]  # the per-frame solve of it, as auto ran it
        W1s = range_pf(inputs["personalize"]["deltas"], restyled.deltas, 0.0, 1.0, restyled.valid, ridge=1e-2)
    info = auto["solve"]["info"]
    assert "fitted on the take" in info["auto"] and "re-sculpted" not in info["auto"]
    assert info["chosen"]["method"] == "bounded"
    W, W0 = np.asarray(auto["synthesize"]["weights"]), np.asarray(plain["synthesize"]["weights"])
    assert W.min() >= 0 and W.max() <= 1
    err = float(np.nanmean(vertex_errors(rig.deltas, W, Wt, face, ok)[0]))
    err0 = float(np.nanmean(vertex_errors(rig.deltas, W0, Wt, face, ok)[0]))
    W1 = np.zeros_like(W)
    W1[:, np.asarray(inputs["shapes"]["shape_index"])] = W1s
    err1 = float(np.nanmean(vertex_errors(rig.deltas, W1, Wt, face, ok)[0]))
    assert err < 0.9 * err0 and err < err1, (err, err0, err1)
