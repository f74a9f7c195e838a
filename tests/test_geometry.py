"""Mesh operators: hand-derived single-triangle cases, identities, and the real ICT mesh."""

import numpy as np
import pytest
import scipy.sparse as sp

from core import geometry as g


def _tri():
    # right triangle with legs 1 (x) and 2 (y): angles 90 deg at 0, atan(2) at 1, atan(1/2) at 2
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    F = np.array([[0, 1, 2]])
    return V, F


def _grid(nx=6, ny=5, seed=0, jitter=0.15):
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="xy")
    V = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    V[:, :2] += rng.uniform(-jitter, jitter, size=(len(V), 2))
    V[:, 2] = 0.3 * np.sin(V[:, 0]) * np.cos(V[:, 1])
    F = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a = j * nx + i
            F += [[a, a + 1, a + nx + 1], [a, a + nx + 1, a + nx]]
    return V, np.array(F)


def test_cotangent_single_triangle_hand_derived():
    V, F = _tri()
    L = g.cotangent_laplacian(V, F).toarray()
    # cot at corner 0 = 0, at corner 1 = 1/2, at corner 2 = 2
    # edge (1,2) opposite corner 0 -> weight 0; edge (0,2) opposite corner 1 -> 1/4; edge (0,1) opposite 2 -> 1
    want = np.array([[1.25, -1.0, -0.25], [-1.0, 1.0, 0.0], [-0.25, 0.0, 0.25]])
    np.testing.assert_allclose(L, want, atol=1e-14)


def test_cotangent_psd_rows_sum_zero_and_gradient_identity():
    V, F = _grid()
    L = g.cotangent_laplacian(V, F)
    assert (abs(L - L.T)).max() < 1e-12
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0, atol=1e-12 * abs(L).max())
    ev = np.linalg.eigvalsh(L.toarray())
    assert ev.min() > -1e-10 * ev.max()  # positive semi-definite
    G = g.gradient(V, F)
    A = 0.5 * g.doublearea(V, F)
    LG = (G.T @ sp.diags(np.tile(A, 3)) @ G).toarray()
    np.testing.assert_allclose(L.toarray(), LG, atol=1e-12 * abs(L).max())


def test_gradient_exact_on_linear_function():
    V, F = _grid()
    a = np.array([0.3, -1.2, 0.7])
    u = V @ a
    gr = (g.gradient(V, F) @ u).reshape(3, -1).T
    n = g.face_normals(V, F)
    tangential = a - (n @ a)[:, None] * n  # the gradient of a linear function restricted to each face
    np.testing.assert_allclose(gr, tangential, atol=1e-12)


def test_cotangent_reproduces_planar_linear_functions():
    V, F = _grid(jitter=0.2)
    V[:, 2] = 0
    L = g.cotangent_laplacian(V, F)
    interior = np.flatnonzero((V[:, 0] > 0.5) & (V[:, 0] < 4.5) & (V[:, 1] > 0.5) & (V[:, 1] < 3.5))
    for c in range(2):
        np.testing.assert_allclose((L @ V[:, c])[interior], 0, atol=1e-12)


def test_massmatrix_single_triangle_and_total_area():
    V, F = _tri()
    # right angle at 0 is not obtuse: Voronoi areas, circumcentre at the hypotenuse midpoint
    Mv = g.massmatrix(V, F, "voronoi").diagonal()
    # hand: corner 0: (|01|^2 cot2 + |02|^2 cot1)/8 = (1*2 + 4*0.5)/8 = 0.5
    #       corner 1: (|01|^2 cot2 + |12|^2 cot0)/8 = (2 + 0)/8 = 0.25 ; corner 2: (4*0.5 + 0)/8 = 0.25
    np.testing.assert_allclose(Mv, [0.5, 0.25, 0.25], atol=1e-14)
    np.testing.assert_allclose(g.massmatrix(V, F, "barycentric").diagonal(), [1 / 3] * 3)
    obt = np.array([[0.0, 0, 0], [4, 0, 0], [2, 0.5, 0]])  # obtuse at corner 2, area 1
    np.testing.assert_allclose(g.massmatrix(obt, F).diagonal(), [0.25, 0.25, 0.5])
    Vg, Fg = _grid()
    total = 0.5 * g.doublearea(Vg, Fg).sum()
    for kind in ("voronoi", "barycentric"):
        d = g.massmatrix(Vg, Fg, kind).diagonal()
        assert (d > 0).all()
        np.testing.assert_allclose(d.sum(), total, rtol=1e-12)
    with pytest.raises(ValueError, match="kind"):
        g.massmatrix(Vg, Fg, "cotan")


