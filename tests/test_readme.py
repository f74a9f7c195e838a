"""The README's library example runs and returns what it says (one column per target shape)."""

import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def test_library_example_returns_one_column_per_target_shape(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Library"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    code = code.replace('"shot.json"', repr(str(tmp_path / "shot.json")))
    monkeypatch.chdir(ROOT)
    env: dict = {}
    exec(compile(code, "README.md", "exec"), env)
    W, pipe = env["W"], env["pipe"]
    rig = pipe.results(["load"])["load"]["target_rig"]
    assert W.shape == (2028, rig.n_shapes)
    assert (tmp_path / "shot.json").exists()
    assert pipe.edit.edits and np.isfinite(pipe.results(["synthesize"])["synthesize"]["weights"]).all()
