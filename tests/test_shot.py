"""The shot document: plain data that round-trips, migrates, and reproduces a pipeline exactly."""

import csv
import json
import shutil

import numpy as np
import pytest

from core.cli import main
from core.pipeline import Pipeline, StageCache, shot_from_settings
from core.shot import SCHEMA_VERSION, EditHistory, Shot, file_hash, migrate
from datapaths import PERFORMANCES, RIGS

FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "jeeliz_tiger.glb"))
POSE = {"frame": 30, "weights": {"mouthOpen": 0.5}, "window": [20, 40]}


@pytest.fixture
def pipe():
    return Pipeline(cache=StageCache(), method="spacetime", alpha=0.05, last_frame=59, **FILES)


def test_shot_holds_files_settings_edits_and_round_trips_exactly(pipe):
    pipe.add_edit("spacetime", POSE)
    pipe.add_edit("spacetime", {**POSE, "frame": 35})
    pipe.undo("spacetime")
    pipe.frame, pipe.notes = 12, [{"frame": 12, "author": "lead", "text": "jaw late"}]
    shot = pipe.shot()
    assert shot.schema_version == SCHEMA_VERSION
    assert shot.files["source"].sha == file_hash(FILES["source"])
    assert shot.files["target_layout"].path.endswith("jeeliz_tiger.json")  # the default layout, recorded as used
    assert shot.settings["solve"]["alpha"] == 0.05 and shot.settings["frames"]["last_frame"] == 59
    assert shot.edits["spacetime"].done == [POSE] and shot.edits["spacetime"].undone == [{**POSE, "frame": 35}]
    text = shot.to_json()
    again = Shot.from_json(text)
    assert again.to_dict() == shot.to_dict() and again.to_json() == text
    assert json.loads(text)["edits"]["transfer"] == {"done": [], "undone": []}


def test_from_shot_reproduces_every_stage_key(pipe, tmp_path):
    pipe.add_edit("spacetime", POSE)
    path = tmp_path / "shot.json"
    pipe.shot().to_json(path)
    other = Pipeline.from_shot(path, cache=StageCache())
    cfg_a, cfg_b = pipe.config(), other.config()
    for name in pipe.stages:
        assert pipe.key(name, _cfg=cfg_a) == other.key(name, _cfg=cfg_b), name
    Wa = pipe.results(["synthesize"])["synthesize"]["weights"]
    Wb = other.results(["synthesize"])["synthesize"]["weights"]
    assert np.array_equal(Wa, Wb)
    assert other.edits("spacetime").done == [POSE]


def test_undo_redo_remove_through_the_pipeline(pipe):
    a, b = POSE, {**POSE, "frame": 40, "window": [30, 50]}
    pipe.add_edit("spacetime", a)
    pipe.add_edit("spacetime", b)
    assert pipe.edit.edits == [a, b]
    assert pipe.undo("spacetime") and pipe.edit.edits == [a] and pipe.redo["spacetime"] == [b]
    assert pipe.redo_edit("spacetime") and pipe.edit.edits == [a, b]
    assert pipe.remove_edit("spacetime", 0) == a and pipe.edit.edits == [b]
    pipe.add_edit("spacetime", a)  # a new edit clears the redo stack
    assert pipe.redo["spacetime"] == [] and not pipe.redo_edit("spacetime")
    pipe.configure(edits=[])  # an edit list set from outside starts a new history
    assert pipe.edits("spacetime") == EditHistory([], [])
    assert not pipe.undo("spacetime")


def test_a_changed_file_is_refused_and_an_override_wins(pipe, tmp_path):
    take = tmp_path / "take.csv"
    shutil.copy(FILES["source"], take)
    pipe.configure(source=str(take))
    path = tmp_path / "shot.json"
    pipe.shot().to_json(path)
    with open(take, "a") as f:
        f.write("\n")
    with pytest.raises(ValueError, match="take.csv.*changed since the shot was saved"):
        Pipeline.from_shot(path)
    other = Pipeline.from_shot(path, source=FILES["source"])  # an override is not checked against the shot
    assert other.take.source == FILES["source"]
    take.unlink()
    with pytest.raises(FileNotFoundError, match="source file .*take.csv not found"):
        Pipeline.from_shot(path)


