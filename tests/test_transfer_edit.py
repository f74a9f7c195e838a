"""Xu 2014 editing: large-scale (eq. 12-15) and fine-scale propagation (eq. 18-21) against
dense / general-solver references."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import lsq_linear

from core.transfer import DeformationTransfer, taubin_smooth
from core.geometry import weld_vertices
from core.transfer.detail_edit import (_reference_propagation, detail_window, propagate_details, region_near_curve,
                                       scale_details)
from core.transfer.edit import DistanceConstraint, LargeScaleEditor, PointConstraint, _reference_weights


@pytest.fixture(scope="module")
def editor(tiger):
    wi, rep, F = weld_vertices(tiger.neutral, tiger.faces)
    S0 = taubin_smooth(tiger.neutral[rep], F)
    T0 = S0 * [1.1, 0.95, 1.0]
    dt = DeformationTransfer(S0, T0, F)
    D = dt.transfer(S0 + tiger.deltas[:, rep]) - T0
    t = np.arange(120)
    K = tiger.n_shapes
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (9 + 3 * np.arange(K)) + np.arange(K)), 0, 1)
    return LargeScaleEditor(dt, T0, D, W), F


def _constraint(ed, frame=60, lift=(0.0, 0.003, 0.001)):
    v = int(np.argmax(np.linalg.norm(ed.D0[6], axis=1)))  # mouthOpen's most moving vertex
    return v, PointConstraint(frame, v, tuple(ed.mesh(ed.W0[frame])[v] + np.array(lift)))


def _objective(ed, W, D, rows, lam_w, lam_e, window):
    ts, te = window
    n, K = te - ts + 1, ed.K
    Dn = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))
    x = W[ts:te + 1]
    e = lam_w * ((Dn @ x - np.diff(ed.W0[ts:te + 1], axis=0)) ** 2).sum() + 1e-8 * lam_w * ((x - ed.W0[ts:te + 1]) ** 2).sum()
    for t, g, y in rows:
        v = sum(c * np.tensordot(W[t], D[:, i], axes=1) for i, c in g.items())
        e += lam_e * ((v - y) ** 2).sum()
    return e


def test_weights_step_matches_bounded_least_squares(editor):
    ed, _ = editor
    v, c = _constraint(ed)
    rows = ed._rows([c])
    for window in ((0, 119), (40, 80)):
        ours = ed.update_weights(ed.D0, ed.W0, rows, 1.0, 1e4, window)
        assert (ours >= 0).all()
        outside = np.ones(120, bool)
        outside[window[0]:window[1] + 1] = False
        assert np.array_equal(ours[outside], ed.W0[outside])
    # the general bounded least-squares solver on a 30-frame sequence (whole window)
    small = LargeScaleEditor(ed.dt, ed.T0, ed.D0, ed.W0[45:75])
    rows = small._rows([PointConstraint(15, v, c.position)])
    ours = small.update_weights(small.D0, small.W0, rows, 1.0, 1e4, (0, 29))
    ref = _reference_weights(small, small.D0, small.W0, rows, 1.0, 1e4, (0, 29), lsq_linear)
    eo, er = (_objective(small, w, small.D0, rows, 1.0, 1e4, (0, 29)) for w in (ours, ref))
    assert eo <= er * (1 + 1e-6) + 1e-15 and (ours >= 0).all()
    assert np.abs(ours - small.W0).max() > 1e-3  # the edit did change the weights


def test_bases_step_matches_dense_normal_equations(editor):
    ed, F = editor
    v, c = _constraint(ed)
    rows = ed._rows([c])
    lam_b, lam_e = 1.0, 1e3
    ours = ed.update_bases(ed.D0, ed.W0, rows, lam_b, lam_e)
    # dense reference on the x coordinate: (λ_b I⊗A + λ_e C^T C) x = λ_e C^T (y - C x0), x = vec(Δ - Δ0)
    from scipy.sparse.linalg import spsolve

    K, V = ed.K, ed.V
    t, g, y = rows[0]
    w = ed.W0[t]
    for coord in range(3):
        C = sp.csr_matrix(np.kron(w, np.eye(V)[v])[None])  # (1, K V), x ordered k-major
        H = (lam_b * sp.kron(sp.identity(K), ed.A) + lam_e * (C.T @ C)).tocsc()
        x0 = ed.D0[:, :, coord].ravel()
        r = lam_e * (C.T @ (np.array([y[coord]]) - C @ x0))
        x = spsolve(H, r)
        assert np.abs(ours[:, :, coord].ravel() - x0 - x).max() < 1e-8 * max(np.abs(x).max(), 1e-12)


def test_edit_meets_constraints_energy_decreases_and_modes(editor):
    ed, _ = editor
    v, c = _constraint(ed)
    full = ed.edit([c], 1.0, 1.0, 100.0)
    assert all(b <= a * (1 + 1e-9) for a, b in zip(full.energies, full.energies[1:]))
    pos = lambda r: ed.T0[v] + np.tensordot(r.weights[60], r.deltas[:, v], axes=1)
    miss0 = np.linalg.norm(ed.mesh(ed.W0[60])[v] - np.array(c.position))
    assert np.linalg.norm(pos(full) - np.array(c.position)) < 0.05 * miss0
    weights_only = ed.edit([c], 0.0, 1.0, 100.0, window=(40, 80))
    assert np.array_equal(weights_only.deltas, ed.D0)
    assert np.array_equal(weights_only.weights[:40], ed.W0[:40])  # outside the window: unchanged
    bases_only = ed.edit([c], 1.0, 0.0, 100.0)
    assert np.array_equal(bases_only.weights, ed.W0)
    assert np.linalg.norm(pos(bases_only) - np.array(c.position)) < 0.5 * miss0
    # bases-only edits reach every frame that uses the edited bases (Fig. 4 b)
    far = 5
    assert np.abs(ed.T0[v] + ed.W0[far] @ bases_only.deltas[:, v] - ed.mesh(ed.W0[far])[v]).max() > 0


def test_distance_constraint_sets_the_distance(editor):
    ed, _ = editor
    D = ed.D0
    i = int(np.argmax(np.linalg.norm(D[6], axis=1)))
    j = int(np.argsort(np.linalg.norm(ed.T0 - ed.T0[i], axis=1))[30])
    cur = ed.mesh(ed.W0[60])
    want = 1.3 * np.linalg.norm(cur[i] - cur[j])
    r = ed.edit([DistanceConstraint(60, i, j, want)], 1.0, 1.0, 1e4)
    m = ed.T0 + np.tensordot(r.weights[60], r.deltas, axes=1)
    assert abs(np.linalg.norm(m[i] - m[j]) - want) < 0.1 * abs(want / 1.3 * 0.3)


def test_edit_validation(editor):
    ed, _ = editor
    v, c = _constraint(ed)
    with pytest.raises(ValueError, match="lam_b"):
        ed.edit([c], 0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="window"):
        ed.edit([c], window=(10, 500))
    with pytest.raises(ValueError, match="frame"):
        ed.edit([PointConstraint(999, v, (0, 0, 0))])


def test_fine_propagation_matches_sparse_spacetime_solve(tiger):
    wi, rep, F = weld_vertices(tiger.neutral, tiger.faces)
    V = len(rep)
    region = np.argsort(np.linalg.norm(tiger.neutral[rep] - tiger.neutral[rep][100], axis=1))[:60]
    rng = np.random.default_rng(0)
    edit = rng.standard_normal((60, 3)) * 1e-4
    ours = propagate_details(edit, F, V, region, (3, 40), 17)
    ref = _reference_propagation(edit, F, V, region, (3, 40), 17)
    assert np.abs(ours - ref).max() < 1e-10 * np.abs(ref).max()
    # E_s keeps the window ends close to unchanged, the key frame close to the edit
    assert np.abs(ours[0]).max() < 0.2 * np.abs(edit).max()
    assert np.abs(ours[17 - 3] - edit).max() < 0.5 * np.abs(edit).max()
    with pytest.raises(ValueError, match="key_frame"):
        propagate_details(edit, F, V, region, (3, 10), 17)


def test_detail_window_scale_and_region(tiger):
    norms = np.zeros((30, tiger.n_vertices))
    norms[10:20, :5] = 1.0
    norms[14, :5] = 2.0
    assert detail_window(norms, np.arange(5), 14, mu=0.23) == (10, 19)
    assert detail_window(norms, np.arange(5), 14, mu=0.6) == (14, 14)
    d = np.ones((tiger.n_vertices, 3))
    region = np.arange(10)
    s = scale_details(d, tiger.faces, region, 0.0, band=2)
    assert np.all(s[region] == 0) and s.max() == 1.0 and (s < 1).sum() > len(region)
    curve = tiger.neutral[[0, 50]]
    sel = region_near_curve(tiger.neutral, curve, 1e-3)
    assert 0 in sel and 50 in sel


def test_transfer_editor_uses_the_results_system_or_rebuilds_it(tiger, rocketbox):
    """TransferEditor (the large-scale editor of a TransferResult): the result carries its
    factorised eq. 9 system; one that does not is rebuilt from the source rig and settings,
    and consistency() tells whether the rebuild is the system the transfer used."""
    import dataclasses

    from core.transfer import TransferSettings, transfer_sequence
    from core.transfer.edit import TransferEditor

    t = np.arange(30)
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (5 + 2 * np.arange(tiger.n_shapes))), 0, 1)
    res = transfer_sequence(tiger.neutral, tiger.faces, tiger.evaluate(W), tiger.neutral * [1.1, 0.95, 1.0], tiger.faces,
                            max_bases=6)
    assert res.system is not None and res.editor().consistency() < 1e-12
    bare = dataclasses.replace(res, system=None, welded=None)
    assert TransferEditor(bare, tiger).consistency() < 1e-9
    # other smoothing than the transfer used: not the same system, and the check says so
    assert TransferEditor(bare, tiger, TransferSettings(iterations=5)).consistency() > 1e-3
    with pytest.raises(ValueError, match="source_rig 'rocketbox.*expected the topology"):
        TransferEditor(bare, rocketbox)
    with pytest.raises(ValueError, match="give the source rig"):
        TransferEditor(bare)
    # an edit spec (plain data, as the shot stores it) moves a vertex towards its target
    S = res.sequence()
    v = int(np.argmax(np.linalg.norm(S - S.mean(0), axis=2).max(0)))
    target = (S[10, v] + 0.5 * (S[20, v] - S[10, v])).tolist()
    spec = {"constraints": [{"kind": "point", "frame": 10, "vertex": v, "target": target}], "window": [5, 15],
            "lam_b": 0.0, "lam_w": 1.0, "lam_e": 100.0}
    D, Wn, rep = res.editor().apply((res.deltas, res.weights), spec)
    assert rep["after_mm"][0] < 0.5 * rep["before_mm"][0]
    np.testing.assert_array_equal(Wn[16:], res.weights[16:])
