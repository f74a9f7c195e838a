"""Xu 2014 end to end: detail transfer (eq. 16, 5), the whole pipeline on real data, and the
§3 registration, against per-frame references."""

import numpy as np
import pytest

from core.io.layout import read_layout
from core.io.livelink import read_livelink
from core.names import NameMap
from core.transfer import (TransferSettings, feature_lines_near, line_edges, naive_transfer, register, seam_loops, loops_near,
                           transfer_sequence)
from core.transfer import DetailTransfer, FactoredSequence, PoissonReconstructor, TaubinFilter, factor_sequence
from core.transfer import details
from core.geometry import first_neighbour, vertex_face_incidence, vertex_frames, weld_vertices
from core.transfer.details import _FramedSequence
from tests.conftest import LAYOUTS, PERFORMANCES


def local_frames(P, F):
    """(V, 3, 3) frames with columns [t, b, n]: world = frame @ local."""
    return np.stack(vertex_frames(P, F), axis=-1)


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
@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
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
    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    coarse = register(ict.neutral[rep], Fw, rocketbox.neutral, rocketbox.faces, wi[src], tgt, icp=False)
    reg = register(ict.neutral[rep], Fw, rocketbox.neutral, rocketbox.faces, wi[src], tgt)
    assert reg.report["surface_distance_mm_median"] < 0.5 * coarse.report["surface_distance_mm_median"]
    assert reg.report["surface_distance_mm_median"] < 1.0
    assert reg.report["landmark_residual_mm_mean"] < coarse.report["landmark_residual_mm_mean"]
    # the snap onto the surface skips vertices whose move would fold a triangle (95.9 % projected
    # when measured); 227 of 28,068 triangles stay folded (474 before that rule), mostly inside the
    # mouth bag and eye sockets
    assert reg.report["projected_fraction"] > 0.93
    assert reg.report["flipped_triangles"] < 0.015 * len(Fw)


# -- detail stage (eq. 16, 5): the batched implementation against the formulas frame by frame --

@pytest.fixture(scope="module")
def tiger_detail_case(tiger):
    """Welded tiger: a factored smoothed source, its coating, a deformed target with its own
    factored smoothed frames (3 bases), all as transfer_sequence builds them."""
    wi, rep, Fw = weld_vertices(tiger.neutral, tiger.faces)
    N = tiger.neutral[rep]
    V = len(N)
    rng = np.random.default_rng(7)
    seq = tiger.evaluate(rng.random((7, tiger.n_shapes)))[:, rep]
    fac = factor_sequence(seq, 1e-9, base=N)
    filt = TaubinFilter(Fw, V, 10)
    smooth = fac.map_basis(filt.apply)
    size = tiger.size
    T0 = N * [1.1, 0.9, 1.05] + 0.01 * size * np.sin(N / (0.2 * size))  # not a similarity of N
    Tb0 = filt.apply(T0)
    deltas = filt.apply(tiger.deltas[:3, rep] * [1.2, 0.8, 1.0])
    tgt = FactoredSequence(Tb0, rng.random((7, 3)), deltas, 0.0)
    return dict(Fw=Fw, N=N, fac=fac, smooth=smooth, T0=T0, Tb0=Tb0, tgt=tgt, wi=wi, size=size)


def _coat(P, fac, smooth):
    return FactoredSequence(np.asarray(P.L @ (fac.base - smooth.base)), fac.coeffs,
                            np.stack([np.asarray(P.L @ (q - qb)) for q, qb in zip(fac.basis, smooth.basis)]),
                            fac.residual_rms)


