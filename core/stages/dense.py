"""Dense transfer (Xu et al. 2014) as pipeline stages, each cached on its own.

::

    take, source_face, frames ── dense_source ──────────────┐
    source_face ── weld ─┬──────────────────── decompose ── bases ──┐
    target_face ─────────┴── register (per rig pair) ───────────────┴── deform ── details ── transfer
                                                                                               │
                                                      transfer_edit (Xu §4.3) ── detail_edit (§5.2) ── detail_morphs
                                                                                 target_face ── dense_output (target | source mesh)

The registration depends on the two rigs and their layouts only: a new take, frame range or
basis setting reuses it (it is most of a transfer's time). The steps are the functions
:func:`core.transfer.transfer_sequence` composes, so the library call and the pipeline compute
the same numbers. Edits are the shot's ``transfer_edits`` and ``detail_edits`` lists (plain
data, see :class:`core.transfer.edit.TransferEditor` and
:meth:`core.transfer.detail_edit.DetailEditor.key_edit`).
"""

from __future__ import annotations

import numpy as np
import param

from ..model import Rig
from ..progress import report
from ..stage import Stage, register
from ..transfer import (
    TransferSettings, assemble_result, decompose_sequence, register_target, select_sequence_bases, transfer_bases,
    transfer_details, weld_source)
from ..transfer.carry import carry_back
from ..transfer.correspond import face_crop
from ..transfer.detail_edit import DetailEditor, apply_detail_edits
from ..transfer.details import detail_morph_targets
from ..transfer.edit import apply_transfer_edits
from ..transfer.performance import default_feature_lines, dense_sequence, shared_landmarks
from .sequence import source_face


def _settings(**fields):

    return TransferSettings(**fields)


@register("dense_source")
class DenseSource(Stage):
    """The dense source sequence (T, V, 3): a mesh sequence as is, or the weight curves driving
    the source rig, over the frames of the shot's range that are also in the transfer's range.
    Tracking-loss frames are gaps (:mod:`core.gaps`): their weights are filled before the rig
    is driven, and ``valid`` flags them."""

    deps = ("take", "source_face", "frames")
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_first_frame = param.Integer(label='First frame of the transfer', default=0, bounds=(0, None), doc="First frame of the take the dense transfer uses")
    transfer_last_frame = param.Integer(label='Last frame of the transfer', default=-1, bounds=(-1, None), doc=(
        "Last frame of the take the dense transfer uses (-1: the end); it runs on the frames in both this range and "
        "the retargeting range (a transfer of 2,000 ICT frames takes minutes)"))

    def run(self, inputs, s, progress=None):

        src = inputs["take"]["source"]
        fr = inputs["frames"]
        first = max(fr["first"], s.transfer_first_frame)
        stop = fr["stop"] if s.transfer_last_frame < 0 else min(fr["stop"], s.transfer_last_frame + 1)
        if first >= stop:
            raise ValueError(f"dense transfer: no frame is in both the retargeting range ({fr['first']}–{fr['stop'] - 1}) "
                             f"and the transfer range ({s.transfer_first_frame}–{s.transfer_last_frame})")
        part = src.frames(first, stop)
        report(progress, 0.2, "dense source")
        seq, valid = dense_sequence(part, inputs["source_face"]["source_rig"], inputs["source_face"]["name_map"])
        return {"sequence": seq, "valid": valid, "first": first, "stop": stop, "fps": part.fps,
                "times": part.times - part.times[0]}


@register("weld")
class Weld(Stage):
    """The source rig welded at UV seams (:func:`core.transfer.weld_source`); for a mesh sequence
    without a source rig, its own topology (first frame with data, :mod:`.sequence`)."""

    deps = ("source_face", "sequence_face")

    def run(self, inputs, s, progress=None):

        rig, _ = source_face(inputs)
        if rig is None:
            raise ValueError("transfer needs a source topology: the source rig (--source-rig) that weight curves drive, "
                             "or a mesh-sequence source (which carries its own)")
        return {"welded": weld_source(rig.neutral, rig.faces)}


