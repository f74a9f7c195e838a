"""CLI parity with the page (issue 32 item 7): a rig or mesh sequence without a marker layout gets
its markers placed automatically (core.registration.place_markers, what the page's button runs),
with the page's report of the markers that landed badly; ``--no-auto-markers`` refuses instead.
On the previous code each run here was refused with exit code 2."""

import json
import shutil

import numpy as np
import pytest

from datapaths import PERFORMANCES, RIGS
from dense_case import tiger_weights

from core.cli import main
from core.io.curves_csv import read_curves_csv
from core.io.gltf import read_rig
from core.io.layout import read_layout
from core.model import Performance

TAKE = ["--source", str(PERFORMANCES / "livelinkface_take_s07.csv"), "--source-rig", str(RIGS / "ict_facekit.glb"),
        "--last-frame", "29", "--method", "bounded", "--quiet"]


@pytest.fixture()
def own_head(tmp_path):
    """A head the project has no layout for: the Rocketbox rig under a name of its own."""
    path = tmp_path / "my_head.glb"
    shutil.copy(RIGS / "rocketbox_female_adult_02.glb", path)
    return path


def test_a_rig_without_a_layout_gets_markers_placed_and_reported(own_head, tmp_path, capsys):
    csv = tmp_path / "w.csv"
    assert main(["retarget", *TAKE, "--target-rig", str(own_head), "--weights-csv", str(csv)]) == 0
    out = capsys.readouterr().out
    side = tmp_path / "my_head.layout.json"
    # the page's report (core.registration.place_markers' message), and where the layout went
    assert "Placed 41 markers on my_head" in out and f"wrote {side}" in out
    layout = read_layout(side, rig=read_rig(own_head))
    assert layout.n_markers == 41
    W = read_curves_csv(csv)
    assert W.n_frames == 30 and W.data.max() > 0.05  # the take moved the head through those markers
    # the next run finds the sidecar: nothing placed again
    assert main(["retarget", *TAKE, "--target-rig", str(own_head)]) == 0
    assert "Placed" not in capsys.readouterr().out


def test_no_auto_markers_refuses_and_writes_nothing(own_head, tmp_path, capsys):
    assert main(["retarget", *TAKE, "--target-rig", str(own_head), "--no-auto-markers"]) == 2
    err = capsys.readouterr().err
    assert "no marker layout for my_head.glb" in err and "--target-layout" in err and "face-retarget layout" in err
    assert not (tmp_path / "my_head.layout.json").exists()


def test_evaluate_places_markers_too(own_head, tmp_path, capsys):
    js = tmp_path / "r.json"
    assert main(["evaluate", *TAKE[:-3], "--target-rig", str(own_head), "--methods", "bounded", "--json", str(js),
                 "--quiet"]) == 0
    assert "Placed 41 markers on my_head" in capsys.readouterr().out
    assert json.loads(js.read_text())["methods"]["bounded"]["marker_mean_mm"] < 5


def test_a_mesh_sequence_without_a_layout_gets_markers_on_its_own_topology(tmp_path, capsys):
    """The tiger take as a folder of OBJ frames, no source rig, no --source-layout: markers are
    placed on the sequence's first frame (its frames stand in for shapes when flagging markers
    that land where nothing moves) and the take drives the target."""
    from core.io.sequence import write_mesh_sequence

    rig = read_rig(RIGS / "jeeliz_tiger.glb")
    W = np.vstack([np.zeros((1, rig.n_shapes)), tiger_weights(rig.n_shapes, 29)])
    seq = write_mesh_sequence(tmp_path / "take", Performance.meshes(rig.evaluate(W), 30.0, faces=rig.faces, name="take"))
    target = tmp_path / "tiger_copy.glb"
    shutil.copy(RIGS / "jeeliz_tiger.glb", target)  # a layout of its own placed too
    args = ["retarget", "--source", str(seq), "--target-rig", str(target), "--method", "bounded", "--quiet"]
    assert main([*args, "--no-auto-markers"]) == 2
    assert "no marker layout" in capsys.readouterr().err
    csv = tmp_path / "w.csv"
    assert main([*args, "--weights-csv", str(csv)]) == 0
    out = capsys.readouterr().out
    assert out.count("Placed") == 2 and f"wrote {seq / 'layout.json'}" in out
    assert read_layout(seq / "layout.json").n_markers == 41
    assert read_curves_csv(csv).data.max() > 0.3  # the take really moves the target
