"""Renders for docs/transfer.md (Xu et al. 2014): source frame, transfer with / without
feature lines (Fig. 3), with / without fine details, and the non-human targets (the Jeeliz
tiger and triceratops, registered with the 41-marker layouts and the face crop of §3).

    python scripts/xu_renders.py [--fast] [--animals]

``--fast`` skips the non-rigid ICP (landmark similarity + closest-point projection only);
``--animals`` renders only the tiger / triceratops figures.
Writes docs/transfer/*.png (pyvista, off-screen).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "docs" / "transfer"
DATA = ROOT / "data"


def _plot(meshes, titles, path, faces, zoom=1.0, focus=None, scalars=None, clim=None, window=(1600, 620),
          flagged=None, view=(0.0, 0.0, 1.0)):
    """One row of meshes. ``faces`` one (F, 3) array for all or a list (one per mesh);
    ``flagged`` a list of (F,) bool (or None) drawn red (folded-over triangles); ``view`` the
    direction from the focus to the camera, or one per mesh."""
    import pyvista as pv

    pv.OFF_SCREEN = True
    n = len(meshes)
    pl = pv.Plotter(off_screen=True, shape=(1, n), window_size=(window[0], window[1]), border=False)
    views = [np.asarray(v, dtype=np.float64) for v in (view if np.ndim(view) == 2 else [view] * n)]
    for i, (V, title) in enumerate(zip(meshes, titles)):
        pl.subplot(0, i)
        F = faces[i] if isinstance(faces, (list, tuple)) else faces
        f = np.hstack([np.full((len(F), 1), 3), F]).ravel()
        mesh = pv.PolyData(np.asarray(V, dtype=np.float64), f).compute_normals(split_vertices=False)
        if scalars is not None and scalars[i] is not None:
            mesh["mm"] = scalars[i]
            pl.add_mesh(mesh, scalars="mm", cmap="magma", clim=clim, smooth_shading=True,
                        scalar_bar_args=dict(title="mm", vertical=False, height=0.06, position_y=0.02))
        else:
            pl.add_mesh(mesh, color="#d8c3b0", smooth_shading=True, specular=0.2)
        if flagged is not None and flagged[i] is not None and np.any(flagged[i]):
            bad = np.asarray(F)[np.asarray(flagged[i])]
            fb = np.hstack([np.full((len(bad), 1), 3), bad]).ravel()
            pl.add_mesh(pv.PolyData(np.asarray(V, dtype=np.float64), fb), color="#e00000")
        pl.add_text(title, font_size=10)
        c = np.asarray(V).mean(0) if focus is None else focus[i]
        size = np.linalg.norm(np.ptp(np.asarray(V), 0))
        pl.camera.focal_point = c
        pl.camera.position = c + views[i] / np.linalg.norm(views[i]) * 1.6 * size / zoom
        pl.camera.up = (0.0, 1.0, 0.0)
    pl.screenshot(str(path))
    pl.close()
    print("wrote", path)


def main(fast: bool = False, animals_only: bool = False):
    from core.io.gltf import read_rig
    from core.io.layout import read_layout
    from core.io.livelink import read_livelink
    from core.names import NameMap
    from core.transfer import feature_lines_near
    from core.geometry import weld_vertices

    OUT.mkdir(parents=True, exist_ok=True)
    ict = read_rig(DATA / "rigs" / "ict_facekit.glb")
    rb = read_rig(DATA / "rigs" / "rocketbox_female_adult_02.glb")
    li = read_layout(DATA / "layouts" / "ict_facekit.json", ict)
    lr = read_layout(DATA / "layouts" / "rocketbox_female_adult_02.json", rb)
    names = [n for n in li.names if n in lr.names]
    src_lm = li.vertices[[li.names.index(n) for n in names], 0]
    tgt_pts = lr.select(names).points(rb.neutral)
    perf = read_livelink(DATA / "performances" / "livelinkface_take_s07.csv")
    G = NameMap.automatic(perf.names, ict.names).matrix(perf.names, ict.names)
    W = np.nan_to_num(perf.data[:600:2]) @ G.T
    seq = ict.evaluate(W)
    eye_mouth = ["Leye_Up", "Leye_Down", "Reye_Up", "Reye_Down", "Mouth_Up", "Mouth_Down", "Mouth_Lend", "Mouth_Rend"]
    lines = feature_lines_near(ict.neutral, ict.faces, li.select(eye_mouth).points(ict.neutral), 0.012)

    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    reports = {}
    if not animals_only:
        reports["rocketbox"] = _rocketbox(ict, li, rb, src_lm, tgt_pts, seq, lines, wi, rep, Fw, fast)
    reports.update(_animals(ict, li, seq, W, lines, wi, rep, Fw, fast))
    return reports


def _rocketbox(ict, li, rb, src_lm, tgt_pts, seq, lines, wi, rep, Fw, fast):
    from core.transfer import DeformationTransfer, line_edges, naive_transfer, register, taubin_smooth, transfer_sequence

    # §3 preprocessing once, then transfers onto the resampled target (same topology)
    t = time.time()
    reg = register(ict.neutral[rep], Fw, rb.neutral, rb.faces, wi[src_lm], tgt_pts, icp=not fast)
    print("registration", round(time.time() - t, 1), "s", reg.report)
    T0 = reg.resampled[wi]
    res = transfer_sequence(ict.neutral, ict.faces, seq, T0, ict.faces, feature_lines=lines, max_bases=20)
    print("transfer", res.timings, "K =", res.n_bases, "errors", res.selection_errors[-1])
    # the most expressive frame: largest source motion
    motion = np.linalg.norm(seq - ict.neutral, axis=2).mean(1)
    f = int(np.argmax(motion))
    out = res.sequence(f)[0]
    naive = naive_transfer(ict.neutral, T0, ict.faces, seq[f:f + 1], line_edges([wi[l] for l in lines]))[0]
    dist = lambda a, b: np.linalg.norm(a - b, axis=1) * 1000
    _plot([seq[f], out, naive], [f"source ICT, frame {2 * f}", "ours (Xu 2014) on Rocketbox", "naive per-frame DT"],
          OUT / "frame_transfer.png", ict.faces)
    _plot([seq[f], out, out], ["source motion (mm)", "ours: motion (mm)", "ours vs naive (mm)"],
          OUT / "frame_transfer_error.png", ict.faces,
          scalars=[dist(seq[f], ict.neutral), dist(out, T0), dist(out, naive)], clim=(0, 6))

    # Fig. 3: one base expression with and without feature lines (mouth close-up)
    jaw_smile = ict.neutral + 0.9 * ict.deltas[ict.index("jawOpen")] + ict.deltas[ict.index("mouthSmile_L")] \
        + ict.deltas[ict.index("eyeBlink_R")] * 0.7
    Sb0 = taubin_smooth(ict.neutral[rep], Fw)
    Tb0 = taubin_smooth(T0[rep], Fw)
    Sb = taubin_smooth(jaw_smile[rep], Fw)
    E = line_edges([wi[l] for l in lines])
    with_l = DeformationTransfer(Sb0, Tb0, Fw, E, 100.0).transfer(Sb)[wi]
    without = DeformationTransfer(Sb0, Tb0, Fw, None).transfer(Sb)[wi]
    mouth = li.select(["Mouth_Up"]).points(ict.neutral)[0]
    focus = [Sb[wi][li.vertices[li.names.index("Mouth_Up"), 0]], with_l[li.vertices[li.names.index("Mouth_Up"), 0]],
             without[li.vertices[li.names.index("Mouth_Up"), 0]]]
    _plot([Sb[wi], with_l, without], ["smoothed source base (jawOpen+smile+blink)", "transfer, feature lines a=100",
                                       "transfer, no feature lines"], OUT / "feature_lines.png", ict.faces, zoom=2.2,
          focus=focus)
    del mouth

    # with and without fine details (the same frame, close-up on the eyes/mouth)
    large = res.large_scale(f)[0] + (res.neutral - res.target_smooth_ref)
    _plot([seq[f], large, out], ["source frame", "target: large scale only", "target: + fine details (eq. 16)"],
          OUT / "details.png", ict.faces, zoom=1.8)
    src_detail = dist(seq[f] - np.asarray(taubin_smooth(seq[f][rep], Fw))[wi],
                      ict.neutral - np.asarray(taubin_smooth(ict.neutral[rep], Fw))[wi])
    _plot([seq[f], out, out], ["source detail motion |D_t| (mm)", "target detail motion |T_t - large| (mm)",
                               "ours vs naive per-frame DT (mm)"], OUT / "details_error.png", ict.faces,
          scalars=[src_detail, dist(out, large), dist(out, naive)], clim=(0, 1.5))
    return reg.report


def _animals(ict, li, seq, W, lines, wi, rep, Fw, fast):
    """The Jeeliz tiger and triceratops: registration before (whole head) / after (face crop,
    §3 "semi-automatic" with the 41 hand-placed markers), and a few transferred frames."""
    from core.io.gltf import read_rig
    from core.io.layout import read_layout
    from core.transfer import register, transfer_sequence
    from core.transfer.correspond import face_crop
    from core.geometry import face_cross
    from core.transfer.performance import shared_landmarks

    # a few expressive frames of the take: largest motion, jaw open, blink, smile
    motion = np.linalg.norm(seq - ict.neutral, axis=2).mean(1)
    picks = [int(np.argmax(motion))] + [int(np.argmax(W[:, ict.index(n)])) for n in ("jawOpen", "eyeBlink_L", "mouthSmile_L")]
    picks = list(dict.fromkeys(picks))
    frames = seq[picks]
    S = ict.neutral[rep]
    folded = lambda reg: np.einsum("fi,fi->f", face_cross(reg.aligned, Fw), face_cross(reg.resampled, Fw)) < 0
    reports = {}
    for stem in ("jeeliz_tiger", "jeeliz_triceratops"):
        short = stem.split("_")[1]
        rig = read_rig(DATA / "rigs" / f"{stem}.glb")
        ids, pts = shared_landmarks(li, read_layout(DATA / "layouts" / f"{stem}.json", rig), rig.neutral)
        t = time.time()
        old = register(S, Fw, rig.neutral, rig.faces, wi[ids], pts, icp=not fast, crop="none")
        print(short, "whole-head registration", round(time.time() - t, 1), "s", old.report)
        t = time.time()
        res = transfer_sequence(ict.neutral, ict.faces, frames, rig.neutral, rig.faces, landmarks=(ids, pts),
                                icp=not fast, feature_lines=lines, max_bases=len(frames))
        reg = res.registration
        print(short, "face-crop registration + transfer", round(time.time() - t, 1), "s", reg.report, res.timings)
        reports[short] = (old.report, reg.report)
        focus = [rig.neutral.mean(0), pts.mean(0), pts.mean(0)]
        for view, tag in (((0.0, 0.0, 1.0), ""), ((0.75, 0.05, 0.66), "_side")):
            _plot([rig.neutral, old.resampled, reg.resampled],
                  [f"{short} target ({rig.n_vertices} vertices, its own topology)",
                   f"crop='none' (whole head): {old.report['flipped_triangles']} folded (red)",
                   f"crop='auto' (face crop): {reg.report['flipped_triangles']} folded (red)"],
                  OUT / f"{short}_registration{tag}.png", [rig.faces, Fw, Fw], flagged=[None, folded(old), folded(reg)],
                  view=view, focus=focus, zoom=1.2, window=(1800, 640))
        src_focus = S[wi[ids]].mean(0)
        meshes, titles, foc = [], [], []
        for i, p in enumerate(picks):
            meshes += [frames[i], res.sequence(i)[0]]
            titles += [f"source, take frame {2 * p}", f"{short}"]
            foc += [src_focus, pts.mean(0)]
        _plot(meshes, titles, OUT / f"{short}.png", ict.faces, focus=foc, zoom=1.5, window=(2400, 520))
    # the source crop the animals use (the same 41 ICT markers for both)
    crop = face_crop(S, Fw, wi[ids])
    in_crop = crop[wi][ict.faces].all(1)
    _plot([ict.neutral, ict.neutral], [f"ICT face crop (red): {crop.mean():.0%} of the vertices", "side"],
          OUT / "tiger_crop.png", ict.faces, flagged=[in_crop, in_crop], view=[(0.0, 0.0, 1.0), (1.0, 0.0, 0.35)],
          window=(1200, 620), zoom=1.4, focus=[S[wi[ids]].mean(0)] * 2)
    return reports


if __name__ == "__main__":
    main(fast="--fast" in sys.argv, animals_only="--animals" in sys.argv)