@register("register")
class Register(Stage):
    """§3: the target reference in the source topology, by landmarks (the markers both layouts
    share) + non-rigid ICP + closest points. Depends on the rig pair only."""
    cost = 6.0  # seconds for ICT → Rocketbox (14K vertices, 5–6 s, docs/transfer.md)

    deps = ("source_face", "target_face", "weld", "sequence_face")
    persist = True
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_crop = param.Selector(label='Part of the source head fitted', default="auto", objects=["auto", "face", "none"], doc=(
        "Which part of the source head the registration fits: auto = the face crop when the target lacks the rest of "
        "the head (animal heads), face, or none (the whole head)"))
    transfer_icp = param.Boolean(label='Fit the surface (non-rigid ICP)', default=True, doc="Non-rigid ICP after the landmark similarity (off: similarity + closest points only)")

    def run(self, inputs, s, progress=None):

        tf = inputs["target_face"]
        (_, layout), target = source_face(inputs), tf["target_rig"]
        welded = inputs["weld"]["welded"]
        same = len(target.neutral) == len(welded.neutral) and np.array_equal(target.faces, welded.source_faces)
        if layout is None and not same:
            raise ValueError("transfer: registering the target needs landmarks: give the source layout on the mesh "
                             "sequence's topology (--source-layout)")
        landmarks = shared_landmarks(layout, tf["target_layout"], target.neutral) if layout is not None else None
        cfg = _settings(landmarks=landmarks, crop=s.transfer_crop, icp=s.transfer_icp)
        Tw0, reg = register_target(welded, target.neutral, target.faces, cfg, progress)
        return {"target_welded": Tw0, "registration": reg, "landmarks": landmarks}


@register("decompose")
class Decompose(Stage):
    """Eq. 1-4: Taubin smoothing and Laplacian coating of the source sequence."""
    cost = 6.7  # seconds on the 56K-vertex benchmark (decomposition_s, docs/transfer.md)

    deps = ("weld", "dense_source")
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_iterations = param.Integer(label='Smoothing of the large scale (Taubin iterations)', default=40, bounds=(0, 500), doc="Taubin smoothing iterations of the decomposition (about 40 in the paper)")

    def run(self, inputs, s, progress=None):

        report(progress, 0.1, "decomposition (smoothing + Laplacian coating)")
        return {"decomposition": decompose_sequence(inputs["weld"]["welded"], inputs["dense_source"]["sequence"],
                                                    _settings(iterations=s.transfer_iterations))}


@register("bases")
class Bases(Stage):
    """Eq. 6-7: greedy basis selection with non-negative weights."""
    cost = 0.3  # seconds on the 56K-vertex benchmark (basis_selection_s, docs/transfer.md)

    deps = ("decompose",)
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_eps = param.Number(label='Basis accuracy (Xu ε)', default=1e-3, bounds=(0, None), softbounds=(0, 0.01), doc="Basis selection stops below this relative residual energy ε (eq. 7)")
    transfer_max_bases = param.Integer(label='At most this many bases', default=30, bounds=(1, 200), doc="At most this many bases")

    def run(self, inputs, s, progress=None):

        sel, src_bases = select_sequence_bases(inputs["decompose"]["decomposition"],
                                               _settings(eps=s.transfer_eps, max_bases=s.transfer_max_bases))
        return {"selection": sel, "source_bases": src_bases}


