"""The Retarget tab's Edit card: set a shape's weight at the current frame and let the change
propagate over a window by movement matching (Seol et al. 2012 §6), with the list of edits
(remove one, or add its mirror image) and undo/redo.

*Use as example pose* adds the result at this frame (with the slider's weight) to the shot's
example poses, which ``auto`` learns a correspondence for the whole take from; *Suggest frames to
pose* proposes frames far apart in expression.

The edits are the pipeline's (``pipe.add_edit("spacetime", ...)``, ``pipe.undo``,
``pipe.redo_edit``; the mirrored edit is :func:`core.controls.mirror_edit`'s); the card only
collects the next edit and lists them. It talks to the page through its ``host``
(:class:`dashboard.app.DashboardApp`): ``host.s``, ``host.pipe``, ``host.frame`` (the current
frame), ``host.notify`` and ``host.refresh``.
"""

from __future__ import annotations

import numpy as np
import panel as pn

from core.controls import mirror_edit


class PoseEditView(pn.viewable.Viewer):
    """The Edit card (spacetime propagation, any method)."""

    def __init__(self, host, **params):
        super().__init__(**params)
        self.host = host
        self.s, self.pipe = host.s, host.pipe
        self.w_shape = pn.widgets.Select(name="Shape", options=[], sizing_mode="stretch_width")
        self.w_value = pn.widgets.FloatSlider(name="Weight at this frame", start=-0.5, end=1.5, step=0.01, value=0.0, sizing_mode="stretch_width")
        self.w_shape.param.watch(lambda e: self.sync_value(), "value")
        self.w_window = pn.widgets.IntSlider(name="Propagation half-window (frames, 0: whole take)", start=0, end=120, value=12, sizing_mode="stretch_width")
        # the card is 330 px wide: its rows share that width (fixed widths made Redo stick out of
        # the card and the page by 3 px at every width)
        self.w_add = pn.widgets.Button(name="Set pose at this frame", button_type="primary", sizing_mode="stretch_width")
        self.w_add.on_click(lambda e: self.add())
        self.w_undo = pn.widgets.Button(name="Undo", width=60)
        self.w_redo = pn.widgets.Button(name="Redo", width=60)
        self.w_undo.on_click(lambda e: self.undo())
        self.w_redo.on_click(lambda e: self.redo())
        self.w_list = pn.Column(sizing_mode="stretch_width")
        # example poses: the whole result at this frame, with the slider's weight, as a pose auto learns from
        self.w_pose = pn.widgets.Button(name="Use as example pose", button_type="default", sizing_mode="stretch_width",
                                        description="auto learns from the poses you set which target shapes each of the "
                                                    "actor's expressions maps to, for the whole take")
        self.w_pose.on_click(lambda e: self.use_as_pose())
        self.w_suggest = pn.widgets.Button(name="Suggest frames to pose", button_type="light", sizing_mode="stretch_width",
                                           description="frames far apart in expression, not posed yet")
        self.w_suggest.on_click(lambda e: self.suggest())
        self.w_clear = pn.widgets.Button(name="Clear poses", button_type="light", width=100)
        self.w_clear.on_click(lambda e: self.clear_poses())
        self.w_poses = pn.pane.Markdown("", css_classes=["fr-muted"], margin=(2, 5), sizing_mode="stretch_width")
        self.card = pn.Card(
            pn.pane.Markdown("Set a weight at the current frame; the change propagates over the window by movement "
                             "matching (Seol 2012 §6).", css_classes=["fr-muted"]),
            self.w_shape, self.w_value, self.w_window,
            pn.Row(self.w_add, self.w_undo, self.w_redo, sizing_mode="stretch_width"), self.w_list,
            pn.Row(self.w_pose, self.w_suggest, sizing_mode="stretch_width"),
            pn.Row(self.w_poses, self.w_clear, sizing_mode="stretch_width"),
            title="Edit (spacetime propagation, any method)", collapsed=False, sizing_mode="stretch_width")

    def __panel__(self):
        return self.card

    def set_shapes(self, names: list, weights) -> None:
        """The target's shapes ``names`` as the choices; the one chosen stays, else the shape that
        moves most in ``weights`` (T, K)."""
        if self.w_shape.options != names:
            keep = self.w_shape.value if self.w_shape.value in names else names[int(np.nanargmax(np.ptp(weights, axis=0)))]
            self.w_shape.param.update(options=names, value=keep)

    def sync_value(self) -> None:
        """The weight slider: its range the solve's bounds, its value the chosen shape's weight at
        the current frame."""
        snap = self.s.snapshot
        shape = self.w_shape.value
        if snap:
            lo, hi = snap.get("edit_bounds", (None, None))
            lo, hi = (-0.5 if lo is None else float(np.min(lo))), (1.5 if hi is None else float(np.max(hi)))
            if (self.w_value.start, self.w_value.end) != (lo, hi):
                self.w_value.param.update(start=lo, end=hi, value=float(np.clip(self.w_value.value, lo, hi)))
        if snap and shape in snap["target_names"]:
            w = snap["weights"][min(self.host.frame, len(snap["weights"]) - 1), snap["target_names"].index(shape)]
            self.w_value.value = float(np.clip(np.nan_to_num(w), self.w_value.start, self.w_value.end))

    def add(self) -> None:
        """Add the edit the card shows: the chosen shape at the slider's weight at the current
        frame, propagated over ± the half-window (0: the whole take)."""
        snap = self.s.snapshot
        if not snap or not self.w_shape.value:
            return
        f, r, T = self.host.frame, self.w_window.value, len(snap["times"])
        window = None if r == 0 else [max(0, f - r), min(T - 1, f + r)]
        if window is not None and (window[0] == f or window[1] == f):
            self.host.notify("warning", "the window must extend on both sides of the frame; choose a frame away from the ends")
            return
        edit = {"frame": int(f), "weights": {self.w_shape.value: round(float(self.w_value.value), 4)}, "window": window}
        self.pipe.add_edit("spacetime", edit)
        self.host.refresh()

    def use_as_pose(self) -> None:
        """The result at the current frame, with the chosen shape at the slider's weight, becomes an
        example pose (frames of the take, like the CSV's ``frame`` column); auto learns from them."""
        snap = self.s.snapshot
        if not snap:
            return
        f, names = self.host.frame, snap["target_names"]
        w = np.nan_to_num(np.asarray(snap["weights"][f], dtype=float))
        if self.w_shape.value in names:
            w[names.index(self.w_shape.value)] = float(self.w_value.value)
        frame = int(f + snap["first_frame"])
        pose = {"frame": frame, "weights": {n: round(float(v), 4) for n, v in zip(names, w) if abs(v) > 1e-3}}
        self.pipe.configure(example_poses=[p for p in self.pipe.solve.example_poses if p["frame"] != frame] + [pose])
        if self.pipe.solve.method != "auto":
            self.host.notify("info", "example poses are learned by the auto method: choose it under Solver to use them")
        self.host.refresh()

    def suggest(self) -> None:
        """Say which frames to pose next (far apart in expression) and show the first of them."""
        try:
            frames = self.s.suggest_poses(8)
        except Exception as e:  # noqa: BLE001 - shown on the page
            self.host.notify("error", self.s.readable(e))
            return
        if not frames:
            self.host.notify("info", "every frame with data is posed already")
            return
        snap = self.s.snapshot
        self.host.notify("info", "frames to pose, far apart in expression: " + ", ".join(map(str, frames)))
        if snap:
            self.host.playback.w_frame.value = int(frames[0] - snap["first_frame"])

    def clear_poses(self) -> None:
        self.pipe.configure(example_poses=[])
        self.host.refresh()

    def remove(self, i: int) -> None:
        self.pipe.remove_edit("spacetime", i)
        self.host.refresh()

    def mirror(self, i: int) -> None:
        """Add edit ``i`` mirrored (the same edit on the other side of the face)."""
        e = self.pipe.edit.edits[i]
        self.pipe.add_edit("spacetime", mirror_edit(e, self.s.snapshot["solver_names"]))
        self.host.refresh()

    def undo(self) -> None:
        if self.pipe.undo("spacetime"):
            self.host.refresh()

    def redo(self) -> None:
        if self.pipe.redo_edit("spacetime"):
            self.host.refresh()

    _drawn = None  # the edits listed

    def draw(self) -> None:
        """The list of edits and the undo/redo buttons' state, and the example poses."""
        poses = sorted(p["frame"] for p in self.pipe.solve.example_poses)
        text = (f"Example poses at frames {', '.join(map(str, poses))}" if poses else
                "No example poses: pose the target at a few frames and *Use as example pose*")
        if self.w_poses.object != text:
            self.w_poses.object = text
        self.w_clear.visible = bool(poses)
        self.w_undo.disabled = not self.pipe.edit.edits
        self.w_redo.disabled = not self.pipe.redo["spacetime"]
        key = repr(self.pipe.edit.edits)
        if key == self._drawn:
            return  # unchanged: new children would make Bokeh walk the page's models again (~50 ms)
        self._drawn = key
        rows = []
        for i, e in enumerate(self.pipe.edit.edits):
            (shape, value), = e["weights"].items()
            win = "whole take" if not e["window"] else f"{e['window'][0]}–{e['window'][1]}"
            b = pn.widgets.Button(name="✕", width=34, button_type="light", description="remove this edit")
            b.on_click(lambda ev, i=i: self.remove(i))
            m = pn.widgets.Button(name="⇄", width=34, button_type="light", description="the same edit on the other side")
            m.on_click(lambda ev, i=i: self.mirror(i))
            # the slider's step is 0.01: two decimals, never 1e-05
            rows.append(pn.Row(pn.pane.Markdown(f"frame {e['frame']}: `{shape}` = {value:.2f} ({win})", margin=(2, 5),
                                                sizing_mode="stretch_width"), m, b, sizing_mode="stretch_width"))
        self.w_list[:] = rows or [pn.pane.Markdown("*no edits*", css_classes=["fr-muted"])]
