"""Shape-to-shape correspondence from geometry (core.shape_matching), and auto without shared names
(the source rig's curves mapped through the sparse shape map over dense correspondence)."""

import warnings

import numpy as np
import pytest
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from core.shape_matching import (SPARSE_L1, jaw_rescaled_map, jaw_shapes, rigid_motion, shape_map, mapped_weights, match_shapes, motion_affinity, pseudo_names, restyled_motion,
                                 shape_map)
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


@pytest.mark.parametrize("ridge", [0.0, 1e-2])
@pytest.mark.parametrize("l1", [0.05, 0.3])
def test_sparse_shape_map_against_bvls(ridge, l1):
    """The L1 fit against SciPy's bounded least squares: with x >= 0 the L1 term is linear,
    ``l1 ||s||² 1ᵀx``, and equals a shift of the right-hand side by ``z = Tᵀ(T Tᵀ)⁻¹ ½ l1 ||s||² 1``
    (T of full row rank): ``||Tᵀx − s||² + l1 ||s||² 1ᵀx = ||Tᵀx − (s − z)||² + const``."""
    rng = np.random.default_rng(9)
    target = rng.normal(size=(8, 15, 3))
    source = rng.normal(size=(4, 15, 3))
    M = shape_map(source, target, 0.0, 1.0, ridge=ridge, l1=l1)
    assert M.shape == (8, 4) and (M >= 0).all() and (M <= 1).all()
    T = target.reshape(8, -1)
    G = T @ T.T
    smax2 = np.linalg.eigvalsh(G)[-1]
    A = np.vstack([T.T, np.sqrt(max(ridge, 1e-9) * smax2) * np.eye(8)])
    for j in range(4):
        s = source[j].ravel()
        z = T.T @ np.linalg.solve(G, np.full(8, 0.5 * l1 * (s @ s)))
        ref = lsq_linear(A, np.concatenate([s - z, np.zeros(8)]), bounds=(0, 1), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(M[:, j], ref, atol=1e-7)
    # the L1 term only ever removes shapes: fewer active than the plain fit, none outside its support
    assert (M > 1e-9).sum() < (shape_map(source, target, 0.0, 1.0, ridge=ridge) > 1e-9).sum()



@pytest.mark.parametrize("per_source", [False, True])
def test_weighted_l1_shape_map_against_bvls(per_source):
    """Per-shape L1 weights ``c_jk`` (``l1_scale``) against SciPy's bounded least squares, as the
    plain L1 fit above: the shift of the right-hand side is then ``z = Tᵀ(T Tᵀ)⁻¹ ½ l1 ‖s‖² c_j``.
    A weight of 0 frees a shape from the L1 term, a large one leaves it out (exactly 0); all ones
    is the plain L1 fit."""
    rng = np.random.default_rng(11)
    target = rng.normal(size=(8, 15, 3))
    source = rng.normal(size=(4, 15, 3))
    c = rng.uniform(0.0, 3.0, (4, 8)) if per_source else rng.uniform(0.0, 3.0, 8)
    c[..., 2] = 0.0
    c[..., 5] = 1e6
    l1 = 0.3
    M = shape_map(source, target, 0.0, 1.0, ridge=0.0, l1=l1, l1_scale=c)
    T = target.reshape(8, -1)
    G = T @ T.T
    A = np.vstack([T.T, np.sqrt(1e-9 * np.linalg.eigvalsh(G)[-1]) * np.eye(8)])
    for j in range(4):
        s = source[j].ravel()
        cj = c[j] if per_source else c
        z = T.T @ np.linalg.solve(G, 0.5 * l1 * (s @ s) * cj)
        ref = lsq_linear(A, np.concatenate([s - z, np.zeros(8)]), bounds=(0, 1), method="bvls", tol=1e-12).x
        np.testing.assert_allclose(M[:, j], ref, atol=1e-7)
    assert (M[5] == 0).all()
    np.testing.assert_allclose(shape_map(source, target, 0.0, 1.0, ridge=0.0, l1=l1, l1_scale=np.ones(8)),
                               shape_map(source, target, 0.0, 1.0, ridge=0.0, l1=l1), atol=1e-12)
    with pytest.raises(ValueError, match="l1_scale"):
        shape_map(source, target, l1=l1, l1_scale=np.ones(7))
    with pytest.raises(ValueError, match="l1_scale"):
        shape_map(source, target, l1=l1, l1_scale=-np.ones(8))

def _decoys(rng, K=8, M=300, markers=12):
    """Target shapes and decoys that agree with the source at a few 'markers' but not elsewhere.

    ``target`` (2K, M, 3): K true shapes (localised bumps) then K decoys; ``source`` (K, M, 3) the
    true shapes permuted and re-sculpted (turned 20°, scaled); decoy ``K + j`` equals source shape
    ``j`` at the markers exactly and moves another patch of the face elsewhere — at the markers
    each source shape's best match is a decoy, over the whole face its true shape."""
    true = _localised_shapes(rng, K, M)
    perm = rng.permutation(K)
    source = _resculpted(rng, true, perm, degrees=20.0)
    mk = rng.choice(M, markers, replace=False)
    decoys = _localised_shapes(rng, K, M) * np.linalg.norm(source, axis=(1, 2))[:, None, None] / np.sqrt(M / 8)
    decoys[:, mk] = source[:, mk]
    return np.concatenate([true, decoys]), source, perm, mk


def test_dense_points_recover_what_markers_cannot():
    """Hidden names: over every point the matching and the sparse map find each source shape's
    true target shape; at the 'markers' alone the decoys (equal there) win."""
    rng = np.random.default_rng(21)
    target, source, perm, mk = _decoys(rng)
    K = len(source)
    dense = match_shapes(source, target)
    assert np.array_equal(dense.target, perm)
    at_markers = match_shapes(source[:, mk], target[:, mk])
    assert (at_markers.target != perm).sum() >= K // 2 and (at_markers.target >= K).sum() >= K // 2
    # the sparse map: each source shape carried mostly by its true shape over the face ...
    M = shape_map(source, target, l1=SPARSE_L1, ridge=0.0)
    assert np.array_equal(M.argmax(0), perm)
    # ... by its decoy at the markers
    Mm = shape_map(source[:, mk], target[:, mk], l1=SPARSE_L1, ridge=0.0)
    assert (Mm.argmax(0) == np.arange(K) + K).sum() >= K // 2
    # the whole-take mapping drives the true shapes, within the bounds
    Ws = rng.uniform(0, 1, (40, K))
    W = mapped_weights(M, Ws)
    assert W.shape == (40, 2 * K) and W.min() >= 0 and W.max() <= 1
    assert W[:, perm].sum() > 5 * W[:, K:].sum()


def test_sparse_map_errors_name_the_argument():
    with pytest.raises(ValueError, match="l1"):
        shape_map(np.zeros((2, 4, 3)), np.ones((3, 4, 3)), l1=-1.0)
    with pytest.raises(ValueError, match="lower"):
        shape_map(np.ones((2, 4, 3)), np.ones((3, 4, 3)), lower=-0.5, l1=0.1)
    with pytest.raises(ValueError, match="source_weights"):
        mapped_weights(np.zeros((3, 2)), np.zeros((5, 4)))


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
def test_auto_without_names_maps_shapes_and_beats_plain_geometry(hidden_rocketbox):
    """S07 on Rocketbox with every shape renamed, 300 frames: auto says it maps the curves shape by
    shape over dense correspondence, carries the actor's jaw drop mostly by a jaw-opening shape of
    the character's, stays in [0, 1], and its face error is below the plain per-frame solve
    (bounded, rom, ridge 1e-2) and below the re-sculpted solve it ran before."""
    from core.geometry import face_vertices
    from core.io.gltf import read_rig
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
    assert "mapped shape by shape" in info["auto"] and "face points (dense correspondence)" in info["auto"]
    true_names = dict(zip(read_rig(hidden_rocketbox).names, rig.names))
    assert "jaw" in true_names[info["shape_matches"]["jawOpen"]].lower()
    W, W0 = np.asarray(auto["synthesize"]["weights"]), np.asarray(plain["synthesize"]["weights"])
    assert W.min() >= 0 and W.max() <= 1
    err = float(np.nanmean(vertex_errors(rig.deltas, W, Wt, face, ok)[0]))
    err0 = float(np.nanmean(vertex_errors(rig.deltas, W0, Wt, face, ok)[0]))
    W1 = np.zeros_like(W)
    W1[:, np.asarray(inputs["shapes"]["shape_index"])] = W1s
    err1 = float(np.nanmean(vertex_errors(rig.deltas, W1, Wt, face, ok)[0]))
    assert err < 0.9 * err0 and err < err1, (err, err0, err1)


def _jaw_face(seed=0):
    """Points of a face (x across, y up, z forward, metres): a jaw below y = 0 and the rest above."""
    rng = np.random.default_rng(seed)
    P = np.column_stack([rng.uniform(-0.06, 0.06, 600), rng.uniform(-0.08, 0.08, 600), rng.uniform(0.0, 0.04, 600)])
    return P, P[:, 1] < 0


def _turn(P, jaw, pivot, degrees):
    d = np.zeros_like(P)
    R = Rotation.from_rotvec([np.radians(degrees), 0, 0])
    d[jaw] = R.apply(P[jaw] - pivot) + pivot - P[jaw]
    return d


def test_rigid_motion_recovers_rotation_and_translation():
    P, jaw = _jaw_face()
    rv, _ = rigid_motion(P, _turn(P, jaw, np.array([0, 0.02, -0.08]), 9.0))
    assert np.degrees(rv) == pytest.approx([9.0, 0, 0], abs=1e-6)
    d = np.where(jaw[:, None], [0, 0, 0.006], 0.0)
    rv, tr = rigid_motion(P, d)
    assert np.linalg.norm(rv) < 1e-9 and tr == pytest.approx([0, 0, 0.006])
    assert np.all(rigid_motion(P, np.zeros_like(P))[0] == 0)


def test_jaw_mapped_by_its_angle_where_the_displacement_fit_misjudges_it():
    """The actor's jaw turns 8° about a pivot above and behind the chin (the chin moves back as much
    as down); the character's turns 15° per unit about a pivot level with the chin (straight down).
    The sparse displacement map takes the jaw at another amount (it fits the chin's path, not the
    turn); the rescaled one turns it by the actor's 8° (weight 8/15). A brow shape is not a jaw shape
    and its column is unchanged; a jaw slide is mapped by its translation times the faces' size
    ratio. (The whole column is scaled: a shape the map added to make up the chin's path would be
    scaled with it — on the sample the jaw's column is one shape.)"""
    P, jaw = _jaw_face()
    brow = np.where((P[:, 1] > 0.04)[:, None], [0, 0.004, 0], 0.0)
    src = np.stack([_turn(P, jaw, np.array([0, 0.05, -0.05]), 8.0), brow, np.where(jaw[:, None], [0, 0, 0.006], 0.0)])
    Pt = 0.8 * P  # a smaller character: the same points, 0.8 the size
    tgt = np.stack([_turn(Pt, jaw, np.array([0, -0.04, -0.09]), 15.0), 0.5 * brow, np.where(jaw[:, None], [0, 0, 0.008], 0.0)])
    assert list(jaw_shapes(P, src)) == [True, False, True]
    M0 = shape_map(src, tgt, ridge=0.0, l1=SPARSE_L1)
    M, scales = jaw_rescaled_map(M0, P, src, Pt, tgt)
    assert abs(M0[0, 0] - 8 / 15) > 0.05  # the displacement fit misjudges the jaw ...
    assert M[0, 0] == pytest.approx(8 / 15, abs=0.02)  # ... the angle does not
    assert np.array_equal(M[:, 1], M0[:, 1]) and scales[1] == 1.0
    assert M[2, 2] == pytest.approx(0.8 * 0.006 / 0.008, abs=0.02)  # the slide: 6 mm × 0.8 on an 8 mm shape
    truth = np.array([8 / 15, 0, 0.6])
    w = np.array([[1.0, 0.0, 1.0]])
    assert np.abs(mapped_weights(M, w)[0] - truth).sum() < np.abs(mapped_weights(M0, w)[0] - truth).sum()
    with pytest.raises(ValueError, match="shape_map_"):
        jaw_rescaled_map(M0[:, :2], P, src, Pt, tgt)
