"""Fine-scale detail editing on real data (Xu et al. 2014 §5.2) for docs/transfer.md.

ICT-FaceKit driven by the Live Link take s07 (300 frames) is transferred onto Rocketbox
(landmarks + non-rigid ICP, as in scripts/xu_renders.py); at the most expressive frame the
region with the most detail is removed, enhanced, copy-pasted to the other cheek's mirror
place and reshaped (eq. 17), each applied to every frame of its μ window ("per_frame"); the
profile plot compares with the paper's eq. 18-21 propagation. Prints one line per edit
(window, time, activity at the key frame before/after) and writes
docs/transfer/detail_edit.png (shaded close-ups), detail_edit_magnitude.png (|D_t| and each edit's change, mm)
and detail_edit_profile.png (the selection's detail activity over time).

    python scripts/xu_detail_edits.py [--fast]

``--fast`` skips the non-rigid ICP (landmark similarity + closest-point projection only).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))
OUT = ROOT / "docs" / "transfer"
DATA = ROOT / "data"


def transfer(fast: bool):
    from core.io.gltf import read_rig
    from core.io.layout import read_layout
    from core.io.livelink import read_livelink
    from core.names import NameMap
    from core.transfer import register, transfer_sequence
    from core.geometry import weld_vertices
    from core.transfer.performance import shared_landmarks

    ict = read_rig(DATA / "rigs" / "ict_facekit.glb")
    rb = read_rig(DATA / "rigs" / "rocketbox_female_adult_02.glb")
    li = read_layout(DATA / "layouts" / "ict_facekit.json", ict)
    lr = read_layout(DATA / "layouts" / "rocketbox_female_adult_02.json", rb)
    src_lm, tgt_pts = shared_landmarks(li, lr, rb.neutral)
    perf = read_livelink(DATA / "performances" / "livelinkface_take_s07.csv")
    G = NameMap.automatic(perf.names, ict.names).matrix(perf.names, ict.names)
    seq = ict.evaluate(np.nan_to_num(perf.data[:600:2]) @ G.T)
    wi, rep, Fw = weld_vertices(ict.neutral, ict.faces)
    t = time.time()
    reg = register(ict.neutral[rep], Fw, rb.neutral, rb.faces, wi[src_lm], tgt_pts, icp=not fast)
    print(f"registration {time.time() - t:.1f} s")
    t = time.time()
    res = transfer_sequence(ict.neutral, ict.faces, seq, reg.resampled[wi], ict.faces, max_bases=20)
    print(f"transfer {time.time() - t:.1f} s, K = {res.n_bases}")
    return ict, seq, res


def main(fast: bool = False):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from core.transfer.detail_edit import DetailEditor
    from xu_renders import _plot

    OUT.mkdir(parents=True, exist_ok=True)
    ict, seq, res = transfer(fast)
    ed = DetailEditor.from_result(res)
    motion = np.linalg.norm(seq - ict.neutral, axis=2).mean(1)
    k = int(np.argmax(motion))
    X = ed.surface(k)
    N = ed.normals(k)
    coat = np.linalg.norm(ed.coating(k), axis=1)
    # the busiest front-facing vertex on the face (not inside the mouth or the eyes)
    centre = X.mean(0)
    front = (N[:, 2] > 0.7) & (X[:, 2] > centre[2]) & (np.abs(X[:, 0] - centre[0]) > 0.015)
    v = int(np.flatnonzero(front)[np.argmax(coat[front])])
    radius = 0.008
    region = ed.select_paint([v], radius, k)
    mirror = X[v] * [-1, 1, 1] + [2 * centre[0], 0, 0]
    anchor = int(np.flatnonzero(front)[np.argmin(np.linalg.norm(X[front] - mirror, axis=1))])
    # a "wrinkle": the chain through the region along its principal direction, moved 4 mm up
    P = X[region] - X[region].mean(0)
    axis = np.linalg.svd(P, full_matrices=False)[2][0]
    ends = region[[np.argmin(P @ axis), np.argmax(P @ axis)]]
    curve = [int(ends[0]), v, int(ends[1])]
    target = X[curve] + [0, 0.004, 0]

    edits = {
        "remove (×0)": ed.scale(region, k, 0.0),
        "enhance (×2.5)": ed.scale(region, k, 2.5),
        "copy-paste, mirrored, to the other cheek": ed.copy_paste(region, k, anchor, mode="replace", mirror=True),
        "reshape: wrinkle 4 mm up (eq. 17)": ed.reshape(curve, target, k, 0.004),
    }
    base_act = ed.activity(region)
    shown, mags, profiles = [], [], {"transfer": base_act}
    for name, e in edits.items():
        out = ed.apply(e, propagation="per_frame")
        after = ed.rebase(details=out.details)
        sel = e.vertices if e.kind == "copy_paste" else e.selection
        before_k, after_k = ed.activity(sel)[k], after.activity(sel)[k]
        ts, te = out.window
        untouched = np.array_equal(out.details[:ts], res.details[:ts]) and np.array_equal(out.details[te + 1:],
                                                                                          res.details[te + 1:])
        print(f"{name}: key frame {k}, window {ts}-{te} ({te - ts + 1} frames), {out.seconds['total']:.2f} s, "
              f"rank {out.rank}, edit vertices {len(e.vertices)}, activity at key frame {before_k:.3e} -> "
              f"{after_k:.3e} (x{after_k / max(before_k, 1e-300):.2f}), max change {out.max_change_mm:.3f} mm, "
              f"frames outside the window unchanged: {untouched}")
        shown.append((name, res.large_scale(k)[0] + (res.neutral - res.target_smooth_ref) + out.details[k]))
        mags.append(np.linalg.norm(out.details[k] - res.details[k], axis=1) * 1000)
        if e.kind == "scale":
            profiles[name + ", per frame"] = after.activity(region)
            paper = ed.apply(e)  # eq. 18-21 with the paper's weights
            profiles[name + ", eq. 18-21"] = ed.rebase(details=paper.details).activity(region)
    base = res.large_scale(k)[0] + (res.neutral - res.target_smooth_ref)
    meshes = [base + res.details[k]] + [m for _, m in shown]
    titles = [f"transfer, frame {k}"] + [n for n, _ in shown]
    faces = np.asarray(res.faces)
    _plot(meshes, titles, OUT / "detail_edit.png", faces, zoom=3.0, focus=[(X[v] + X[anchor]) / 2] * len(meshes),
          window=(2200, 520))
    _plot(meshes, [f"details |D_{k}| (mm)"] + ["change (mm): " + t for t in titles[1:]], OUT / "detail_edit_magnitude.png",
          faces, zoom=3.0,
          focus=[(X[v] + X[anchor]) / 2] * len(meshes), scalars=[np.linalg.norm(res.details[k], axis=1) * 1000] + mags,
          clim=(0, 1.0), window=(2200, 520))
    fig, ax = plt.subplots(figsize=(8, 3))
    for name, p in profiles.items():
        ax.plot(p, label=name)
    ax.axvline(k, color="k", lw=0.5)
    ax.set_xlabel("frame")
    ax.set_ylabel("Σ |ξ_t| in the selection")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "detail_edit_profile.png", dpi=110)
    print("wrote", OUT / "detail_edit_profile.png")


if __name__ == "__main__":
    main(fast="--fast" in sys.argv)