def test_uniform_laplacian_and_adjacency():
    F = np.array([[0, 1, 2], [0, 2, 3]])
    A = g.vertex_adjacency(F, 5).toarray()
    want = np.zeros((5, 5))
    for i, j in [(0, 1), (1, 2), (0, 2), (2, 3), (0, 3)]:
        want[i, j] = want[j, i] = 1
    np.testing.assert_array_equal(A, want)
    L = g.uniform_laplacian(F, 5).toarray()
    np.testing.assert_array_equal(L, np.diag(want.sum(1)) - want)
    assert g.vertex_adjacency(F).shape == (4, 4)
    with pytest.raises(ValueError, match="out of range"):
        g.vertex_adjacency(F, 3)


def test_normals_and_orientation():
    V, F = _tri()
    np.testing.assert_allclose(g.face_normals(V, F), [[0, 0, 1]])
    np.testing.assert_allclose(g.face_normals(V, F[:, ::-1]), [[0, 0, -1]])
    Vg, Fg = _grid()
    vn = g.vertex_normals(Vg, Fg)
    np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1)
    # area weighting: a vertex's normal is the normalised sum of 2A n over its faces
    fn = g.face_normals(Vg, Fg) * g.doublearea(Vg, Fg)[:, None]
    i = 14
    s = fn[(Fg == i).any(1)].sum(0)
    np.testing.assert_allclose(vn[i], s / np.linalg.norm(s))


def test_vertex_normals_hand_derived_two_faces():
    # a flat triangle N1 = (0, 0, 1) (2A = 1) and a slanted one N2 = (v3 - v0) x (v1 - v0) = (0, 2, 2)
    # (2A = 2 sqrt 2) on the shared edge 0-1: the shared corners get normalize(N1 + N2) = (0, 2, 3) / sqrt 13
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -2, 2]])
    F = np.array([[0, 1, 2], [0, 3, 1]])
    want = np.array([[0, 2, 3], [0, 2, 3], [0, 0, 1], [0, 1, 1]]) / np.array([[13 ** 0.5], [13 ** 0.5], [1], [2 ** 0.5]])
    np.testing.assert_allclose(g.vertex_normals(V, F), want, atol=1e-15)
    Vt, Ft = _tri()
    np.testing.assert_array_equal(g.vertex_normals(Vt, Ft), [[0, 0, 1]] * 3)


def test_vertex_normals_batch_rotation_and_per_face_loop(tiger):
    """The batch equals pose-by-pose calls to the bit, and a plain loop over the faces in face
    order (the sums of the incidence product); normals turn with a rotation."""
    from scipy.spatial.transform import Rotation

    V, F = tiger.neutral, tiger.faces
    poses = np.concatenate([V[None], V + tiger.deltas[:4]])
    batch = g.vertex_normals(poses, F)
    for k in range(len(poses)):
        assert np.array_equal(batch[k], g.vertex_normals(poses[k], F))
    ref = np.zeros_like(V)
    for a, b, c in F:
        ref[[a, b, c]] += np.cross(V[b] - V[a], V[c] - V[a])
    assert np.array_equal(batch[0], ref / np.linalg.norm(ref, axis=1, keepdims=True))
    f32 = g.vertex_normals(poses.astype(np.float32), F)
    dev = np.abs(f32 - batch).max(axis=-1)  # float32 rounding, worse on the tiger's tiniest faces
    assert f32.dtype == np.float32 and np.median(dev) < 1e-7 and np.percentile(dev, 99) < 1e-5 and dev.max() < 1e-4
    R = Rotation.from_rotvec([0.3, -0.7, 0.2]).as_matrix()
    np.testing.assert_allclose(g.vertex_normals(V @ R.T + [1.0, 2.0, 3.0], F), batch[0] @ R.T, atol=1e-12)


def test_vertex_normals_across_a_seam_and_fallback():
    # a unit square folded along its diagonal 0-2, the two halves' copies of 0 and 2 split (a seam)
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0], [1, 1, 0], [0, 1, 1], [5, 5, 5]])
    F = np.array([[0, 1, 2], [3, 4, 5]])
    wi = np.array([0, 1, 2, 0, 2, 3, 4])
    seam = g.vertex_normals(V, F)
    assert np.allclose(seam[0], [0, 0, 1]) and not np.allclose(seam[3], seam[0])  # cut: one face each
    n = g.vertex_normals(V, F, weld_index=wi)
    welded = g.vertex_normals(V[[0, 1, 2, 5, 6]], wi[F])  # the same mesh without the seam
    np.testing.assert_allclose(n, welded[wi], atol=1e-15)
    assert np.array_equal(n[0], n[3]) and np.array_equal(n[2], n[4])
    # vertex 6 is on no face: zero, or the fallback (glTF's +Z)
    assert np.array_equal(n[6], [0, 0, 0])
    assert np.array_equal(g.vertex_normals(V, F, fallback=(0, 0, 1))[6], [0, 0, 1])
    with pytest.raises(ValueError, match="weld_index"):
        g.vertex_normals(V, F, weld_index=wi[:3])


