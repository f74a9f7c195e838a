"""The Live tab: a Live Link Face stream retargeted as it arrives (core/live.py), shown on the
source and target rigs; the incoming rate, dropped and bad packets; Record, whose frames become
the shot's take (so the offline methods can refine them afterwards).

The view holds no numerics: :class:`core.live.LiveRetargeter` is built from the page's
pipeline and :func:`core.live.listen` runs in a thread. Each frame it answers is sent to the two
viewers as it comes (``MeshViewer.stream_weights``: a message of a few hundred bytes, the K
float32 as one base64 string), on the page's event loop: the listener thread schedules one send
(``Document.add_next_tick_callback``, Bokeh's thread-safe entry) unless one is pending, and the
send takes the latest frame. A 16 ms timer polling for new frames sent only 25-39 of the 60 a
second (its ticks drift against the stream's, and a late tick skips a frame), so the page had no
new frame to draw at a third of its animation frames. A periodic callback updates the counts.
"""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import panel as pn
from panel.io.callbacks import PeriodicCallback

from core.io.livelink import write_livelink
from core.live import LiveRetargeter, LiveSession, listen, parse_address
from dashboard.viewer import MeshViewer

VIEW_HEIGHT = 400
#: how often the status line's counts are refreshed (ms); frames are sent as they come
STATUS_MS = 250