@register("deform")
class Deform(Stage):
    """Eq. 9-11: feature-preserving deformation transfer of the bases."""
    cost = 1.6  # seconds on the 56K-vertex benchmark (transfer_s, docs/transfer.md)

    deps = ("weld", "decompose", "bases", "register", "source_face", "sequence_face")
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_alpha = param.Number(label='Keep eye and mouth rims (Xu α)', default=100.0, bounds=(0, None), softbounds=(0, 1000), doc="Weight α of the eye and mouth feature lines in eq. 9 (100 in the paper)")
    transfer_feature_lines = param.Boolean(label='Eye and mouth feature lines', default=True, doc="Feature lines from the rims near the source layout's eye and mouth markers (eq. 9)")

    def relevant(self, cfg):
        return ("transfer_alpha", "transfer_feature_lines") if cfg.deform.transfer_feature_lines else ("transfer_feature_lines",)

    def run(self, inputs, s, progress=None):

        rig, layout = source_face(inputs)
        lines = default_feature_lines(rig, layout) if s.transfer_feature_lines else None
        report(progress, 0.2, f"deformation transfer of {len(inputs['bases']['source_bases'])} bases")
        bt = transfer_bases(inputs["weld"]["welded"], inputs["decompose"]["decomposition"], inputs["bases"]["source_bases"],
                            inputs["register"]["target_welded"], _settings(feature_lines=lines, alpha=s.transfer_alpha if lines is not None else 100.0))
        return {"transfer": bt, "feature_lines": lines}


@register("details")
class Details(Stage):
    """Eq. 16, 5: the fine-scale details of every frame, as displacements on the target."""
    cost = 19.5  # seconds on the 56K-vertex benchmark (details_s, docs/transfer.md)

    deps = ("weld", "decompose", "bases", "register", "deform")
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_details = param.Selector(label='Fine details (wrinkles)', default="morphs", objects=["morphs", "none"], doc=(
        "Fine-scale details: 'morphs' transfers them (and writes them as low-rank morph targets xu_detail_NN in the "
        "GLB), 'none' the large-scale bases only"))

    def run(self, inputs, s, progress=None):

        if s.transfer_details == "none":
            return {"details": None}
        details = transfer_details(inputs["weld"]["welded"], inputs["decompose"]["decomposition"], inputs["bases"]["selection"],
                                   inputs["register"]["target_welded"], inputs["deform"]["transfer"], _settings(details=True),
                                   progress)
        return {"details": details}


@register("transfer")
class Transfer(Stage):
    """The assembled :class:`core.transfer.TransferResult` (source topology fitted to the target)."""

    deps = ("weld", "register", "decompose", "bases", "deform", "details", "dense_source")

    def run(self, inputs, s, progress=None):

        b = inputs["bases"]
        result = assemble_result(inputs["weld"]["welded"], inputs["register"]["target_welded"], inputs["decompose"]["decomposition"],
                                 b["selection"], b["source_bases"], inputs["deform"]["transfer"], inputs["details"]["details"],
                                 inputs["register"]["registration"])
        ds = inputs["dense_source"]
        return {"result": result, "first": ds["first"], "times": ds["times"], "fps": ds["fps"], "valid": ds["valid"]}


@register("transfer_edit")
class TransferEdit(Stage):
    """Large-scale edits (Xu 2014 §4.3, eq. 12-15) of the transfer, in order."""

    deps = ("transfer",)
    transfer_edits = param.List(default=[], item_type=dict, doc=(
        "Large-scale edits: {constraints: [{kind: point|fixed, frame, vertex, target} | {kind: distance, frame, i, j, "
        "distance}], window: [a, b] or null, lam_b, lam_w, lam_e}"))

    def run(self, inputs, s, progress=None):

        r = inputs["transfer"]["result"]
        if not s.transfer_edits:
            return {"deltas": r.deltas, "weights": r.weights, "reports": []}
        return apply_transfer_edits(r.editor(), s.transfer_edits)