def _has_frame(P, F):
    """(V,) bool: the vertex's normal is more than rounding noise,
    |Σ N_f| >= NORMAL_CANCEL Σ |e1_f| |e2_f| (N_f = e1_f × e2_f)."""
    from core.geometry import face_cross

    N = face_cross(P, F)
    e1, e2 = P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]]
    inc = vertex_face_incidence(F, len(P))
    bound = inc @ (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
    return np.linalg.norm(inc @ N, axis=1) >= details.NORMAL_CANCEL * bound


def _reference_details(det, smooth, coat, tgt):
    """Eq. 16 and 5 as written, one frame at a time in float64: frames from
    geometry.vertex_frames, R_v = F'_t F_t^T per vertex (I where a side has no frame,
    :func:`_has_frame`), and the per-frame reconstruction PoissonReconstructor.displacement
    (checked against dense solves in test_transfer_decompose)."""
    F = det.faces
    y0 = det.ref_displacement
    F0 = local_frames(smooth.base, F)
    Ft0 = local_frames(tgt.base, F)
    out = []
    for t in range(smooth.n_frames):
        Fs = local_frames(smooth.frames(t)[0], F)
        Ft = local_frames(tgt.frames(t)[0], F)
        none = ~(_has_frame(smooth.frames(t)[0], F) & _has_frame(tgt.frames(t)[0], F))
        G0, Gt0 = F0.copy(), Ft0.copy()
        Fs[none] = Ft[none] = G0[none] = Gt0[none] = np.eye(3)
        xi = coat.frames(t)[0]
        if det.rotate_reference:
            local = np.einsum("vji,vj->vi", Gt0, det.That0) + det.gain * (
                np.einsum("vji,vj->vi", Fs, xi) - np.einsum("vji,vj->vi", G0, det.xi0))
            c = np.einsum("vij,vj->vi", Ft, local)
        else:
            c = det.That0 + det.gain * np.einsum("vij,vkj,vk->vi", Ft, Fs, xi - det.xi0)
        out.append(det.poisson.displacement(c, det.mean, y0))
    return np.stack(out), y0


@pytest.mark.parametrize("rotate,screening", [(False, 0.01), (True, 0.01), (False, 0.0), (True, 0.0)])
def test_detail_displacements_match_per_frame_reference(tiger_detail_case, rotate, screening, monkeypatch):
    c = tiger_detail_case
    P = PoissonReconstructor(c["Fw"], len(c["N"]), screening=screening)
    coat = _coat(P, c["fac"], c["smooth"])
    det = DetailTransfer(c["Fw"], P, c["smooth"].base, coat.base, c["T0"], c["Tb0"], 1.3, rotate)
    ref, y0 = _reference_details(det, c["smooth"], coat, c["tgt"])
    motion = np.abs(ref - y0).max()
    assert motion > 1e-4 * c["size"]  # the details really move
    # production precision: float32 frames, rotation and solve. The frames are computed in
    # float64 and rounded once (they were float32 throughout before, where random weights on
    # every tiger shape turn some coarse-mesh frames nearly degenerate: the worst vertex was
    # then ~2e-4 of the motion off, and 8e-4 with edges rounded another way); now ~5e-7
    ours = det.displacements(c["smooth"], coat, c["tgt"], 7, chunk=3)  # 3 + 3 + 1 frames
    assert ours.dtype == np.float32 and ours.shape == ref.shape
    err = np.abs(ours - ref).max(axis=(0, 2))
    assert err.max() < 5e-6 * motion and np.percentile(err, 99) < 2e-6 * motion
    # without the rotation R_v (eq. 16) the answer would be far off: the test can fail
    if not rotate:
        flat = np.stack([P.displacement(det.That0 + det.gain * (coat.frames(t)[0] - det.xi0), det.mean, y0)
                         for t in range(7)])
        assert np.abs(flat - ref).max() > 100 * err.max()

    # the algorithm itself, in float64 working precision: equal to the formulas to rounding,
    # for a factored and a callable target, relative output, unwelded rows, any chunking
    monkeypatch.setattr(details, "_WORK", np.float64)
    det = DetailTransfer(c["Fw"], P, c["smooth"].base, coat.base, c["T0"], c["Tb0"], 1.3, rotate)
    tol = 1e-9 * motion
    ours = det.displacements(c["smooth"], coat, c["tgt"], 7, chunk=3, dtype=np.float64)
    assert np.abs(ours - ref).max() < tol
    rel = det.displacements(c["smooth"], coat, c["tgt"], 7, chunk=4, dtype=np.float64, relative=True, vertices=c["wi"])
    assert rel.shape == (7, len(c["wi"]), 3) and np.abs(rel - (ref - y0)[:, c["wi"]]).max() < tol
    call = det.displacements(c["smooth"], coat, lambda idx: c["tgt"].frames(idx), 7, chunk=7, dtype=np.float64)
    assert np.abs(call - ref).max() < tol
    # the public per-chunk coatings (eq. 5's right-hand side minus L T̄_t)
    cs = det.coatings(c["smooth"].frames(slice(0, 2)), coat.frames(slice(0, 2)), c["tgt"].frames(slice(0, 2)))
    Fs = local_frames(c["smooth"].frames(1)[0], det.faces)
    Ft = local_frames(c["tgt"].frames(1)[0], det.faces)
    if rotate:
        local = np.einsum("vji,vj->vi", local_frames(c["tgt"].base, det.faces), det.That0) + det.gain * (
            np.einsum("vji,vj->vi", Fs, coat.frames(1)[0]) - np.einsum("vji,vj->vi", local_frames(c["smooth"].base, det.faces), det.xi0))
        want = np.einsum("vij,vj->vi", Ft, local)
    else:
        want = det.That0 + det.gain * np.einsum("vij,vkj,vk->vi", Ft, Fs, coat.frames(1)[0] - det.xi0)
    assert np.abs(cs[1] - want).max() < 1e-9 * np.abs(want).max()


def test_detail_chunks_on_two_cores_are_bit_identical_to_one(tiger_detail_case, monkeypatch):
    """With a second core a worker solves one chunk while this thread forms the next one's
    right-hand sides (one compiled call, two alternating workspaces); every chunk lands in its
    own frames, in the same floats, with progress in order."""
    c = tiger_detail_case
    P = PoissonReconstructor(c["Fw"], len(c["N"]), screening=0.01)
    coat = _coat(P, c["fac"], c["smooth"])
    runs = {}
    for cores in (1, 2):
        monkeypatch.setattr(details, "free_cores", lambda: cores)
        det = DetailTransfer(c["Fw"], P, c["smooth"].base, coat.base, c["T0"], c["Tb0"], 1.3)
        calls = []
        runs[cores] = det.displacements(c["smooth"], coat, c["tgt"], 7, chunk=2, relative=True, vertices=c["wi"],
                                        progress=lambda f, m: calls.append(m))
        assert calls == [f"fine details: {n}/7 frames" for n in (2, 4, 6, 7)]
        # a callable target takes the call-by-call path (no compiled chunk): the same pipeline
        runs[cores, "callable"] = det.displacements(c["smooth"], coat, lambda idx: c["tgt"].frames(idx), 7, chunk=2)
    np.testing.assert_array_equal(runs[1], runs[2])
    np.testing.assert_array_equal(runs[1, "callable"], runs[2, "callable"])
    # the compiled chunk (target frames rotating as they are made, not stored) is the
    # call-by-call path's arithmetic, rounded the same way
    for rotate in (False, True):
        det = DetailTransfer(c["Fw"], P, c["smooth"].base, coat.base, c["T0"], c["Tb0"], 1.3, rotate)
        fused = det.displacements(c["smooth"], coat, c["tgt"], 7, chunk=3)
        np.testing.assert_array_equal(fused, det.displacements(c["smooth"], coat, lambda idx: c["tgt"].frames(idx), 7, chunk=3))
    assert np.abs(runs[1]).max() > 1e-4 * c["size"]  # the details move


def test_transfer_on_two_cores_is_bit_identical_to_one(tiger, monkeypatch):
    """With a second core, transfer_sequence builds the eq. 9 system, the detail factorisation
    and the output pages in a second thread beside the decomposition (and the Taubin blocks
    and detail chunks run on two threads): the same floats as one core, and the system built
    beside is the one used (its references are the decomposition's, bit for bit)."""
    import core.transfer as ct
    from core.transfer import decompose

    K = tiger.n_shapes
    t = np.arange(40)
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (3 + np.arange(K))), 0, 1)
    target = tiger.neutral * [1.1, 0.9, 1.05]
    built = []
    real = ct.transfer_system
    monkeypatch.setattr(ct, "transfer_system", lambda *a: built.append(real(*a)) or built[-1])
    runs = {}
    for cores in (1, 2):
        for m in (ct, details, decompose):
            monkeypatch.setattr(m, "free_cores", lambda: cores)
        runs[cores] = ct.transfer_sequence(tiger.neutral, tiger.faces, tiger.evaluate(W), target, tiger.faces,
                                           max_bases=4, chunk=16)
    assert len(built) == 1 and runs[2].system is built[0]  # one core builds it inside transfer_bases
    a, b = runs[1], runs[2]
    for name in ("neutral", "deltas", "weights", "details", "frames", "target_smooth_ref", "source_bases"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert np.abs(a.details).max() > 1e-5 * tiger.size  # the details move


def test_screened_detail_reference_is_a_dense_solve(tiger_detail_case, monkeypatch):
    """The batched details, for one frame, against np.linalg.solve of eq. 5 screened."""
    monkeypatch.setattr(details, "_WORK", np.float64)
    c = tiger_detail_case
    P = PoissonReconstructor(c["Fw"], len(c["N"]), screening=0.01)
    coat = _coat(P, c["fac"], c["smooth"])
    det = DetailTransfer(c["Fw"], P, c["smooth"].base, coat.base, c["T0"], c["Tb0"], 1.0)
    ours = det.displacements(c["smooth"], coat, c["tgt"], 2, dtype=np.float64)
    F = det.faces
    Fs, Ft = local_frames(c["smooth"].frames(1)[0], F), local_frames(c["tgt"].frames(1)[0], F)
    cc = det.That0 + np.einsum("vij,vkj,vk->vi", Ft, Fs, coat.frames(1)[0] - det.xi0)
    A = P.L.toarray() + P.eps * np.eye(P.n)
    dense = np.linalg.solve(A, cc + P.eps * det.ref_displacement)
    assert np.abs(ours[1] - dense).max() < 1e-9 * np.abs(dense - det.ref_displacement).max()


@pytest.mark.parametrize("factored", [True, False])
@pytest.mark.parametrize("work", [np.float64, np.float32])
def test_batched_frames_equal_vertex_frames(tiger_detail_case, factored, work, monkeypatch):
    monkeypatch.setattr(details, "_WORK", work)
    c = tiger_detail_case
    F = np.asarray(c["Fw"])
    V = len(c["N"])
    nb = first_neighbour(F, V)
    seq = c["smooth"] if factored else (lambda idx: c["smooth"].frames(idx))
    fs = _FramedSequence(seq, F, np.where(nb < 0, np.arange(V), nb))
    got = fs.frames(slice(2, 6))  # (3, V, t) each
    for i, t in enumerate(range(2, 6)):
        want = vertex_frames(c["smooth"].frames(t)[0], F)
        for g, w in zip(got, want):
            dev = np.abs(g[:, :, i].T - w).max(axis=1)
            assert g.dtype == work
            if work == np.float64:
                assert dev.max() < 1e-9
            else:  # float32: computed in float64 from float64 positions and rounded once, so
                # within rounding of the unit vectors everywhere (before, in float32 from float32
                # edges, up to 1e-4 off where the tangent edge is near the normal)
                assert dev.max() < 1e-7


def test_batched_frames_fall_back_where_the_tangent_edge_vanishes():
    """A vertex whose first neighbour nearly coincides with it: vertex_frames' axis fallback."""
    import trimesh

    g = trimesh.creation.box().subdivide().subdivide()
    V = np.array(g.vertices, dtype=np.float64)
    F = np.asarray(g.faces, dtype=np.int64)
    nb = first_neighbour(F, len(V))
    V[nb[0]] = V[0] + 1e-9 * (V[nb[0]] - V[0])  # the edge 0 -> nb[0] shrinks to nothing
    fac = FactoredSequence(V, np.zeros((1, 0)), np.zeros((0, len(V), 3)), 0.0)
    fs = _FramedSequence(fac, F, np.where(nb < 0, np.arange(len(V)), nb))
    got = fs.frames(slice(0, 1))
    want = vertex_frames(V, F)
    n0 = want[2][0]
    axis = np.array([1.0, 0, 0]) if abs(n0[0]) < 0.9 else np.array([0, 1.0, 0])
    fallback = axis - (axis @ n0) * n0
    assert np.allclose(want[0][0], fallback / np.linalg.norm(fallback))  # the fallback did happen
    for gv, w in zip(got, want):
        assert np.abs(gv[:, :, 0].T - w).max() < 1e-5


def test_static_source_transfers_no_motion(tiger):
    """A sequence that never leaves the reference factors to rank 0: no bases, zero details."""
    res = transfer_sequence(tiger.neutral, tiger.faces, np.repeat(tiger.neutral[None], 3, 0),
                            tiger.neutral * [1.1, 0.9, 1.0], tiger.faces)
    assert res.n_bases == 0 and res.weights.shape == (3, 0)
    assert res.details.shape == (3, tiger.n_vertices, 3) and np.abs(res.details).max() < 1e-12 * tiger.size


def test_progress_is_reported_per_stage_and_per_detail_chunk(tiger):
    t = np.arange(30)
    K = tiger.n_shapes
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (4 + np.arange(K))), 0, 1)
    calls = []
    transfer_sequence(tiger.neutral, tiger.faces, tiger.evaluate(W), tiger.neutral * 1.1, tiger.faces, max_bases=4,
                      chunk=8, progress=lambda f, m: calls.append((f, m)))
    fr = [f for f, _ in calls]
    assert fr == sorted(fr) and fr[-1] == 1.0 and 0 <= fr[0] < 0.5
    details = [m for _, m in calls if m.startswith("fine details")]
    assert details == [f"fine details: {n}/30 frames" for n in (8, 16, 24, 30)]
    assert any("basis selection" in m for _, m in calls) and any("deformation transfer" in m for _, m in calls)


