"""Normal-map blending (Liu et al. 2011 §5) as pipeline stages.

``normalmap_bake`` (the target rig's per-shape maps, per rig and resolution),
``normalmap_decimate`` (the low-resolution copy the blended maps are shown on) and
``normalmap_masks`` (the local method's region masks in texture space) are cached like every
other stage; blending one frame (:func:`core.normalmap.frame_normal_map`) is a cheap pure
function the views call per frame, not a stage (a stage per frame would churn the cache).
"""

from __future__ import annotations

import param

from ..normalmap import bake_rig, decimate, mask_texels
from ..stage import Stage, register
from .methods import method_of


@register("normalmap_bake")
class NormalMapBake(Stage):
    """Object-space normal maps of every target shape, baked from the full-resolution rig."""

    deps = ("target_face",)
    group, title = "normalmap", "Normal maps (Liu 2011 §5)"
    normalmap_resolution = param.Selector(default=256, objects=[256, 512], doc="Texels per UV unit of the baked and blended maps")

    def run(self, inputs, s, progress=None):

        return {"bake": bake_rig(inputs["target_face"]["target_rig"], s.normalmap_resolution)}


@register("normalmap_decimate")
class NormalMapDecimate(Stage):
    """The decimated target (VTK quadric decimation, deltas sampled at the closest points)."""

    deps = ("target_face",)
    group, title = "normalmap", "Normal maps (Liu 2011 §5)"
    normalmap_reduction = param.Number(default=0.9, bounds=(0.05, 0.99), doc="Fraction of the triangles the decimation removes")

    def run(self, inputs, s, progress=None):

        return {"rig": decimate(inputs["target_face"]["target_rig"], s.normalmap_reduction)[0]}


@register("normalmap_masks")
class NormalMapMasks(Stage):
    """The local method's region masks at the baked maps' covered texels (None otherwise)."""

    deps = ("normalmap_bake", "segment", "target_face")

    def active(self, cfg):
        return "segment" in method_of(cfg).needs

    def run(self, inputs, s, progress=None):

        return {"masks": mask_texels(inputs["normalmap_bake"]["bake"], inputs["target_face"]["target_rig"].faces,
                                     inputs["segment"]["masks"])}
