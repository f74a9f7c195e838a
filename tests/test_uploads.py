"""Uploads are checked when they arrive (core/io/check.py through the dashboard session): each
bad file gets a message naming it as the user called it — never a server path, a byte string or
a command-line flag — and stays out of the lists; good files go where they belong."""

import numpy as np
import pytest

from core.pipeline import StageCache
from datapaths import LAYOUTS, PERFORMANCES, RIGS


@pytest.fixture
def session():
    from dashboard.session import Session

    return Session(cache=StageCache())


def _no_shapes_glb(tmp_path, tiger):
    from core.io.gltf import write_rig
    from core.model import Rig

    p = tmp_path / "plain.glb"
    write_rig(p, Rig(tiger.neutral, tiger.faces, np.zeros((0,) + tiger.neutral.shape), [], None, "m", "plain"))
    return p.read_bytes()


def test_bad_uploads_are_refused_in_plain_words(session, tmp_path, tiger):
    before = {k: dict(v) for k, v in session.files.items()}
    cases = [("empty.glb", b"", "empty.glb is empty"),
             ("garbage.glb", b"\x00\x01 not a binary glTF", "garbage.glb is not a GLB file"),
             ("plain.glb", _no_shapes_glb(tmp_path, tiger), "plain.glb has no blend shapes"),
             ("no_frames.csv", b"Timecode,BlendShapeCount,EyeBlinkLeft\n", "no_frames.csv"),
             ("words.csv", b"hello,world\n1,2\n", "words.csv"),
             ("binary.csv", b"\x00\xff\x00\xfe" * 100, "binary.csv is not a text file"),
             ("notes.txt", b"hello", "notes.txt: files of type .txt"),
             ("broken.json", b"{not json", "broken.json is not valid JSON"),
             ("list.json", b"[1, 2]", "expected a JSON object")]
    for name, data, want in cases:
        with pytest.raises(ValueError) as e:
            session.add_upload(name, data)
        msg = str(e.value)
        assert want in msg, msg
        assert str(session.upload_dir) not in msg and "/tmp" not in msg and "b'" not in msg and "--" not in msg, msg
        assert not (session.upload_dir / name).exists(), f"{name} was kept"
    assert session.files == before


@pytest.mark.slow
def test_good_uploads_go_where_they_belong(session, tmp_path):
    msg = session.add_upload("take.csv", (PERFORMANCES / "livelinkface_rom.csv").read_bytes())
    assert "weight curves" in msg and session.source == "⤒ take.csv"
    msg = session.add_upload("tiger copy.glb", (RIGS / "jeeliz_tiger.glb").read_bytes())
    assert "11 blend shapes" in msg and "⤒ tiger copy.glb" in session.files["rigs"]
    # a layout applies to the chosen target rig
    session.target_rig = "⤒ tiger copy.glb"
    msg = session.add_upload("my.layout.json", (LAYOUTS / "jeeliz_tiger.json").read_bytes())
    assert "41 markers" in msg and session.pipeline.target_face.target_layout.endswith("my.layout.json")
    assert session.recompute(), session.error
    # a rig without a layout: the page's words, not the command line's
    session.add_upload("other.glb", (RIGS / "jeeliz_triceratops.glb").read_bytes())
    session.pipeline.configure(target_layout="")
    session.target_rig = "⤒ other.glb"
    assert session.needs_layout == "other.glb"
    assert not session.recompute()
    assert "has no marker layout yet" in session.error and "--" not in session.error and "/tmp" not in session.error
    report = session.place_markers()
    assert "Placed 41 markers" in report["message"] and session.layout_path().exists()
    assert session.recompute(), session.error
    assert session.needs_layout == ""
    assert len(session.result_bytes("glb")) > 1000 and session.result_bytes("csv").startswith(b"time_s,frame,valid")


@pytest.mark.slow
def test_upload_folder_is_made_on_use_and_removed_with_the_session():
    """A page that never uploads leaves no folder; a session's uploads go when it does (a server
    kept one temp folder per page ever opened, with every file uploaded into it)."""
    import gc

    from dashboard.session import Session

    idle = Session(cache=StageCache())
    assert idle._upload_dir is None
    s = Session(cache=StageCache())
    s.add_upload("take.csv", (PERFORMANCES / "livelinkface_rom.csv").read_bytes())
    folder = s.upload_dir
    assert (folder / "take.csv").is_file()
    del s
    gc.collect()
    assert not folder.exists()


