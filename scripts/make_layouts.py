"""Make the bundled marker layouts data/layouts/<rig>.json (reproducible; run from the repo root).

    python scripts/make_layouts.py [rig_stem ...] [--render]

The 41 AnimFace markers (data/performances/animface_markers_jaw_60hz.csv, frame 0, the actor at
rest) are placed on every bundled rig in four stated steps, then checked by eye on the renders
docs/layouts/<rig>.png (front and 3/4 views with labels):

1. **Rig features** found from geometry and the rig's own shapes, no hand-picked vertex ids:
   * *skin*: the largest connected component (after merging UV-seam duplicates), minus vertices
     whose outward normal ray hits the mesh again (eye-socket and mouth-bag interior, nostrils);
   * *rims*: visible skin vertices on a mesh boundary or next to a hidden vertex — the eyelid
     margins around each eye (found near the vertex the eye-close shape moves most) and the lip
     margins around the mouth;
   * upper lid = rim vertices the eye-close shape moves by > 50 % of its maximum, lower lid = the
     rest; canthi = the rim's two ends along its principal axis; upper/lower lip rims split by the
     jaw-open displacement; commissures = the lip rim's lateral ends.
2. **Similarity alignment** (Umeyama, trimesh.registration.procrustes) of the actor's eye corners,
   nose tip and mouth corners to the rig's canthi, nose tip and commissures, then similarity ICP
   of all 41 markers onto the visible skin of the face.
3. **Snap with anatomical rules**, each marker to the closest vertex of its allowed set:
   * eye corners -> the canthus vertex, mouth corners -> the commissure vertex (rule, not nearest);
   * Leye_Up/Reye_Up -> upper lid skin that the eye-close shape moves by > 50 % of its maximum
     (so a blink moves the marker); Leye_Down/Reye_Down -> lower lid skin within a lid band
     below the lower rim;
   * Mouth_Up, Mouth_UpL1/R1 -> upper lip (above the lip line, jaw-open moves it < 35 % of the
     jaw maximum); Mouth_Down, Mouth_DownL/R and all Chin markers -> skin the jaw-open shape moves
     by > 40 % of its maximum (the lower lip and chin ride the jaw);
   * every other marker -> nearest visible skin vertex of the aligned position;
   * left/right: the rig's +X side gets the actor's L markers (both are the person's own left).
4. **Per-rig notes** (animals): where a marker has no anatomical counterpart the nearest sensible
   spot is used and said in the layout's "notes".

The AnimFace capture is CC BY-SA 4.0 (data/licenses/AnimFace_CC-BY-SA-4.0.md); the layouts are
derived from its marker names and rest positions, so they carry that licence.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.geometry import weld_vertices  # noqa: E402
from core.io.gltf import read_rig  # noqa: E402
from core.io.layout import write_layout  # noqa: E402
from core.model import MarkerLayout, Rig  # noqa: E402

ANIMFACE = ROOT / "data" / "performances" / "animface_markers_jaw_60hz.csv"
LAYOUTS = ROOT / "data" / "layouts"
DOCS = ROOT / "docs" / "layouts"

#: per-rig shape names used to find features: (eye close left, eye close right, jaw open)
CONFIG = {
    "ict_facekit": dict(blink=("eyeBlink_L", "eyeBlink_R"), jaw="jawOpen"),
    "rocketbox_female_adult_02": dict(blink=("AK_09_EyeBlinkLeft", "AK_10_EyeBlinkRight"), jaw="AK_25_JawOpen"),
    # Jeeliz names its brow shapes from the viewer's side: eyeBrowRightUp raises the +X brow
    # (the character's left), while eyeLeftClose closes the +X eye (checked on the renders)
    "jeeliz_tiger": dict(blink=("eyeLeftClose", "eyeRightClose"), jaw="mouthOpen", warp=True, face_radius=2.6,
                         brow=("eyeBrowRightUp", "eyeBrowLeftUp")),
    # the triceratops' mouth slit runs far back along the beak: look for its corners deeper
    "jeeliz_triceratops": dict(blink=("eyeLeftClose", "eyeRightClose"), jaw="mouthOpen", mouth_depth=3.0, warp=True, face_radius=2.6,
                               brow=("eyeBrowRightUp", "eyeBrowLeftUp")),
}

UPPER_LIP = ("Mouth_Up", "Mouth_UpL1", "Mouth_UpR1")
LOWER_LIP = ("Mouth_Down", "Mouth_DownL", "Mouth_DownR")
CHIN = ("Chin", "Chin_L1", "Chin_R1", "Chin_L2", "Chin_R2")
MIDLINE = ("ForeHead_M", "Eyebrow_Center", "NoseTop", "NoseHead", "Mouth_Up", "Mouth_Down", "Chin")


# ---------------------------------------------------------------------------------------------
# the actor
def animface_rest(path: Path = ANIMFACE):
    """(names, (41, 3) metres) of frame 0 of the AnimFace capture (header frame,time_s,<n>_X...)."""
    with open(path) as f:
        header = next(csv.reader(f))
    cols = header[2:]
    names = [c[:-2] for c in cols[::3]]
    row = np.loadtxt(path, delimiter=",", skiprows=1, max_rows=1)
    return names, row[2:].reshape(-1, 3) * 0.01  # centimetres -> metres


# ---------------------------------------------------------------------------------------------
# rig features
class Features:
    """Merged topology, visible skin, rims and shape displacements of one rig."""

    def __init__(self, rig: Rig, cfg: dict):
        self.rig = rig
        V = rig.n_vertices
        # merge UV-seam duplicates: unique positions (to 1e-7 of the rig's size)
        inverse, first, mfaces = weld_vertices(rig.neutral, rig.faces, tol=1e-7 * rig.size)
        self.rep = first  # merged id -> one original vertex
        self.merged_of = inverse  # original vertex -> merged id
        mesh = trimesh.Trimesh(rig.neutral[first], mfaces, process=False)
        comps = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mfaces)))
        main_faces = max(comps, key=len)
        self.main = trimesh.Trimesh(mesh.vertices, mfaces[np.sort(main_faces)], process=False)
        on_main = np.zeros(len(first), bool)
        on_main[np.unique(self.main.faces)] = True
        # visibility: the outward normal ray must leave the surface (trimesh's ray_triangle; slow
        # for ICT, ~15 s, but this script runs once)
        normals = self.main.vertex_normals
        cand = np.flatnonzero(on_main)
        hit = self.main.ray.intersects_any(self.main.vertices[cand] + normals[cand] * rig.size * 2e-4, normals[cand])
        visible = np.zeros(len(first), bool)
        visible[cand[~hit]] = True
        # keep the largest edge-connected patch of visible vertices: socket floors and mouth-bag
        # walls seen through an opening are visible too, but cut off from the face by hidden lids
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        e = self.main.edges_unique
        e = e[visible[e[:, 0]] & visible[e[:, 1]]]
        A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(first),) * 2)
        _, label = connected_components(A, directed=False)
        big = np.bincount(label[visible]).argmax()
        self.visible = visible & (label == big)
        self.normals = normals
        # rims: visible and on a boundary or next to a hidden main vertex
        edges = self.main.edges_unique
        bnd = trimesh.grouping.group_rows(self.main.edges_sorted, require_count=1)
        boundary = np.zeros(len(first), bool)
        boundary[self.main.edges_sorted[bnd].ravel()] = True
        hidden = on_main & ~self.visible  # includes the cut-off visible patches
        next_hidden = np.zeros(len(first), bool)
        for a, b in ((0, 1), (1, 0)):
            next_hidden[edges[:, a][hidden[edges[:, b]]]] = True
        self.rim = self.visible & (boundary | next_hidden)
        self.P = self.main.vertices
        self.size = rig.size

        def disp(name):
            d = np.linalg.norm(rig.deltas[rig.index(name)], axis=1)
            return d[first]

        self.blink = [disp(n) for n in cfg["blink"]]
        self.jaw = disp(cfg["jaw"])

    def orig(self, merged_ids):
        return self.rep[np.asarray(merged_ids)]

    def _rim_component(self, seed: int, limit: float) -> np.ndarray:
        """Rim vertices connected to ``seed`` through rim-rim edges, within ``limit`` of it."""
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        e = self.main.edges_unique
        ok = self.rim & (np.linalg.norm(self.P - self.P[seed], axis=1) < limit)
        e = e[ok[e[:, 0]] & ok[e[:, 1]]]
        n = len(self.P)
        _, label = connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
        return np.flatnonzero(ok & (label == label[seed]))

    # eyes ------------------------------------------------------------------------------------
    def eye(self, side: int):
        """Rim features of eye ``side`` (0 left = +X, 1 right): dict of merged vertex ids."""
        b = self.blink[side]
        vis_b = np.where(self.visible, b, 0)
        top = int(np.argmax(vis_b))
        centre = self.P[top]
        # the eye's rim: the rim-connected ring through the rim vertex nearest the lid top (within
        # half the distance between the eyes), so a tall cartoon eye is followed all the way round
        other = self.P[int(np.argmax(np.where(self.visible, self.blink[1 - side], 0)))]
        width = 0.5 * np.linalg.norm(centre - other)
        near = np.flatnonzero(self.rim & (np.linalg.norm(self.P - centre, axis=1) < width))
        seed = near[np.argmin(np.linalg.norm(self.P[near] - centre, axis=1))]
        cand = self._rim_component(seed, limit=2 * width)
        rim = _outer_loop(self.P[cand], cand)
        upper = rim[b[rim] > 0.5 * b[top]]
        lower = rim[b[rim] <= 0.5 * b[top]]
        # canthi: the loop's ends in x (inner = towards the midline), among the loop points in
        # the middle 60 % of its height (a tall cartoon eye has its corners at mid-height)
        y = self.P[rim, 1]
        mid = rim[(y > y.min() + 0.2 * np.ptp(y)) & (y < y.max() - 0.2 * np.ptp(y))]
        med, lat = mid[np.argmin(np.abs(self.P[mid, 0]))], mid[np.argmax(np.abs(self.P[mid, 0]))]
        return dict(top=top, rim=rim, upper=upper, lower=lower, inner=med, outer=lat)

    # mouth -----------------------------------------------------------------------------------
    def mouth(self, nose: int, ipd: float, depth: float = 1.5):
        """Lip margins and corners (merged ids).

        The lip line at the midline is the top of the lower lip: the highest visible midline vertex
        below the nose that the jaw-open shape moves by more than half its maximum. The lip rim is
        the ring of rim vertices connected to the rim vertex nearest that point (within ``depth``
        eye distances: a triceratops' slit runs far back); its margins are split by the jaw-open
        displacement, and each corner is the ring vertex farthest from the midline on its side.
        """
        d = self.P - self.P[nose]
        below = self.visible & (d[:, 1] < 0) & (d[:, 1] > -2 * ipd) & (np.abs(d[:, 0]) < 1.2 * ipd) & (d[:, 2] > -depth * ipd)
        jmax = self.jaw[below].max()
        mid = np.flatnonzero(below & (np.abs(d[:, 0]) < 0.1 * ipd) & (self.jaw > 0.5 * jmax))
        centre = self.P[mid[np.argmax(self.P[mid, 1])]]
        y_lip = centre[1]
        near = np.flatnonzero(self.rim & below)
        seed = near[np.argmin(np.linalg.norm(self.P[near] - centre, axis=1))]
        cand = self._rim_component(seed, limit=depth * ipd)
        cand = cand[below[cand]]
        dist = np.linalg.norm(self.P[cand] - centre, axis=1)
        pos, neg = self.P[cand, 0] > centre[0], self.P[cand, 0] < centre[0]
        left = cand[pos][np.argmax(dist[pos])]
        right = cand[neg][np.argmax(dist[neg])]
        # the two lip margins: the jaw moves the lower one
        lower = cand[self.jaw[cand] > 0.5 * jmax]
        upper = cand[self.jaw[cand] <= 0.5 * jmax]
        return dict(rim=cand, upper=upper, lower=lower, left=left, right=right, jmax=jmax, y=y_lip)

    def nose_tip(self, eye_l, eye_r):
        """The front-most (max z) visible midline vertex below the lowest eye-rim point and above
        1.2 eye distances below the eyes (below the eyes keeps a triceratops' horn out)."""
        mid = 0.5 * (self.P[eye_l["top"]] + self.P[eye_r["top"]])
        ipd = np.linalg.norm(self.P[eye_l["top"]] - self.P[eye_r["top"]])
        y_eye = min(self.P[eye_l["rim"], 1].min(), self.P[eye_r["rim"], 1].min())
        ok = self.visible & (np.abs(self.P[:, 0] - mid[0]) < 0.15 * ipd) & (self.P[:, 1] < y_eye) & (self.P[:, 1] > mid[1] - 1.2 * ipd)
        return int(np.flatnonzero(ok)[np.argmax(self.P[ok, 2])])


# ---------------------------------------------------------------------------------------------
def place(rig: Rig, cfg: dict, names, actor, log=print):
    """Place the actor's markers on ``rig``; returns (MarkerLayout, aligned actor (41, 3), info)."""
    f = Features(rig, cfg)
    ix = {n: i for i, n in enumerate(names)}
    eL, eR = f.eye(0), f.eye(1)
    nose = f.nose_tip(eL, eR)
    ipd = np.linalg.norm(f.P[eL["top"]] - f.P[eR["top"]])
    # 1. similarity from eyes and nose
    src = actor[[ix[n] for n in ("Leye_Inside", "Leye_Outside", "Reye_Inside", "Reye_Outside", "NoseHead")]]
    dst = f.P[[eL["inner"], eL["outer"], eR["inner"], eR["outer"], nose]]
    T0, _, cost = trimesh.registration.procrustes(src, dst, reflection=False, scale=True)
    aligned = trimesh.transform_points(actor, T0)
    # 2. add the mouth corners and refit
    m = f.mouth(nose, ipd, cfg.get("mouth_depth", 1.5))
    src = actor[[ix[n] for n in ("Leye_Inside", "Leye_Outside", "Reye_Inside", "Reye_Outside", "NoseHead", "Mouth_Lend", "Mouth_Rend")]]
    dst = f.P[[eL["inner"], eL["outer"], eR["inner"], eR["outer"], nose, m["left"], m["right"]]]
    T1, _, cost = trimesh.registration.procrustes(src, dst, reflection=False, scale=True)
    # 3. similarity ICP onto the visible face skin
    face_radius = cfg.get("face_radius", 1.8) * ipd
    keep = f.visible & (np.linalg.norm(f.P - f.P[nose], axis=1) < face_radius)
    fm = f.main.faces[keep[f.main.faces].all(1)]
    skin = trimesh.Trimesh(f.P, fm, process=False)
    T2, aligned, icp_cost = trimesh.registration.icp(actor, skin, initial=T1, max_iterations=50, reflection=False, scale=True)
    # 3b. animals: thin-plate-spline warp that puts the actor's eye and mouth corners and nose tip
    # exactly on the rig's (a similarity cannot match a tiger's proportions). Not for humans: the
    # similarity already fits to ~4 mm rms, and the actor's corner markers sit ~1 cm off the canthi
    # and commissures, an offset the warp would drag the brows and cheeks along with.
    from scipy.interpolate import RBFInterpolator

    # plus the lids: the actor's Up/Down lid markers onto the top of the upper lid and the bottom
    # of the lower rim, so the warp learns the eye's height (a tiger's eye is taller than wide)
    lm_names = ("Leye_Inside", "Leye_Outside", "Reye_Inside", "Reye_Outside", "NoseHead", "Mouth_Lend", "Mouth_Rend",
                "Leye_Up", "Reye_Up", "Leye_Down", "Reye_Down")
    lids = [eL["top"], eR["top"]] + [e["lower"][np.argmin(f.P[e["lower"], 1])] for e in (eL, eR)]
    lm_dst = np.vstack([dst, f.P[lids]])
    lm_src = aligned[[ix[n] for n in lm_names]]
    warp = RBFInterpolator(lm_src, lm_dst - lm_src, kernel="thin_plate_spline", degree=1)
    before = aligned
    if cfg.get("warp", False):
        aligned = aligned + warp(aligned)
    log(f"  {rig.name}: landmark fit rms {np.sqrt(cost / 7) * 1000:.1f} mm, ICP rms {np.sqrt(icp_cost) * 1000:.1f} mm, "
        f"TPS moved markers by median {np.median(np.linalg.norm(aligned - before, axis=1)) * 1000:.1f} mm")
    # 4. snap with rules
    vis = np.flatnonzero(keep)
    chosen = {}

    used = set()

    def nearest(p, pool):
        """Closest vertex of ``pool`` to ``p`` not already holding a marker."""
        pool = np.asarray([v for v in pool if v not in used])
        v = int(pool[np.argmin(np.linalg.norm(f.P[pool] - p, axis=1))])
        used.add(v)
        return v

    eye_band = {}
    for side, e, pre in ((0, eL, "L"), (1, eR, "R")):
        bmax = f.blink[side][e["top"]]
        chosen[f"{pre}eye_Inside"] = e["inner"]
        chosen[f"{pre}eye_Outside"] = e["outer"]
        used.update((e["inner"], e["outer"]))
        up = vis[f.blink[side][vis] > 0.5 * bmax]
        chosen[f"{pre}eye_Up"] = nearest(aligned[ix[f"{pre}eye_Up"]], up)
        # lower lid band: visible, below the lower rim, within 25 % of the eye width of it
        low = f.P[e["lower"]]
        width = np.linalg.norm(f.P[e["inner"]] - f.P[e["outer"]])
        x0, x1 = sorted((f.P[e["inner"], 0], f.P[e["outer"], 0]))
        dist_low = np.min(np.linalg.norm(f.P[vis, None, :] - low[None], axis=2), axis=1)
        below = f.P[vis, 1] < np.interp(f.P[vis, 0], *_sorted_xy(low))
        band = vis[below & (dist_low < 0.25 * width) & (f.P[vis, 0] > x0) & (f.P[vis, 0] < x1) & (f.blink[side][vis] < 0.5 * bmax)]
        eye_band[pre] = band
        chosen[f"{pre}eye_Down"] = nearest(aligned[ix[f"{pre}eye_Down"]], band)
    chosen["Mouth_Lend"] = m["left"]
    chosen["Mouth_Rend"] = m["right"]
    used.update((m["left"], m["right"]))
    # lip markers sit mid-vermilion: on the lip line's height at their x, raised (upper lip) or
    # lowered (lower lip) by 7 % of the eye distance, and must be on the right lip: the upper
    # lip barely moves with jaw-open (< 35 % of its maximum), the lower lip moves (> 40 %)
    up_y = lambda x: np.interp(x, *_sorted_xy(f.P[m["upper"]]))  # noqa: E731  upper lip margin
    low_y = lambda x: np.interp(x, *_sorted_xy(f.P[m["lower"]]))  # noqa: E731  lower lip margin
    x_end = sorted((f.P[m["left"], 0], f.P[m["right"], 0]))
    within = vis[(f.P[vis, 0] > x_end[0]) & (f.P[vis, 0] < x_end[1])]
    dy_up = f.P[within, 1] - up_y(f.P[within, 0])
    dy_low = f.P[within, 1] - low_y(f.P[within, 0])
    tol = 0.01 * ipd
    upper_lip = within[(dy_up > -tol) & (dy_up < 0.15 * ipd) & (f.jaw[within] < 0.35 * m["jmax"])]
    lower_lip = within[(dy_low < tol) & (dy_low > -0.18 * ipd) & (f.jaw[within] > 0.4 * m["jmax"])]
    x0 = f.P[nose, 0]  # the midline
    midline = vis[np.abs(f.P[vis, 0] - x0) < 0.03 * ipd]
    for n in MIDLINE:  # midline markers go on the midline: x of the nose tip
        aligned[ix[n], 0] = x0
    for n in UPPER_LIP + LOWER_LIP:
        p = aligned[ix[n]].copy()
        p[1] = up_y(p[0]) + 0.06 * ipd if n in UPPER_LIP else low_y(p[0]) - 0.07 * ipd
        pool = upper_lip if n in UPPER_LIP else lower_lip
        if n in MIDLINE:
            on_mid = pool[np.abs(f.P[pool, 0] - x0) < 0.03 * ipd]
            # no lip band on the midline (a beak's overhang): the midline vertex on the right jaw
            jaw_ok = f.jaw[midline] < 0.35 * m["jmax"] if n in UPPER_LIP else f.jaw[midline] > 0.4 * m["jmax"]
            pool = on_mid if len(on_mid) else midline[jaw_ok]
        chosen[n] = nearest(p, pool)
    # chin and jaw-line markers ride the jaw: > 40 % of jaw-open's maximum (Chin_L2/R2, near
    # the hinge on the jaw line, > 15 %)
    # and Chin sits below Mouth_Down (on a beak the aligned chin lands on the underside, behind it)
    for n in CHIN:
        frac = 0.15 if n in ("Chin_L2", "Chin_R2") else 0.4
        pool = midline if n in MIDLINE else vis
        ok = f.jaw[pool] > frac * m["jmax"]
        if n == "Chin":
            ok &= f.P[pool, 1] < f.P[chosen["Mouth_Down"], 1] - 0.05 * ipd
        chosen[n] = nearest(aligned[ix[n]], pool[ok])
    # brows (rigs that name their brow shapes in CONFIG): on skin the side's brow-raise moves by
    # > 30 % of its maximum
    # within 0.1-0.6 eye distances above the eye's top (a tiger's brow shape also moves its ears)
    for side, shape, e in zip("LR", cfg.get("brow", ()), (eL, eR)):
        b = np.linalg.norm(rig.deltas[rig.index(shape)], axis=1)[f.rep]
        top = f.P[e["rim"], 1].max()
        pool = vis[(b[vis] > 0.3 * b[vis].max()) & (f.P[vis, 1] > top + 0.1 * ipd) & (f.P[vis, 1] < top + 0.6 * ipd)]
        for n in (f"{side}eyebrow_Inside", f"{side}eyebrow_M", f"{side}eyebrow_Outside"):
            chosen[n] = nearest(aligned[ix[n]], pool)
    chosen["Eyebrow_Center"] = nearest(aligned[ix["Eyebrow_Center"]], midline)
    # the forehead is above the brows (a tiger's is a narrow strip under the ears)
    brow_top = max(f.P[chosen[n], 1] for n in chosen if "brow" in n)
    for n in ("ForeHead_M", "ForeHead_L", "ForeHead_R"):
        pool = midline if n in MIDLINE else vis
        chosen[n] = nearest(aligned[ix[n]], pool[f.P[pool, 1] > brow_top + 0.05 * ipd])
    for n in names:
        if n not in chosen:
            chosen[n] = nearest(aligned[ix[n]], midline if n in MIDLINE else vis)
    merged = np.array([chosen[n] for n in names])
    layout = MarkerLayout.from_vertices(names, f.orig(merged), rig=rig.name + ".glb")
    moved = np.linalg.norm(f.P[merged] - aligned, axis=1)
    info = dict(features=f, eyes=(eL, eR), mouth=m, nose=nose, aligned=aligned, snap_mm=moved * 1000, eye_band=eye_band)
    for n, d in zip(names, moved):
        if d > 0.02 * rig.size:
            log(f"    {n}: rule moved it {d * 1000:.1f} mm from the aligned actor position")
    return layout, aligned, info


def _outer_loop(pts, ids):
    """ids of the points on the convex hull of their front projection (x, y): the outer margin
    of an eye or mouth opening, without the socket / mouth-bag vertices seen through it."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(pts[:, :2])
    return ids[np.sort(hull.vertices)]


def _sorted_xy(pts):
    o = np.argsort(pts[:, 0])
    return pts[o, 0], pts[o, 1]


# ---------------------------------------------------------------------------------------------
def render(rig: Rig, layout: MarkerLayout, out: Path, size=1000):
    """Front and 3/4-left views of the rig with its markers (red: seen, orange: hidden behind the
    surface) and every label (pyvista off screen; labels drawn with PIL so none is culled)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv
    from PIL import Image, ImageDraw, ImageFont

    pv.OFF_SCREEN = True
    faces = np.hstack([np.full((len(rig.faces), 1), 3), rig.faces]).ravel()
    mesh = pv.PolyData(np.asarray(rig.neutral), faces)
    pts = layout.points(rig.neutral)
    c = pts.mean(0)
    spread = np.linalg.norm(pts.max(0) - pts.min(0))
    panels = []
    for title, direction in (("front", np.array([0, 0, 1.0])), ("3/4 left", np.array([0.62, 0, 0.78]))):
        p = pv.Plotter(off_screen=True, window_size=(size, size))
        p.add_mesh(mesh, color="wheat", smooth_shading=True)
        p.camera_position = [tuple(c + direction * 1.9 * spread), tuple(c), (0, 1, 0)]
        img = p.screenshot(return_img=True)
        depth = p.get_image_depth(fill_value=np.inf)  # distance along the view, (size, size), row 0 at top
        cam = p.camera
        M = _matrix(cam.GetCompositeProjectionTransformMatrix(1.0, -1, 1))
        p.close()
        h = np.c_[pts, np.ones(len(pts))] @ M.T
        ndc = h[:, :3] / h[:, 3:]
        px = np.c_[(ndc[:, 0] + 1) / 2 * size, (1 - ndc[:, 1]) / 2 * size]
        dist = (pts - np.array(cam.position)) @ (np.array(cam.focal_point) - np.array(cam.position))
        dist /= np.linalg.norm(np.array(cam.focal_point) - np.array(cam.position))
        im = Image.fromarray(img)
        draw = ImageDraw.Draw(im)
        font = ImageFont.load_default(size=max(11, size // 80))
        for (x, y), dz, name in zip(px, dist, layout.names):
            xi, yi = int(np.clip(x, 0, size - 1)), int(np.clip(y, 0, size - 1))
            # pyvista's depth image is minus the distance along the view; hidden = surface in front
            seen = not np.isfinite(depth[yi, xi]) or -depth[yi, xi] >= dz - 0.02 * spread
            col = (220, 0, 0) if seen else (255, 150, 0)
            r = max(3, size // 200)
            draw.ellipse([x - r, y - r, x + r, y + r], fill=col, outline=(0, 0, 0))
            draw.text((x + r + 1, y - r - 2), name, fill=(0, 0, 0) if seen else (150, 90, 0), font=font)
        draw.text((8, 8), f"{rig.name}: {title}", fill=(0, 0, 0), font=ImageFont.load_default(size=max(14, size // 50)))
        panels.append(np.asarray(im))
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.hstack(panels)).save(out)


def _matrix(vtk_matrix) -> np.ndarray:
    return np.array([[vtk_matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rigs", nargs="*", default=list(CONFIG))
    ap.add_argument("--render", action="store_true", help="also write docs/layouts/<rig>.png")
    ap.add_argument("--out", default=str(LAYOUTS))
    args = ap.parse_args(argv)
    names, actor = animface_rest()
    for stem in args.rigs:
        rig = read_rig(ROOT / "data" / "rigs" / f"{stem}.glb")
        layout, aligned, info = place(rig, CONFIG[stem], names, actor)
        layout = MarkerLayout(layout.names, layout.vertices, layout.weights, layout.rig,
                              {"notes": NOTES.get(stem, "") + COMMON_NOTE})
        out = Path(args.out) / f"{stem}.json"
        write_layout(out, layout, rig.name + ".glb")
        print(f"wrote {out}")
        if args.render:
            render(rig, layout, DOCS / f"{stem}.png")
            print(f"wrote {DOCS / (stem + '.png')}")


COMMON_NOTE = (
    " Marker set and rest positions: AnimFace (bigoMay/AnimFace, CC BY-SA 4.0). Made by "
    "scripts/make_layouts.py (similarity + ICP of the actor's rest frame, then rule-based snapping) "
    "and checked by eye on docs/layouts/<rig>.png. L = the character's own left (+X)."
)
NOTES = {
    "ict_facekit": "ICT FaceKit generic neutral. Eye corners on the canthi, mouth corners on the commissures; "
                   "Leye_Up/Reye_Up on the upper lid (eyeBlink moves them), Leye_Down/Reye_Down just under the "
                   "lower lid margin; lip markers mid-vermilion on the right lip (jawOpen moves the lower ones).",
    "rocketbox_female_adult_02": "Rocketbox Female_Adult_02 head (game resolution, 2,458 vertices, so markers are "
                                 "on the nearest vertex, up to ~5 mm from the ideal spot). Same rules as ICT.",
    "jeeliz_tiger": "Stylised tiger: placed by analogy after a thin-plate-spline warp onto its eye corners, eye "
                    "heights, nose and mouth corners. The forehead is the narrow strip between the tall eyes and "
                    "the ears: brows sit in a band just above the eyes, ForeHead_* above them between the ears. "
                    "NoseHead is the front of the muzzle top (no nose pad geometry); NoseHead_L/R sit above the "
                    "muzzle, not on nostrils (there are none); mouth corners are tucked under the muzzle lobes. "
                    "Brow markers are on skin the brow shapes move: Jeeliz names brows from the viewer's side "
                    "(eyeBrowRightUp raises the +X brow).",
    "jeeliz_triceratops": "Stylised triceratops: placed by analogy (thin-plate-spline warp as for the tiger). "
                          "NoseHead on the snout front below the nose horn (the horn is not a nose); mouth "
                          "corners at the back ends of the beak slit; Mouth_Up/Down on the beak's upper/lower "
                          "edge at the midline; ForeHead_L/R at the brow-horn bases; the cheek markers sit on "
                          "the jaw-frill bulges; the jaw-line markers (Chin_L2/R2) crowd the front of the lower "
                          "beak. Brow shapes are named from the viewer's side as on the tiger.",
}

if __name__ == "__main__":
    main()
