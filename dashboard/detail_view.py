"""Fine-scale detail editing in the dense-transfer tab (Xu et al. 2014 §5.2, eq. 17-21).

The card drives :class:`core.transfer.detail_edit.DetailEditor` from clicks on the transfer's
3D view (the tab's "Click does" selector routes the viewer's ``picked`` events here):

* **select** — *paint*: every vertex within the radius of a clicked vertex or of a stroke (a
  drag across the mesh, from its start vertex to the vertex nearest its end); *curve*: click along
  a wrinkle, every vertex within the radius (the distance threshold) of the polyline. The key
  frame is the frame of the first click; the selection is coloured on the mesh.
* **operation** — *scale* (0 removes, < 1 weakens, > 1 enhances), *copy-paste* (click the
  anchor vertex where the selection's details go; rotation about the normal, scale, replace or
  add, mirror), *reshape wrinkle* (a curve selection is the wrinkle; click the new curve's points).
* **apply** — the key-frame edit spread over the frames where the selection's details are
  active (coating ratio μ): *per frame* (default) repeats the operation on every frame of that
  window, so the edit follows the details' motion; *eq. 18-21* is the paper's propagation with
  λ_e, λ_t, λ_s (it keeps fine-grained edits near the key frame, see docs/transfer.md). The
  edit is a spec appended to the shot's ``detail_edits`` (undo/redo are the pipeline's); the
  pipeline's ``detail_edit`` stage computes the new details.

Details are shown on the paused frame as the viewer's ``offsets`` (``TransferResult.details``
is a per-frame displacement the blendshape rig does not hold); while playing, the viewer shows
the large-scale rig only (one (V, 3) array per frame would be 175 KB per frame on ICT) unless
*Details while playing* is ticked: the details then travel once as a few dozen extra morph
targets (:func:`core.transfer.details.detail_morph_targets`, error ≤ 5 % of the largest
detail, measured and shown) played with the bases.
No numerics here: the view only maps rig ids, frames and widget values to specs and core calls.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np
import panel as pn

from core.transfer.detail_edit import DetailEditor

# vertex colours are linear RGB in three.js (mesh_color is sRGB): MESH_RGB is #d8b49c, the
# viewer's default mesh_color, in linear RGB, so the unselected skin keeps its colour
SELECTION_RGB = (1.0, 0.6, 0.02)
MESH_RGB = (0.6866, 0.4566, 0.3327)
TOOLS = ["large-scale constraint", "detail selection", "paste anchor", "wrinkle target"]


class DetailPanel:
    """The fine-scale card of :class:`dashboard.transfer_view.TransferView` (its ``host``).

    The host owns the viewer, the state stack and the edit list; it calls :meth:`reset` when a
    new transfer is shown, :meth:`on_pick` for clicks while a detail tool is active and
    :meth:`show_frame` when the frame or play state changes.
    """

    def __init__(self, host):
        self.host = host
        self.editor: Optional[DetailEditor] = None  # for the selection preview (the stage makes the edits)
        self.picks: list[int] = []        # rig vertex ids (selection clicks, in order)
        self.strokes: list[tuple] = []    # (rig id, rig id): drags across the mesh (paint)
        self.key_frame: Optional[int] = None
        self.anchor: Optional[int] = None  # rig vertex id
        self.targets: list[list] = []     # wrinkle target points (metres)
        self._build()

    def _build(self):
        self.w_show = pn.widgets.Toggle(name="Show fine details (paused frame)", value=True, button_type="light")
        self.w_show.param.watch(lambda e: self.show_frame(), "value")
        self.w_play = pn.widgets.Toggle(name="Details while playing (extra morph targets)", value=False, button_type="light")
        self.w_play.param.watch(lambda e: self._on_play_details(), "value")
        self.w_select = pn.widgets.RadioButtonGroup(name="Selection", options=["paint", "curve"], value="paint",
                                                    button_type="light")
        self.w_select.param.watch(lambda e: self.draw(), "value")
        self.w_radius = pn.widgets.FloatInput(name="Radius / distance threshold (mm)", value=4.0, start=0.0, step=0.5,
                                              width=170)
        self.w_radius.param.watch(lambda e: self.draw(), "value")
        self.w_op = pn.widgets.Select(name="Operation", options=["scale", "copy-paste", "reshape wrinkle"], value="scale",
                                      width=170)
        self.w_factor = pn.widgets.FloatSlider(name="Scale factor (0 removes)", start=0.0, end=3.0, step=0.05, value=0.0,
                                               sizing_mode="stretch_width")
        self.w_angle = pn.widgets.FloatInput(name="Paste rotation (deg)", value=0.0, step=15.0, width=110)
        self.w_pscale = pn.widgets.FloatInput(name="Paste scale", value=1.0, start=0.1, step=0.1, width=90)
        self.w_pmode = pn.widgets.Select(name="Paste mode", options=["replace", "add"], value="replace", width=100)
        self.w_mirror = pn.widgets.Toggle(name="Mirror: paste on the other side of the face", value=False, button_type="light")
        self.w_lam_l = pn.widgets.FloatInput(name="λ_l — stiffness of a reshaped wrinkle (eq. 17)", value=0.2, start=0.0, step=0.05, sizing_mode="stretch_width")
        self.w_prop = pn.widgets.RadioButtonGroup(
            name="Propagation", options={"per frame (follows the details)": "per_frame", "eq. 18-21 (paper)": "eq18"},
            value="per_frame", button_type="light")
        self.w_mu = pn.widgets.FloatInput(name="μ — which frames an edit reaches", value=0.23, start=0.0, end=1.0, step=0.01, sizing_mode="stretch_width")
        self.w_lam_e = pn.widgets.FloatInput(name="λ_e — follow the key frame", value=1.0, start=0.0, step=0.5, sizing_mode="stretch_width")
        self.w_lam_t = pn.widgets.FloatInput(name="λ_t — smooth in time", value=0.1, start=0.0, step=0.05, sizing_mode="stretch_width")
        self.w_lam_s = pn.widgets.FloatInput(name="λ_s — smooth on the skin", value=1.0, start=0.0, step=0.5, sizing_mode="stretch_width")
        self.w_apply = pn.widgets.Button(name="Apply detail edit", button_type="success", width=150)
        self.w_apply.on_click(lambda e: self.apply())
        self.w_clear = pn.widgets.Button(name="Clear selection", width=130)
        self.w_clear.on_click(lambda e: self.clear())
        self.w_undo = pn.widgets.Button(name="Undo detail edit", width=130)
        self.w_undo.on_click(lambda e: self.host.undo("detail"))
        self.w_redo = pn.widgets.Button(name="Redo detail edit", width=130)
        self.w_redo.on_click(lambda e: self.host.redo("detail"))
        self.w_info = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.w_edits = pn.pane.Markdown("", sizing_mode="stretch_width")
        help_ = pn.pane.Markdown(
            "Set **Click does** to *detail selection* and click on the mesh (or drag across it: a stroke): *paint* "
            "takes every vertex within the radius of a click or a stroke, *curve* every vertex within it of the line through your clicks (draw along a "
            "wrinkle). *copy-paste*: switch to *paste anchor* and click where the details go. *reshape wrinkle*: "
            "select the wrinkle as a curve, switch to *wrinkle target* and click the new curve. The edit is made at "
            "the key frame (the first click's) and spread over the frames where the selection's details are "
            "active (μ).", css_classes=["fr-muted"], sizing_mode="stretch_width")
        self.card = pn.Card(
            help_, self.w_show, self.w_play, pn.Row(self.w_select, self.w_radius), self.w_op, self.w_factor,
            pn.Row(self.w_angle, self.w_pscale, self.w_pmode), self.w_mirror, self.w_lam_l,
            self.w_prop, pn.Column(self.w_mu, self.w_lam_e, self.w_lam_t, self.w_lam_s, sizing_mode="stretch_width"), pn.Row(self.w_apply, self.w_clear),
            pn.Row(self.w_undo, self.w_redo), self.w_edits, self.w_info,
            title="Fine-scale details (Xu 2014 §5.2)", sizing_mode="stretch_width", collapsed=False)

    # -- state ---------------------------------------------------------------------------------
    def reset(self, result) -> None:
        """A new transfer: an editor on its details (factorises the detail Poisson operator)."""
        self.editor = DetailEditor.from_result(result) if result.details is not None else None
        if self.editor is not None:  # a brush of ~3 edges whatever the mesh's size
            self.w_radius.value = round(3000 * self.editor.mean_edge(), 1)
        self.clear(draw=False)
        self.w_info.object = ("" if self.editor is not None else
                              "*this transfer has no fine-scale details (details off)*")

    def current(self) -> Optional[DetailEditor]:
        """The editor on the host's current state (bases, weights, details)."""
        if self.editor is None or not self.host.dense:
            return None
        D, W = self.host.state
        return self.editor.rebase(details=self.host.current_details, deltas=D, weights=W)

    def morphs(self):
        """The current details as low-rank morph targets ``(coeffs (T, r), basis (r, V, 3),
        max error m)`` (the pipeline's ``detail_morphs`` stage); None without details."""
        if self.host.current_details is None:
            return None
        m = self.host.pipe.results(["detail_morphs"])["detail_morphs"]
        return None if m["basis"] is None else (m["coeffs"], m["basis"], m["max_error"])

    def _on_play_details(self) -> None:
        self.host._show_state()
        self.show_frame()
        m = self.morphs() if self.w_play.value else None
        if m is not None:
            self.host.status = (f"details play as {m[1].shape[0]} extra morph targets (largest error "
                                f"{m[2] * 1000:.3f} mm)")

    def clear(self, draw: bool = True) -> None:
        self.picks, self.strokes, self.key_frame, self.anchor, self.targets = [], [], None, None, []
        if draw:
            self.draw()

    def on_pick(self, tool: str, vertex: int, frame: int, position) -> None:
        """A click on the mesh while ``tool`` (one of :data:`TOOLS` but the first) is active."""
        if self.editor is None:
            self.host.status = "⚠ this transfer has no fine-scale details to edit"
            return
        if tool == "detail selection":
            if self.key_frame is None:
                self.key_frame = int(frame)
            self.picks.append(int(vertex))
            self.host.status = (f"selection: vertex {vertex}, {len(self.picks)} click(s) at key frame {self.key_frame}"
                                + (f" (this click was on frame {frame}; the key frame stays)" if frame != self.key_frame else ""))
        elif tool == "paste anchor":
            self.anchor = int(vertex)
            self.host.status = f"paste anchor: vertex {vertex}"
        elif tool == "wrinkle target":
            self.targets.append([float(x) for x in position])
            self.host.status = f"wrinkle target: {len(self.targets)} point(s)"
        self.draw()

    def on_stroke(self, vertex: int, frame: int, end) -> None:
        """A drag that started on the mesh while selecting: paint a stroke from ``vertex`` to the
        surface vertex nearest the drag's end (the viewer reports the end in the view plane
        through the start vertex); in curve mode both ends join the wrinkle chain."""
        if self.editor is None:
            self.host.status = "⚠ this transfer has no fine-scale details to edit"
            return
        if self.key_frame is None:
            self.key_frame = int(frame)
        ed = self.current()
        X = ed.surface(self.key_frame)[ed.wi]
        last = int(np.argmin(np.linalg.norm(X - np.asarray(end, dtype=float), axis=1)))
        self.picks += [int(vertex), last]
        if self.w_select.value == "paint":
            self.strokes.append((int(vertex), last))
        self.host.status = (f"selection: stroke from vertex {vertex} to {last}, {len(self.picks)} points at key frame "
                            f"{self.key_frame}")
        self.draw()

    def selection(self) -> dict:
        """The selection spec of the current picks (see :meth:`DetailEditor.select`)."""
        return {"mode": self.w_select.value, "picks": list(self.picks), "strokes": [list(s) for s in self.strokes],
                "radius": float(self.w_radius.value) / 1000}

    def region(self, ed: DetailEditor) -> np.ndarray:
        """Editor ids of the current selection (empty when nothing is picked)."""
        return ed.select(self.selection(), self.key_frame if self.key_frame is not None else 0)

    # -- drawing -------------------------------------------------------------------------------
    def highlight_ids(self) -> list:
        """Rig ids the host draws as spheres: curve clicks and the paste anchor."""
        ids = list(self.picks) if self.w_select.value == "curve" else []
        return ids + ([self.anchor] if self.anchor is not None else [])

    def draw(self) -> None:
        v = self.host.viewer
        ed = self.current()
        n_sel = 0
        if v is not None:
            if ed is not None and self.picks:
                sel = ed.to_rig(self.region(ed))
                n_sel = len(sel)
                colors = np.tile(np.asarray(MESH_RGB, dtype=np.float32), (v.neutral.shape[0], 1))
                colors[sel] = SELECTION_RGB
                v.set_colors(colors)
            elif v.colors is not None:
                v.set_colors(None)
        parts = []
        if self.picks:
            parts.append(f"selection: {n_sel} vertices ({self.w_select.value}, {len(self.picks)} clicks), key frame "
                         f"{self.key_frame}")
        if self.anchor is not None:
            parts.append(f"paste anchor: vertex {self.anchor}")
        if self.targets:
            parts.append(f"wrinkle target: {len(self.targets)} points")
        if self.editor is not None:
            self.w_info.object = " · ".join(parts) if parts else "*nothing selected*"
        done = self.host.pipe.detail_edit.detail_edits
        reports = self.host.dense["detail_edit"]["reports"] if self.host.dense else []
        self.w_edits.object = ("**Detail edits**\n\n" + "\n".join(
            f"{k}. {r['what']} at frame {r['frame']}, frames {r['window'][0]}–{r['window'][1]}, max change "
            f"{r['max_change_mm']:.2f} mm" for k, r in enumerate(reports, start=1))) if done and reports else ""
        self.w_undo.disabled = not done
        self.w_redo.disabled = not self.host.pipe.redo["detail"]
        self.host._draw_lists()

    def show_frame(self, *_) -> None:
        """Offsets of the shown frame (or none while playing / when hidden)."""
        v = self.host.viewer
        if v is None:
            return
        details = self.host.current_details
        if (self.editor is None or not self.w_show.value or v.playing or details is None
                or self.w_play.value):  # playing along as morph targets: no offsets on top
            if v.offsets is not None:
                v.set_offsets(None)
            return
        f = min(int(v.frame), len(details) - 1)
        v.set_offsets(details[f])

    # -- editing -------------------------------------------------------------------------------
    def spec(self) -> dict:
        """The detail edit the card describes now (plain data for the shot)."""
        op = {"scale": "scale", "copy-paste": "copy_paste", "reshape wrinkle": "reshape"}[self.w_op.value]
        spec = {"op": op, "frame": int(self.key_frame if self.key_frame is not None else 0), "selection": self.selection(),
                "mu": float(self.w_mu.value), "lam_e": float(self.w_lam_e.value), "lam_t": float(self.w_lam_t.value),
                "lam_s": float(self.w_lam_s.value), "propagation": self.w_prop.value}
        if op == "scale":
            spec["factor"] = float(self.w_factor.value)
        elif op == "copy_paste":
            spec.update(anchor=self.anchor, angle_deg=float(self.w_angle.value), scale=float(self.w_pscale.value),
                        mode=self.w_pmode.value, mirror=bool(self.w_mirror.value))
        else:
            spec.update(targets=[list(map(float, t)) for t in self.targets], lam_l=float(self.w_lam_l.value))
        return spec

    def apply(self) -> bool:
        """Append the card's detail edit to the shot and show the new details (False + status if not)."""
        ed = self.current()
        if ed is None:
            self.host.status = "⚠ no transfer with fine-scale details to edit"
            return False
        if not self.picks:
            self.host.status = "nothing selected: set Click does to detail selection and click on the mesh"
            return False
        spec = self.spec()
        try:
            ed.key_edit(spec)  # says what is missing (anchor, target curve, no details here) before anything runs
        except ValueError as e:
            self.host.status = f"⚠ {e}"
            return False
        t0 = time.perf_counter()
        try:
            with self.host.pipe.transaction():  # an edit that does not solve leaves no trace, here or in a review
                self.host.pipe.add_edit("detail", spec)
                self.host._recompute()
        except (ValueError, RuntimeError) as e:
            self.host.status = f"⚠ detail edit failed: {e}"
            return False
        rep = self.host.dense["detail_edit"]["reports"][-1]
        report = (f"{rep['what']} at frame {rep['frame']}, frames {rep['window'][0]}–{rep['window'][1]}, max change "
                  f"{rep['max_change_mm']:.2f} mm, {time.perf_counter() - t0:.2f} s")
        self.clear()
        self.show_frame()
        self.host.status = f"detail edit {len(self.host.pipe.detail_edit.detail_edits)}: {report}"
        return True
