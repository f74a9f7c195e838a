"""Normal-map blending (Liu et al. 2011 §5): rasteriser exactness on hand-made cases, maps of
known planes, eq. 3 on maps, and recovered detail on a decimated ICT face."""

import numpy as np
import pytest

from core.model import Rig
from core.normalmap import (angle_deg, bake, blend_normal_maps, decimate, mask_maps, sample, shape_normal_maps, uv_raster,
                            vertex_normals_seamless)


def plane_rig(n=9, tilt=0.3):
    """A unit-UV square plane z = 0 (0.1 m wide); shape 0 tilts it (z += tilt·x), shape 1
    tilts it along y."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    uv = np.stack([x.ravel(), y.ravel()], 1)
    P = np.stack([0.1 * x.ravel(), 0.1 * y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    D = np.zeros((2, n * n, 3))
    D[0, :, 2] = tilt * P[:, 0]
    D[1, :, 2] = tilt * P[:, 1]
    return Rig(P, F, D, ["tiltX", "tiltY"], uvs=uv, name="plane")


def test_raster_single_triangle_area_and_barycentrics():
    uv = np.array([[0.1, 0.1], [0.9, 0.2], [0.3, 0.8]])
    F = np.array([[0, 1, 2]])
    res = 200
    ras = uv_raster(uv, F, res)
    assert ras.shape == (res, res)
    e1, e2 = uv[1] - uv[0], uv[2] - uv[0]
    area = 0.5 * abs(e1[0] * e2[1] - e1[1] * e2[0])
    # texel count ≈ area·res², within the texels the perimeter cuts through
    perim = sum(np.linalg.norm(uv[i] - uv[(i + 1) % 3]) for i in range(3))
    assert abs(ras.covered.sum() - area * res**2) <= perim * res
    # baking the uvs themselves gives every covered texel its own centre (linear = exact)
    U = bake(ras, F, uv)
    i, j = np.nonzero(ras.covered)
    centre = np.stack([(j + 0.5) / res, (i + 0.5) / res], 1)
    assert np.abs(U[i, j] - centre).max() < 1e-12
    assert ras.bary[ras.covered].min() >= -1e-9 and np.allclose(ras.bary[ras.covered].sum(1), 1)


def test_raster_udim_extent_and_validation():
    uv = np.array([[0.2, 0.2], [1.8, 0.3], [1.5, 0.9]])
    ras = uv_raster(uv, np.array([[0, 1, 2]]), 16)
    assert ras.extent == (0.0, 2.0, 0.0, 1.0) and ras.shape == (16, 32)
    with pytest.raises(ValueError, match="uvs"):
        uv_raster(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="faces"):
        uv_raster(uv, np.array([[0, 1, 5]]))
    with pytest.raises(ValueError, match="resolution"):
        uv_raster(uv, np.array([[0, 1, 2]]), 1)


def test_plane_maps_are_the_analytic_normals_and_blend_by_eq3():
    rig = plane_rig()
    ras = uv_raster(rig.uvs, rig.faces, 32)
    maps = shape_normal_maps(rig, ras)
    cov = ras.covered
    assert cov.mean() > 0.9
    assert np.allclose(maps[0][cov], [0, 0, 1], atol=1e-6)
    t = 0.3  # z = t·x: normal ∝ (-t, 0, 1)
    assert np.allclose(maps[1][cov], np.array([-t, 0, 1]) / np.hypot(t, 1), atol=1e-6)
    assert np.allclose(maps[2][cov], np.array([0, -t, 1]) / np.hypot(t, 1), atol=1e-6)
    # one region, one shape fully on: that shape's map; all off: the neutral's
    ones = np.ones((1,) + ras.shape)
    assert np.allclose(blend_normal_maps(maps, np.array([[1.0, 0.0]]), ones)[cov], maps[1][cov], atol=1e-6)
    assert np.allclose(blend_normal_maps(maps, np.zeros((1, 2)), ones)[cov], maps[0][cov], atol=1e-6)
    # two hard regions (left/right half of the texture) with different weights: each half
    # shows its own region's shape
    masks = np.stack([(rig.uvs[:, 0] < 0.5).astype(float), (rig.uvs[:, 0] >= 0.5).astype(float)])
    Muv = mask_maps(ras, rig.faces, masks)
    assert np.allclose(Muv.sum(0)[cov], 1)
    out = blend_normal_maps(maps, np.array([[1.0, 0.0], [0.0, 1.0]]), Muv)
    left = cov & (Muv[0] == 1)
    right = cov & (Muv[1] == 1)
    assert left.any() and right.any()
    assert np.allclose(out[left], maps[1][left], atol=1e-6) and np.allclose(out[right], maps[2][right], atol=1e-6)
    with pytest.raises(ValueError, match="region_weights"):
        blend_normal_maps(maps, np.zeros((1, 3)), ones)


def test_sample_and_angles():
    rig = plane_rig()
    ras = uv_raster(rig.uvs, rig.faces, 16)
    img = np.random.default_rng(0).random(ras.shape + (2,))
    i, j = 5, 7
    uv = np.array([[(j + 0.5) / 16, (i + 0.5) / 16]])
    assert np.allclose(sample(img, ras, uv)[0], img[i, j])
    mid = np.array([[(j + 1.0) / 16, (i + 0.5) / 16]])
    assert np.allclose(sample(img, ras, mid)[0], 0.5 * (img[i, j] + img[i, j + 1]))
    assert angle_deg(np.array([1.0, 0, 0]), np.array([0, 1.0, 0])) == pytest.approx(90)
    assert angle_deg(np.array([1.0, 0, 0]), np.array([1.0, 1e-9, 0])) == pytest.approx(0, abs=1e-6)


def test_blended_maps_recover_detail_on_a_decimated_ict_face(ict):
    """The blended map, read on the coarse mesh's UVs, is closer to the full-resolution
    normals of the same expression than the coarse mesh's own normals are."""
    from core.segment import segment
    from core.solvers.local import synthesize

    rig = ict.subset(["jawOpen", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R", "eyeBlink_L",
                      "mouthFunnel", "noseSneer_L", "cheekPuff_L"])
    seg = segment(rig, n_regions=4, seed=0)
    ras = uv_raster(rig.uvs, rig.faces, 256)
    maps = shape_normal_maps(rig, ras)
    Muv = mask_maps(ras, rig.faces, seg.masks)
    rng = np.random.default_rng(1)
    U = rng.uniform(0, 0.6, (1, 4, rig.n_shapes)) * (rng.random((1, 4, rig.n_shapes)) < 0.6)
    blended = blend_normal_maps(maps, U[0], Muv)
    # truth: normals of the full-resolution synthesized mesh
    full = synthesize(rig, U, seg.masks)[0]
    truth = vertex_normals_seamless(rig, full)
    # coarse: the decimated rig, same weights and masks, normals interpolated at each vertex
    low, low_masks = decimate(rig, 0.9, seg.masks)
    low_pos = synthesize(low, U, low_masks)[0]
    import trimesh

    from core.geometry import vertex_normals

    low_n = vertex_normals(low_pos, low.faces)
    closest, _, tri = trimesh.proximity.closest_point(trimesh.Trimesh(low.neutral, low.faces, process=False), rig.neutral)
    bc = trimesh.triangles.points_to_barycentric(low.neutral[low.faces[tri]], closest)
    coarse = np.einsum("nj,njc->nc", bc, low_n[low.faces[tri]])
    # compare on moving face vertices whose four bilinear texels are all covered
    moving = np.linalg.norm(rig.deltas, axis=2).max(0) > 2e-3
    inside = sample(ras.covered[..., None].astype(float), ras, rig.uvs)[:, 0] > 1 - 1e-9
    sel = moving & inside
    assert sel.sum() > 2000
    err_map = angle_deg(sample(blended, ras, rig.uvs[sel]), truth[sel])
    err_low = angle_deg(coarse[sel], truth[sel])
    print(f"mean angle to full-res normals: blended map {np.mean(err_map):.2f} deg, coarse mesh {np.mean(err_low):.2f} deg")
    assert np.mean(err_map) < 0.5 * np.mean(err_low), (np.mean(err_map), np.mean(err_low))
    assert np.median(err_map) < 2.0
