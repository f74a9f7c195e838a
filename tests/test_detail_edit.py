"""Fine-scale detail editing (core/transfer/detail_edit.py, Xu et al. 2014 §5.2 eq. 17-21).

Geometry (selection, copy-paste, reshape) is checked on a flat grid where the answer is known
exactly; the propagation + Poisson reconstruction against a slow direct solve, on the grid and
on a real transfer (tiger, same topology)."""

from __future__ import annotations

import numpy as np
import pytest

from core.transfer import transfer_sequence
from core.transfer.detail_edit import DetailEditor, KeyEdit, detail_window, region_near_points

H = 1e-3  # grid spacing, metres


def grid(nx=40, ny=30):
    x, y = np.meshgrid(np.arange(nx) * H, np.arange(ny) * H, indexing="ij")
    P = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return P, F, idx


def vid(idx, i, j):
    return int(idx[i, j])


@pytest.fixture(scope="module")
def ridge():
    """A wrinkle: a z-ridge along y = 10 for x in [8, 28], growing and fading over 30 frames."""
    P, F, idx = grid()
    gx, gy = P[:, 0] / H, P[:, 1] / H
    shape = np.exp(-0.5 * (gy - 10) ** 2) * ((gx >= 8) & (gx <= 28))
    g = np.clip(1 - np.abs(np.arange(30) - 15) / 8.0, 0, None)  # active for t in (7, 23)
    D = np.zeros((30, len(P), 3))
    D[:, :, 2] = 1e-4 * g[:, None] * shape[None]
    return P, F, idx, D, g


