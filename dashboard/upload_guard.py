"""A file input that refuses a file over the server's upload limit in the browser, with a message.

Panel's :class:`~panel.widgets.FileInput` reads the whole file in the browser and sends it to
the server as one websocket message. The server caps messages (``face-retarget serve`` allows
twice the upload limit, so that a file just over the limit still arrives and gets its message);
a larger one closes the connection and the page shows only Panel's "connection lost". Panel
1.9's FileInput has no size limit of its own, so :class:`UploadGuard` wraps it: in the browser a
listener on the input's shadow root, in the capture phase (before the input's own listener),
stops the ``change`` event of a file over ``max_bytes``, clears the input and tells the server,
which calls ``on_refused(filename, size)``. The server checks the size again (a page without
this script can still send anything up to the message cap).

``page_drop=True`` makes the whole page a drop target for the same input: a file dropped anywhere
(outside another file input) is handed to the input as if chosen in it, so it goes through the
same size check and reaches the server the same way (one upload path, one routing).

A file that is taken is announced first: ``on_start(filename)`` is called before its content
arrives (the input then sends the content, the name and the type as separate messages, which a
loaded server may read apart: the name announced tells it which file the content is).
``max_bytes_by_suffix`` gives some kinds of file another limit (e.g. ``{".zip": ...}``).
"""

from __future__ import annotations

from typing import Callable, Optional

import panel as pn
import param
from panel.custom import Child

__all__ = ["UploadGuard"]


class UploadGuard(pn.custom.JSComponent):
    """``UploadGuard(file_input, max_bytes=..., on_refused=callback)``: shows ``file_input``."""

    child = Child(class_=pn.widgets.FileInput, doc="The guarded file input.")
    max_bytes = param.Integer(default=0, bounds=(0, None), doc="Largest file sent (0: no limit).")
    max_bytes_by_suffix = param.Dict(default={}, doc="Another limit for files of these suffixes ({'.zip': bytes}).")
    page_drop = param.Boolean(default=False, doc="A file dropped anywhere on the page goes to this input.")

    _esm = """
export function render({ model, el }) {
  const host = model.get_child("child")
  el.append(host)
  const limit = (f) => {
    const dot = f.name.lastIndexOf(".")
    const suffix = dot >= 0 ? f.name.slice(dot).toLowerCase() : ""
    const own = (model.max_bytes_by_suffix || {})[suffix]
    return own !== undefined ? own : model.max_bytes
  }
  const guard = (ev) => {
    const input = ev.target
    if (!input || !input.files) return
    const big = Array.from(input.files).find((f) => limit(f) && f.size > limit(f))
    if (big === undefined) {  // taken: the server hears its name before its content arrives
      if (input.files.length) model.send_msg({ starting: input.files[0].name, size: input.files[0].size })
      return
    }
    ev.stopImmediatePropagation()  // the input's own listener never reads the file
    input.value = ""
    model.send_msg({ filename: big.name, size: big.size })
  }
  let tries = 0
  const attach = () => {  // the child's shadow root exists once it has rendered
    if (host.shadowRoot) host.shadowRoot.addEventListener("change", guard, true)
    else if (tries++ < 100) setTimeout(attach, 50)
  }
  attach()
  if (!model.page_drop) return
  const input = () => host.shadowRoot && host.shadowRoot.querySelector("input[type=file]")
  const isFileInput = (ev) => ev.composedPath().some((n) => n.tagName === "INPUT" && n.type === "file")
  const carriesFiles = (ev) => ev.dataTransfer && Array.from(ev.dataTransfer.types || []).includes("Files")
  const over = (ev) => {
    if (!carriesFiles(ev) || isFileInput(ev)) return
    ev.preventDefault()  // the page takes the drop (the browser would open the file instead)
    ev.dataTransfer.dropEffect = "copy"
    document.body.classList.add("fr-drop-over")
  }
  const leave = (ev) => { if (!ev.relatedTarget) document.body.classList.remove("fr-drop-over") }
  const drop = (ev) => {
    document.body.classList.remove("fr-drop-over")
    if (!carriesFiles(ev) || isFileInput(ev)) return  // a file input takes its own drops
    ev.preventDefault()
    const box = input()
    if (!box || !ev.dataTransfer.files.length) return
    const one = new DataTransfer()  // one file a time, like the input itself
    one.items.add(ev.dataTransfer.files[0])
    box.files = one.files
    box.dispatchEvent(new Event("change", { bubbles: true }))  // the guard, then the input's own listener
  }
  document.addEventListener("dragover", over)
  document.addEventListener("dragleave", leave)
  document.addEventListener("drop", drop)
  model.on("remove", () => {
    document.removeEventListener("dragover", over)
    document.removeEventListener("dragleave", leave)
    document.removeEventListener("drop", drop)
  })
}
"""

    def __init__(self, child: pn.widgets.FileInput, on_refused: Optional[Callable[[str, int], None]] = None,
                 on_start: Optional[Callable[[str], None]] = None, **params):
        super().__init__(child=child, **params)
        self._on_refused = on_refused
        self._on_start = on_start

    def _handle_msg(self, msg) -> None:
        if not isinstance(msg, dict):
            return
        if "starting" in msg:
            if self._on_start is not None:
                self._on_start(str(msg.get("starting", ""))[:200])
            return
        if self._on_refused is not None:
            name = str(msg.get("filename", ""))[:200]
            try:
                size = int(msg.get("size", 0))
            except (TypeError, ValueError):
                size = 0
            self._on_refused(name, size)
