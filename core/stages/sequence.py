"""The source face of a mesh-sequence source that has no source rig.

A dense mesh sequence (a folder of OBJ/PLY frames, a glTF with morph-target frames, a USD mesh
with time-sampled points; :mod:`core.io.sequence`) carries its own topology. When no source rig
is chosen, this stage makes that topology the source face: the first frame with data and the
sequence's faces (:func:`core.io.sequence.topology_rig`), and the source layout
(``--source-layout``, a layout on the sequence's vertices) read on it. The marker methods read
the sequence's markers through that layout (their neutral is the range's neutral frame, as for a
capture); the dense stages (:mod:`.dense`) weld, register and transfer on that topology.

It is active only without a source rig, so a weight-curve source keeps the keys it had: its
registration (the long step of a transfer) is still shared by every take of a rig pair.
"""

from __future__ import annotations

import warnings

from ..io.layout import LayoutRigMismatch, read_layout
from ..io.sequence import topology_rig
from ..progress import report
from ..stage import Stage, register


@register("sequence_face")
class SequenceFace(Stage):
    """A mesh sequence's own topology and the source layout on it (see the module docstring)."""

    deps = ("take", "source_face")

    def active(self, cfg):
        return not cfg.source_face.source_rig

    def run(self, inputs, s, progress=None):
        src = inputs["take"]["source"]
        if src.kind != "meshes":
            return {"source_rig": None, "source_layout": None}

        report(progress, 0.5, "mesh-sequence topology")
        rig = topology_rig(src)
        path = inputs["source_face"].get("source_layout_path")
        layout = None
        if path:
            with warnings.catch_warnings():  # a sequence has no rig file name to compare the layout's with
                warnings.simplefilter("ignore", LayoutRigMismatch)
                layout = read_layout(path, rig=rig)
        return {"source_rig": rig, "source_layout": layout}


def source_face(inputs) -> tuple:
    """``(rig, layout)`` of the source: the source rig and its layout, else a mesh sequence's own
    topology and layout (``inputs["sequence_face"]``), else ``(None, None)``."""
    sf = inputs["source_face"]
    if sf["source_rig"] is not None:
        return sf["source_rig"], sf["source_layout"]
    sq = inputs.get("sequence_face") or {}
    return sq.get("source_rig"), sq.get("source_layout")