class LiveView(pn.viewable.Viewer):
    """Listen / Record controls, the status line and the two live viewers.

    ``pipeline``: the page's pipeline (its shot's rigs and settings); ``on_take(filename, data)``
    receives a recording as Live Link Face CSV bytes (the page adds it as the take);
    ``notify(kind, message)`` shows messages."""

    def __init__(self, pipeline, on_take: Callable[[str, bytes], None], notify: Callable = lambda kind, msg: None, **params):
        super().__init__(**params)
        self.pipe = pipeline
        self.on_take = on_take
        self.notify = notify
        self.w_address = pn.widgets.TextInput(name="Listen on (HOST:PORT, the address to give the iPhone app)",
                                              value="0.0.0.0:11111", placeholder="HOST:PORT", width=320)
        self.w_listen = pn.widgets.Toggle(name="Listen", button_type="success", width=120)
        self.w_record = pn.widgets.Toggle(name="● Record", button_type="danger", width=120, disabled=True)
        self.w_take = pn.widgets.Button(name="Use the recording as the take", width=240, disabled=True)
        self.status = pn.pane.Markdown("Not listening.", css_classes=["fr-status"], sizing_mode="stretch_width")
        self.source_box = pn.Column(sizing_mode="stretch_width")
        self.target_box = pn.Column(sizing_mode="stretch_width")
        self.w_listen.param.watch(self._on_listen, "value")
        self.w_record.param.watch(self._on_record, "value")
        self.w_take.on_click(lambda e: self.use_recording())
        self.session: Optional[LiveSession] = None
        self.rt: Optional[LiveRetargeter] = None
        self.source_viewer = self.target_viewer = None
        self._stop = threading.Event()
        self._thread = None
        self._latest = None
        self._shown = None
        self._callback = None
        self._doc = None         # the page's document: frames are sent on its event loop
        self._scheduled = False  # a send of the latest frame is pending on that loop
        self._rate = (time.monotonic(), 0, 0.0)
        self.bound = None
        self.push_ms = 0.0
        self.pushes = self._pushes0 = 0  # frames sent to the viewers, and at the last status
        self.push_rate = 0.0

    def update(self, snap) -> None:
        """Nothing to redraw for a new result: Listen builds the per-frame system from the pipeline."""

    def __panel__(self):
        return pn.Column(
            pn.pane.Markdown("Point the Live Link Face app at this machine (Settings → Live Link → add target: this "
                             "computer's IP and the port below). Every packet is retargeted as it arrives with the "
                             "shot's rigs and settings (docs/live.md).", css_classes=["fr-muted"]),
            pn.Row(self.w_address, self.w_listen, self.w_record, self.w_take),
            self.status,
            pn.Row(self.source_box, self.target_box, sizing_mode="stretch_width"),
            sizing_mode="stretch_width")

    # -- listening ------------------------------------------------------------------------
    def start(self) -> tuple:
        """Build the per-frame system from the page's pipeline, bind the socket and start the
        listener thread; returns the bound (host, port)."""
        host, port = parse_address(self.w_address.value, "0.0.0.0")
        self.rt = LiveRetargeter(self.pipe)
        self.session = LiveSession(self.rt, record=bool(self.w_record.value))
        res = self.pipe.results(["load"])["load"]
        self._viewers(res["source_rig"], res["source_layout"], res["target_rig"], res["target_layout"])
        self._stop = threading.Event()
        ready = threading.Event()
        failed = []

        def run():
            try:
                listen(self.session, host, port, (), self._stop, self._on_frame,
                       lambda h, p: (setattr(self, "bound", (h, p)), ready.set()))
            except OSError as e:
                failed.append(e)
                ready.set()

        self._thread = threading.Thread(target=run, name="face-retarget-live", daemon=True)
        self._thread.start()
        ready.wait(10)
        if failed:
            raise ValueError(f"cannot listen on {host}:{port}: {failed[0]}")
        self._doc = pn.state.curdoc
        if self._doc is not None and self._callback is None:
            # background: not counted as the app being busy (pn.state.add_periodic_callback's
            # callbacks set state.busy on and off at every call: the template's busy indicator
            # changed twice per call, 120 model updates a second to the page); no log line per call
            self._callback = PeriodicCallback(callback=self.push, period=STATUS_MS, background=True, log=False)
            self._callback.start()
        self.w_record.disabled = False
        self._rate = (time.monotonic(), 0, 0.0)
        return self.bound

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        self._thread = None
        if self._callback is not None:
            self._callback.stop()
            self._callback = None
        self.push()
        self.status.object = "Stopped. " + self.status.object

    def _on_listen(self, event):
        if event.new:
            try:
                h, p = self.start()
                self.status.object = f"Listening on {h}:{p} — {self.rt.choice}."
            except ValueError as e:
                self.notify("error", str(e))
                self.w_listen.value = False
        elif self._thread is not None:
            self.stop()

    def _on_frame(self, frame, latency):
        """The listener thread: keep the frame, and have the page's loop send the latest one
        (one pending send at most: frames that come faster than the loop sends are skipped)."""
        self._latest = frame
        doc = self._doc
        if doc is None or self._scheduled:
            return
        self._scheduled = True
        try:
            doc.add_next_tick_callback(self._send_latest)
        except Exception:  # noqa: BLE001 - the page's session is gone; stop() follows
            self._scheduled = False

    def _send_latest(self) -> None:
        self._scheduled = False  # before reading the frame: one that comes meanwhile schedules again
        self.draw_latest()

    def _viewers(self, source_rig, source_layout, target_rig, target_layout) -> None:
        zeros = lambda rig: np.zeros((1, rig.n_shapes), np.float32)  # noqa: E731
        self.source_viewer = MeshViewer.from_rig(source_rig, zeros(source_rig), layout=source_layout,
                                                 label=f"live source: {source_rig.name}", sync_group="live",
                                                 height=VIEW_HEIGHT, sizing_mode="stretch_width")
        self.target_viewer = MeshViewer.from_rig(target_rig, zeros(target_rig), layout=target_layout,
                                                 label=f"live target: {target_rig.name}", sync_group="live",
                                                 height=VIEW_HEIGHT, sizing_mode="stretch_width")
        self.source_box[:] = [self.source_viewer]
        self.target_box[:] = [self.target_viewer]

    def draw_latest(self) -> None:
        """Send the latest frame to the two viewers, if it is new."""
        f = self._latest
        if f is not None and f is not self._shown and self.target_viewer is not None:
            self._shown = f
            t = time.perf_counter()
            with pn.io.unlocked():  # both views' messages go out as one patch (one websocket write)
                self.target_viewer.stream_weights(f.weights)
                if f.values is not None:
                    self.source_viewer.stream_weights(np.clip(self.rt.source_weights(f.values), -1.0, 2.0))
            self.push_ms = 1e3 * (time.perf_counter() - t)
            self.pushes += 1

    def push(self) -> None:
        """Draw the latest frame (if new) and, twice a second, the counts."""
        self.draw_latest()
        t0, n0, rate = self._rate
        now = time.monotonic()
        if self.session is not None and now - t0 >= 0.5:
            st = self.session.stats()
            n = sum(s["answered"] for s in st["subjects"].values())
            rate = (n - n0) / (now - t0)
            self.push_rate = (self.pushes - self._pushes0) / (now - t0)
            self._pushes0 = self.pushes
            self._rate = (now, n, rate)
            self.status.object = self.summary(st, rate)

    def summary(self, st: dict, rate: float) -> str:
        """The status line: address, incoming rate, per subject dropped / tracking loss, bad packets."""
        subs = st["subjects"]
        where = f"{self.bound[0]}:{self.bound[1]}" if self.bound else "?"
        parts = [f"**{'Listening on' if self._thread is not None else 'Was listening on'} {where}** — "
                 f"{rate:.0f} frames/s, {st['received']} packets"]
        for k, s in subs.items():
            parts.append(f"{k or '(no name)'}: {s['answered']} answered, {s['dropped']} dropped, "
                         f"{s['repeated'] + s['out_of_order']} late/repeated, {s['tracking_lost']} tracking lost"
                         + (f", {s['recorded']} recorded" if s["recorded"] else ""))
        bad = sum(st["bad"].values())
        parts.append(f"bad packets: {bad}" + (f" ({', '.join(f'{k} {v}' for k, v in st['bad'].items())})" if bad else ""))
        parts.append(f"page update {self.push_ms:.1f} ms, {self.push_rate:.0f}/s")
        return " · ".join(parts)

    # -- recording --------------------------------------------------------------------------
    def _on_record(self, event):
        if self.session is None:
            return
        self.session.set_recording(bool(event.new))
        if not event.new:
            self.w_take.disabled = not any(s.recorded for s in self.session.streams.values())

    def recording(self) -> tuple:
        """``(filename, Live Link Face CSV bytes)`` of the longest recorded stream.

        Raises ValueError when nothing was recorded."""
        streams = [s for s in (self.session.streams.values() if self.session else ()) if s.recorded]
        if not streams:
            raise ValueError("nothing recorded: press Record while the stream comes")
        st = max(streams, key=lambda s: len(s.recorded))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "live.csv"
            write_livelink(path, st.take())
            data = path.read_bytes()
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in (st.subject or "live"))
        return f"live_{name}_{time.strftime('%H%M%S')}.csv", data

    def use_recording(self) -> None:
        try:
            name, data = self.recording()
            self.notify("info", self.on_take(name, data))
        except ValueError as e:
            self.notify("error", str(e))
