"""Batch on Dask (core.batch): the bundled captures x two rigs on a 2-worker LocalCluster, a broken
shot beside good ones, an interrupted batch that resumes without recomputing, bit-identical
re-runs, and an existing scheduler with two `dask worker` processes on 127.0.0.1.

Every process a test starts is stopped in a finally block; frame ranges are short except in the
interrupt test (full takes, so the batch is still running when it is interrupted)."""

import csv
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import distributed  # a dependency of face-retarget: fail, do not skip, when it is missing
import numpy as np
import pytest

from core import batch
from core.batch import BatchShot, collect_shots, read_results, run_batch, write_result, zip_results
from core.cli import main
from core.evaluate import summarize
from core.pipeline import Pipeline, StageCache
from core.shot import Shot
from datapaths import PERFORMANCES, RIGS


CAPTURES = sorted(PERFORMANCES.glob("*.csv"))  # 3 Live Link takes, 2 optical-marker takes
TARGETS = ("jeeliz_tiger", "jeeliz_triceratops")
#: the folder whose `core` this test imports: worker processes must import the same one
CODE_ROOT = str(Path(batch.__file__).resolve().parents[1])


def template(folder: Path, rig: str, last_frame: int = 59) -> Path:
    """A template shot: Live Link curves drive ICT, retargeted onto ``rig`` (the marker captures
    ignore the source rig)."""
    pipe = Pipeline(cache=StageCache(), source=str(CAPTURES[-1]), source_rig=str(RIGS / "ict_facekit.glb"),
                    target_rig=str(RIGS / f"{rig}.glb"), method="bounded", last_frame=last_frame)
    path = folder / f"template_{rig}.json"
    pipe.shot().to_json(path)
    return path


def shot_folder(folder: Path, last_frame: int = 59, captures=CAPTURES) -> Path:
    """One shot file per capture x target rig."""
    folder.mkdir(parents=True, exist_ok=True)
    for rig in TARGETS:
        for job in collect_shots([str(c) for c in captures], template=template(folder.parent, rig, last_frame)):
            job.shot.to_json(folder / f"{job.name}__{rig}.json")
    return folder


@pytest.fixture(scope="module")
def client():
    """A 2-worker LocalCluster shared by the tests below (closed at the end)."""
    c = batch.start_local_cluster(2, dashboard_address=None)
    try:
        yield c
    finally:
        cluster = c.cluster
        c.close()
        cluster.close()


def manifest(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())


def complete(folder: Path) -> bool:
    """A shot folder whose manifest lists files that are all there with their recorded sizes."""
    m = manifest(folder)
    return all((folder / f).is_file() and (folder / f).stat().st_size == info["bytes"] for f, info in m["files"].items())


# -- inputs, records, summary: no cluster ------------------------------------------------------

def test_collect_shots_from_folders_lists_globs_and_a_template(tmp_path):
    t = template(tmp_path, "jeeliz_tiger")
    jobs = collect_shots([str(PERFORMANCES / "*.csv")], template=t)
    assert [j.name for j in jobs] == [c.stem for c in CAPTURES]
    for j, c in zip(jobs, CAPTURES):  # the template's source replaced by each capture, the rest kept
        assert Path(j.shot.files["source"].path) == c.resolve()
        assert j.shot.files["target_rig"] == Shot.from_json(t).files["target_rig"]
        assert j.shot.settings == Shot.from_json(t).settings
    with pytest.raises(ValueError, match="--template"):
        collect_shots([str(CAPTURES[0])])
    with pytest.raises(FileNotFoundError, match="no file matches"):
        collect_shots([str(tmp_path / "nothing*.csv")], template=t)
    # a folder of shot files, a list file (relative lines, comments), clashing names made unique
    folder = tmp_path / "shots"
    folder.mkdir()
    for j in jobs[:2]:
        j.shot.to_json(folder / f"{j.name}.json")
    (folder / "corrupt.json").write_text("{not json")
    listing = tmp_path / "list.txt"
    listing.write_text(f"# the week's shots\nshots/{jobs[0].name}.json\n\n{CAPTURES[0]}\n")
    got = collect_shots([str(folder), str(listing)], template=t)
    names = [j.name for j in got]
    assert names == sorted(names[:3]) + names[3:] and len(set(n.lower() for n in names)) == len(names)
    assert names[3:] == [f"{jobs[0].name}-2", f"{CAPTURES[0].stem}-3"]  # jobs[0] is CAPTURES[0]'s shot
    seq = tmp_path / "take_0042"  # a mesh-sequence capture: a folder of frames, not of shots
    seq.mkdir()
    (seq / "frame_0001.obj").write_text("v 0 0 0\n")
    (seq / "sequence.json").write_text('{"fps": 24}')
    (job,) = collect_shots([str(seq)], template=t)
    assert job.name == "take_0042" and Path(job.shot.files["source"].path) == seq.resolve()
    bad = next(j for j in got if j.name == "corrupt")
    assert bad.shot is None and "not a shot file" in bad.error  # reported as a failed shot, not raised