def test_old_normal_callers_are_the_shared_function(tiger):
    """glTF's NORMAL, the seam-welded normals of the normal maps and the transfer's frames are
    geometry.vertex_normals with their option (same bits)."""
    from core.io.gltf import vertex_normals as gltf_normals
    from core.normalmap import vertex_normals_seamless
    from core.segment import welded_graph

    V, F = tiger.neutral, tiger.faces
    poses = np.concatenate([V[None], V + tiger.deltas])
    assert np.array_equal(gltf_normals(poses, F), g.vertex_normals(poses, F, fallback=(0.0, 0.0, 1.0)))
    assert np.array_equal(vertex_normals_seamless(tiger), g.vertex_normals(V, F, weld_index=welded_graph(tiger).index))
    t, b, n = g.vertex_frames(poses, F)
    assert np.array_equal(n, g.vertex_normals(poses, F))
    np.testing.assert_allclose(np.einsum("...i,...i->...", t, n), 0, atol=1e-12)
    np.testing.assert_allclose(np.cross(n, t), b, atol=1e-15)


def test_weld_hand_derived_seam():
    # two triangles of a square whose diagonal 0-2 is a seam: 3 and 4 copy 0 and 2
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0], [1, 1, 0], [0, 1, 0]])
    F = np.array([[0, 1, 2], [3, 4, 5], [0, 3, 1]])  # the last collapses once 0 and 3 are one
    w = g.weld_vertices(V, F)
    np.testing.assert_array_equal(w.index, [0, 1, 2, 0, 2, 3])
    np.testing.assert_array_equal(w.first, [0, 1, 2, 5])
    np.testing.assert_array_equal(w.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(w.kept, [True, True, False])
    assert w.n == 4
    index, first, faces = w  # unpacks as the transfer code takes it
    assert index is w.index and first is w.first and faces is w.faces
    # within the tolerance (1e-9 of the size by default) a copy merges; beyond it, not
    near = V.copy()
    near[3] += 1e-13
    assert g.weld_vertices(near, F).n == 4 and g.weld_vertices(near, F, tol=0).n == 5
    signed = V.copy()
    signed[3] = -0.0
    assert g.weld_vertices(signed, F, tol=0).n == 4  # -0.0 and 0.0 are one value
    # attributes that differ keep vertices apart (closed lips: same rest position, other deltas)
    deltas = np.zeros((2, 6, 3))
    deltas[1, 3] = [0, 0, 1e-3]
    assert g.weld_vertices(V, F, tol=0, attributes=deltas).n == 5
    with pytest.raises(ValueError, match="attributes"):
        g.weld_vertices(V, F, attributes=deltas[:, :4])
    with pytest.raises(ValueError, match="tol"):
        g.weld_vertices(V, F, tol=-1.0)


def test_weld_identity_and_the_old_callers(ict, tiger):
    """A mesh without duplicates keeps its numbering; the segmentation's graph, the transfer's
    welded_graph and the layout transfer's merged mesh are geometry.weld_vertices with their options."""
    from core.registration import merged_mesh
    from core.segment import welded_graph

    w = g.weld_vertices(tiger.neutral, tiger.faces)
    np.testing.assert_array_equal(w.index, np.arange(tiger.n_vertices))
    np.testing.assert_array_equal(w.faces, tiger.faces)
    w = g.weld_vertices(ict.neutral, ict.faces)
    assert w.n == 14062 and len(w.faces) == len(ict.faces)  # ICT: 14,629 vertices, 14,062 distinct
    np.testing.assert_array_equal(ict.neutral[w.first][w.index], ict.neutral)  # copies coincide
    exact = g.weld_vertices(ict.neutral, ict.faces, tol=0, attributes=ict.deltas)
    graph = welded_graph(ict)
    np.testing.assert_array_equal(graph.index, exact.index)
    np.testing.assert_array_equal(graph.first, exact.first)
    np.testing.assert_array_equal(exact.index, w.index)  # ICT's seam copies share their deltas
    P, Fm, merged_of, fidx = merged_mesh(ict)
    np.testing.assert_array_equal(merged_of, w.index)
    np.testing.assert_array_equal(Fm, w.faces)
    np.testing.assert_array_equal(fidx, np.flatnonzero(w.kept))


def test_boundary_loops_ordered():
    V, F = _grid(4, 4, jitter=0)
    loops = g.boundary_loops(F)
    assert len(loops) == 1
    loop = loops[0]
    assert sorted(loop.tolist()) == sorted(set(range(16)) - {5, 6, 9, 10})
    # consecutive vertices are mesh neighbours, closing back to the start
    A = g.vertex_adjacency(F, 16)
    assert all(A[a, b] for a, b in zip(loop, np.roll(loop, -1)))
    # the faces orient the walk: a CCW grid seen from +z walks the outer rim counter-clockwise
    P = V[loop, :2]
    signed_area = 0.5 * np.sum(P[:, 0] * np.roll(P[:, 1], -1) - np.roll(P[:, 0], -1) * P[:, 1])
    assert signed_area > 0
    # a hole: remove the two centre faces -> an inner loop of 4
    centre = [k for k, f in enumerate(F) if set(f) <= {5, 6, 9, 10}]
    loops = g.boundary_loops(np.delete(F, centre, axis=0))
    assert [len(l) for l in loops] == [12, 4]
    assert set(loops[1].tolist()) == {5, 6, 9, 10}


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"V: expected"):
        g.cotangent_laplacian(np.zeros((3, 4)), [[0, 1, 2]])
    with pytest.raises(ValueError, match=r"F: expected"):
        g.cotangent_laplacian(np.zeros((3, 3)), [[0, 1]])


