"""Normal-map test page, served by tests/browser/test_normalmap_browser.py.

Default: the dashboard's :class:`~dashboard.normalmap_view.NormalMapView` on ICT FaceKit with a
synthetic, deterministic track (:func:`track`) at frame :data:`FRAME` (a strong, asymmetric
expression), plus a frame selector that calls ``view.update(snapshot, frame)`` as the
dashboard does.

``?check=orientation``: three full-resolution ICT neutrals side by side (one shape kept, so
the page is light): ``plain`` (vertex normals), ``neutral map`` (the neutral's own baked map
read through the rig's UVs), ``flipped map`` (the same map upside down, a control) and
``fast + map`` (the neutral map on a viewer with ``shading="auto"``, i.e. the per-vertex
"fast" shader on SwiftShader, which a normal map must replace by the standard one); the
button "remove map" takes that viewer's map away again.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import panel as pn

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io.gltf import read_rig  # noqa: E402
from core.normalmap import frame_normal_map, texture_coordinates  # noqa: E402
from core.pipeline import Pipeline  # noqa: E402
from dashboard import normalmap_view as nv  # noqa: E402
from dashboard.viewer import MeshViewer  # noqa: E402

RIG = ROOT / "data" / "rigs" / "ict_facekit.glb"
FRAME = 12
T = 24
ORIENTATION_LABELS = ("plain", "neutral map", "flipped map", "fast + map")


def track(rig, T: int = T) -> np.ndarray:
    """(T, K): a smile, raised brows, an open jaw and a left squint building up and fading."""
    W = np.zeros((T, rig.n_shapes))
    ramp = np.sin(np.pi * np.arange(T) / (T - 1)) ** 2  # 0 at the ends, 1 mid-way
    for name, peak in (("mouthSmile_L", 1.0), ("mouthSmile_R", 0.7), ("jawOpen", 0.45), ("browInnerUp_L", 0.9),
                       ("browInnerUp_R", 0.9), ("browOuterUp_L", 0.6), ("cheekSquint_L", 0.8), ("eyeSquint_L", 0.6),
                       ("noseSneer_L", 0.7), ("mouthDimple_R", 0.5)):
        W[:, rig.index(name)] = peak * ramp
    return W


def snapshot(rig, W) -> dict:
    return {"target_rig": rig, "weights": W, "fps": 30.0, "times": np.arange(len(W)) / 30.0, "method": "bounded",
            "segment": None, "solve_info": {}, "solver_names": list(rig.names)}


def query(name: str, default: str) -> str:
    args = pn.state.session_args if pn.state.curdoc and pn.state.curdoc.session_context else {}
    vals = args.get(name) if args else None
    return vals[0].decode() if vals else default


def pipeline(**settings) -> Pipeline:
    """A pipeline on the ICT target: its normal-map stages bake what the page shows."""
    return Pipeline(target_rig=str(RIG), **settings)


def orientation_page(rig):
    b = pipeline(normalmap_resolution=512).results(["normalmap_bake"])["normalmap_bake"]["bake"]
    st = texture_coordinates(rig.uvs, b.raster)
    neutral = frame_normal_map(b, np.zeros((1, rig.n_shapes)))
    one = rig.subset(["jawOpen"])
    lo, hi = rig.neutral.min(0), rig.neutral.max(0)
    common = dict(shading="standard", sync_group="orientation", width=310, height=460, frame_bounds=list(np.r_[lo, hi]))
    views = [MeshViewer.from_rig(one, label=ORIENTATION_LABELS[0], **common),
             MeshViewer.from_rig(one, uvs=st, normal_map=neutral, label=ORIENTATION_LABELS[1], **common),
             MeshViewer.from_rig(one, uvs=st, normal_map=np.ascontiguousarray(neutral[::-1]), label=ORIENTATION_LABELS[2], **common),
             MeshViewer.from_rig(one, uvs=st, normal_map=neutral, label=ORIENTATION_LABELS[3], **dict(common, shading="auto"))]
    remove = pn.widgets.Button(name="remove map")
    remove.on_click(lambda e: views[3].set_normal_map(None))
    return pn.Column(remove, pn.Row(*views))


def app():
    rig = read_rig(RIG)
    if query("check", "") == "orientation":
        return orientation_page(rig)
    W = track(rig)
    snap = snapshot(rig, W)
    view = nv.NormalMapView(pipeline(), view_width=400)
    view.update(snap, FRAME)
    frame = pn.widgets.Select(name="frame", options=list(range(T)), value=FRAME, width=120)
    frame.param.watch(lambda e: view.update(snap, e.new), "value")
    return pn.Column(frame, view, sizing_mode="stretch_width")


if __name__.startswith("bokeh"):
    pn.extension()
    app().servable(title="normal map test")