def test_summarize_by_hand():
    W = np.array([[0.0, 0.5], [0.02, 1.2], [np.nan, np.nan]])
    ev = {"frame_valid": np.array([True, True, False]), "marker_error_mm": np.array([1.0, 3.0, np.nan]),
          "velocity_error_mm_per_frame": np.array([0.0, 2.0, np.nan]), "velocity_error_total_mm2": 8.0,
          "jitter": np.array([np.nan, np.nan, np.nan])}
    s = summarize(ev, W, np.array([True, True, False]), ["a", "b"], active=0.01)
    assert s["frames"] == 3 and s["frames_without_data"] == 1
    assert s["marker_mean_mm"] == 2.0 and s["marker_max_mm"] == 3.0
    assert s["marker_p95_mm"] == pytest.approx(1.0 + 0.95 * 2.0)
    assert s["velocity_error_mm_per_frame"] == 1.0 and s["velocity_error_max_mm_per_frame"] == 2.0
    assert s["velocity_error_total_mm2"] == 8.0 and s["jitter"] is None
    assert s["weight_min"] == 0.0 and s["weight_max"] == 1.2 and s["outside_01"] == 0.25
    assert s["active_per_frame"] == 1.5 and s["active_per_frame_max"] == 2  # |w| > 0.01: b in frame 0, both in frame 1
    assert s["weight_range_per_shape"] == {"a": [0.0, 0.02], "b": [0.5, 1.2]}
    json.dumps(s, allow_nan=False)  # plain numbers
    dense = summarize(None, W[:2])  # dense transfer: no markers, weight statistics only
    assert "marker_mean_mm" not in dense and dense["frames_without_data"] == 0


