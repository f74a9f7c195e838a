"""Figures for docs/local.md: segmentation masks, and global vs local retargeting with
normal-map blending on a decimated face (Liu et al. 2011, Fig. 1, 2 and 4 analogues).

Panels of ``docs/local/retarget_normalmaps.png`` (one Live Link ROM frame, chosen as the
frame where the global solve errs most):
  1 truth: full ICT rig (53 shapes) driven by the captured curves
  2 global: symmetric 22-shape rig, one region (eq. 1)
  3 local: same rig, 12 regions (eq. 2 + eq. 3)
  4 local on the decimated mesh (10 % of the triangles), its own vertex normals
  5 the same decimated mesh textured with the blended normal map (§5)
All panels use one Lambert shading model with a fixed light in the rig's frame: per vertex
for 1–4, per texel (from the normal map) for 5, rendered unlit by pyvista so the shading
is exactly what we computed.

Run: ``python scripts/liu_render.py`` (writes docs/local/*.png, prints the numbers).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import liu_table1 as L  # noqa: E402

from core.normalmap import (angle_deg, blend_normal_maps, decimate, mask_maps, sample, shape_normal_maps,  # noqa: E402
                            uv_raster, vertex_normals_seamless)
from core.segment import marker_weights, segment  # noqa: E402
from core.solvers.local import local_precompute, masks_at, reconstruct_markers, synthesize  # noqa: E402

OUT = ROOT / "docs" / "local"
LIGHT = np.array([0.35, 0.45, 0.82])
LIGHT /= np.linalg.norm(LIGHT)


def shade(N):
    return np.clip(0.18 + 0.82 * np.clip(N @ LIGHT, 0, None), 0, 1)


def tab_colors(R):
    import matplotlib

    cm = matplotlib.colormaps["tab20"]
    return np.array([cm((2 * i) % 20 + (i // 10))[:3] for i in range(R)])


def polydata(P, F):
    import pyvista as pv

    return pv.PolyData(np.asarray(P, dtype=np.float64), np.hstack([np.full((len(F), 1), 3), F]).ravel())


def main():
    import pyvista as pv

    pv.OFF_SCREEN = True
    OUT.mkdir(parents=True, exist_ok=True)
    s = L.setup("livelinkface_rom.csv", n_markers=97)
    ict, sym, layout, targets = s["ict"], s["sym"], s["layout"], s["targets"]
    n0, D = layout.on_rig(sym)
    seg = segment(sym, n_regions=12)
    mw = marker_weights(sym, layout, seg.masks, graph=seg.graph)
    Ug = local_precompute(n0, D, None, "simplex").solve(targets)
    err_g = np.linalg.norm(reconstruct_markers(n0, D, Ug, np.ones((1, len(n0)))) - targets, axis=2).mean(1)
    t = int(np.argmax(err_g))
    Ul = local_precompute(n0, D, mw, "simplex").solve(targets[t:t + 1])
    err_l = np.linalg.norm(reconstruct_markers(n0, D, Ul, masks_at(layout, seg.masks)) - targets[t:t + 1], axis=2).mean()
    print(f"frame {t}: mean marker error global {err_g[t] * 1000:.2f} mm, local R=12 {err_l * 1000:.2f} mm")

    truth = ict.evaluate(s["weights"][t])
    glob = synthesize(sym, Ug[t:t + 1], np.ones((1, sym.n_vertices)))[0]
    loc = synthesize(sym, Ul, seg.masks)[0]
    low, low_masks = decimate(sym, 0.9, seg.masks)
    loc_low = synthesize(low, Ul, low_masks)[0]
    ras = uv_raster(sym.uvs, sym.faces, 512)
    maps = shape_normal_maps(sym, ras)
    Nb = blend_normal_maps(maps, Ul[0], mask_maps(ras, sym.faces, seg.masks))
    from core.geometry import closest_points, vertex_normals

    # numbers: angle to the full-resolution local result's normals, at face vertices
    N_loc = vertex_normals_seamless(sym, loc)
    moving = np.linalg.norm(sym.deltas, axis=2).max(0) > 2e-3
    inside = sample(ras.covered[..., None].astype(float), ras, sym.uvs)[:, 0] > 1 - 1e-9
    sel = moving & inside
    _, _, tri, bc = closest_points(sym.neutral[sel], low.neutral, low.faces)
    Nlow = vertex_normals(loc_low, low.faces)
    coarse = np.einsum("nj,njc->nc", bc, Nlow[low.faces[tri]])
    e_map = angle_deg(sample(Nb, ras, sym.uvs[sel]), N_loc[sel])
    e_low = angle_deg(coarse, N_loc[sel])
    print(f"normals vs full-res local result ({sel.sum()} face vertices): blended map mean {e_map.mean():.2f} "
          f"median {np.median(e_map):.2f} deg; decimated mesh mean {e_low.mean():.2f} median {np.median(e_low):.2f} deg "
          f"({low.n_vertices} vertices, {len(low.faces)} triangles)")

    # --- figure 1: masks
    cols = tab_colors(12)
    pl = pv.Plotter(off_screen=True, window_size=(1200, 600), shape=(1, 2), border=False)
    for i, cam in enumerate(([(0, 0.02, 0.75), (0, 0.02, 0), (0, 1, 0)], [(0.55, 0.05, 0.5), (0, 0.02, 0), (0, 1, 0)])):
        pl.subplot(0, i)
        m = polydata(sym.neutral, sym.faces)
        m["rgb"] = (np.clip(seg.masks.T @ cols, 0, 1) * shade(vertex_normals_seamless(sym))[:, None] * 255).astype(np.uint8)
        pl.add_mesh(m, scalars="rgb", rgb=True, lighting=False)
        pl.camera_position = cam
    pl.screenshot(str(OUT / "segmentation_R12.png"))
    pl.close()

    # --- figure 2: retargeting and normal maps
    cam = [(0, 0.03, 0.62), (0, 0.03, 0), (0, 1, 0)]
    pl = pv.Plotter(off_screen=True, window_size=(1500, 360), shape=(1, 5), border=False)
    titles = ["truth (53 shapes)", "global, 22 sym. shapes", "local R=12", "local, decimated 10%", "decimated + blended normal map"]
    meshes = [(truth, ict), (glob, sym), (loc, sym)]
    for i, (P, rig) in enumerate(meshes):
        pl.subplot(0, i)
        m = polydata(P, rig.faces)
        g = (shade(vertex_normals_seamless(rig, P)) * 255).astype(np.uint8)
        m["rgb"] = np.repeat(g[:, None], 3, axis=1)
        pl.add_mesh(m, scalars="rgb", rgb=True, lighting=False)
        pl.add_text(titles[i], font_size=8)
        pl.camera_position = cam
    pl.subplot(0, 3)
    m = polydata(loc_low, low.faces)
    g = (shade(Nlow) * 255).astype(np.uint8)
    m["rgb"] = np.repeat(g[:, None], 3, axis=1)
    pl.add_mesh(m, scalars="rgb", rgb=True, lighting=False)
    pl.add_text(titles[3], font_size=8)
    pl.camera_position = cam
    pl.subplot(0, 4)
    tex = (shade(Nb) * 255).astype(np.uint8)
    tex[~ras.covered] = 0
    img = np.ascontiguousarray(np.repeat(tex[:, :, None], 3, axis=2))  # pyvista: array row 0 = image top = t 1
    m = polydata(loc_low, low.faces)
    u0, u1, v0, v1 = ras.extent
    m.active_texture_coordinates = np.stack([(low.uvs[:, 0] - u0) / (u1 - u0), 1 - (low.uvs[:, 1] - v0) / (v1 - v0)], 1).astype(np.float32)
    pl.add_mesh(m, texture=pv.Texture(img), lighting=False)
    pl.add_text(titles[4], font_size=8)
    pl.camera_position = cam
    pl.screenshot(str(OUT / "retarget_normalmaps.png"))
    pl.close()
    print(f"wrote {OUT / 'segmentation_R12.png'} and {OUT / 'retarget_normalmaps.png'}")


if __name__ == "__main__":
    main()
