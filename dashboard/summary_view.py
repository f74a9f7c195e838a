"""The Retarget tab's result summary and downloads: the result as GLB or CSV (a browser user cannot
reach the server's disk), and one line on what was retargeted and how well (frames, markers,
method, marker and velocity error, the weights' range), with the data-quality notes under it.
The numbers are the evaluate stage's (:mod:`core.evaluate`); the files are the session's
(:meth:`dashboard.session.Session.result_bytes`).
"""

from __future__ import annotations

import html
import io
import re
from pathlib import Path
from typing import Callable

import panel as pn

from core.evaluate import worst_frame
from dashboard import widgets


def download_stem(source, target_rig, method: str) -> str:
    """``<take>_on_<rig>_<method>``: the name a result's files download under (file stems, safe
    characters only)."""
    parts = [Path(str(source or "take")).stem, "on", Path(str(target_rig or "rig")).stem, method]
    return re.sub(r"[^A-Za-z0-9._-]+", "_", "_".join(parts)).strip("_")


class SummaryView(pn.viewable.Viewer):
    """The download buttons and the summary line. ``notify(kind, message)`` shows an error.

    ``rows`` are the objects the page stacks (the downloads, the summary)."""

    def __init__(self, session, notify: Callable[[str, str], None], **params):
        super().__init__(**params)
        self.s = session
        self._notify = notify
        self.w_summary = widgets.Markdown("", sizing_mode="stretch_width")  # updates send the text alone
        self.w_glb = pn.widgets.FileDownload(callback=lambda: self._download("glb"), filename="result.glb",
                                             label="Download GLB", button_type="light", width=140)
        self.w_csv = pn.widgets.FileDownload(callback=lambda: self._download("csv"), filename="result.csv",
                                             label="Download CSV", button_type="light", width=140)
        self.rows = [pn.Row(self.w_glb, self.w_csv, sizing_mode="stretch_width"), self.w_summary]

    def __panel__(self):
        return pn.Column(*self.rows, sizing_mode="stretch_width")

    def _download(self, kind: str):
        try:
            return io.BytesIO(self.s.result_bytes(kind))
        except Exception as e:  # noqa: BLE001 - shown on the page
            self._notify("error", self.s.readable(e))
            return None

    def draw(self, snap: dict) -> None:
        """The summary of the snapshot ``snap`` (of the session's current files), and the
        downloads named after them (``<take>_on_<rig>_<method>.glb``: ten downloads are not ten
        ``result.glb``)."""
        stem = download_stem(self.s.source, self.s.target_rig, snap["method"])
        for w, ext in ((self.w_glb, "glb"), (self.w_csv, "csv")):
            if w.filename != f"{stem}.{ext}":
                w.filename = f"{stem}.{ext}"
        ev = snap["evaluate"]
        self.w_summary.object = (
            f"**{self.s.source}** → **{self.s.target_rig}** · {len(snap['times'])} frames @ {snap['fps']:g} fps · "
            f"{len(snap['marker_names'])} markers · method **{snap['method']}** · marker error RMS "
            f"**{ev['marker_rms_mm']:.2f} mm** (per frame: max {self._worst_link(ev)}) · velocity error "
            f"{ev['velocity_error_mean_mm_per_frame'] or float('nan'):.3f} mm per frame (RMS per marker, Seol 2012 eq. 2) · weights in [{ev['weight_low']:.2f}, {ev['weight_high']:.2f}] "
            f"({100 * ev['outside_01']:.1f}% outside 0..1)")
        chose = snap["solve_info"].get("auto")
        if chose:  # what the default chose, and why, in its own sentence
            self.w_summary.object = f"{html.escape(chose)}\n\n{self.w_summary.object}"
        notes = list(dict.fromkeys(snap.get("warnings", [])))  # data-quality notes stay on the page, not as toasts
        if notes:
            self.w_summary.object += "\n\n" + "\n".join(f"ℹ {html.escape(n)}" for n in notes[:4])

    @staticmethod
    def _worst_link(ev) -> str:
        """The largest per-frame marker error RMS as a link to its frame (``data-fr-frame``: the
        page's :class:`dashboard.contact_sheet_view.FrameLinks` jumps there): the number the contact
        sheet's worst frame shows."""
        f = worst_frame(ev)
        return (f'<a href="#" data-fr-frame="{f}" class="fr-worst-frame" title="show frame {f}, the worst (marker '
                f'error RMS over its markers)">{ev["marker_error_mm"][f]:.1f} mm at frame {f}</a>')

    def show_stale(self, last: str) -> None:
        """The current selection failed: say the views show the ``last`` good result (its files)."""
        self.w_summary.object = (f"The views show the last good result ({html.escape(last)}), not the current "
                                 "selection." if last else "No result yet.")
