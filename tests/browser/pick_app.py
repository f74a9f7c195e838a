"""Picking test page: one MeshViewer of the Jeeliz tiger in pick mode, what it reports shown as text.

Served by tests/browser/test_pick.py (``panel serve tests/browser/pick_app.py``). The track is
synthetic and deterministic (:func:`track`), so the test recomputes the shown mesh in numpy:
60 frames of smiles and an open mouth; the page opens on frame 30 (mouth wide open), so
picking happens on a morphed mesh, not on the neutral.

Query parameters: ``?blend=gpu|cpu|auto`` (default auto), ``?pick=vertex|off`` (default vertex).
The page shows ``picked=<json>`` and ``dragged=<json>`` (the Python values of the viewer's
params) and a pick-mode switch; every pick is highlighted from Python (``highlight``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import panel as pn

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io.gltf import read_rig  # noqa: E402
from dashboard.viewer import MeshViewer  # noqa: E402

RIG = ROOT / "data" / "rigs" / "jeeliz_tiger.glb"
FRAME = 30
LABEL = "tiger"


def track(rig, T: int = 60) -> np.ndarray:
    """(T, K) weights: mouthOpen rises to 1 at frame 30, smiles follow a slower wave."""
    t = np.arange(T)
    W = np.zeros((T, rig.n_shapes))
    W[:, rig.index("mouthOpen")] = np.sin(np.pi * t / (T - 1)) ** 2
    W[:, rig.index("smileLeft")] = 0.5 + 0.5 * np.sin(t / 7.0)
    W[:, rig.index("smileRight")] = 0.5 + 0.5 * np.sin(t / 9.0 + 1.0)
    return W


def query(name: str, default: str) -> str:
    args = pn.state.session_args if pn.state.curdoc and pn.state.curdoc.session_context else {}
    vals = args.get(name) if args else None
    return vals[0].decode() if vals else default


def app():
    rig = read_rig(RIG)
    viewer = MeshViewer.from_rig(rig, track(rig), fps=30, label=LABEL, frame=FRAME, pick_mode=query("pick", "vertex"),
                                 blend=query("blend", "auto"), width=640, height=520)
    picked = pn.pane.Str(pn.bind(lambda p: "picked=" + json.dumps(p, sort_keys=True), viewer.param.picked))
    dragged = pn.pane.Str(pn.bind(lambda d: "dragged=" + json.dumps(d, sort_keys=True), viewer.param.dragged))
    viewer.param.watch(lambda e: viewer.set_highlight([e.new["vertex"]]) if e.new else None, ["picked", "dragged"])
    mode = pn.widgets.RadioButtonGroup.from_param(viewer.param.pick_mode, name="Pick mode")
    return pn.Column(mode, viewer, picked, dragged)


if __name__.startswith("bokeh"):
    pn.extension()
    app().servable(title="pick test")