def test_degenerate_face_is_finite():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]])
    F = np.array([[0, 1, 2], [0, 1, 3]])
    L = g.cotangent_laplacian(V, F)
    assert np.isfinite(L.data).all()
    assert np.isfinite(g.massmatrix(V, F).diagonal()).all()


def test_real_ict_mesh(ict):
    V, F = ict.neutral, ict.faces
    L = g.cotangent_laplacian(V, F)
    scale = abs(L).max()
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0, atol=1e-12 * scale)
    assert abs(L - L.T).max() <= 1e-12 * scale
    G = g.gradient(V, F)
    A = 0.5 * g.doublearea(V, F)
    assert abs(L - G.T @ sp.diags(np.tile(A, 3)) @ G).max() <= 1e-10 * scale
    # PSD: Dirichlet energy of random functions is non-negative
    x = np.random.default_rng(1).normal(size=(len(V), 5))
    assert (np.einsum("ij,ij->j", x, L @ x) >= 0).all()
    M = g.massmatrix(V, F).diagonal()
    np.testing.assert_allclose(M.sum(), A.sum(), rtol=1e-10)
    loops = g.boundary_loops(F)
    Ad = g.vertex_adjacency(F, len(V))
    for lp in loops:
        assert all(Ad[a, b] for a, b in zip(lp, np.roll(lp, -1)))
    # every vertex on a boundary loop appears once per loop it bounds, edges once overall
    n_bd_edges = sum(len(lp) for lp in loops)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert n_bd_edges == (counts == 1).sum()


def test_farthest_points_on_a_line_and_errors():
    from core.geometry import farthest_points

    P = np.c_[np.arange(11.0), np.zeros(11), np.zeros(11)]
    assert list(farthest_points(P, 3, start=0)) == [0, 10, 5]
    with pytest.raises(ValueError, match="n must lie"):
        farthest_points(P, 12)


def test_procrustes_hand_derived_rotation_and_reflection():
    # a quarter turn about z, scale 2, shift (1, 2, 3): x -> 2 Rz x + t, recovered exactly
    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    Q = 2 * P @ Rz.T + [1, 2, 3]
    s, R, t = g.procrustes(P, Q, scale=True)
    assert s == pytest.approx(2) and np.allclose(R, Rz, atol=1e-15) and np.allclose(t, [1, 2, 3])
    s, R, t = g.procrustes(P, P @ Rz.T + [1, 2, 3])  # rigid: s = 1
    assert s == 1.0 and np.allclose(R, Rz, atol=1e-15) and np.allclose(t, [1, 2, 3])
    # identity: a point set onto itself
    s, R, t = g.procrustes(P, P, scale=True)
    assert s == pytest.approx(1) and np.allclose(R, np.eye(3)) and np.allclose(t, 0)
    # a mirror image: the best proper rotation, never the reflection
    M = P * [1, 1, -1]
    _, R, _ = g.procrustes(P, M)
    assert np.linalg.det(R) == pytest.approx(1)
    # zero weight: that point may be NaN and is ignored
    Qn = np.vstack([Q, [[np.nan, np.nan, np.nan]]])
    s2, R2, t2 = g.procrustes(np.vstack([P, [[5.0, 5, 5]]]), Qn, [1, 1, 1, 1, 0], scale=True)
    assert np.allclose([s2], [2]) and np.allclose(R2, Rz) and np.allclose(t2, [1, 2, 3])
    with pytest.raises(ValueError, match=r"\(N>=3, 3\)"):
        g.procrustes(P[:2], Q[:2])
    with pytest.raises(ValueError, match="weights"):
        g.procrustes(P, Q, [1, 1, 1])


