"""The contact sheet card: the source and the target side by side at the take's most expressive
frames and the worst one (:mod:`core.contact_sheet`); a click on a frame shows it in the page, and
the sheet downloads as a PNG. :class:`FrameLinks` makes any link of the page that carries
``data-fr-frame="<frame>"`` (the sheet's frames, the summary's "max" error) jump to that frame.

The card renders when it is open (a sheet is about a second and a half of the server's time, on a
worker thread), again for each new result while it stays open. The view holds no numerics: the
frames and pictures are :func:`core.contact_sheet.contact_sheet`'s.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import threading

import panel as pn
import param
from panel.reactive import ReactiveHTML

from core.contact_sheet import contact_sheet
from core.evaluate import worst_frame
from dashboard import widgets
from dashboard.summary_view import download_stem

log = logging.getLogger("face_retarget.dashboard")


class FrameLinks(ReactiveHTML):
    """An invisible element that listens to clicks on the whole page: a click on an element (or
    inside one) with ``data-fr-frame="F"`` sets ``jump`` to ``"F:<count>"`` (the count makes a
    second click on the same frame an event too). Listening on the document in the capture phase
    reaches links inside Bokeh's shadow roots (``composedPath``)."""

    jump = param.String(default="")

    _template = '<div id="fr_frame_links" style="display:none"></div>'
    _scripts = {"render": """
        if (window.__frFrameLinks) document.removeEventListener('click', window.__frFrameLinks, true);
        window.__frFrameLinks = (e) => {
          const a = e.composedPath().find(el => el instanceof Element && el.dataset && el.dataset.frFrame !== undefined);
          if (!a) return;
          e.preventDefault();
          state.clicks = (state.clicks || 0) + 1;
          data.jump = a.dataset.frFrame + ':' + state.clicks;
        };
        document.addEventListener('click', window.__frFrameLinks, true);
    """}


class ContactSheetView(pn.viewable.Viewer):
    """The card; ``host``: the page (its session ``s``, ``playback.w_frame``, ``notify``).

    ``links`` is the page's :class:`FrameLinks` (put it in the page once); ``card`` the card."""

    def __init__(self, host, **params):
        super().__init__(**params)
        self.host = host
        self.s = host.s
        self.sheet = None  # the ContactSheet shown
        self._shown = None  # the snapshot it was made of
        self._busy = False
        self.links = FrameLinks(height=0, width=0, margin=0, sizing_mode="fixed")
        self.links.param.watch(self._on_jump, "jump")
        self.w_info = widgets.HTML("Open to see the source and the target at the take's most expressive frames "
                                   "and at the worst one.", sizing_mode="stretch_width", css_classes=["fr-muted"])
        self.w_sheet = widgets.HTML("", sizing_mode="stretch_width", css_classes=["fr-contact-sheet"])
        self.w_png = pn.widgets.FileDownload(callback=self._png, filename="contact_sheet.png", label="Download PNG",
                                             button_type="light", width=140)
        self.card = pn.Card(self.w_info, self.w_sheet, self.w_png, title="Contact sheet: the most expressive frames and "
                            "the worst", collapsed=True, sizing_mode="stretch_width", css_classes=["fr-contact-card"])
        self.card.param.watch(lambda e: self.draw(self.s.snapshot), "collapsed")

    def __panel__(self):
        return self.card

    # -- events ----------------------------------------------------------------------------
    def _on_jump(self, event) -> None:
        try:
            frame = int(str(event.new).split(":")[0])
        except ValueError:
            return
        w = self.host.playback.w_frame
        w.value = int(min(max(frame, w.start), w.end))

    def _png(self):
        if self.sheet is None:
            self.host.notify("error", "no contact sheet yet: open the card once a result is shown")
            return None
        return io.BytesIO(self.sheet.png())

    # -- drawing ---------------------------------------------------------------------------
    def draw(self, snap: dict, block: bool = False) -> None:
        """Render the sheet of ``snap`` if the card is open and it is not shown yet (a worker
        thread unless ``block`` or outside a server)."""
        if self.card.collapsed or not snap or snap is self._shown or self._busy:
            return
        doc = pn.state.curdoc
        self._busy = True
        self.w_info.object = "rendering the contact sheet…"

        def job():
            try:
                ev = snap["evaluate"]
                res = self.s.pipeline.results(["load", "frames", "stabilize"])
                sheet = contact_sheet(res, snap["weights"], worst_frame(ev), error_mm=ev["marker_error_mm"])
                text = self._html(sheet)
                err = None
            except Exception as e:  # noqa: BLE001 - shown on the page
                log.warning("contact sheet failed", exc_info=True)
                sheet, text, err = None, "", self.s.readable(e)

            def show():
                self._busy = False
                if err is not None:
                    self.w_info.object = "⚠ " + html.escape(err)
                    return
                self.sheet, self._shown = sheet, snap
                stem = download_stem(self.s.source, self.s.target_rig, snap["method"])
                self.w_png.filename = f"{stem}_contact_sheet.png"
                self.w_sheet.object = text
                self.w_info.object = ("Click a frame to show it. The first (red) is the worst: the largest marker error "
                                      "RMS, the summary's max; the others are far apart in the take's expression.")
                if self.s.snapshot is not snap:  # a newer result came while this one rendered
                    self.draw(self.s.snapshot)

            if doc is not None and not block:
                doc.add_next_tick_callback(show)
            else:
                show()

        if doc is not None and not block:
            threading.Thread(target=job, name="contact-sheet", daemon=True).start()
        else:
            job()

    @staticmethod
    def _html(sheet) -> str:
        """The sheet's frames as links (a picture and its caption each)."""
        cells = []
        for i, (f, take_f, caption) in enumerate(zip(sheet.frames, sheet.take_frames, sheet.captions)):
            src = "data:image/png;base64," + base64.b64encode(sheet.tile_png(i)).decode()
            lines = "<br>".join(html.escape(c) for c in caption.split("\n"))
            colour = "#c81e1e" if i == 0 else "#ccc"
            cells.append(f'<a href="#" data-fr-frame="{f}" class="fr-sheet-frame" title="show frame {take_f}" '
                         f'style="display:inline-block;margin:4px;text-decoration:none;color:#333;font-size:12px;'
                         f'border:2px solid {colour};border-radius:4px;padding:2px">'
                         f'<img src="{src}" alt="frame {take_f}" style="display:block;width:270px;height:auto">'
                         f"<span>{lines}</span></a>")
        return f"<div style='display:flex;flex-wrap:wrap'>{''.join(cells)}</div>"