def test_written_results_are_atomic_zip_and_lock(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    job = BatchShot("s1", Shot(), origin="test")
    res = {"name": "s1", "status": "ok", "content_hash": "abc", "files": {"s1.csv": b"time_s\n"}, "evaluation": {"frames": 1},
           "worker": "w", "host": "h", "pid": 1, "started": "t0", "finished": "t1", "seconds": 0.5, "log": "fine"}
    r = write_result(out, job, res, batch.output_options(6))
    assert r.status == "ok" and r.runs == 1 and complete(out / "s1")
    # a Ctrl-C while the folder is being replaced: the earlier result stays whole, nothing half-written
    real = os.rename

    def interrupted(a, b):
        if ".tmp-" in str(a):
            raise KeyboardInterrupt
        return real(a, b)

    monkeypatch.setattr(batch.os, "rename", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_result(out, job, {**res, "files": {"s1.csv": b"other\n"}}, batch.output_options(6))
    monkeypatch.setattr(batch.os, "rename", real)
    assert (out / "s1" / "s1.csv").read_bytes() == b"time_s\n" and complete(out / "s1")
    assert [p.name for p in out.iterdir()] == ["s1"]  # the temporary folder is gone
    assert write_result(out, job, res, batch.output_options(6)).runs == 2
    # killed between the two renames (the older folder moved aside): the next run puts it back
    os.rename(out / "s1", out / ".s1.old-1234abcd")
    (out / ".s2.tmp-1234abcd").mkdir()
    assert run_batch([], out) == [] and sorted(p.name for p in out.iterdir()) == ["s1", "summary.csv", "summary.html"]
    assert complete(out / "s1")
    # the zip holds the shot folders, no hidden files
    (out / ".batch.lock").write_text("x")
    z = zip_results(out)
    assert z == tmp_path / "out.zip"
    names = zipfile.ZipFile(z).namelist()
    assert "out/s1/s1.csv" in names and "out/s1/manifest.json" in names and not any("/." in n for n in names)
    assert "out/summary.html" in names
    (out / ".batch.lock").unlink()
    # one batch per output folder: a live process's lock refuses, a dead one's is taken over
    import socket

    (out / ".batch.lock").write_text(f"{socket.gethostname()} {os.getpid()} token")
    with pytest.raises(ValueError, match="another batch"):
        run_batch([], out)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    (out / ".batch.lock").write_text(f"{socket.gethostname()} {dead} token")
    assert run_batch([], out) == [] and not (out / ".batch.lock").exists()


# -- a local cluster --------------------------------------------------------------------------

@pytest.mark.slow
def test_local_cluster_runs_captures_x_rigs_from_a_thread_and_a_broken_file_fails_alone(tmp_path, capsys, monkeypatch):
    shots = shot_folder(tmp_path / "shots")
    broken = tmp_path / "broken.csv"
    broken.write_text("this,is,not\na,capture,file\n")
    collect_shots([str(broken)], template=template(tmp_path, "jeeliz_tiger"))[0].shot.to_json(shots / "broken.json")
    (shots / "corrupt.json").write_text("{not json")
    jobs = collect_shots([str(shots)])
    assert len(jobs) == 2 * len(CAPTURES) + 2
    calls, lines = [], []

    def progress(fraction, message):
        calls.append((fraction, message, threading.current_thread().name))

    out = tmp_path / "out"
    with ThreadPoolExecutor(1, thread_name_prefix="dashboard") as pool:  # as the dashboard calls it
        results = pool.submit(run_batch, jobs, out, None, progress, workers=2, dashboard_address=":0",
                              log=lines.append).result(timeout=240)
    status = {r.name: r.status for r in results}
    assert [r.name for r in results] == [j.name for j in jobs]
    assert status.pop("broken") == "failed" and status.pop("corrupt") == "failed"
    assert set(status.values()) == {"ok"}
    by = {r.name: r for r in results}
    assert "broken.csv" in by["broken"].error and "not a shot file" in by["corrupt"].error
    assert "broken.csv" in (out / "broken" / "log.txt").read_text()
    assert any("dask dashboard: http://" in line for line in lines)
    assert len({by[n].worker for n in status}) == 2  # both workers took shots
    # progress: once per shot, from the calling thread, ending at 1
    assert len(calls) == len(jobs) and calls[-1][0] == 1.0 and all(t.startswith("dashboard") for _, _, t in calls)
    assert [c[0] for c in calls] == sorted(c[0] for c in calls)
    for name in status:
        folder = out / name
        assert sorted(p.name for p in folder.iterdir()) == sorted(
            [f"{name}.glb", f"{name}.csv", "evaluation.json", "log.txt", "manifest.json", "shot.json"])
        m = manifest(folder)
        assert m["status"] == "ok" and m["content_hash"] == Shot.from_json(shots / f"{name}.json").content_hash()
        assert complete(folder)
        ev = json.loads((folder / "evaluation.json").read_text())
        assert ev["frames"] == 60 and ev["frames_without_data"] == 0
        assert 0 < ev["marker_mean_mm"] <= ev["marker_p95_mm"] <= ev["marker_max_mm"] < 50
        assert 0 <= ev["weight_min"] <= ev["weight_max"] <= 1 and ev["active_per_frame"] >= 0
    # the summary: every shot, its status and metrics; the HTML is self-contained
    rows = list(csv.DictReader(open(out / "summary.csv")))
    assert [r["shot"] for r in rows] == [j.name for j in jobs]
    assert {r["shot"]: r["status"] for r in rows}["broken"] == "failed"
    assert float(rows[0]["marker_mean_mm"]) == by[rows[0]["shot"]].metrics["marker_mean_mm"]
    page = (out / "summary.html").read_text()
    assert "<table>" in page and "broken" in page
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page) and "<script" not in page and "@import" not in page
    # the CSV a batch writes is the CLI's `retarget --shot` output, to the byte
    name = f"{CAPTURES[0].stem}__jeeliz_tiger"
    again = tmp_path / "again.csv"
    assert main(["retarget", "--shot", str(out / name / "shot.json"), "--weights-csv", str(again), "--quiet"]) == 0
    assert again.read_bytes() == (out / name / f"{name}.csv").read_bytes()
    # run again: finished shots are skipped without starting a cluster; the failed ones are retried
    lines.clear()
    started = []  # the work a rerun must not do: start a cluster, hand shots to dask
    monkeypatch.setattr(batch, "start_local_cluster", lambda *a, **k: started.append("cluster"))
    monkeypatch.setattr(batch, "_run_on_dask", lambda todo, *a, **k: started.append([j.name for j in todo]))
    results = run_batch([j for j in jobs if j.name != "broken"], out, log=lines.append)
    assert started == [] and not any("running" in line for line in lines)
    assert {r.name: r.status for r in results} == {**{n: "skipped" for n in status}, "corrupt": "failed"}
    assert manifest(out / "corrupt")["runs"] == 2 and all(manifest(out / n)["runs"] == 1 for n in status)


@pytest.mark.slow
def test_rerun_gives_bit_identical_csvs(client, tmp_path):
    jobs = collect_shots([str(shot_folder(tmp_path / "shots", captures=CAPTURES[1:3]))])
    out = tmp_path / "out"
    first = run_batch(jobs, out, client=client, csv_precision="full")
    assert all(r.status == "ok" for r in first)
    before = {p.relative_to(out): p.read_bytes() for p in out.glob("*/*.[cg][sl][vb]")}  # .csv, .glb
    assert len(before) == 2 * len(jobs)
    again = run_batch(jobs, out, client=client, csv_precision="full", force=True)
    assert all(r.status == "ok" and r.runs == 2 for r in again)
    after = {p.relative_to(out): p.read_bytes() for p in out.glob("*/*.[cg][sl][vb]")}
    assert after == before
    # another output option is not "done": the shots are recomputed at 6 decimals
    assert all(r.status == "ok" for r in run_batch(jobs, out, client=client))


@pytest.mark.slow
def test_stop_event_cancels_the_rest(client, tmp_path):
    jobs = collect_shots([str(shot_folder(tmp_path / "shots", last_frame=-1, captures=CAPTURES[:2]))])
    stop = threading.Event()
    results = run_batch(jobs, tmp_path / "out", client=client, progress=lambda f, m: stop.set(), stop=stop)
    statuses = [r.status for r in results]
    assert statuses.count("ok") >= 1 and statuses.count("pending") >= 1 and set(statuses) <= {"ok", "pending"}
    assert {r["status"] for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))} == set(statuses)
    assert sorted(read_results(tmp_path / "out")) == sorted(r.name for r in results if r.status == "ok")


