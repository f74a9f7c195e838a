"""Dense transfer (Xu et al. 2014) in the dashboard: run it on the loaded take, then edit it by
dragging vertices on the 3D view (large-scale edits, §4.3 eq. 12-15) and by selecting and
editing its fine-scale details (§5.2).

* **Run**: :func:`core.transfer.performance.transfer_performance` on a frame range of the
  session's source (its weight curves drive the source rig into a dense sequence; the marker
  layouts give the landmarks of the §3 registration) with the settings card's Taubin
  iterations, ε, max bases, α, feature lines (eye and mouth rims near the layout's markers,
  :func:`~core.transfer.performance.default_feature_lines`) and details. Runs on a worker
  thread with per-stage progress; about 30-90 s on this machine for a few hundred ICT frames,
  most of it the non-rigid ICP.
* **Show**: the transferred rig (``result.to_rig()``: target neutral in the source topology +
  K bases) playing ``result.weights`` in a :class:`~dashboard.viewer.MeshViewer` with
  ``pick_mode="vertex"``. Fine-scale details are not part of the rig: the paused frame shows
  them as the viewer's ``offsets``.
* **Fine-scale details** (§5.2): :class:`~dashboard.detail_view.DetailPanel` — shown on the
  paused frame, selected by paint or curve, scaled / copy-pasted / reshaped and propagated.
* **Edit**: *point* mode — drag a vertex: :class:`~core.transfer.edit.PointConstraint` at that
  frame, target = the drag's end (with *fixed* on, a click pins the vertex where it is);
  *distance* mode — pick two vertices, type a distance: a
  :class:`~core.transfer.edit.DistanceConstraint`. *Apply edit* runs
  :meth:`~core.transfer.edit.LargeScaleEditor.edit` with λ_b, λ_w, λ_e and the window
  (constraint frames ± half-width) and shows the new bases/weights. Edits stack; undo pops.

No numerics here: :class:`EditableTransfer` only rebuilds, from the result and the source rig,
the objects core's editor needs (see its docstring for what core could provide instead).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Optional

import numpy as np
import panel as pn
import param

from core.transfer import DeformationTransfer, TaubinFilter, TransferSettings, line_edges
from core.transfer._mesh import weld
from core.transfer.edit import DistanceConstraint, EditResult, LargeScaleEditor, PointConstraint
from core.transfer.performance import default_feature_lines, transfer_performance

from .detail_view import TOOLS, DetailPanel
from .viewer import MeshViewer

log = logging.getLogger("face_retarget.dashboard")

DEFAULT_FRAMES = 300
VIEW_HEIGHT = 460


class EditableTransfer:
    """A :class:`~core.transfer.TransferResult` made editable with core's
    :class:`~core.transfer.edit.LargeScaleEditor` (Xu et al. 2014 eq. 12-15).

    The result does not keep the factorised eq. 9 system nor the seam welding it was solved
    on, so they are rebuilt exactly as :func:`core.transfer.transfer_sequence` builds them:
    ``weld`` of the source rig, ``S̄_0`` = Taubin filter (``settings``) of the welded source
    neutral, ``T̄_0`` = the result's ``target_smooth_ref``, feature lines from ``settings``.
    :meth:`consistency` re-transfers the result's source bases with the rebuilt system and
    compares with the result's deltas. (Core should rather return these with the result,
    e.g. ``TransferResult.editor()``; this class would then shrink to the id mapping.)

    The editor's mesh is ``reference + w Δ``. The rig shown is ``neutral + w Δ``, which differs
    from the smoothed ``T̄_0 + w Δ`` by the reference details ``neutral - T̄_0``, a constant per
    vertex; E_b and E_w (eq. 9, 13) do not involve the reference, so handing the editor the
    shown neutral makes point and distance constraints act on what the user sees.

    Parameters
    ----------
    result : TransferResult     from :func:`transfer_performance` (source topology)
    source_rig : core.model.Rig the rig whose topology carried the dense sequence
    settings : TransferSettings the settings the transfer ran with (default: the defaults)

    Raises
    ------
    ValueError
        ``source_rig`` is not the topology of ``result``.
    """

    def __init__(self, result, source_rig, settings: Optional[TransferSettings] = None):
        self.result = result
        self.settings = settings or TransferSettings()
        V = len(result.neutral)
        if source_rig.n_vertices != V or not np.array_equal(np.asarray(source_rig.faces), np.asarray(result.faces)):
            raise ValueError(f"source_rig {source_rig.name!r}: expected the topology of the transfer result "
                             f"({V} vertices, {len(result.faces)} faces), got {source_rig.n_vertices} vertices")
        s = self.settings
        self.welded, self.rep, faces_w = weld(source_rig.neutral, source_rig.faces)
        n = len(self.rep)
        smooth_src = TaubinFilter(faces_w, n, s.iterations, s.lam, s.mu).apply(np.asarray(source_rig.neutral)[self.rep])
        edges = (line_edges([self.welded[np.asarray(ln, dtype=np.int64)] for ln in s.feature_lines], closed=True)
                 if s.feature_lines is not None else None)
        self.transfer = DeformationTransfer(smooth_src, np.asarray(result.target_smooth_ref)[self.rep], faces_w, edges, s.alpha)
        self.reference = np.asarray(result.neutral, dtype=np.float64)[self.rep]

    @property
    def n_frames(self) -> int:
        return len(self.result.weights)

    def consistency(self) -> float:
        """max |Δ_rebuilt - Δ_result| / max |Δ_result|: the rebuilt eq. 9 system re-transfers
        the result's source bases; ~1e-12 when it is the one the transfer used."""
        r = self.result
        if not r.n_bases:
            return 0.0
        again = self.transfer.transfer(np.asarray(r.source_bases)[:, self.rep]) - np.asarray(r.target_smooth_ref)[self.rep]
        want = np.asarray(r.deltas)[:, self.rep]
        return float(np.abs(again - want).max() / max(np.abs(want).max(), 1e-300))

    def constraint(self, spec: dict):
        """A core constraint (welded ids) from a dashboard one: ``{"kind": "point"|"fixed",
        "frame", "vertex", "target": [x, y, z]}`` or ``{"kind": "distance", "frame", "i", "j",
        "distance"}`` (metres, rig vertex ids)."""
        w = self.welded
        if spec["kind"] in ("point", "fixed"):
            return PointConstraint(int(spec["frame"]), int(w[spec["vertex"]]), tuple(float(x) for x in spec["target"]))
        if spec["kind"] == "distance":
            return DistanceConstraint(int(spec["frame"]), int(w[spec["i"]]), int(w[spec["j"]]), float(spec["distance"]))
        raise ValueError(f"constraint kind: expected 'point', 'fixed' or 'distance', got {spec['kind']!r}")

    def edit(self, deltas, weights, specs, lam_b: float, lam_w: float, lam_e: float, window=None):
        """Run :meth:`LargeScaleEditor.edit` from the state ``(deltas (K, V, 3), weights (T, K))``.

        Returns ``(deltas (K, V, 3), weights (T, K), EditResult)`` in the rig's vertex ids.
        """
        D = np.asarray(deltas, dtype=np.float64)
        editor = LargeScaleEditor(self.transfer, self.reference, D[:, self.rep], weights)
        res = editor.edit([self.constraint(s) for s in specs], lam_b, lam_w, lam_e, window)
        return np.ascontiguousarray(res.deltas[:, self.welded]), res.weights, res