@register("detail_edit")
class DetailEdit(Stage):
    """Fine-scale detail edits (Xu 2014 §5.2, eq. 17-21), in order, on the edited large scale."""

    deps = ("transfer", "transfer_edit")
    detail_edits = param.List(default=[], item_type=dict, doc=(
        "Detail edits: {op: scale|copy_paste|reshape, frame, selection: {mode, picks, strokes, radius}, ...}"))

    def run(self, inputs, s, progress=None):
        r = inputs["transfer"]["result"]
        if r.details is None or not s.detail_edits:
            if s.detail_edits:
                raise ValueError("detail edits need a transfer with fine-scale details (transfer_details = morphs)")
            return {"details": r.details, "reports": []}

        te = inputs["transfer_edit"]
        editor = DetailEditor.from_result(r, deltas=te["deltas"], weights=te["weights"])
        return apply_detail_edits(editor, s.detail_edits)


@register("detail_morphs")
class DetailMorphs(Stage):
    """The (edited) details as a few low-rank morph targets, for playback and the GLB
    (:func:`core.transfer.details.detail_morph_targets`)."""

    deps = ("detail_edit",)
    group, title = "dense", "Dense transfer (Xu 2014)"
    detail_tolerance = param.Number(label='Detail morph-target accuracy', default=0.05, bounds=(0, 1), doc=(
        "Largest allowed error of the detail morph targets, relative to the largest detail"))

    def run(self, inputs, s, progress=None):

        details = inputs["detail_edit"]["details"]
        if details is None:
            return {"coeffs": None, "basis": None, "max_error": 0.0}
        C, B, err = detail_morph_targets(details, rtol=s.detail_tolerance)
        return {"coeffs": C, "basis": B, "max_error": float(err)}


@register("dense_output")
class DenseOutput(Stage):
    """The rig the transfer is written as: on the target's own mesh (its neutral, vertex order,
    faces and UVs; the bases and detail morph targets carried back through the registration,
    :func:`core.transfer.carry.carry_back`), or on the fitted source topology the transfer ran
    in. A stage of its own: switching ``transfer_output`` re-runs no transfer."""

    deps = ("transfer", "transfer_edit", "detail_morphs", "target_face", "register")
    group, title = "dense", "Dense transfer (Xu 2014)"
    transfer_output = param.Selector(default="target", objects=["target", "source"], doc=(
        "Mesh of the written rig: target = the target's own mesh (its vertices, faces and UVs; the transfer carried "
        "back through the registration, neutral outside the face), source = the source topology fitted to the target"))

    def run(self, inputs, s, progress=None):

        r = inputs["transfer"]["result"]
        te, dm = inputs["transfer_edit"], inputs["detail_morphs"]
        target = inputs["target_face"]["target_rig"]
        names = list(r.to_rig().names)
        deltas, weights = te["deltas"], te["weights"]
        if dm["basis"] is not None:  # the per-frame details as extra morph targets
            names += [f"xu_detail_{j:02d}" for j in range(len(dm["basis"]))]
            deltas = np.concatenate([deltas, dm["basis"]])
            weights = np.hstack([weights, dm["coeffs"]])
        carry, name = None, f"{target.name}_transfer"
        if s.transfer_output == "source":
            rig = Rig(r.neutral, r.faces, deltas, names, None, "m", name)
        elif r.registration is None:  # the target has the source's topology: its own mesh already
            rig = Rig(target.neutral, target.faces, deltas, names, target.uvs, "m", name)
        else:
            report(progress, 0.1, "carrying the transfer back to the target's own mesh")

            reg, w = r.registration, r.welded
            # the face skin the motion is carried from: the registration's crop, or the face crop
            crop = reg.crop if reg.crop is not None else face_crop(w.welded_neutral, w.faces, w.index[inputs["register"]["landmarks"][0]])
            trusted = crop[w.index]
            carry = carry_back(r.neutral, r.faces, target.neutral, trusted, target_faces=target.faces)
            rig = Rig(target.neutral, target.faces, carry.apply(deltas), names, target.uvs, "m", name)
        return {"rig": rig, "weights": weights, "carry": carry, "mesh": s.transfer_output,
                "n_details": 0 if dm["basis"] is None else len(dm["basis"]), "detail_error": dm["max_error"]}
