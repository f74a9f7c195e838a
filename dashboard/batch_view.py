"""The dashboard's Batch tab: the page's current shot (rigs, settings, edits) applied to several
captures, run by the same batch code as ``face-retarget batch`` (core.batch.run_batch, Dask),
with a row per shot that fills in as the shots finish, a Stop button and the results as a zip.

The batch runs in a worker thread of its own (run_batch starts a LocalCluster and waits on it);
what it reports reaches the page on the page's event loop (``doc.add_next_tick_callback``).
"""

from __future__ import annotations

import html
import io
import logging
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import pandas as pd
import panel as pn

log = logging.getLogger("face_retarget.dashboard")

#: the columns the table shows (a subset of core.batch.SUMMARY_COLUMNS, plainly named)
COLUMNS = {"shot": "shot", "status": "status", "seconds": "seconds", "frames": "frames",
           "marker_mean_mm": "marker error (mm)", "weight_min": "w min", "weight_max": "w max", "error": "error"}


class BatchView(pn.viewable.Viewer):
    """The Batch tab (see the module docstring). ``session``: the page's
    :class:`dashboard.session.Session` (its shot is the template, its take list the choices)."""

    def __init__(self, session, out_root: Optional[Path] = None, **params):
        super().__init__(**params)
        self.s = session
        self.out_root = Path(out_root) if out_root else Path(tempfile.gettempdir()) / "face-retarget-batches"
        takes = dict(self.s.files["performances"])
        self.w_takes = pn.widgets.MultiSelect(name="Captures (the current rigs and settings are applied to each)",
                                              options=takes, value=[], size=min(8, max(3, len(takes))),
                                              sizing_mode="stretch_width")
        cores = os.cpu_count() or 1
        self.w_workers = pn.widgets.IntInput(name="Worker processes", value=min(2, cores), start=1, end=max(cores, 1),
                                             width=160)
        self.w_start = pn.widgets.Button(name="Run the batch", button_type="primary", width=160)
        self.w_stop = pn.widgets.Button(name="Stop", button_type="light", width=90, disabled=True)
        self.w_progress = pn.indicators.Progress(value=0, max=100, height=12, sizing_mode="stretch_width",
                                                 bar_color="primary", visible=False)
        self.w_status = pn.pane.Markdown("Pick captures, then run: each becomes a shot with this page's rigs, "
                                         "settings and edits, computed on a local Dask cluster.",
                                         sizing_mode="stretch_width")
        self.w_table = pn.widgets.Tabulator(pd.DataFrame(columns=list(COLUMNS.values())), disabled=True,
                                            show_index=False, sizing_mode="stretch_width", height=260)
        self.w_zip = pn.widgets.FileDownload(callback=self._zip_bytes, filename="batch.zip", label="Download the results (.zip)",
                                             button_type="light", disabled=True, width=240)
        self.w_start.on_click(lambda e: self.start())
        self.w_stop.on_click(lambda e: self.stop())
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._active = False
        self.out_dir: Optional[Path] = None
        self.names: list = []
        self.results: list = []
        self._doc = pn.state.curdoc
        self._layout = pn.Column(
            pn.pane.Markdown("### Batch\nThe same code as `face-retarget batch` (docs/batch.md): one output folder per "
                             "shot with its GLB, CSV, evaluation and log, and a summary.", sizing_mode="stretch_width"),
            self.w_takes, pn.Row(self.w_workers, self.w_start, self.w_stop), self.w_progress, self.w_status,
            self.w_table, self.w_zip, sizing_mode="stretch_width")

    def __panel__(self):
        return self._layout

    def update(self, snapshot=None) -> None:
        """The take list follows the page's (uploads join it)."""
        takes = dict(self.s.files["performances"])
        if takes != self.w_takes.options:
            self.w_takes.param.update(options=takes, value=[v for v in self.w_takes.value if v in takes.values()])

    # -- running ----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._active or (self._thread is not None and self._thread.is_alive())

    def start(self) -> bool:
        """Start the batch of the chosen captures (False, with a message, when there is nothing to do)."""
        from core.batch import collect_shots

        if self.running:
            return False
        captures = list(self.w_takes.value)
        if not captures:
            self.w_status.object = "**Choose at least one capture.**"
            return False
        try:
            jobs = collect_shots(captures, template=self.s.shot())
        except (ValueError, FileNotFoundError) as e:
            self.w_status.object = f"**Error:** {html.escape(str(e))}"
            return False
        self.out_root.mkdir(parents=True, exist_ok=True)
        self.out_dir = Path(tempfile.mkdtemp(prefix=time.strftime("batch-%Y%m%d-%H%M%S-"), dir=self.out_root))
        self.names = [j.name for j in jobs]
        self.results = []
        self._stop.clear()
        self._active = True
        self._rows({})
        self.w_start.disabled, self.w_stop.disabled, self.w_zip.disabled = True, False, True
        self.w_progress.param.update(value=0, visible=True)
        self.w_status.object = f"Starting {len(jobs)} shots on {self.w_workers.value} worker process(es)…"
        workers = int(self.w_workers.value)
        self._thread = threading.Thread(target=self._run, args=(jobs, workers), name="dashboard-batch", daemon=True)
        self._thread.start()
        return True

    def stop(self) -> None:
        self._stop.set()
        self.w_status.object = "Stopping: the shots that are running finish, the others are left for the next run…"

    def _run(self, jobs, workers: int) -> None:
        from core.batch import run_batch

        def progress(fraction, message):
            self._later(lambda: self._on_progress(fraction, message))

        try:
            results = run_batch(jobs, self.out_dir, workers=workers, progress=progress, stop=self._stop,
                                dashboard_address=None, log=lambda line: log.info("batch: %s", line))
            self._later(lambda: self._on_done(results, None))
        except Exception as e:  # shown in the tab; the trace goes to the log
            log.warning("batch failed", exc_info=True)
            self._later(lambda err=e: self._on_done([], err))  # bound now: Python unbinds `e` after the block

    def _later(self, fn) -> None:
        doc = self._doc
        if doc is not None and doc.session_context is not None:
            doc.add_next_tick_callback(fn)
        else:
            fn()

    def _on_progress(self, fraction: float, message: str) -> None:
        from core.batch import read_results

        self.w_progress.value = int(round(100 * fraction))
        self.w_status.object = html.escape(message)
        self._rows(read_results(self.out_dir))

    def _on_done(self, results, error) -> None:
        self.results = results
        self._active = False
        self.w_start.disabled, self.w_stop.disabled = False, True
        self.w_progress.visible = False
        if error is not None:
            self.w_status.object = f"**Error:** the batch did not run: {html.escape(str(error))}"
            return
        self._rows({r.name: r for r in results})
        counts = {}
        for r in results:
            counts[r.status] = counts.get(r.status, 0) + 1
        self.w_status.object = "Done: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())) + \
            (" — download the results below" if any(r.ok for r in results) else "")
        self.w_zip.disabled = not any(r.ok for r in results)

    def _rows(self, done: dict) -> None:
        rows = []
        for name in self.names:
            r = done.get(name)
            row = r.row() if r is not None else {"shot": name, "status": "to do" if self._active else "not run"}
            rows.append({label: (round(v, 3) if isinstance(v := row.get(key, ""), float) else v)
                         for key, label in COLUMNS.items()})
        self.w_table.value = pd.DataFrame(rows, columns=list(COLUMNS.values()))

    def _zip_bytes(self):
        from core.batch import zip_results

        if self.out_dir is None:
            return None
        dest = zip_results(self.out_dir)
        self.w_zip.filename = dest.name
        return io.BytesIO(dest.read_bytes())
