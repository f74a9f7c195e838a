"""Detail-editing test page: the dense-transfer tab on a same-topology transfer of the Jeeliz
tiger onto a stretched copy (tests/dense_case.py: no registration, a few seconds), opened on
frame 20 with "Click does" set to detail selection and the scale factor at 3 (enhance), so a
click and Apply make a visible edit.

Served by tests/browser/test_detail_browser.py (``panel serve tests/browser/detail_app.py``).
:func:`transfer` is deterministic; the test recomputes the same transfer.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import panel as pn

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

if str(ROOT / "tests") not in sys.path:
    sys.path.insert(0, str(ROOT / "tests"))

RIG = ROOT / "data" / "rigs" / "jeeliz_tiger.glb"
#: the case's files, the same for the test process and the server process (deterministic)
CASE = Path(tempfile.gettempdir()) / "face-retarget-tiger-case"
KEY = 20
LABEL = "tiger_big (dense transfer)"
FACTOR = 3.0
LAM_E = 100.0


def session():
    """A dashboard session on the tiger case (tests/dense_case.py), dense settings as the test expects."""
    from core.pipeline import StageCache
    from dashboard.session import Session
    from dense_case import tiger_files

    s = Session(cache=StageCache())
    s.use_files(**tiger_files(CASE))
    s.pipeline.configure(transfer_max_bases=8, transfer_last_frame=-1)
    return s


def transfer():
    """The transfer the page shows (the pipeline's dense stages on the case)."""
    return session().dense()["transfer"]["result"]


def app():
    from dashboard.transfer_view import TransferView

    view = TransferView(session())
    assert view.run(block=True), view.status
    view.w_tool.value = "detail selection"
    view.w_frame.value = KEY
    view.details.w_factor.value = FACTOR
    view.details.w_lam_e.value = LAM_E
    return view.layout


if __name__.startswith("bokeh"):
    pn.extension()
    app().servable(title="detail editing test")