def test_window_follows_the_coating_ratio(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    region = ed.select_curve([vid(idx, 10, 10), vid(idx, 25, 10)], 1.5 * H, 15)
    act = ed.activity(region)
    assert np.allclose(act / act[15], g / g[15], atol=1e-9)  # activity is linear in the details
    ts, te = ed.window(region, 15, mu=0.23)
    ok = np.flatnonzero(g / g[15] >= 0.23)
    assert (ts, te) == (ok.min(), ok.max())
    assert detail_window(act[:, None], [0], 15, 0.9) == (15, 15)


def test_selection_by_paint_and_curve(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    sel = ed.select_paint([vid(idx, 5, 5)], 1.01 * H)
    assert sorted(sel) == sorted([vid(idx, 5, 5), vid(idx, 4, 5), vid(idx, 6, 5), vid(idx, 5, 4), vid(idx, 5, 6)])
    cur = ed.select_curve([vid(idx, 10, 10), vid(idx, 20, 10)], 0.5 * H)
    assert sorted(cur) == sorted(vid(idx, i, 10) for i in range(10, 21))
    with pytest.raises(ValueError, match="paint at least one"):
        region_near_points(P, [], 1.0)
    with pytest.raises(ValueError, match="ids must lie"):
        ed.select_paint([10 ** 6], 1.0)


def test_scale_edit_and_propagation_match_the_direct_solve(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    region = ed.select_curve([vid(idx, 12, 10), vid(idx, 22, 10)], 2.5 * H, 15)
    e = ed.scale(region, 15, 0.0)
    assert e.kind == "scale" and e.frame == 15 and len(e.vertices) > len(region)  # the fall-off band
    res = ed.apply(e, window=(6, 24))
    ref = ed.apply_reference(e, (6, 24))
    ch, chr_ = res.details - D, ref - D
    assert np.abs(ch - chr_).max() < 1e-5 * np.abs(chr_).max()
    assert res.rank < 19 and res.window == (6, 24)
    assert np.array_equal(res.details[:6], D[:6].astype(np.float32)) and np.array_equal(res.details[25:], D[25:].astype(np.float32))
    # λ_e large: the key frame takes the edit: the region's details are (nearly) gone
    strong = ed.apply(e, window=(6, 24), lam_e=1e4)
    after = DetailEditor(F, P, strong.details)
    assert after.activity(region)[15] < 0.1 * ed.activity(region)[15]
    # default window: the μ rule on the selection
    assert ed.apply(e).window == ed.window(region, 15)
    # per frame: the same scaling in every frame of the window (faded over 3 frames at its
    # ends) — the details are gone in the whole window, not only near the key frame
    pf = ed.apply(e, window=(6, 24), propagation="per_frame")
    np.testing.assert_allclose(pf.details - D, ed.apply_reference(e, (6, 24), propagation="per_frame") - D,
                               atol=1e-5 * np.abs(pf.details - D).max())
    act = DetailEditor(F, P, pf.details).activity(region)
    before = ed.activity(region)
    assert np.all(act[10:21] < 0.1 * before[10:21]) and np.all(act[:6] == before[:6])
    assert np.all(DetailEditor(F, P, res.details).activity(region)[[10, 20]] > 0.5 * before[[10, 20]])  # eq. 18 does not
    with pytest.raises(ValueError, match="propagation"):
        ed.apply(e, window=(6, 24), propagation="spline")
    # factor 1 changes nothing
    assert np.array_equal(ed.apply(ed.scale(region, 15, 1.0), window=(6, 24)).details, D.astype(np.float32))


def test_copy_paste_on_a_grid_moves_and_rotates_the_details(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    src = np.array([vid(idx, i, j) for i in range(12, 17) for j in range(8, 13)])
    # 90° about +z: (i, j) around (14, 10) -> (30 - (j - 10), 20 + (i - 14)); the region and a
    # 2-ring band (feathered) go over
    e = ed.copy_paste(src, 15, anchor=vid(idx, 30, 20), angle=np.pi / 2, mode="add")
    dy = e.info["displacement"]
    ratios = []
    for i in range(10, 19):
        for j in range(6, 15):
            d = D[15, vid(idx, i, j), 2]
            if abs(d) > 1e-9 and not (12 <= i <= 16 and 8 <= j <= 12):
                ratios.append(dy[vid(idx, 30 - (j - 10), 20 + (i - 14)), 2] / d)
    # the band: feathered to 2/3 and 1/3 of the source's detail
    # the band: feathered to 2/3 and 1/3 of the source's detail (0 beyond it: the corners of
    # the 9x9 square that are 3 rings away across the triangulation's diagonals)
    r = np.round(ratios, 12)
    assert set(np.unique(r)) == {0.0, round(1 / 3, 12), round(2 / 3, 12)} and (r == 0).sum() <= 12
    inner = [vid(idx, 30 - (j - 10), 20 + (i - 14)) for i in range(12, 17) for j in range(8, 13)]
    np.testing.assert_allclose(dy[inner, 2], D[15, src, 2], atol=1e-15)
    assert e.info["pasted_vertices"] >= 81 - 8  # region + band (the band's corners depend on the diagonals)
    # the coating of the change is the edit, and reconstructing it gives the change back
    np.testing.assert_allclose(ed.poisson.solve(np.asarray(ed.A @ dy)), dy, atol=1e-12)
    # pasting a region onto itself (replace) changes nothing
    same = ed.copy_paste(src, 15, anchor=vid(idx, 14, 10), mode="replace")
    assert np.abs(same.info["displacement"]).max() < 1e-15 and np.abs(same.delta).max() < 1e-15
    # scale 2: the footprint grows about 4x
    big = ed.copy_paste(src, 15, anchor=vid(idx, 25, 15), scale=2.0, mode="add")
    assert 3.0 < big.info["pasted_vertices"] / e.info["pasted_vertices"] < 5.0
    # mirror: reflected across the plane through the anchor spanned by its normal (+z) and +y,
    # i.e. x -> -x about the anchor column: an asymmetric block lands reversed in x
    # (details with an x component that changes along x: a reflection must reverse both)
    D2 = D.copy()
    D2[:, :, 0] = D[:, :, 2] * (P[:, 0] / H - 8) / 10
    ed2 = DetailEditor(F, P, D2)
    blk = np.array([vid(idx, i, j) for i in range(7, 10) for j in range(8, 13)])  # the ridge's start, centre column 8
    mir = ed2.copy_paste(blk, 15, anchor=vid(idx, 30, 20), mode="add", mirror=True).info["displacement"]
    for i in range(7, 10):
        for j in range(8, 13):
            d = D2[15, vid(idx, i, j)]
            np.testing.assert_allclose(mir[vid(idx, 30 - (i - 8), 20 + (j - 10))], [-d[0], d[1], d[2]], atol=1e-15)
    assert np.abs(D2[15, blk, 2] - D2[15, blk[::-1], 2]).max() > 1e-5  # the block is not symmetric in x
    with pytest.raises(ValueError, match="mode"):
        ed.copy_paste(src, 15, anchor=0, mode="swap")
    with pytest.raises(ValueError, match="anchor"):
        ed.copy_paste(src, 15, anchor=-1)


def test_pasted_wrinkle_appears_at_the_key_frame(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    src = ed.select_curve([vid(idx, 12, 10), vid(idx, 20, 10)], 4.5 * H, 15)
    e = ed.copy_paste(src, 15, anchor=vid(idx, 20, 22), angle=0.0, mode="replace")
    res = ed.apply(e, window=(7, 23), lam_e=1e3)
    moved = res.details[15, :, 2]
    # the pasted ridge: along y = 22 near x = 20, shaped like the original along y = 10
    orig = np.array([D[15, vid(idx, i, 10), 2] for i in range(17, 24)])
    new = np.array([moved[vid(idx, i, 22)] for i in range(17, 24)])
    assert np.abs(new - orig).max() < 0.2 * orig.max()
    assert moved[vid(idx, 20, 26)] < 0.2 * orig.max()  # and not everywhere


def test_reshape_solves_eq17_and_moves_the_wrinkle(ridge):
    P, F, idx, D, g = ridge
    ed = DetailEditor(F, P, D)
    curve = [vid(idx, i, 10) for i in range(10, 27)]
    target = np.array([[10 * H, 13 * H, 0], [26 * H, 13 * H, 0]])
    region = ed.select_curve(curve, 2.5 * H, 15)
    X = ed.surface(15)
    x = ed.deform_region(region, curve, target, X, 0.2)
    # reference: eq. 17 stacked densely and solved by lstsq
    Pn = np.unique(region)
    n = len(Pn)
    A = np.zeros((n, n))
    pos = {v: i for i, v in enumerate(Pn)}
    for f in F:
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            if a in pos and b in pos:
                A[pos[a], pos[b]] = A[pos[b], pos[a]] = 1
    L = np.diag(A.sum(1)) - A
    S = np.zeros((len(curve), n))
    S[np.arange(len(curve)), [pos[c] for c in curve]] = 1
    s = np.linspace(0, 1, len(curve))
    q = (1 - s)[:, None] * target[0] + s[:, None] * target[1]
    M = np.vstack([S, np.sqrt(0.2) * L])
    rhs = np.vstack([q, np.sqrt(0.2) * L @ X[Pn]])
    xref = np.linalg.lstsq(M, rhs, rcond=None)[0]
    assert np.abs(x - xref).max() < 1e-9
    assert np.allclose(x[:, 1] - X[Pn, 1], 3 * H, atol=1e-9)  # a pure translation satisfies both terms
    e = ed.reshape(curve, target, 15, 2.5 * H)
    res = ed.apply(e, window=(7, 23), lam_e=1e3)
    z = res.details[15, :, 2].reshape(40, 30)
    prof = z[12:25].mean(0)  # mean profile across the wrinkle
    assert abs(int(np.argmax(prof)) - 13) <= 0 and prof[10] < 0.3 * prof.max()
    with pytest.raises(ValueError, match="curve"):
        ed.reshape(curve[:1], target, 15, H)


def test_real_transfer_detail_edit_matches_reference(tiger):
    t = np.arange(24)
    K = tiger.n_shapes
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (3 + 2 * np.arange(K)) + np.arange(K)), 0, 1)
    res = transfer_sequence(tiger.neutral, tiger.faces, tiger.evaluate(W), tiger.neutral * [1.1, 0.95, 1.0], tiger.faces,
                            max_bases=6)
    ed = DetailEditor.from_result(res)
    key = 12
    busiest = int(np.argmax(np.linalg.norm(ed.coating(key), axis=1)))
    region = ed.select_paint([busiest], 0.012, key)
    assert 5 < len(region) < 300
    edits = (ed.scale(region, key, 2.0), ed.copy_paste(region, key, anchor=int(np.argmax(ed.surface(key)[:, 0])), angle=0.5))
    for e, prop in [(e, p) for e in edits for p in ("eq18", "per_frame")]:
        out = ed.apply(e, window=(4, 20), propagation=prop)
        ref = ed.apply_reference(e, (4, 20), propagation=prop)
        ch = out.details - res.details
        chr_ = ref - res.details
        assert np.abs(ch - chr_).max() < 1e-4 * np.abs(chr_).max()
        assert np.abs(ch[:4]).max() == 0 and np.abs(ch[21:]).max() == 0
        # the seam duplicates move together
        assert np.abs(out.details[:, np.arange(len(ed.wi))] - out.details[:, ed.rep[ed.wi]]).max() == 0


def test_detail_morph_targets_rank_and_measured_error():
    from core.transfer.details import detail_morph_targets

    rng = np.random.default_rng(1)
    T, V = 50, 300
    B = rng.standard_normal((5, V, 3)) * 1e-4
    C = rng.standard_normal((T, 5))
    D = np.einsum("tk,kvc->tvc", C, B)
    c, b, err = detail_morph_targets(D, ranks=(3, 5, 8))
    assert b.shape == (5, V, 3) and err < 1e-15  # rank 3 misses, rank 5 is exact
    np.testing.assert_allclose(np.einsum("tk,kvc->tvc", c, b), D, atol=1e-15)
    # noise on top: the measured error is the true largest vertex error, and within the bound
    Dn = D + rng.standard_normal(D.shape) * 1e-7
    c, b, err = detail_morph_targets(Dn, rtol=0.05)
    true = np.linalg.norm(np.einsum("tk,kvc->tvc", c, b) - Dn, axis=2).max()
    assert abs(err - true) < 1e-15 and err <= 0.05 * np.linalg.norm(Dn, axis=2).max()
    c, b, err = detail_morph_targets(np.zeros((4, 10, 3)))
    assert b.shape == (0, 10, 3) and err == 0.0
    with pytest.raises(ValueError, match="details"):
        detail_morph_targets(np.zeros((4, 10)))
