"""Detail-editing test page: the dense-transfer tab on a same-topology transfer of the Jeeliz
tiger (no registration, a few seconds), opened on frame 20 with "Click does" set to detail
selection and the scale factor at 3 (enhance), so a click and Apply make a visible edit.

Served by tests/browser/test_detail_browser.py (``panel serve tests/browser/detail_app.py``).
:func:`transfer` is deterministic; the test recomputes the same transfer in numpy.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import panel as pn

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io.gltf import read_rig  # noqa: E402
from core.transfer import transfer_sequence  # noqa: E402

RIG = ROOT / "data" / "rigs" / "jeeliz_tiger.glb"
KEY = 20
LABEL = "tiger (dense transfer)"
FACTOR = 3.0
LAM_E = 100.0


def transfer(rig):
    t = np.arange(40)
    K = rig.n_shapes
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (5 + 2 * np.arange(K)) + np.arange(K)), 0, 1)
    return transfer_sequence(rig.neutral, rig.faces, rig.evaluate(W), rig.neutral * [1.1, 0.95, 1.0], rig.faces,
                             max_bases=8)


def app():
    from dashboard.session import Session
    from dashboard.transfer_view import EditableTransfer, TransferView

    rig = read_rig(RIG)
    view = TransferView(Session())
    view.show(EditableTransfer(transfer(rig), rig), first_frame=0, target_name="tiger")
    view.w_tool.value = "detail selection"
    view.w_frame.value = KEY
    view.details.w_factor.value = FACTOR
    view.details.w_lam_e.value = LAM_E
    return view.layout


if __name__.startswith("bokeh"):
    pn.extension()
    app().servable(title="detail editing test")
