"""Xu 2014 end to end: detail transfer (eq. 16, 5), the whole pipeline on real data, and the
§3 registration, against per-frame references."""

import numpy as np
import pytest

from core.io.layout import read_layout
from core.io.livelink import read_livelink
from core.names import NameMap
from core.transfer import (TransferSettings, feature_lines_near, line_edges, naive_transfer, register, seam_loops, loops_near,
                           transfer_sequence)
from core.transfer._mesh import weld
from tests.conftest import LAYOUTS, PERFORMANCES


@pytest.fixture(scope="module")
def take(ict):
    perf = read_livelink(PERFORMANCES / "livelinkface_take_s07.csv")
    G = NameMap.automatic(perf.names, ict.names).matrix(perf.names, ict.names)
    return np.nan_to_num(perf.data) @ G.T  # (T, K) ICT weights


@pytest.fixture(scope="module")
def ict_rocketbox(ict, rocketbox):
    """ICT welded + Rocketbox resampled in ICT's topology (landmark similarity + projection)."""
    li = read_layout(LAYOUTS / "ict_facekit.json", ict)
    lr = read_layout(LAYOUTS / "rocketbox_female_adult_02.json", rocketbox)
    names = [n for n in li.names if n in lr.names]
    src = li.vertices[[li.names.index(n) for n in names], 0]
    tgt = lr.select(names).points(rocketbox.neutral)
    return src, tgt


def _rms_mm(a, b):
    return float(np.sqrt(((a - b) ** 2).sum(-1).mean()) * 1000)


@pytest.mark.parametrize("rotate", [False, True])
def test_identity_transfer_reproduces_the_source_sequence(ict, take, rotate):
    """Target = source: DT is exact on the same mesh, R_v = I, so eq. 5 must give S_t back."""
    seq = ict.evaluate(take[100:900:100])
    res = transfer_sequence(ict.neutral, ict.faces, seq, ict.neutral, ict.faces,
                            eps=0, max_bases=len(seq), candidates=len(seq), rotate_reference_details=rotate,
                            detail_screening=0.0)
    out = res.sequence()
    for t in range(len(seq)):
        off = (out[t] - seq[t]).mean(0)  # the gauge: one translation per frame at most
        assert np.abs(out[t] - seq[t] - off).max() < 1e-5 * ict.size
        assert np.linalg.norm(off) < 1e-4 * ict.size
    # large scale alone misses the details, and the details are not nothing
    assert _rms_mm(res.large_scale() + (res.neutral - res.target_smooth_ref), seq) > 10 * _rms_mm(out, seq)


def test_rigid_rotation_moves_details_with_the_face(ict):
    """A rigidly rotated source frame: coating read in local frames is unchanged (D̂ = 0), so
    the target frame is the rotated target (eq. 16's R_v; §3 "invariant" claim)."""
    from scipy.spatial.transform import Rotation

    c = ict.neutral.mean(0)
    Rs = [Rotation.from_euler("xyz", a, degrees=True).as_matrix() for a in ([8, 0, 0], [0, 15, 5])]
    seq = np.stack([(ict.neutral - c) @ R.T + c for R in Rs])
    T0 = ict.neutral * [1.1, 0.95, 1.05]
    res = transfer_sequence(ict.neutral, ict.faces, seq, T0, ict.faces, eps=0, max_bases=2, candidates=2,
                            rotate_reference_details=True, detail_screening=0.0)
    out = res.sequence()
    for t, R in enumerate(Rs):
        want = T0 @ R.T
        d = out[t] - want
        assert np.abs(d - d.mean(0)).max() < 2e-3 * ict.size
        # without the frame rotation (details added unrotated) it would be clearly worse
        flat = res.large_scale(t)[0] + (T0 - res.target_smooth_ref)
        df = flat - want
        assert np.abs(df - df.mean(0)).max() > 2 * np.abs(d - d.mean(0)).max()


def test_detail_gain_scales_only_the_detail_motion(ict, take):
    seq = ict.evaluate(take[200:500:100])
    kw = dict(eps=0, max_bases=3, candidates=3)
    z, a, b = (transfer_sequence(ict.neutral, ict.faces, seq, ict.neutral * 1.2, ict.faces, detail_gain=g, **kw)
               for g in (0.0, 1.0, 2.0))
    assert np.allclose(a.weights, b.weights) and np.allclose(a.deltas, b.deltas)
    # details = rotated target reference coating + g * transferred motion (eq. 5): linear in g
    motion = a.details - z.details
    assert np.abs(motion).max() > 1e-5 * ict.size
    assert np.abs(b.details - a.details - motion).max() < 1e-3 * np.abs(motion).max()