def test_procrustes_batch_and_the_old_callers():
    """A batch equals item by item; the stabilisation's Kabsch is procrustes (same bits)."""
    from scipy.spatial.transform import Rotation

    from core.stabilize import kabsch

    rng = np.random.default_rng(4)
    Y = rng.normal(size=(9, 3))
    R = Rotation.from_rotvec(rng.normal(scale=0.5, size=(6, 3))).as_matrix()
    X = np.einsum("tij,mj->tmi", R, Y) + rng.normal(size=(6, 1, 3)) + rng.normal(scale=0.01, size=(6, 9, 3))
    W = rng.random((6, 9))
    s, Rb, tb = g.procrustes(Y, X, W)
    assert s.shape == (6,) and (s == 1).all()
    for k in range(6):
        _, Rk, tk = g.procrustes(Y, X[k], W[k])
        np.testing.assert_allclose(Rb[k], Rk, atol=1e-14)
        np.testing.assert_allclose(tb[k], tk, atol=1e-14)
    Rk, tk = kabsch(Y, X, W)
    assert np.array_equal(Rk, Rb) and np.array_equal(tk, tb)


def test_nricp_steps_are_the_old_schedules():
    """One schedule, the callers' variants as options (the literals the two modules had)."""
    from core.registration import DEFAULT_STEPS as LAYOUT_STEPS
    from core.transfer.correspond import CROP_STEPS, DEFAULT_STEPS

    assert g.nricp_steps() == ((0.02, 10, 0.5, 10), (0.007, 5, 0.5, 10), (0.002, 2.5, 0.5, 10), (0.0005, 1, 0.0, 10))
    assert DEFAULT_STEPS == g.nricp_steps()
    assert CROP_STEPS == ((0.02, 10, 0.5, 10), (0.007, 5, 0.5, 10), (0.002, 2.5, 0.5, 10), (0.0005, 1, 0.5, 10))
    assert LAYOUT_STEPS == ((0.02, 10.0, 0.5, 6), (0.007, 5.0, 0.5, 6), (0.002, 2.5, 0.5, 6), (0.0007, 1.0, 0.0, 4))
    with pytest.raises(ValueError, match="iterations"):
        g.nricp_steps(iterations=(1, 2))


def test_nonrigid_icp_identity_and_a_moved_sphere():
    import trimesh

    sph = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(sph.vertices), np.asarray(sph.faces)
    lm = np.array([0, 10, 40, 90])
    # onto itself, landmarks where they are: nothing moves
    same = g.nonrigid_icp(V, F, V, F, lm, V[lm], steps=g.nricp_steps(iterations=3))
    assert np.abs(same - V).max() < 1e-6
    # onto a scaled, shifted copy (units do not matter: a 100x larger pair gives 100x the result)
    T = 1.1 * V + [0.05, -0.02, 0.03]
    got = g.nonrigid_icp(V, F, T, F, lm, T[lm])
    # on the target sphere (radius 1.1 about the shift; the facets' sag is ~1 %), landmarks on theirs
    r = np.linalg.norm(got - [0.05, -0.02, 0.03], axis=1)
    before = np.abs(np.linalg.norm(V - [0.05, -0.02, 0.03], axis=1) - 1.1).max()
    assert np.abs(r - 1.1).max() < 0.02 and np.abs(r - 1.1).max() < 0.1 * before
    assert np.abs(got[lm] - T[lm]).max() < 1e-3
    big = g.nonrigid_icp(100 * V, F, 100 * T, F, lm, 100 * T[lm])
    np.testing.assert_allclose(big, 100 * got, atol=1e-6 * 100)
    with pytest.raises(ValueError, match="both or neither"):
        g.nonrigid_icp(V, F, T, F, lm)
    with pytest.raises(ValueError, match="landmark_positions"):
        g.nonrigid_icp(V, F, T, F, lm, T[:2])


def test_marker_triangulation_hand_derived_square():
    # four corners and a raised centre: four triangles around the centre, all facing forward
    P = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 0.1]])
    for unroll in ("cylinder", "plane"):
        F = g.marker_triangulation(P, unroll=unroll)
        assert sorted(map(tuple, np.sort(F, 1))) == [(0, 1, 4), (0, 3, 4), (1, 2, 4), (2, 3, 4)]
        assert (g.face_normals(P, F)[:, 2] > 0).all()
        back = g.marker_triangulation(P, forward=(0, 0, -1), unroll=unroll)
        assert (g.face_normals(P, back)[:, 2] < 0).all()
    with pytest.raises(ValueError, match="unroll"):
        g.marker_triangulation(P, unroll="sphere")
    with pytest.raises(ValueError, match="points"):
        g.marker_triangulation(P[:2])


