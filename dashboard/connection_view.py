"""The page's connection to its server: when it is lost, say so and refuse edits.

A page whose server died (killed, restarted, the laptop asleep) kept showing its widgets and
took changes that went nowhere. :class:`ConnectionWatch` listens in the browser to the Bokeh
document's ``connection_lost`` event (sent when the page's websocket closes) and then covers the
page with a banner, "Connection lost", over a veil that takes every click and key, so nothing
looks accepted that is not; Bokeh's ``client_reconnected`` lifts it. The banner offers a reload
(a server that came back has a new session for the page). Nothing is sent to the server.
"""

from __future__ import annotations

import panel as pn

__all__ = ["ConnectionWatch", "LOST_TEXT"]

#: the banner's words (the browser test looks for them)
LOST_TEXT = "Connection lost"


class ConnectionWatch(pn.custom.JSComponent):
    """Invisible until the page's connection is lost; then a banner and a veil over the page
    (``window.__faceRetargetConnection.lost`` is true meanwhile, for tests)."""

    _esm = """
export function render({ view }) {
  const state = (window.__faceRetargetConnection = window.__faceRetargetConnection || { lost: false })
  let veil = null
  const refuse = (ev) => { if (state.lost && !(ev.target && ev.target.closest && ev.target.closest(".fr-connection"))) {
    ev.stopImmediatePropagation(); ev.preventDefault() } }
  const lost = () => {
    state.lost = true
    if (veil !== null) return
    veil = document.createElement("div")
    veil.className = "fr-connection"
    veil.setAttribute("role", "alert")
    veil.style.cssText = "position:fixed;inset:0;z-index:100000;background:rgba(30,30,30,0.35);display:flex;" +
      "align-items:flex-start;justify-content:center;padding-top:12px"
    const box = document.createElement("div")
    box.style.cssText = "background:#b00020;color:white;font:15px sans-serif;padding:10px 16px;border-radius:6px;" +
      "box-shadow:0 2px 8px rgba(0,0,0,0.4);max-width:640px"
    box.innerHTML = "<b>LOST_TEXT to the server.</b> Changes made now would not be kept, so the page takes none. " +
      "Reload the page when the server is back. "
    const reload = document.createElement("button")
    reload.textContent = "Reload"
    reload.style.cssText = "margin-left:8px"
    reload.onclick = () => window.location.reload()
    box.append(reload)
    veil.append(box)
    document.body.append(veil)
  }
  const back = () => {
    state.lost = false
    if (veil !== null) { veil.remove(); veil = null }
  }
  for (const type of ["keydown", "keyup", "input", "change", "pointerdown", "mousedown", "click", "wheel"])
    window.addEventListener(type, refuse, true)
  const doc = view.model.document
  doc.on_event("connection_lost", lost)
  doc.on_event("client_reconnected", back)
}
""".replace("LOST_TEXT", LOST_TEXT)

    def __init__(self, **params):
        params.setdefault("width", 0)
        params.setdefault("height", 0)
        params.setdefault("margin", 0)
        super().__init__(**params)
