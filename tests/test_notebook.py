"""The tutorial notebook (examples/tutorial.ipynb) runs top to bottom on the bundled data:
load, retarget, compare two methods, edit, export, and the dashboard inline as a Panel object."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_tutorial_notebook_executes():
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(ROOT / "examples" / "tutorial.ipynb", as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(ROOT / "examples")}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "300 frames x 175 shapes" in text and "JawOpen at frame 150" in text and "shot.json" in text
    # the last cell displays the dashboard: Panel's notebook output (a bokeh/panel mime bundle)
    last = nb.cells[-1]["outputs"]
    assert any("application/vnd.holoviews_exec.v0+json" in o.get("data", {}) or "text/html" in o.get("data", {})
               for o in last if o.output_type in ("display_data", "execute_result"))