def test_marker_triangulation_is_a_disk_in_any_frame_and_the_old_callers():
    """On the AnimFace markers both unrollings give a disk over every marker; the plane one
    does not depend on the capture's frame (a rotated take gives the same triangles) and is
    the mesh the dashboard shows (retarget.marker_rig); personalize's is this function."""
    from scipy.spatial.transform import Rotation

    from core import personalize
    from core.io.markers import read_marker_csv
    from core.retarget import marker_rig
    from datapaths import PERFORMANCES

    perf = read_marker_csv(PERFORMANCES / "animface_markers_jaw_60hz.csv", units="cm")
    X = perf.data[0]
    assert personalize.marker_triangulation is g.marker_triangulation
    for unroll in ("cylinder", "plane"):
        F = g.marker_triangulation(X, unroll=unroll)
        assert set(F.ravel()) == set(range(len(X)))
        assert len(X) - len(g.edges(F)) + len(F) == 1 and len(g.boundary_loops(F)) == 1
    F = g.marker_triangulation(X, unroll="plane")
    R = Rotation.from_rotvec([0.4, -0.3, 1.2]).as_matrix()
    Fr = g.marker_triangulation(X @ R.T, forward=R @ [0, 0, 1.0], unroll="plane")
    tris = lambda F: sorted(map(tuple, np.sort(F, 1)))  # noqa: E731  (Delaunay's order may differ)
    assert tris(Fr) == tris(F)
    assert (g.face_normals(X @ R.T, Fr) @ (R @ [0, 0, 1.0]) > 0).all()
    rig, track = marker_rig(perf.data)
    np.testing.assert_array_equal(rig.faces, F)
    assert track.shape == (len(perf.data), 1)
    # marker_rig's former mesh (plane Delaunay, triangles with an edge >= 3 x the median longest
    # edge dropped anywhere): the same triangles, now all facing the camera (+Z); they faced
    # whichever way the SVD's sign put them (away, on this take)
    from scipy.spatial import Delaunay

    c = X - X.mean(0)
    old = Delaunay(c @ np.linalg.svd(c, full_matrices=False)[2][:2].T).simplices
    longest = np.linalg.norm(X[old] - X[np.roll(old, 1, axis=1)], axis=2).max(1)
    old = old[longest < 3 * np.median(longest)]
    assert tris(old) == tris(F)
    assert (g.face_normals(X, F)[:, 2] > 0).all()


def test_decimate_plane_identity_and_uvs():
    """A plane stays a plane (its quadrics are zero); texture coordinates that are a linear
    function of the position stay that function; a small enough mesh comes back as it is."""
    V, F = _grid(12, 10, jitter=0.0)
    V[:, 2] = 0.2 * V[:, 0] - 0.1 * V[:, 1]  # a tilted plane
    uv = V[:, :2] / 10
    Vd, Fd, uvd = g.decimate(V, F, 0.5, uvs=uv)
    assert len(Fd) <= 0.55 * len(F) and len(Vd) < len(V)
    np.testing.assert_allclose(Vd[:, 2], 0.2 * Vd[:, 0] - 0.1 * Vd[:, 1], atol=1e-6)
    np.testing.assert_allclose(uvd, Vd[:, :2] / 10, atol=1e-5)
    assert 0.5 * g.doublearea(Vd, Fd).sum() == pytest.approx(0.5 * g.doublearea(V, F).sum(), rel=1e-5)
    same = g.decimate(V, F, max_vertices=len(V))
    assert same[0] is not None and np.array_equal(same[0], V) and np.array_equal(same[1], F) and same[2] is None
    Vm, Fm, _ = g.decimate(V, F, max_vertices=60)
    assert 40 <= len(Vm) <= 80
    with pytest.raises(ValueError, match="one of"):
        g.decimate(V, F)
    with pytest.raises(ValueError, match="reduction"):
        g.decimate(V, F, 1.5)
    with pytest.raises(ValueError, match="uvs"):
        g.decimate(V, F, 0.5, uvs=uv[:3])


def test_decimate_is_the_normal_maps_low_rig(ict):
    """normalmap.decimate is geometry.decimate with the UVs, deltas carried by closest point."""
    from core.normalmap import decimate as low_rig

    low, _ = low_rig(ict, 0.9)
    P, F, uv = g.decimate(ict.neutral, ict.faces, 0.9, uvs=ict.uvs)
    assert np.array_equal(low.faces, F) and np.array_equal(low.uvs, uv)
    assert np.abs(low.neutral - P).max() < 0.005 * ict.size  # its vertices snapped onto the full surface