@dataclass
class _Edit:
    specs: list
    window: Optional[tuple]
    lams: tuple
    result: Optional[EditResult]
    report: str = ""
    kind: str = "large"  # "large" (eq. 12-15) or "detail" (§5.2)


class TransferView(param.Parameterized):
    """The dense-transfer tab: run Xu 2014 on the session's take, play it, edit it by dragging."""

    busy = param.Boolean(default=False)
    status = param.String(default="")

    def __init__(self, session, **params):
        super().__init__(**params)
        self.session = session
        self.snapshot: dict = {}
        self.editable: Optional[EditableTransfer] = None
        self.viewer: Optional[MeshViewer] = None
        self.first_frame = 0
        self.fps = 30.0
        self.states: list = []  # (deltas (K, V, 3), weights (T, K)); [0] is the transfer
        self.detail_states: list = []  # details (T, V, 3) or None, one per state
        self._basis_names: list = []
        self.edits: list[_Edit] = []
        self.pending: list[dict] = []
        self._pair: list = []
        self._thread: Optional[threading.Thread] = None
        self._key = None
        self._links: list = []
        self._build()

    # -- layout -----------------------------------------------------------------------------
    def _build(self):
        self.w_range = pn.widgets.IntRangeSlider(name="Frames of the take", start=0, end=DEFAULT_FRAMES - 1,
                                                 value=(0, DEFAULT_FRAMES - 1), step=1, sizing_mode="stretch_width")
        self.w_run = pn.widgets.Button(name="Run dense transfer (Xu 2014)", button_type="primary", sizing_mode="stretch_width")
        self.w_run.on_click(lambda e: self.run())
        self.w_iter = pn.widgets.IntInput(name="Taubin iterations", value=40, start=0, step=5, width=110)
        self.w_eps = pn.widgets.FloatInput(name="ε (basis selection)", value=1e-3, start=0.0, step=5e-4, width=120)
        self.w_maxk = pn.widgets.IntInput(name="max bases", value=30, start=1, step=1, width=90)
        self.w_alpha = pn.widgets.FloatInput(name="α (feature lines)", value=100.0, start=0.0, step=10.0, width=110)
        self.w_lines = pn.widgets.Checkbox(name="feature lines (eye and mouth rims)", value=True)
        self.w_details = pn.widgets.Checkbox(name="fine details (eq. 16)", value=True)
        settings_card = pn.Card(
            pn.Row(self.w_iter, self.w_eps, self.w_maxk), pn.Row(self.w_alpha, pn.Column(self.w_lines, self.w_details)),
            title="Transfer settings", sizing_mode="stretch_width", collapsed=True)
        self.w_progress = pn.indicators.Progress(value=0, max=100, height=12, sizing_mode="stretch_width", bar_color="primary")
        self.w_status = pn.pane.Markdown("Transfers the take's dense motion onto the target's face (Xu et al. 2014). "
                                         "2,000 ICT frames take minutes; start with a few hundred.", sizing_mode="stretch_width")
        self.viewer_box = pn.Column(pn.pane.Markdown("*no transfer yet*"), sizing_mode="stretch_width", min_height=VIEW_HEIGHT)
        self.w_frame = pn.widgets.IntSlider(name="Frame (of the range)", start=0, end=1, value=0, sizing_mode="stretch_width")
        self.w_play = pn.widgets.Toggle(name="▶ Play / ❚❚ Pause", button_type="success", width=150)
        self.w_mode = pn.widgets.RadioButtonGroup(name="Constraint", options=["point", "distance"], value="point", button_type="light")
        self.w_mode.param.watch(lambda e: self._clear_pair(), "value")
        self.w_fixed = pn.widgets.Checkbox(name="fixed: a click pins the vertex where it is", value=False)
        self.w_lam_b = pn.widgets.FloatInput(name="λ_b (bases, eq. 9)", value=1.0, start=0.0, step=0.1, width=100)
        self.w_lam_w = pn.widgets.FloatInput(name="λ_w (weights, eq. 13)", value=1.0, start=0.0, step=0.1, width=100)
        self.w_lam_e = pn.widgets.FloatInput(name="λ_e (constraints)", value=100.0, start=0.0, step=10.0, width=100)
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
            help_, self.w_mode, self.w_fixed, pn.Row(self.w_lam_b, self.w_lam_w, self.w_lam_e), self.w_half,
            pn.Row(self.w_distance, self.w_add_distance), self.w_pending, pn.Row(self.w_apply, self.w_clear, self.w_undo),
            self.w_edits, title="Edit (Xu 2014 §4.3)", sizing_mode="stretch_width")
        self.layout = pn.Row(
            pn.Column(self.w_range, settings_card, self.w_run, self.w_progress, self.w_status, self.w_tool, edit_card,
                      self.details.card, width=380),
            pn.Column(self.viewer_box, pn.Row(self.w_play, self.w_frame, sizing_mode="stretch_width"), sizing_mode="stretch_width"),
            sizing_mode="stretch_width")
        self._draw_lists()

    def __panel__(self):
        return self.layout

    # -- session ----------------------------------------------------------------------------
    def _selection(self) -> tuple:
        s = self.session
        return (s.source, s.source_rig, s.target_rig)

    def update(self, snapshot: dict) -> None:
        """New session results: fit the frame range to the take; say when the shown transfer is stale."""
        self.snapshot = snapshot or {}
        if not self.snapshot:
            return
        self.fps = float(self.snapshot.get("fps", self.fps))
        T = self._source_frames()
        if T:
            lo, hi = self.w_range.value
            end = max(T - 1, 1)
            self.w_range.param.update(end=end, value=(min(lo, end), min(hi, end)) if self._key else (0, min(DEFAULT_FRAMES, T) - 1))
        dense = self.snapshot.get("source_rig") is not None and self.snapshot.get("source_weights") is not None
        self.w_run.disabled = not dense or self.busy
        if not dense:
            self.status = "Dense transfer needs weight curves and the rig they drive (choose a source rig)."
        elif self._key is not None and self._key != self._selection():
            self.status = f"Shown: the transfer of {self._key[0]} → {self._key[2]}; run again for the current selection."

    def _source_frames(self) -> int:
        try:
            return int(self.session.pipeline.results(["load"])["load"]["source"].n_frames)
        except Exception:  # noqa: BLE001 - the session reports load errors itself
            return len(self.snapshot.get("times", []))

    # -- running ----------------------------------------------------------------------------
    def run(self, block: bool = False) -> bool:
        """Start the transfer of the chosen frame range (on a worker thread unless ``block``).

        Returns False when nothing was started (busy, or the inputs are not loaded: see ``status``).
        """
        if self.busy:
            return False
        try:
            ld = self.session.pipeline.results(["load"])["load"]
        except Exception as e:  # noqa: BLE001 - shown, not raised
            self.status = f"⚠ {e}"
            return False
        a, b = (int(x) for x in self.w_range.value)
        if ld["source_rig"] is None or ld["source_layout"] is None:
            self.status = "⚠ dense transfer needs weight curves and the rig they drive (choose a source rig)"
            return False
        settings = dict(iterations=int(self.w_iter.value), eps=float(self.w_eps.value), max_bases=int(self.w_maxk.value),
                        alpha=float(self.w_alpha.value), details=bool(self.w_details.value))
        job = dict(source=ld["source"].frames(a, b + 1), source_rig=ld["source_rig"], source_layout=ld["source_layout"],
                   settings=settings, lines=bool(self.w_lines.value),
                   target_rig=ld["target_rig"], target_layout=ld["target_layout"], name_map=ld.get("name_map"),
                   first=a, key=self._selection())
        self.busy = True
        self.w_run.disabled = True
        self.w_progress.value = 0
        self.status = f"transferring frames {a}–{b} ({b - a + 1} frames): registration (non-rigid ICP), bases, details…"
        if block:
            self._job(job)
        else:
            self._thread = threading.Thread(target=self._job, args=(job,), name="xu-transfer", daemon=True)
            self._thread.start()
        return True

    def wait(self, timeout: Optional[float] = None) -> None:
        """Join the worker thread (tests, scripts)."""
        if self._thread is not None:
            self._thread.join(timeout)

    def _job(self, job: dict) -> None:
        t0 = time.perf_counter()
        try:
            lines = default_feature_lines(job["source_rig"], job["source_layout"]) if job["lines"] else None
            settings = TransferSettings(**job["settings"], feature_lines=lines)
            result = transfer_performance(job["source"], job["source_rig"], job["source_layout"], job["target_rig"],
                                          job["target_layout"], name_map=job["name_map"],
                                          progress=lambda f, m: self._progress(f, m, t0),
                                          **job["settings"], feature_lines=lines)
            self.status = "preparing the editor (factorising eq. 9)…"
            editable = EditableTransfer(result, job["source_rig"], settings)
            self.show(editable, job["first"], job["target_rig"].name, job["key"], time.perf_counter() - t0)
        except Exception as e:  # noqa: BLE001 - shown in the view; the trace goes to the log
            log.warning("dense transfer failed: %s", traceback.format_exc())
            self.status = f"⚠ transfer failed: {e}"
        finally:
            self.busy = False
            self.w_run.disabled = False
            self.w_progress.value = 100 if self.editable is not None else 0

    def _progress(self, fraction: float, message: str, t0: float) -> None:
        self.w_progress.value = int(100 * min(max(fraction, 0.0), 1.0))
        self.status = f"{message} ({time.perf_counter() - t0:.0f} s)"

    def show(self, editable: EditableTransfer, first_frame: int = 0, target_name: str = "target", key=None,
             seconds: Optional[float] = None) -> None:
        """Show a transfer (and forget the previous one's edits): a pick-mode viewer of its rig."""
        r = editable.result
        self.editable = editable
        self.first_frame = int(first_frame)
        self._key = key
        self.states = [(np.asarray(r.deltas, dtype=np.float64), np.asarray(r.weights, dtype=np.float64))]
        self.detail_states = [r.details]
        self.edits, self.pending, self._pair = [], [], []
        rig = r.to_rig(name=f"{target_name}_transfer")
        self._basis_names = list(rig.names)  # the viewer's shape names; detail morphs are appended after them
        self.viewer = MeshViewer.from_rig(rig, r.weights, fps=self.fps, pick_mode="vertex", label=f"{target_name} (dense transfer)",
                                          height=VIEW_HEIGHT, sizing_mode="stretch_width")
        self.viewer.param.watch(self._on_picked, "picked")
        self.viewer.param.watch(self._on_dragged, "dragged")
        self.viewer.param.watch(self.details.show_frame, ["frame", "playing"])
        self.details.reset(r, editable.settings)
        if self.details.w_play.value:
            self._show_state()
        for widget, link in self._links:  # the old viewer's reverse links go with it
            widget.param.unwatch(link)
        self.w_frame.param.update(end=max(len(r.weights) - 1, 1), value=0)
        self._links = [(self.w_frame, self.w_frame.link(self.viewer, value="frame", bidirectional=True)),
                       (self.w_play, self.w_play.link(self.viewer, value="playing", bidirectional=True))]
        self.viewer_box[:] = [self.viewer]
        self.details.show_frame()
        stages = ", ".join(f"{k} {v:.1f} s" for k, v in r.timings.items() if isinstance(v, (int, float)))
        rep = r.registration.report if r.registration is not None else {}
        regtxt = (f" · registration: landmarks {rep['landmark_residual_mm_mean']:.2f} mm mean, surface "
                  f"{rep['surface_distance_mm_p95']:.2f} mm p95" if "landmark_residual_mm_mean" in rep else "")
        took = "" if seconds is None else f" in {seconds:.0f} s"
        self.status = (f"{len(r.weights)} frames (take frames {first_frame}–{first_frame + len(r.weights) - 1}) → "
                       f"**{r.n_bases} bases** on {rig.n_vertices} vertices{took} ({stages}){regtxt}")
        self._draw_lists()

    # -- picking -----------------------------------------------------------------------------
    def _clear_pair(self):
        self._pair = []
        self.w_distance.disabled = self.w_add_distance.disabled = True
        self._draw_lists()

    def _on_picked(self, event):
        p = event.new
        if not p or self.editable is None:
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
        if d and self.editable is not None and self.w_tool.value == "detail selection":
            self.details.on_stroke(int(d["vertex"]), int(d["frame"]), d["end"])
            return
        if not d or self.editable is None or self.w_mode.value != "point" or self.w_tool.value != TOOLS[0]:
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
        D, W = self.states[-1]
        return self.editable.result.neutral[v] + W[frame] @ D[:, v]

    # -- editing -----------------------------------------------------------------------------
    def window(self) -> Optional[tuple]:
        """Frames the edit may change: the constraints' frames ± the half-width (None: all)."""
        h = int(self.w_half.value or 0)
        if h <= 0 or not self.pending:
            return None
        frames = [p["frame"] for p in self.pending]
        return (max(0, min(frames) - h), min(self.editable.n_frames - 1, max(frames) + h))

    def apply_edit(self) -> bool:
        """Run the large-scale edit with the pending constraints; False (and a status) when not possible."""
        if self.editable is None or not self.pending:
            self.status = "nothing to apply: drag a vertex (point) or pick two (distance) first"
            return False
        lams = (float(self.w_lam_b.value), float(self.w_lam_w.value), float(self.w_lam_e.value))
        window = self.window()
        D, W = self.states[-1]
        t0 = time.perf_counter()
        try:
            D2, W2, res = self.editable.edit(D, W, self.pending, *lams, window=window)
        except (ValueError, TypeError, RuntimeError) as e:
            self.status = f"⚠ edit failed: {e}"
            return False
        before = [self._miss(p, D, W) for p in self.pending]
        after = [self._miss(p, D2, W2) for p in self.pending]
        report = ", ".join(f"{b:.1f}→{a:.1f} mm" for b, a in zip(before, after))
        win = "whole range" if window is None else f"frames {window[0]}–{window[1]}"
        edit = _Edit(list(self.pending), window, lams, res, report)
        self.states.append((D2, W2))
        self.detail_states.append(self.detail_states[-1])
        self.edits.append(edit)
        self.pending, self._pair = [], []
        self._show_state()
        self.status = (f"edit {len(self.edits)} ({win}, {res.iterations} rounds, {time.perf_counter() - t0:.1f} s): "
                       f"constraint miss {report}")
        return True

    def _miss(self, spec: dict, D, W) -> float:
        """How far (mm) the state is from a constraint, on the shown rig."""
        neutral = self.editable.result.neutral
        if spec["kind"] == "distance":
            i, j, f = spec["i"], spec["j"], spec["frame"]
            d = (neutral[i] + W[f] @ D[:, i]) - (neutral[j] + W[f] @ D[:, j])
            return abs(float(np.linalg.norm(d)) - spec["distance"]) * 1000
        v, f = spec["vertex"], spec["frame"]
        return float(np.linalg.norm(neutral[v] + W[f] @ D[:, v] - np.asarray(spec["target"]))) * 1000

    def push_details(self, details, report: str) -> None:
        """A detail edit's result becomes the current state (bases and weights unchanged)."""
        self.states.append(self.states[-1])
        self.detail_states.append(details)
        self.edits.append(_Edit([], None, (), None, report, kind="detail"))
        self._draw_lists()

    def undo(self) -> bool:
        if not self.edits:
            return False
        self.edits.pop()
        self.states.pop()
        self.detail_states.pop()
        self._show_state()
        self.details.show_frame()
        self.status = f"undone; {len(self.edits)} edit(s) left"
        return True

    def shapes(self) -> tuple:
        """What the viewer plays: ``(deltas (K', V, 3), track (T, K'), names)`` — the current
        bases and weights, plus the details as low-rank morph targets when they play along."""
        D, W = self.states[-1]
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
        for k, e in enumerate(self.edits, start=1):
            if e.kind == "detail":
                erows.append(f"{k}. details: {e.report}")
                continue
            win = "whole range" if e.window is None else f"frames {e.window[0]}–{e.window[1]}"
            erows.append(f"{k}. {len(e.specs)} constraint(s), {win}, λ = {e.lams}: miss {e.report}")
        self.w_edits.object = ("**Edits**\n\n" + "\n".join(erows)) if erows else ""
        if self.viewer is not None:
            ids = [p["vertex"] for p in self.pending if "vertex" in p]
            ids += [x for p in self.pending if p["kind"] == "distance" for x in (p["i"], p["j"])]
            ids += [v for v, _ in self._pair]
            ids += self.details.highlight_ids()
            self.viewer.set_highlight(sorted(set(ids)))

    def _on_status(self, *events):
        self.w_status.object = self.status
