"""A small dense-transfer case as files, for tests that go through the pipeline: the Jeeliz
tiger driven by smooth weight curves (a GLB animation on the tiger) transferred onto a
stretched copy of itself (same topology: no registration, a few seconds)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from datapaths import LAYOUTS, RIGS

T = 40
STRETCH = (1.1, 0.95, 1.0)


def tiger_weights(K: int, T: int = T) -> np.ndarray:
    t = np.arange(T)
    return np.clip(0.5 + 0.5 * np.sin(t[:, None] / (5 + 2 * np.arange(K)) + np.arange(K)), 0, 1)


def tiger_files(folder) -> dict:
    """Write the case into ``folder``; returns the pipeline's file settings."""
    from core.io.gltf import read_rig, write_rig
    from core.model import Rig

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rig = read_rig(RIGS / "jeeliz_tiger.glb")
    source = folder / "tiger_take.glb"
    write_rig(source, rig, weights=tiger_weights(rig.n_shapes), fps=30.0)
    s = np.asarray(STRETCH)
    big = Rig(rig.neutral * s, rig.faces, rig.deltas * s, rig.names, rig.uvs, rig.units, "tiger_big")
    target = folder / "tiger_big.glb"
    write_rig(target, big)
    layout = json.loads((LAYOUTS / "jeeliz_tiger.json").read_text())
    layout["rig"] = target.name
    (folder / "tiger_big.layout.json").write_text(json.dumps(layout))
    return {"source": str(source), "source_rig": str(RIGS / "jeeliz_tiger.glb"), "target_rig": str(target)}