def test_closest_points_against_brute_force():
    """Every query's closest point is the nearest of all triangles' (closest_on_triangles on
    every pair); mixed triangle sizes, points on, near and far from the surface."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    V = np.asarray(m.vertices) * [1.0, 0.7, 1.3]
    F = np.asarray(m.faces)
    big = np.array([[3.0, 0, 0], [3.0, 2, 0], [3.0, 0, 2]])  # one large triangle beside it
    V = np.vstack([V, big])
    F = np.vstack([F, [[len(V) - 3, len(V) - 2, len(V) - 1]]])
    rng = np.random.default_rng(3)
    P = np.vstack([rng.normal(size=(300, 3)) * 1.5, V[F[:40]].mean(1), [[3.2, 0.5, 0.5]]])
    pts, d, f, b = g.ClosestPoints(V, F).query(P)
    A, B, C = (np.repeat(V[F[:, i]][None], len(P), 0).reshape(-1, 3) for i in range(3))
    allp, allb = g.closest_on_triangles(np.repeat(P, len(F), 0), A, B, C)
    alld = np.linalg.norm(allp - np.repeat(P, len(F), 0), axis=1).reshape(len(P), len(F))
    np.testing.assert_allclose(d, alld.min(1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", b, V[F[f]]), pts, atol=1e-12)
    assert np.allclose(b.sum(1), 1) and (b >= -1e-12).all()
    # max_distance: farther points report inf and -1, nearer ones the same answer
    _, d2, f2, _ = g.ClosestPoints(V, F).query(P, max_distance=0.2)
    assert np.array_equal(np.isinf(d2), d > 0.2) and (f2[d > 0.2] == -1).all()
    np.testing.assert_array_equal(d2[d <= 0.2], d[d <= 0.2])


def test_closest_points_against_dense_sampling():
    """A second reference (moved from the layout transfer's own closest-point query): every
    triangle sampled on a fine barycentric grid."""
    import trimesh

    rng = np.random.default_rng(1)
    mesh = trimesh.creation.icosphere(subdivisions=1)
    V = mesh.vertices * rng.uniform(0.8, 1.2, size=(len(mesh.vertices), 1))
    F = mesh.faces
    q = rng.normal(scale=1.3, size=(25, 3))
    pt, dist, fid, bary = g.closest_points(q, V, F)
    # the result is a point of the returned triangle, at the returned distance
    np.testing.assert_allclose(np.einsum("nj,njc->nc", bary, V[F[fid]]), pt, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q - pt, axis=1), dist, atol=1e-12)
    assert (bary >= 0).all() and np.allclose(bary.sum(1), 1)
    # reference: every triangle sampled on a fine barycentric grid
    n = 80
    i, j = np.mgrid[0 : n + 1, 0 : n + 1]
    keep = i + j <= n
    B = np.c_[i[keep], j[keep], n - i[keep] - j[keep]] / n
    samples = np.einsum("sj,fjc->fsc", B, V[F]).reshape(-1, 3)
    ref = np.min(np.linalg.norm(q[:, None] - samples[None], axis=2), axis=1)
    edge = mesh.edges_unique_length.max() * 1.2
    assert (dist <= ref + 1e-12).all()  # never worse than any surface sample
    assert (ref - dist <= edge / n).all()  # and within the grid spacing of the sampled optimum


def test_largest_component_hand_derived():
    """Two triangles sharing an edge through seam copies (welded: one part) and a separate
    triangle: the pair is the largest part; vertex_components counts the three parts of the
    unwelded mesh plus an isolated vertex."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0],
                  [5, 5, 5], [6, 5, 5], [5, 6, 5], [9, 9, 9]], float)
    F = np.array([[0, 1, 2], [3, 5, 4], [6, 7, 8]])
    assert g.largest_component(V, F).tolist() == [True, True, False]
    n, label = g.vertex_components(F, len(V))
    assert n == 4 and label[0] == label[2] != label[3] == label[5] != label[6] != label[9]


def test_flipped_faces_single_triangle_and_batch():
    ref = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2]])
    assert not g.flipped_faces(ref, ref * 2 + 5, F).any()
    assert g.flipped_faces(ref, ref * [1, -1, 1], F).all()  # mirrored: the normal points down
    # a rotation by 180° counts too: compare against a reference in the same orientation
    assert g.flipped_faces(ref, ref @ np.diag([1.0, -1.0, -1.0]), F).all()
    assert not g.flipped_faces(ref, ref * [1, 0, 1], F).any()  # degenerate: not counted
    poses = np.stack([ref, ref * [1, -1, 1], ref * [-1, 1, 1]])
    assert g.flipped_faces(ref, poses, F).tolist() == [[False], [True], [True]]


def test_face_vertices_hand_derived():
    d = np.zeros((2, 4, 3))
    d[0, 0] = [0, 0, 1.0]  # the largest move
    d[1, 1] = [0.02, 0, 0]  # 2 % of it: face
    d[1, 2] = [0.005, 0, 0]  # 0.5 %: not face
    assert g.face_vertices(d).tolist() == [True, True, False, False]
    assert g.face_vertices(d, fraction=0.001).tolist() == [True, True, True, False]
    with pytest.raises(ValueError, match="deltas"):
        g.face_vertices(np.zeros((4, 3)))


