"""How the generated setting cards draw a stage's settings (shared by the sidebar and the tabs),
and the small static pieces the pages share."""

from __future__ import annotations

import panel as pn
import param

#: tiny relative weights read better typed than on a slider that shows 1e-5 as "0"
TYPED = {"ridge": pn.widgets.FloatInput, "rbf_smoothing": pn.widgets.FloatInput, "l1": pn.widgets.FloatInput,
         "name_weight": pn.widgets.FloatInput, "transfer_eps": pn.widgets.FloatInput,
         "transfer_alpha": pn.widgets.FloatInput, "transfer_iterations": pn.widgets.IntInput,
         "transfer_max_bases": pn.widgets.IntInput, "detail_tolerance": pn.widgets.FloatInput}


def param_widgets(stage, names, extra=None) -> dict:
    """pn.Param widget choices for ``names`` of ``stage``: a Boolean setting is a toggle button
    (its whole label is clickable — a Bokeh checkbox toggles only from its box), tiny relative
    weights are typed; ``extra`` adds more."""
    out = {n: {"type": pn.widgets.Toggle, "button_type": "light"} for n in names if isinstance(stage.param[n], param.Boolean)}
    out.update({k: v for k, v in TYPED.items() if k in names})
    out.update({k: v for k, v in (extra or {}).items() if k in names})
    return out


#: a thin rule, as HTML: put in one pane with the heading under it (a Divider and a heading are two
#: Panel objects, and each costs every page ~25-35 KB of server memory)
RULE = "<hr style='border:none;border-top:1px solid #ddd;margin:4px 0 8px 0'>"


def ruled_heading(text: str, note: str = "") -> str:
    """HTML of a rule and a bold heading ``text`` (plain text) with an optional ``note`` after it."""
    import html

    return f"{RULE}<p><strong>{html.escape(text)}</strong>{(' ' + html.escape(note)) if note else ''}</p>"


class _TextUpdate:
    """A text pane whose new ``object`` reaches its model as the new text alone. Panel's own update
    of a text pane (``HTMLBasePane._update``) recomputes every property of the model — design,
    stylesheets, sizing — for each new text: ~1.3 ms a time, and a shared shot's change updates a
    page's status, summary and timings on every page of the shot. Only ``object`` (and the
    sanitising settings, folded into ``_transform_object``) re-render a text pane; every other
    parameter still takes Panel's normal path."""

    def _update(self, ref, model) -> None:
        model.update(text=self._transform_object(self.object)["object"])


class Markdown(_TextUpdate, pn.pane.Markdown):
    """``pn.pane.Markdown`` whose updates send only the new text (see :class:`_TextUpdate`)."""


class HTML(_TextUpdate, pn.pane.HTML):
    """``pn.pane.HTML`` whose updates send only the new text (see :class:`_TextUpdate`)."""