def test_upload_folders_of_dead_servers_are_swept(tmp_path):
    """A killed server cannot remove its sessions' upload folders; the next server start removes
    those of processes that are gone and leaves the living ones' (and anything else) alone."""
    import os
    import subprocess
    import sys

    from dashboard.session import UPLOAD_PREFIX, sweep_orphan_uploads

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f"{UPLOAD_PREFIX}{gone.pid}-abc"
    mine = tmp_path / f"{UPLOAD_PREFIX}{os.getpid()}-def"
    other = tmp_path / f"{UPLOAD_PREFIX}notapid"
    for d in (dead, mine, other):
        d.mkdir()
        (d / "take.csv").write_text("x")
    assert sweep_orphan_uploads(tmp_path) == 1
    assert not dead.exists() and mine.exists() and other.exists()


def test_a_data_note_of_an_uploaded_take_names_the_file_not_the_server_path(session):
    """Issue 33.6: the note under the summary (a take's data-quality warning) showed the server's
    temporary path of the upload; it names the file as uploaded."""
    lines = (PERFORMANCES / "livelinkface_take_s07.csv").read_bytes().splitlines(keepends=True)
    lines[5], lines[6] = lines[6], lines[5]  # the timecode goes backwards once
    session.add_upload("jumpy.csv", b"".join(lines))
    assert session.recompute(), session.error
    notes = session.snapshot["warnings"]
    assert any(n.startswith("jumpy.csv: column Timecode goes backwards") for n in notes), notes
    assert not any(str(session.upload_dir) in n for n in notes), notes


def test_an_uploaded_rig_is_offered_as_the_target_or_the_source_rig():
    """Issue 32 item 2: the note of an uploaded rig carries *Use as target* / *Use as source rig*;
    the button selects it, and the offer goes with the next note."""
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    app.s.auto_update = False  # what is chosen is the point here, not the result
    app.sidebar.w_upload.param.update(filename="tiger copy.glb", value=(RIGS / "jeeliz_tiger.glb").read_bytes())
    assert "tiger copy.glb" in app.w_alert.object and "rig lists" in app.w_alert.object and app.w_offer.visible
    assert app.s.target_rig != "⤒ tiger copy.glb"
    app.w_use_source_rig.clicks += 1
    assert app.s.source_rig == "⤒ tiger copy.glb" and not app.w_offer.visible
    app.sidebar.w_upload.param.update(filename="tiger again.glb", value=(RIGS / "jeeliz_tiger.glb").read_bytes())
    assert app.w_offer.visible
    app.w_use_target.clicks += 1
    assert app.s.target_rig == "⤒ tiger again.glb" and app.s.source_rig == "⤒ tiger copy.glb"
    # a take is the source at once, and offers nothing
    app.sidebar.w_upload.param.update(filename="take.csv", value=(PERFORMANCES / "livelinkface_rom.csv").read_bytes())
    assert app.s.source == "⤒ take.csv" and not app.w_offer.visible


def test_an_uploaded_source_rig_gets_its_own_markers_never_the_previous_rigs():
    """*Use as source rig* with an uploaded rig of another mesh, on a page of a shot (the shot names
    the ICT layout by path): the rig gets markers placed on it, as *Use as target* does, and the
    result is computed. Before, the ICT layout stayed and the page failed with "vertex 8208 out of
    range for rig my_head"; a target switched the same way kept the previous target's layout."""
    from core.io.layout import read_layout
    from core.io.rigs import load_rig
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    app.s.pipeline.configure(last_frame=59)
    app.s.open_shot(app.s.shot())  # as a page of a shot: every layout set by path
    assert app.s.pipeline.source_face.source_layout.endswith("ict_facekit.json")
    head = (RIGS / "rocketbox_female_adult_02.glb").read_bytes()
    app.sidebar.w_upload.param.update(filename="my_head.glb", value=head)
    app.w_use_source_rig.clicks += 1
    assert app.s.source_rig == "⤒ my_head.glb"
    assert "Placed 41 markers on my_head" in app.markers.w_info.object
    layout = app.s.pipeline.source_face.source_layout
    assert layout == str(app.s.upload_dir / "my_head.layout.json")
    assert read_layout(layout, rig=load_rig(app.s.upload_dir / "my_head.glb")).n_markers == 41
    assert not app.s.error and app.s.recompute(), app.s.error
    assert np.nanmax(app.s.snapshot["weights"]) > 0.05
    # the target the same way: the previous target's layout is not kept for another mesh
    app.s.auto_update = False
    app.sidebar.w_upload.param.update(filename="other head.glb", value=(RIGS / "jeeliz_tiger.glb").read_bytes())
    app.s.target_rig = "⤒ other head.glb"
    app.s.shot()  # the selection reaches the pipeline
    assert app.s.needs_layout == "other head.glb" and app.s.pipeline.target_face.target_layout == ""