def test_ict_to_rocketbox_close_to_naive_per_frame_transfer(ict, rocketbox, take, ict_rocketbox):
    src, tgt = ict_rocketbox
    frames = take[:600:15]  # 40 frames of the real take
    seq = ict.evaluate(frames)
    settings = TransferSettings(landmarks=(src, tgt), icp=False, max_bases=12)
    res = transfer_sequence(ict.neutral, ict.faces, seq, rocketbox.neutral, rocketbox.faces, settings)
    assert res.registration is not None
    rep = res.registration.report
    assert rep["landmark_residual_mm_mean"] < 15 and rep["projected_fraction"] > 0.5
    assert res.weights.shape == (len(seq), res.n_bases) and (res.weights >= 0).all()
    assert res.selection_errors[-1] <= max(settings.eps, res.selection_errors.min())
    # naive per-frame DT onto the same resampled target (unsmoothed, no bases): the reference
    naive = naive_transfer(ict.neutral, res.neutral, ict.faces, seq[::8])
    ours = res.sequence(slice(None, None, 8))
    motion = [_rms_mm(n, res.neutral) for n in naive]
    err = [_rms_mm(o, n) for o, n in zip(ours, naive)]
    assert max(motion) > 0.3  # the frames really move (mm RMS over the head)
    for e, m in zip(err, motion):
        assert e < 0.25 * m, (err, motion)
    # the unscreened eq. 5 lets the rotated coating (eq. 16) drift the whole head
    plain = transfer_sequence(ict.neutral, ict.faces, seq[::8], res.neutral, ict.faces, max_bases=12, detail_screening=0.0)
    assert _rms_mm(plain.sequence(), naive) > 2 * np.mean(err)
    # the rig form evaluates to the large-scale + neutral part of the sequence
    rig = res.to_rig()
    assert np.allclose(rig.evaluate(res.weights[:3]) + res.details[:3], res.sequence(slice(0, 3)))


def test_feature_lines_from_seams_near_markers(ict):
    wi, rep, Fw = weld(ict.neutral, ict.faces)
    li = read_layout(LAYOUTS / "ict_facekit.json", ict)
    loops = seam_loops(ict.faces, wi, Fw)
    pts = li.select(["Leye_Up", "Reye_Up", "Mouth_Up", "Mouth_Down"]).points(ict.neutral)
    near = loops_near(loops, ict.neutral[rep], pts, 0.025 * ict.size)
    sizes = sorted(len(l) for l in near)
    assert len(near) == 3 and sizes[-1] > sizes[0]  # two eyelid rims + the lip line
    assert len(line_edges(near)) == sum(sizes)
    lines = feature_lines_near(ict.neutral, ict.faces, pts, 0.025 * ict.size)
    assert sorted(len(l) for l in lines) == sizes and all(l.max() < ict.n_vertices for l in lines)


def test_other_topology_needs_landmarks(ict, rocketbox):
    with pytest.raises(ValueError, match="landmarks"):
        transfer_sequence(ict.neutral, ict.faces, ict.neutral[None], rocketbox.neutral, rocketbox.faces)
    with pytest.raises(ValueError, match="source_seq"):
        transfer_sequence(ict.neutral, ict.faces, ict.neutral, ict.neutral, ict.faces)
    with pytest.raises(ValueError, match="laplacian"):
        TransferSettings(laplacian="mean")


@pytest.mark.slow
def test_nonrigid_icp_registration_residual(ict, rocketbox, ict_rocketbox):
    src, tgt = ict_rocketbox
    wi, rep, Fw = weld(ict.neutral, ict.faces)
    coarse = register(ict.neutral[rep], Fw, rocketbox.neutral, rocketbox.faces, wi[src], tgt, icp=False)
    reg = register(ict.neutral[rep], Fw, rocketbox.neutral, rocketbox.faces, wi[src], tgt)
    assert reg.report["surface_distance_mm_median"] < 0.5 * coarse.report["surface_distance_mm_median"]
    assert reg.report["surface_distance_mm_median"] < 1.0
    assert reg.report["landmark_residual_mm_mean"] < coarse.report["landmark_residual_mm_mean"]
    assert reg.report["projected_fraction"] > 0.95
