"""The Retarget tab's per-shape controls card: a sortable table of the target's shapes with each
one's range (lower…upper, inside the solve), gain and offset (after it, clamped to the range)
and whether the solver may use it, plus the current frame's weight; edits go into the shot's
solve settings (``controls``, :mod:`core.controls`), which also validates them.

The card's widgets are made when it is first opened (:func:`dashboard.lazy.lazy_card`), and
while it is collapsed the table is not kept up to date (a frame change would patch it).
"""

from __future__ import annotations

import copy
import io
import json
from typing import Callable

import numpy as np
import pandas as pd
import panel as pn

from core.controls import FORMAT, default_table, merge_table, validate_table
from dashboard.lazy import lazy_card

COLUMNS = ("shape", "now", "lower", "upper", "gain", "offset", "active")


class ShapeControlsView(pn.viewable.Viewer):
    """The "Shapes (per-shape controls)" card. ``frame()``: the page's current frame;
    ``notify(kind, message)`` shows an error (a control out of range)."""

    def __init__(self, session, frame: Callable[[], int], notify: Callable[[str, str], None], **params):
        super().__init__(**params)
        self.s, self.pipe = session, session.pipeline
        self._frame, self._notify = frame, notify
        self.w_table = self.w_download = self.w_reset = None  # made when the card is first opened
        self.card = lazy_card(build=self._widgets, title="Shapes (per-shape controls)", collapsed=True,
                              sizing_mode="stretch_width")
        # while collapsed the table is not kept up to date (a frame change would patch it): opened, it shows now
        self.card.param.watch(self._on_card, "collapsed")

    def __panel__(self):
        return self.card

    def _widgets(self) -> list:
        """The card's contents, made when it is first opened."""
        if self.w_table is None:
            self.w_table = pn.widgets.Tabulator(
                self.table(), show_index=False, height=320, sizing_mode="stretch_width", pagination=None,
                layout="fit_data_table", selectable=False, disabled=False,
                editors={"shape": None, "now": None, "lower": {"type": "number", "step": 0.05},
                         "upper": {"type": "number", "step": 0.05}, "gain": {"type": "number", "step": 0.1},
                         "offset": {"type": "number", "step": 0.05}, "active": {"type": "tickCross"}})
            self.w_table.on_edit(self._on_edit)
            self.w_download = pn.widgets.FileDownload(callback=self._controls_bytes, filename="controls.json",
                                                      label="Download controls", button_type="light", width=160)
            self.w_reset = pn.widgets.Button(name="Reset controls", button_type="light", width=130)
            self.w_reset.on_click(lambda e: self.pipe.configure(controls={}))
        return [pn.pane.Markdown("Per shape: its range (lower…upper, inside the solve), a gain and offset applied "
                                 "after it (clamped to the range), and whether the solver may use it. Sort by a "
                                 "column; *now* is the weight at the current frame. Upload a controls .json to "
                                 "load a table.", css_classes=["fr-muted"]),
                self.w_table, pn.Row(self.w_download, self.w_reset)]

    def _on_card(self, event):
        if not event.new and self.s.snapshot and self.w_table is not None:
            self.w_table.value = self.table()

    def table(self) -> pd.DataFrame:
        """The table's rows: the target's shapes, the current frame's weight, the controls."""
        snap = self.s.snapshot
        if not snap:
            return pd.DataFrame({c: [] for c in COLUMNS})
        names = snap["target_names"]
        lo, hi = self.pipe.solve.lower, self.pipe.solve.upper
        table = merge_table(self.pipe.solve.controls or {}, default_table(names, lo, hi, symmetry=False))["shapes"]
        f = min(self._frame(), len(snap["weights"]) - 1)
        return pd.DataFrame({"shape": names, "now": np.round(np.nan_to_num(snap["weights"][f]), 3),
                             "lower": [table[n]["lower"] for n in names], "upper": [table[n]["upper"] for n in names],
                             "gain": [table[n]["gain"] for n in names], "offset": [table[n]["offset"] for n in names],
                             "active": [bool(table[n]["active"]) for n in names]})

    def draw(self) -> None:
        """A new result: the open table shows it."""
        if not self.card.collapsed and self.w_table is not None:
            self.w_table.value = self.table()

    def follow_frame(self, frame: int) -> None:
        """The open table's *now* column shows ``frame``'s weights."""
        snap = self.s.snapshot
        if not self.card.collapsed and snap and self.w_table is not None:
            f = min(int(frame), len(snap["weights"]) - 1)
            now = list(np.round(np.nan_to_num(snap["weights"][f]), 3))
            # (an explicit slice: Panel's patch reads slice(None).start as a row index and fails)
            self.w_table.patch({"now": [(slice(0, len(now)), now)]})

    def _on_edit(self, event):
        """A cell changed: that shape's control goes into the solve settings."""
        row = self.w_table.value.iloc[event.row]
        table = copy.deepcopy(self.pipe.solve.controls or {})
        entry = table.setdefault("shapes", {}).setdefault(row["shape"], {})
        entry[event.column] = bool(event.value) if event.column == "active" else float(event.value)
        try:
            validate_table(table, self.s.snapshot["target_names"])
        except ValueError as e:
            self._notify("error", str(e))
            self.w_table.value = self.table()
            return
        self.pipe.configure(controls=table)

    def _controls_bytes(self):
        table = {"format": FORMAT, "version": 1, **(self.pipe.solve.controls or {})}
        return io.BytesIO(json.dumps(table, indent=1).encode("utf-8"))