@pytest.mark.slow
def test_interrupted_batch_resumes_without_recomputing_finished_shots(client, tmp_path):
    shots = shot_folder(tmp_path / "shots", last_frame=-1)  # full takes: ~1 s a shot, 10 shots
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": CODE_ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-m", "core.cli", "batch", str(shots), "--out", str(out), "--workers", "2",
                             "--dashboard-address", ":0", "--quiet"], cwd=CODE_ROOT, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            # started with SIGINT ignored, as a script's `cmd &` starts it: the batch
                            # installs its own handler (without it the run went on to the end, exit 0)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        t0 = time.time()
        # finished folders only: pathlib's * also matches the hidden temporary folder a shot is
        # written in before its rename (its manifest is written last, just before the rename)
        while len([m for m in out.glob("*/manifest.json") if not m.parent.name.startswith(".")]) < 2:
            assert proc.poll() is None, proc.communicate()
            assert time.time() - t0 < 120, "no shot finished in 2 minutes"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole process group, as a terminal sends it
        _, err = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    assert proc.returncode == 130, f"exit {proc.returncode}\n" + err[-2000:]
    assert "run the same command again to resume" in err
    # finished shots are whole; nothing half-written or temporary is left
    finished = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert 2 <= len(finished) < 10 and [p.name for p in out.iterdir() if p.name.startswith(".")] == []
    assert all(complete(out / n) for n in finished)
    rows = {r["shot"]: r["status"] for r in csv.DictReader(open(out / "summary.csv"))}
    assert {rows[n] for n in finished} == {"ok"} and "pending" in rows.values()
    kept = {n: (out / n / "manifest.json").read_bytes() for n in finished}
    # resume: the finished shots are not recomputed (manifests untouched, one run each), the rest are
    results = run_batch(collect_shots([str(shots)]), out, client=client)
    status = {r.name: r.status for r in results}
    assert {status[n] for n in finished} == {"skipped"}
    assert {s for n, s in status.items() if n not in finished} == {"ok"}
    assert all((out / n / "manifest.json").read_bytes() == b for n, b in kept.items())
    assert all(manifest(out / r.name)["runs"] == 1 for r in results)


