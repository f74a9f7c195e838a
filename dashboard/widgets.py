"""How the generated setting cards draw a stage's settings (shared by the sidebar and the tabs)."""

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
