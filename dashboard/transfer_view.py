"""Dense transfer (Xu et al. 2014) in the dashboard: run it on the loaded take, then edit it by
dragging vertices on the 3D view (large-scale edits, §4.3 eq. 12-15) and by selecting and
editing its fine-scale details (§5.2).

Everything numeric is the pipeline's: the dense stages (:mod:`core.stages.dense`: registration
per rig pair, decomposition, bases, deformation transfer, details) with the settings card
generated from their settings, and the shot's edit lists — a large-scale edit is a spec
appended to ``transfer_edits`` (:class:`core.transfer.edit.TransferEditor`), a detail edit one
appended to ``detail_edits`` (:meth:`core.transfer.detail_edit.DetailEditor.key_edit`); undo and
redo are the pipeline's. This view only keeps what is being picked for the next edit and lays
the results out:

* **Run**: the dense stages on a worker thread with per-stage progress; about 30-90 s on this
  machine for a few hundred ICT frames the first time, most of it the registration (cached per
  rig pair: a second take onto the same rig reuses it).
* **Show**: the transferred rig (target neutral in the source topology + K bases) playing the
  (edited) weights in a :class:`~dashboard.viewer.MeshViewer` with ``pick_mode="vertex"``;
  fine-scale details on the paused frame as the viewer's ``offsets``.
* **Edit**: *point* — drag a vertex: a point constraint at that frame, target = the drag's
  end (with *fixed* on, a click pins the vertex where it is); *distance* — pick two vertices,
  type a distance. *Apply edit* appends the edit with λ_b, λ_w, λ_e and the window (constraint
  frames ± half-width).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from typing import Optional

import numpy as np
import panel as pn
import param

from .detail_view import TOOLS, DetailPanel
from .viewer import MeshViewer
from .widgets import param_widgets

log = logging.getLogger("face_retarget.dashboard")

VIEW_HEIGHT = 460
#: settings with their own controls here (the frame range slider)
RANGE = ("transfer_first_frame", "transfer_last_frame")


class TransferView(pn.viewable.Viewer):
    """The dense-transfer tab: run Xu 2014 on the session's take, play it, edit it by dragging."""

    busy = param.Boolean(default=False)
    status = param.String(default="")

    def __init__(self, session, **params):
        super().__init__(**params)
        self.session = session
        self.pipe = session.pipeline
        self.snapshot: dict = {}
        self.dense: dict = {}  # the last dense results shown: transfer, transfer_edit, detail_edit
        self.viewer: Optional[MeshViewer] = None
        self.fps = 30.0
        self._basis_names: list = []
        self.pending: list[dict] = []
        self._pair: list = []
        self._thread: Optional[threading.Thread] = None
        self._key = None  # the transfer stage key shown
        self._links: list = []
        self._build()

    # -- layout -----------------------------------------------------------------------------
    def _build(self):
        ds = self.pipe.dense_source
        self.w_range = pn.widgets.IntRangeSlider(name="Frames of the take", start=0, end=max(1, ds.transfer_last_frame),
                                                 value=(ds.transfer_first_frame, max(ds.transfer_last_frame, 1)), step=1,
                                                 sizing_mode="stretch_width")
        self.w_range.param.watch(self._on_range, "value")
        self.w_run = pn.widgets.Button(name="Run dense transfer (Xu 2014)", button_type="primary", sizing_mode="stretch_width")
        self.w_run.on_click(lambda e: self.run())
        settings = [pn.Param(st, parameters=[n for n in st.setting_names() if n not in RANGE and
                                             not isinstance(st.param[n], param.List)],
                             widgets=param_widgets(st, st.setting_names()), show_name=False,
                             sizing_mode="stretch_width")
                    for st in self.pipe.stages.values() if type(st).group == "dense" and
                    [n for n in st.setting_names() if n not in RANGE]]
        settings_card = pn.Card(*settings, title="Transfer settings", sizing_mode="stretch_width", collapsed=True)
        self.w_progress = pn.indicators.Progress(value=0, max=100, height=12, sizing_mode="stretch_width", bar_color="primary")
        self.w_status = pn.pane.Markdown("Transfers the take's dense motion onto the target's face (Xu et al. 2014). "
                                         "2,000 ICT frames take minutes; start with a few hundred.", sizing_mode="stretch_width")
        self.viewer_box = pn.Column(pn.pane.Markdown("*no transfer yet*"), sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.w_frame = pn.widgets.IntSlider(name="Frame (of the range)", start=0, end=1, value=0, sizing_mode="stretch_width")
        self.w_play = pn.widgets.Toggle(name="▶ Play / ❚❚ Pause", button_type="success", width=150)
        self.w_mode = pn.widgets.RadioButtonGroup(name="Constraint", options=["point", "distance"], value="point", button_type="light")
        self.w_mode.param.watch(lambda e: self._clear_pair(), "value")
        self.w_fixed = pn.widgets.Toggle(name="Fixed: a click pins the vertex where it is", value=False, button_type="light")
        self.w_lam_b = pn.widgets.FloatInput(name="λ_b — how far an edit spreads to similar expressions (bases)", value=1.0, start=0.0, step=0.1, sizing_mode="stretch_width")
        self.w_lam_w = pn.widgets.FloatInput(name="λ_w — keep the timing of the curves (eq. 13)", value=1.0, start=0.0, step=0.1, sizing_mode="stretch_width")
        self.w_lam_e = pn.widgets.FloatInput(name="λ_e — how closely to meet the constraints", value=100.0, start=0.0, step=10.0, sizing_mode="stretch_width")
        self.w_half = pn.widgets.IntInput(name="Window half-width (frames, 0: whole range)", value=15, start=0, sizing_mode="stretch_width")
        self.w_distance = pn.widgets.FloatInput(name="Distance (mm)", value=0.0, start=0.0, step=0.5, width=120, disabled=True)
        self.w_add_distance = pn.widgets.Button(name="Add distance constraint", disabled=True)
        self.w_add_distance.on_click(lambda e: self.add_distance())
        self.w_pending = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.w_clear = pn.widgets.Button(name="Clear constraints", width=120)
        self.w_clear.on_click(lambda e: self.clear_pending())
        self.w_apply = pn.widgets.Button(name="Apply edit", button_type="success", width=95)
        self.w_apply.on_click(lambda e: self.apply_edit())
        self.w_undo = pn.widgets.Button(name="Undo", width=70)
        self.w_undo.on_click(lambda e: self.undo())
        self.w_redo = pn.widgets.Button(name="Redo", width=70)
        self.w_redo.on_click(lambda e: self.redo())
        self.w_edits = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.param.watch(self._on_status, ["status", "busy"])
        self.w_tool = pn.widgets.Select(name="Click does", options=TOOLS, value=TOOLS[0], sizing_mode="stretch_width")
        self.w_tool.param.watch(lambda e: self._draw_lists(), "value")
        self.details = DetailPanel(self)
        help_ = pn.pane.Markdown(
            "**point**: drag a vertex (left button) to where it should be at that frame; **distance**: click two "
            "vertices, set their distance. Orbit: drag off the face, alt + drag or middle-drag; pan: right-drag; "
            "zoom: wheel. λ_b > 0 edits the bases, which changes every frame that uses them; λ_b = 0 edits only "
            "the weights inside the window.", css_classes=["fr-muted"], sizing_mode="stretch_width")
        edit_card = pn.Card(
            help_, self.w_mode, self.w_fixed, pn.Column(self.w_lam_b, self.w_lam_w, self.w_lam_e, sizing_mode="stretch_width"), self.w_half,
            pn.Row(self.w_distance, self.w_add_distance), self.w_pending,
            pn.Row(self.w_apply, self.w_clear), pn.Row(self.w_undo, self.w_redo), self.w_edits,
            title="Edit (Xu 2014 §4.3)", sizing_mode="stretch_width")
        self.layout = pn.Row(
            pn.Column(self.w_range, settings_card, self.w_run, self.w_progress, self.w_status, self.w_tool, edit_card,
                      self.details.card, width=380),
            pn.Column(self.viewer_box, pn.Row(self.w_play, self.w_frame, sizing_mode="stretch_width"), sizing_mode="stretch_width"),
            sizing_mode="stretch_width")
        self._draw_lists()

    def __panel__(self):
        return self.layout

    def _on_range(self, event):
        a, b = (int(x) for x in event.new)
        if b >= self.w_range.end and self.pipe.dense_source.transfer_last_frame < 0:
            b = -1  # "to the end" stays "to the end" (the same key as before)
        self.pipe.configure(transfer_first_frame=a, transfer_last_frame=b)

    # -- the shown state ---------------------------------------------------------------------
    @property
    def result(self):
        """The shown :class:`core.transfer.TransferResult` (None before a run)."""
        return self.dense["transfer"]["result"] if self.dense else None

    @property
    def first_frame(self) -> int:
        return int(self.dense["transfer"]["first"]) if self.dense else 0

    @property
    def state(self) -> tuple:
        """The current (edited) ``(deltas (K, V, 3), weights (T, K))``."""
        te = self.dense["transfer_edit"]
        return np.asarray(te["deltas"], dtype=np.float64), np.asarray(te["weights"], dtype=np.float64)

    @property
    def current_details(self):
        """The current (edited) details (T, V, 3) or None."""
        return self.dense["detail_edit"]["details"] if self.dense else None

    @property
    def editor(self):
        """:class:`core.transfer.edit.TransferEditor` of the shown result."""
        return self.result.editor() if self.dense else None

    def update(self, snapshot: dict) -> None:
        """New session results: fit the frame range to the take; say when the shown transfer is stale."""
        self.snapshot = snapshot or {}
        if not self.snapshot:
            return
        self.fps = float(self.snapshot.get("fps", self.fps))
        T = self._source_frames()
        if T:
            ds = self.pipe.dense_source
            end = max(T - 1, 1)
            hi = end if ds.transfer_last_frame < 0 else min(ds.transfer_last_frame, end)
            self.w_range.param.update(end=end, value=(min(ds.transfer_first_frame, hi), hi))
        dense = self.snapshot.get("source_rig") is not None and self.snapshot.get("source_weights") is not None
        self.w_run.disabled = not dense or self.busy
        if not dense:
            self.status = "Dense transfer needs weight curves and the rig they drive (choose a source rig)."
        elif self._key is not None and self._key != self.pipe.key("transfer"):
            self.status = "Shown: the transfer of an earlier selection or settings; run again for the current ones."

    def _source_frames(self) -> int:
        try:
            return int(self.pipe.results(["take"])["take"]["source"].n_frames)
        except Exception:  # noqa: BLE001 - the session reports load errors itself
            return len(self.snapshot.get("times", []))

    # -- running ----------------------------------------------------------------------------
    def run(self, block: bool = False) -> bool:
        """Run the dense stages (on a worker thread unless ``block``). False when nothing was
        started (busy, or the inputs are not loaded: see ``status``)."""
        if self.busy:
            return False
        try:
            ld = self.pipe.results(["load"])["load"]
        except Exception as e:  # noqa: BLE001 - shown, not raised
            self.status = f"⚠ {self.session.readable(e)}"
            return False
        if ld["source_rig"] is None or ld["source_layout"] is None:
            self.status = "⚠ dense transfer needs weight curves and the rig they drive (choose a source rig)"
            return False
        a, b = (int(x) for x in self.w_range.value)
        self.busy = True
        self.w_run.disabled = True
        self.w_progress.value = 0
        self.status = f"transferring frames {a}–{b} ({b - a + 1} frames): registration (non-rigid ICP), bases, details…"
        if block:
            self._job()
        else:
            self._thread = threading.Thread(target=self._job, name="xu-transfer", daemon=True)
            self._thread.start()
        return True

    def wait(self, timeout: Optional[float] = None) -> None:
        """Join the worker thread (tests, scripts)."""
        if self._thread is not None:
            self._thread.join(timeout)

    def _job(self) -> None:
        t0 = time.perf_counter()
        try:
            res = self.session.dense(progress=lambda f, m: self._progress(f, m, t0))
            self.show(res, time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - shown in the view; the trace goes to the log
            log.warning("dense transfer failed: %s", traceback.format_exc())
            self.status = f"⚠ transfer failed: {self.session.readable(e)}"
        finally:
            self.busy = False
            self.w_run.disabled = False
            self.w_progress.value = 100 if self.dense else 0

    def _progress(self, fraction: float, message: str, t0: float) -> None:
        self.w_progress.value = int(100 * min(max(fraction, 0.0), 1.0))
        self.status = f"{message} ({time.perf_counter() - t0:.0f} s)"

    def _recompute(self) -> None:
        """The dense results after an edit list changed (the transfer itself is a cache hit)."""
        self.show(self.session.dense())

    def show(self, res: dict, seconds: Optional[float] = None) -> None:
        """Show dense results: a new pick-mode viewer for a new transfer, the edited state otherwise."""
        key = self.pipe.key("transfer")
        new = key != self._key
        self.dense = {k: res[k] for k in ("transfer", "transfer_edit", "detail_edit")}
        self._key = key
        r = self.result
        self.fps = float(res["transfer"].get("fps", self.fps))
        if new:
            self.pending, self._pair = [], []
            target = self.pipe.target_face.target_rig
            name = target.rsplit("/", 1)[-1].rsplit(".", 1)[0] if target else "target"
            rig = r.to_rig(name=f"{name}_transfer")
            self._basis_names = list(rig.names)
            D, W = self.state
            self.viewer = MeshViewer.from_rig(rig, W, fps=self.fps, pick_mode="vertex", label=f"{name} (dense transfer)",
                                              height=VIEW_HEIGHT, sizing_mode="stretch_width")
            if not np.array_equal(D, r.deltas):
                self.viewer.set_deltas(D)
            self.viewer.param.watch(self._on_picked, "picked")
            self.viewer.param.watch(self._on_dragged, "dragged")
            self.viewer.param.watch(self.details.show_frame, ["frame", "playing"])
            self.details.reset(r)
            for widget, link in self._links:  # the old viewer's reverse links go with it
                widget.param.unwatch(link)
            self.w_frame.param.update(end=max(len(r.weights) - 1, 1), value=0)
            self._links = [(self.w_frame, self.w_frame.link(self.viewer, value="frame", bidirectional=True)),
                           (self.w_play, self.w_play.link(self.viewer, value="playing", bidirectional=True))]
            self.viewer_box[:] = [self.viewer]
        self._show_state()
        self.details.show_frame()
        if new:
            t = res.get("timings", {})
            stages = ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if v > 0.05)
            rep = r.registration.report if r.registration is not None else {}
            regtxt = (f" · registration: landmarks {rep['landmark_residual_mm_mean']:.2f} mm mean, surface "
                      f"{rep['surface_distance_mm_p95']:.2f} mm p95" if "landmark_residual_mm_mean" in rep else "")
            took = "" if seconds is None else f" in {seconds:.0f} s"
            first = self.first_frame
            self.status = (f"{len(r.weights)} frames (take frames {first}–{first + len(r.weights) - 1}) → "
                           f"**{r.n_bases} bases** on {r.neutral.shape[0]} vertices{took} ({stages}){regtxt}")
        self._draw_lists()

    # -- picking -----------------------------------------------------------------------------
    def _clear_pair(self):
        self._pair = []
        self.w_distance.disabled = self.w_add_distance.disabled = True
        self._draw_lists()

    def _on_picked(self, event):
        p = event.new
        if not p or not self.dense:
            return
        v, f = int(p["vertex"]), int(p["frame"])
        if self.w_tool.value != TOOLS[0]:
            self.details.on_pick(self.w_tool.value, v, f, p.get("position", [0.0, 0.0, 0.0]))
            return
        if self.w_mode.value == "distance":
            self._pair = (self._pair + [(v, f)])[-2:]
            if len(self._pair) == 2:
                (i, fi), (j, _) = self._pair
                d = self._vertex(fi, i) - self._vertex(fi, j)
                self.w_distance.value = round(float(np.linalg.norm(d)) * 1000, 3)
                self.w_distance.disabled = self.w_add_distance.disabled = i == j
                self.status = f"vertices {i} and {j} at frame {fi}: {self.w_distance.value:.2f} mm apart; set the distance and add"
            else:
                self.status = f"vertex {v} at frame {f}: pick the second vertex"
        elif self.w_fixed.value:
            self.pending.append({"kind": "fixed", "frame": f, "vertex": v, "target": [float(x) for x in p["position"]]})
            self.status = f"vertex {v} pinned at frame {f}"
        else:
            self.status = f"vertex {v} at frame {f}: drag it to constrain it"
        self._draw_lists()

    def _on_dragged(self, event):
        d = event.new
        if d and self.dense and self.w_tool.value == "detail selection":
            self.details.on_stroke(int(d["vertex"]), int(d["frame"]), d["end"])
            return
        if not d or not self.dense or self.w_mode.value != "point" or self.w_tool.value != TOOLS[0]:
            return
        start, end = np.asarray(d["start"], dtype=float), np.asarray(d["end"], dtype=float)
        self.pending.append({"kind": "point", "frame": int(d["frame"]), "vertex": int(d["vertex"]),
                             "target": end.tolist(), "start": start.tolist()})
        self.status = f"vertex {d['vertex']} at frame {d['frame']} → moved {1000 * np.linalg.norm(end - start):.1f} mm; Apply edit"
        self._draw_lists()

    def add_distance(self) -> None:
        if len(self._pair) != 2:
            return
        (i, f), (j, _) = self._pair
        self.pending.append({"kind": "distance", "frame": f, "i": i, "j": j, "distance": float(self.w_distance.value) / 1000})
        self._clear_pair()

    def clear_pending(self) -> None:
        self.pending = []
        self._clear_pair()

    def _vertex(self, frame: int, v: int) -> np.ndarray:
        """Vertex ``v`` of the shown rig at ``frame`` of the current state."""
        D, W = self.state
        return self.result.neutral[v] + W[frame] @ D[:, v]

    # -- editing -----------------------------------------------------------------------------
    def window(self) -> Optional[tuple]:
        """Frames the edit may change: the constraints' frames ± the half-width (None: all)."""
        h = int(self.w_half.value or 0)
        if h <= 0 or not self.pending:
            return None
        frames = [p["frame"] for p in self.pending]
        return (max(0, min(frames) - h), min(len(self.result.weights) - 1, max(frames) + h))

    def apply_edit(self) -> bool:
        """Append a large-scale edit of the pending constraints to the shot; False (and a status) when not possible."""
        if not self.dense or not self.pending:
            self.status = "nothing to apply: drag a vertex (point) or pick two (distance) first"
            return False
        win = self.window()
        spec = {"constraints": [{k: v for k, v in p.items() if k != "start"} for p in self.pending],
                "window": None if win is None else [int(win[0]), int(win[1])],
                "lam_b": float(self.w_lam_b.value), "lam_w": float(self.w_lam_w.value), "lam_e": float(self.w_lam_e.value)}
        t0 = time.perf_counter()
        try:
            with self.pipe.transaction():  # an edit that does not solve leaves no trace, here or in a review
                self.pipe.add_edit("transfer", spec)
                self._recompute()
        except (ValueError, TypeError, RuntimeError) as e:
            self.status = f"⚠ edit failed: {self.session.readable(e)}"
            return False
        rep = self.dense["transfer_edit"]["reports"][-1]
        miss = ", ".join(f"{b:.1f}→{a:.1f} mm" for b, a in zip(rep["before_mm"], rep["after_mm"]))
        where = "whole range" if win is None else f"frames {win[0]}–{win[1]}"
        self.pending, self._pair = [], []
        self.status = (f"edit {len(self.pipe.transfer_edit.transfer_edits)} ({where}, {rep['iterations']} rounds, "
                       f"{time.perf_counter() - t0:.1f} s): constraint miss {miss}")
        self._draw_lists()
        return True

    def undo(self, editor: str = "transfer") -> bool:
        if not self.dense or not self.pipe.undo(editor):
            return False
        self._recompute()
        self.status = f"undone; {len(self.pipe.edits(editor).done)} {editor} edit(s) left"
        return True

    def redo(self, editor: str = "transfer") -> bool:
        if not self.dense or not self.pipe.redo_edit(editor):
            return False
        self._recompute()
        self.status = f"redone; {len(self.pipe.edits(editor).done)} {editor} edit(s)"
        return True

    def shapes(self) -> tuple:
        """What the viewer plays: ``(deltas (K', V, 3), track (T, K'), names)`` — the current
        bases and weights, plus the details as low-rank morph targets when they play along."""
        D, W = self.state
        names = list(self._basis_names)
        morphs = self.details.morphs() if self.details.w_play.value else None
        if morphs is None:
            return D, W, names
        C, B, _ = morphs
        return (np.concatenate([D, B]), np.hstack([W, C]), names + [f"detail_{j:02d}" for j in range(len(B))])

    def _show_state(self):
        v = self.viewer
        if v is None:
            return
        deltas, track, names = self.shapes()
        if v.n_shapes == len(deltas) and np.array_equal(deltas.astype(np.float32), v.deltas):
            v.set_track(track)
        else:
            v.set_shapes(deltas, track, names)
        self._draw_lists()

    # -- drawing -----------------------------------------------------------------------------
    def _draw_lists(self):
        def describe(p):
            f = p["frame"]
            if p["kind"] == "distance":
                return f"distance {p['i']}–{p['j']} = {1000 * p['distance']:.2f} mm @ frame {f}"
            if p["kind"] == "fixed":
                return f"fixed vertex {p['vertex']} @ frame {f}"
            move = 1000 * np.linalg.norm(np.subtract(p["target"], p["start"]))
            return f"point vertex {p['vertex']} @ frame {f}, moved {move:.1f} mm"

        rows = [f"- {describe(p)}" for p in self.pending]
        self.w_pending.object = ("**Constraints for the next edit**\n\n" + "\n".join(rows)) if rows else "*no constraints yet*"
        erows = []
        reports = self.dense["transfer_edit"]["reports"] if self.dense else []
        for k, (e, rep) in enumerate(zip(self.pipe.transfer_edit.transfer_edits, reports), start=1):
            win = "whole range" if not e.get("window") else f"frames {e['window'][0]}–{e['window'][1]}"
            miss = ", ".join(f"{b:.1f}→{a:.1f} mm" for b, a in zip(rep["before_mm"], rep["after_mm"]))
            lams = (e.get("lam_b"), e.get("lam_w"), e.get("lam_e"))
            erows.append(f"{k}. {len(e['constraints'])} constraint(s), {win}, λ = {lams}: miss {miss}")
        self.w_edits.object = ("**Edits**\n\n" + "\n".join(erows)) if erows else ""
        self.w_undo.disabled = not self.pipe.transfer_edit.transfer_edits
        self.w_redo.disabled = not self.pipe.redo["transfer"]
        if self.viewer is not None:
            ids = [p["vertex"] for p in self.pending if "vertex" in p]
            ids += [x for p in self.pending if p["kind"] == "distance" for x in (p["i"], p["j"])]
            ids += [v for v, _ in self._pair]
            ids += self.details.highlight_ids()
            self.viewer.set_highlight(sorted(set(ids)))

    def _on_status(self, *events):
        self.w_status.object = self.status