# -- an existing cluster: a scheduler and two `dask worker` processes on 127.0.0.1 -----------------

@pytest.mark.slow
def test_existing_scheduler_with_two_dask_workers(client, tmp_path, capsys):
    jobs_dir = shot_folder(tmp_path / "shots", captures=CAPTURES[1:4])
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "PYTHONPATH": CODE_ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "FACE_RETARGET_BATCH_FILES": str(tmp_path / "worker_files")}
    # the scheduler needs only dask: there `import core` finds a package that refuses to import
    (tmp_path / "no_core" / "core").mkdir(parents=True)
    (tmp_path / "no_core" / "core" / "__init__.py").write_text('raise ImportError("the scheduler imported core")\n')
    sched_env = {**os.environ, "PYTHONPATH": str(tmp_path / "no_core")}
    procs = []
    try:  # random free ports: port 0, the scheduler writes its address into the scheduler file
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                       "--port", "0", "--dashboard-address", "127.0.0.1:0", "--scheduler-file",
                                       str(sched_file)], cwd=tmp_path, env=sched_env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        t0 = time.time()
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert procs[0].poll() is None and time.time() - t0 < 60, "the scheduler did not start"
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for _ in range(2):
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                           "--host", "127.0.0.1", "--no-dashboard", "--death-timeout", "60"],
                                          cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with distributed.Client(address, set_as_default=False, timeout=60) as c:
            c.wait_for_workers(2, timeout=90)
            workers = set(c.nthreads())
        out = tmp_path / "remote"
        assert main(["batch", str(jobs_dir), "--out", str(out), "--scheduler", address, "--quiet"]) == 0
        err = capsys.readouterr().err
        assert f"the cluster at {address}" in err and "(scatter)" in err
        results = read_results(out)
        assert len(results) == 6 and {r.status for r in results.values()} == {"ok"}
        assert {r.worker for r in results.values()} <= workers
        assert any((tmp_path / "worker_files").rglob("jeeliz_tiger.glb"))  # sent, not read from the path
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs[::-1]:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
    # the same shots on the local cluster (files read from the shared path) give the same bytes
    local = tmp_path / "local"
    run_batch(collect_shots([str(jobs_dir)]), local, client=client)
    for name in results:
        for suffix in (".csv", ".glb"):
            assert (out / name / f"{name}{suffix}").read_bytes() == (local / name / f"{name}{suffix}").read_bytes()