def test_default_feature_lines_are_the_eye_and_mouth_rims(ict, tiger):
    from core.io.layout import read_layout
    from core.transfer.performance import default_feature_lines

    lay = read_layout(LAYOUTS / "ict_facekit.json", ict)
    lines = default_feature_lines(ict, lay)
    assert len(lines) == 3  # both eyes and the mouth, nothing else
    centres = np.array([ict.neutral[ln].mean(0) for ln in lines])
    marks = {n: lay.select([n]).points(ict.neutral)[0] for n in ("Leye_Up", "Reye_Up", "Mouth_Up")}
    for p in marks.values():
        assert np.linalg.norm(centres - p, axis=1).min() < 0.02
    assert default_feature_lines(ict, None) is None
    assert default_feature_lines(ict, lay.select(["ForeHead_M", "Chin", "NoseTop"])) is None


def test_details_on_flattened_thin_parts_do_not_turn_at_random(tiger):
    """The tiger's whiskers flatten under 40 Taubin iterations into double-sided sheets whose
    vertex normals are rounding noise: float32-rounded input (7e-9 m off) moved the details by
    10.6 mm there (largest detail 18 mm) through randomly turned frames. Vertices whose face
    normals cancel get no rotation now; 0.4 mm is left (tangent edges along the normal)."""
    from dense_case import STRETCH, tiger_weights

    W = np.vstack([np.zeros((1, tiger.n_shapes)), tiger_weights(tiger.n_shapes, 29)])
    seq = tiger.evaluate(W)
    seq32 = seq.astype(np.float32).astype(np.float64)
    T0 = tiger.neutral * np.asarray(STRETCH)
    a = transfer_sequence(seq[0], tiger.faces, seq, T0, tiger.faces)
    b = transfer_sequence(seq32[0], tiger.faces, seq32, T0, tiger.faces)
    assert np.abs(a.deltas - b.deltas).max() < 1e-7
    diff = np.linalg.norm(a.details - b.details, axis=-1).max()
    assert np.linalg.norm(a.details, axis=-1).max() > 0.01 and diff < 1e-3