def test_relative_paths_are_found_beside_the_shot(tmp_path, monkeypatch):
    shutil.copy(RIGS / "jeeliz_tiger.glb", tmp_path / "tiger.glb")
    shutil.copy(PERFORMANCES / "animface_markers_jaw_60hz.csv", tmp_path / "animface_jaw.csv")
    shutil.copy(RIGS.parent / "layouts" / "jeeliz_tiger.json", tmp_path / "tiger.layout.json")
    monkeypatch.chdir(tmp_path)
    shot = Pipeline(source="animface_jaw.csv", target_rig="tiger.glb", last_frame=9).shot()
    assert shot.files["target_layout"].path == "tiger.layout.json"
    shot.to_json(tmp_path / "s.json")
    monkeypatch.chdir(RIGS)  # elsewhere: the files are found relative to the shot file
    pipe = Pipeline.from_shot(tmp_path / "s.json", cache=StageCache())
    assert pipe.results(["synthesize"])["synthesize"]["weights"].shape == (10, 11)


def test_migration_from_version_0_and_refusals():
    flat = {"source": FILES["source"], "target_rig": FILES["target_rig"], "alpha": 0.2, "method": "prior_pf",
            "edits": [POSE]}
    with pytest.raises(ValueError, match="version-0 document .* Pipeline.from_shot"):
        Shot.from_dict(flat)  # the shot alone does not know which stage owns a setting
    doc = migrate(flat, shot_from_settings)
    assert doc["schema_version"] == SCHEMA_VERSION
    assert doc["settings"]["solve"] == {"alpha": 0.2, "method": "prior_pf"}
    assert doc["files"]["source"]["sha"] == file_hash(FILES["source"])
    assert doc["edits"]["spacetime"]["done"] == [POSE]
    pipe = Pipeline.from_shot(flat)
    assert pipe.solve.method == "prior_pf" and pipe.edit.edits == [POSE]
    with pytest.raises(ValueError, match="newer than this program"):
        Shot.from_dict({"schema_version": SCHEMA_VERSION + 1})
    with pytest.raises(ValueError, match="unknown settings"):
        migrate({"alpah": 1}, shot_from_settings)
    with pytest.raises(ValueError, match="settings.solve.regions: unknown setting .* belongs to stage 'segment'"):
        Pipeline.from_shot(Shot(settings={"solve": {"regions": 3}}))


def test_bad_shot_files_say_what_is_wrong(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad.json: not a shot file .*line 1"):
        Shot.from_json(bad)
    bad.write_text("[1, 2]")
    with pytest.raises(ValueError, match="expected a JSON object"):
        Shot.from_json(bad)
    bad.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match="not UTF-8"):
        Shot.from_json(bad)


def test_content_hash_ignores_paths_frame_notes_and_redo(pipe):
    a = pipe.shot()
    pipe.frame, pipe.notes = 40, [{"frame": 1, "text": "x"}]
    pipe.add_edit("spacetime", POSE)
    pipe.undo("spacetime")
    b = pipe.shot()
    assert a.content_hash() == b.content_hash()
    pipe.configure(alpha=0.06)
    assert pipe.shot().content_hash() != a.content_hash()


def _csv_weights(path):
    rows = list(csv.reader(open(path)))
    return np.array([[float(c) for c in r[3:]] for r in rows[1:]])


def test_cli_save_shot_then_shot_reproduces_to_the_last_bit(tmp_path, capsys):
    base = ["retarget", "--source", FILES["source"], "--source-rig", FILES["source_rig"], "--target-rig",
            FILES["target_rig"], "--last-frame", "59", "--quiet", "--csv-precision", "full"]
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    shot = tmp_path / "shot.json"
    assert main(base + ["--method", "geometric", "--mu", "0.5", "--weights-csv", str(a), "--save-shot", str(shot)]) == 0
    doc = json.loads(shot.read_text())
    assert doc["settings"]["solve"]["method"] == "geometric" and doc["settings"]["solve"]["mu"] == 0.5
    assert main(["retarget", "--shot", str(shot), "--weights-csv", str(b), "--quiet", "--csv-precision", "full"]) == 0
    assert np.array_equal(_csv_weights(a), _csv_weights(b))
    # other flags override the shot
    assert main(["retarget", "--shot", str(shot), "--mu", "0.1", "--weights-csv", str(c), "--quiet", "--csv-precision", "full"]) == 0
    assert not np.array_equal(_csv_weights(a), _csv_weights(c))
    # and the CLI's numbers are the library's
    pipe = Pipeline(cache=StageCache(), method="geometric", mu=0.5, last_frame=59, **FILES)
    assert np.array_equal(_csv_weights(a), pipe.results(["synthesize"])["synthesize"]["weights"])
