"""CLI parity with the page (issue 32 item 7): a rig or mesh sequence without a marker layout gets
its markers placed automatically (core.registration.place_markers, what the page's button runs),
with the page's report of the markers that landed badly; ``--no-auto-markers`` refuses instead.
On the previous code each run here was refused with exit code 2."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from datapaths import PERFORMANCES, RIGS
from dense_case import tiger_weights

from core.batch import collect_shots, place_layouts
from core.cli import main
from core.io.curves_csv import read_curves_csv
from core.io.gltf import read_rig
from core.io.layout import read_layout
from core.model import Performance
from core.pipeline import Pipeline, StageCache
from core.shot import FileRef

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


# -- batch: the same placement, once per rig, before any shot runs ------------------------------

def _template(tmp_path, rig) -> Path:
    path = tmp_path / "template.json"
    Pipeline(cache=StageCache(), source=str(PERFORMANCES / "livelinkface_take_s07.csv"),
             source_rig=str(RIGS / "ict_facekit.glb"), target_rig=str(rig), method="bounded", last_frame=29).shot().to_json(path)
    return path


def test_batch_jobs_get_the_layout_placed_once_and_a_resumed_batch_the_same_shots(own_head, tmp_path):
    """Two captures on a rig without a layout: markers are placed once (the second job finds the
    sidecar the first one wrote) and the layout becomes a file of both shots; preparing the same jobs
    again places nothing and gives the same shot contents (a resumed batch skips what is done);
    refused, each job fails saying how to make a layout."""
    captures = [str(PERFORMANCES / "livelinkface_take_s07.csv"), str(PERFORMANCES / "livelinkface_take_facial.csv")]
    jobs = collect_shots(captures, template=_template(tmp_path, own_head))
    refused = place_layouts(jobs, place=False)
    assert all(j.shot is None and "no marker layout for my_head.glb" in j.error for j in refused)
    assert not (tmp_path / "my_head.layout.json").exists()
    lines = []
    placed = place_layouts(jobs, log=lines.append)
    side = tmp_path / "my_head.layout.json"
    assert sum("Placed 41 markers on my_head" in ln for ln in lines) == 1 and side.exists()
    for j in placed:
        assert j.shot.files["target_layout"] == FileRef.of(side)
    again = []
    same = place_layouts(collect_shots(captures, template=_template(tmp_path, own_head)), log=again.append)
    assert again == [] and [j.shot.content_hash() for j in same] == [j.shot.content_hash() for j in placed]


@pytest.mark.slow
def test_batch_places_markers_like_retarget(own_head, tmp_path, capsys):
    """`face-retarget batch` on a rig without a layout: placed (the page's report on stderr),
    the shot runs, and the next run skips it; --no-auto-markers fails the shot instead."""
    tmpl = _template(tmp_path, own_head)
    take = str(PERFORMANCES / "livelinkface_take_s07.csv")
    base = ["batch", take, "--template", str(tmpl), "--workers", "1", "--dashboard-address", ":0", "--quiet"]
    refused = tmp_path / "refused"
    assert main([*base, "--out", str(refused), "--no-auto-markers"]) == 1
    assert "no marker layout for my_head.glb" in capsys.readouterr().err
    assert not (tmp_path / "my_head.layout.json").exists()
    out = tmp_path / "out"
    assert main([*base, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "Placed 41 markers on my_head" in err
    shot = json.loads((out / "livelinkface_take_s07" / "shot.json").read_text())
    assert shot["files"]["target_layout"]["path"] == str(tmp_path / "my_head.layout.json")
    W = read_curves_csv(out / "livelinkface_take_s07" / "livelinkface_take_s07.csv")
    assert W.n_frames == 30 and W.data.max() > 0.05
    assert main([*base, "--out", str(out)]) == 0
    io = capsys.readouterr()
    assert "1 already done" in io.out and "Placed" not in io.err