def test_closest_on_triangles_single_triangle_regions():
    A, B, C = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    cases = {(-1, -1, 1): [1, 0, 0], (2, -0.5, 0): [0, 1, 0], (0.5, -1, 3): [0.5, 0.5, 0], (0.25, 0.25, -2): [0.5, 0.25, 0.25],
             (1, 1, 0): [0, 0.5, 0.5], (-1, 0.5, 0): [0.5, 0, 0.5], (-0.5, 2, 0): [0, 0, 1]}
    for p, want in cases.items():
        _, b = g.closest_on_triangles(np.array([p], float), A, B, C)
        np.testing.assert_allclose(b[0], want, atol=1e-12)
    # a degenerate triangle (a segment) gives the closest point of the segment, no NaN
    pt, b = g.closest_on_triangles(np.array([[0.5, 1.0, 0]]), A, B, B)
    np.testing.assert_allclose(pt[0], [0.5, 0, 0], atol=1e-12) and np.isfinite(b).all()


@pytest.mark.parametrize("landmarks", ["vertices", "barycentric"])
@pytest.mark.slow
def test_nonrigid_icp_equals_trimesh_with_exact_closest_points(landmarks, monkeypatch):
    """Our loop is trimesh's nricp_amberg (the reference): with the same (exact) closest points
    both give the same registration, to trimesh's float32 right-hand side."""
    import trimesh

    sph = trimesh.creation.icosphere(subdivisions=3)
    V, F = np.asarray(sph.vertices), np.asarray(sph.faces)
    T = V * [1.08, 0.95, 1.0] + 0.02 * np.sin(3 * V + [0.3, 0.7, 1.1]) + [0.01, 0.02, -0.03]
    tgt = trimesh.Trimesh(T, F, process=False).subdivide()
    if landmarks == "vertices":
        lm = np.array([0, 10, 40, 90, 200])
        pos = T[lm]
    else:
        tid = np.array([3, 50, 100, 400])
        bc = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.1, 0.1, 0.8]])
        lm, pos = (tid, bc), np.einsum("lk,lkc->lc", bc, T[F[tid]])
    steps = [(0.02, 10, 0.5, 5), (0.005, 2, 0.5, 5)]
    ours = g.nonrigid_icp(V, F, tgt.vertices, tgt.faces, lm, pos, steps, distance_threshold=0.1)
    monkeypatch.setattr(trimesh.proximity, "closest_point",
                        lambda mesh, p: g.ClosestPoints(mesh.vertices, mesh.faces).query(p)[:3])
    ref = trimesh.registration.nricp_amberg(trimesh.Trimesh(V, F, process=False), trimesh.Trimesh(tgt.vertices, tgt.faces, process=False),
                                            source_landmarks=lm, target_positions=pos, steps=[list(s) for s in steps],
                                            distance_threshold=0.1)
    assert np.abs(ref - V).max() > 0.05  # it moved
    assert np.abs(ours - ref).max() < 2e-7


@pytest.mark.slow
def test_nonrigid_icp_coarse_to_fine_and_progress():
    """Coarse to fine lands as close to the target as the full-mesh schedule, keeps the
    landmarks, and reports every iteration with a time estimate."""
    import trimesh

    sph = trimesh.creation.icosphere(subdivisions=4)  # 2,562 vertices
    V, F = np.asarray(sph.vertices), np.asarray(sph.faces)
    T = V * [1.1, 0.9, 1.0] + 0.03 * np.sin(2 * V + [0.3, 0.7, 1.1])
    lm = np.array([0, 100, 400, 900, 2000])
    calls = []
    full = g.nonrigid_icp(V, F, T, F, lm, T[lm])
    coarse = g.nonrigid_icp(V, F, T, F, lm, T[lm], coarse=600, progress=lambda f, m: calls.append((f, m)))
    cp = g.ClosestPoints(T, F)
    d_full, d_coarse = cp.query(full)[1], cp.query(coarse)[1]
    assert np.percentile(d_coarse, 95) < 2 * np.percentile(d_full, 95) + 1e-4
    assert np.abs(coarse[lm] - T[lm]).max() < 5e-3
    fr = [f for f, _ in calls]
    assert fr == sorted(fr) and fr[-1] == 1.0 and len(calls) >= 5
    assert any("coarse" in m for _, m in calls) and "full mesh" in calls[-1][1]
    assert not any("left" in m for _, m in calls)  # the time left is the whole run's (progress.TimeLeft)
    # a mesh of fewer than 2 x coarse vertices runs at full resolution
    same = g.nonrigid_icp(V, F, T, F, lm, T[lm], coarse=2000)
    np.testing.assert_array_equal(same, full)
