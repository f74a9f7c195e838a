"""The dashboard's Batch tab (dashboard/batch_view.py): the page's shot applied to the captures
picked, run by core.batch on a local Dask cluster, rows filled in per shot, results as a zip;
the CSV of a shot equals what `face-retarget retarget --shot` writes for the same shot."""

import io
import zipfile

import pytest


@pytest.mark.slow
def test_batch_tab_runs_the_chosen_captures_with_the_page_settings(tmp_path):
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    s = Session()
    s.pipeline.configure(last_frame=149, alpha=0.03)
    app = DashboardApp(s)
    view = app.batch_view
    view.out_root = tmp_path
    takes = {k: v for k, v in view.w_takes.options.items() if "livelinkface" in k}
    assert len(takes) >= 2, view.w_takes.options
    picked = sorted(takes.values())[:2]
    assert not view.start()  # nothing chosen: a message, no batch
    assert "at least one" in view.w_status.object
    view.w_takes.value = picked
    view.w_workers.value = 1
    assert view.start()
    assert list(view.w_table.value["status"]) == ["to do", "to do"]
    view._thread.join(timeout=600)
    assert not view.running
    table = view.w_table.value
    assert list(table["status"]) == ["ok", "ok"], table.to_dict("records")
    assert (table["frames"] == 150).all() and (table["marker error (mm)"] > 0).all()
    assert view.w_status.object.startswith("Done: 2 ok") and not view.w_zip.disabled
    with zipfile.ZipFile(io.BytesIO(view._zip_bytes().read())) as z:
        names = z.namelist()
    for take in picked:
        stem = take.rsplit("/", 1)[-1][:-4]
        assert any(n.endswith(f"{stem}/{stem}.csv") for n in names) and any(n.endswith(f"{stem}/{stem}.glb") for n in names)
    # the page's settings went into every shot: the shot a batch folder records is the page's, with its source
    from core.shot import Shot

    stem = picked[0].rsplit("/", 1)[-1][:-4]
    shot = Shot.from_json(view.out_dir / stem / "shot.json")
    assert shot.settings["solve"]["alpha"] == 0.03 and shot.settings["frames"]["last_frame"] == 149
    # and its CSV is what `face-retarget retarget --shot` writes for that shot
    import subprocess
    import sys

    out = tmp_path / "direct.csv"
    subprocess.run([sys.executable, "-m", "core.cli", "retarget", "--shot", str(view.out_dir / stem / "shot.json"),
                    "--out", str(tmp_path / "direct.glb"), "--weights-csv", str(out)], check=True, capture_output=True)
    assert out.read_bytes() == (view.out_dir / stem / f"{stem}.csv").read_bytes()
