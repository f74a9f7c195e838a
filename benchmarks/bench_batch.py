"""Shots per minute of ``face-retarget batch`` (core/batch.py) on the bundled takes.

The shots: every bundled capture (3 Live Link takes driving ICT, 2 optical-marker takes), whole
takes, onto the two Jeeliz rigs (tiger, triceratops), with ``bounded`` and ``spacetime``: 20 shots,
~42,000 frames.

* ``batch_1worker`` / ``batch_2workers``: :func:`core.batch.run_batch` on a new LocalCluster of
  1 / 2 processes, timed from before the cluster starts until it is closed (``start_s``: the
  cluster's start-up alone, spawning the processes; ``run_s``: run_batch alone, which includes
  each worker importing face-retarget and loading the rigs on its first shot).
* reference: a plain Python loop in this process over the same shots, calling the same task
  (:func:`core.batch.run_shot`) and writer (:func:`core.batch.write_result`), with a cold stage cache.

``ratio = ref_s / ours_s``: below 1 with one worker is the distributed path's overhead, above 1
with two workers the speed-up (at most 2 on this 2-core machine, none when other jobs already
keep both cores busy: ``load1`` is the load average at the end of the case). ``task_cpu_s`` /
``ref_task_cpu_s``: CPU seconds inside the shots' tasks, which do not depend on the load.
"""

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core import batch  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402

CAPTURES = sorted((ROOT / "data/performances").glob("*.csv"))
TARGETS = ("jeeliz_tiger", "jeeliz_triceratops")
METHODS = ("bounded", "spacetime")


def shots(folder: Path) -> list:
    jobs = []
    for rig in TARGETS:
        for method in METHODS:
            pipe = Pipeline(cache=StageCache(), source=str(CAPTURES[0]), source_rig=str(ROOT / "data/rigs/ict_facekit.glb"),
                            target_rig=str(ROOT / f"data/rigs/{rig}.glb"), method=method)
            template = folder / f"template_{rig}_{method}.json"
            pipe.shot().to_json(template)
            jobs += [batch.BatchShot(f"{j.name}__{rig}__{method}", j.shot, j.base, j.origin)
                     for j in batch.collect_shots([str(c) for c in CAPTURES], template=template)]
    return jobs


def loop(jobs, out: Path) -> float:
    batch.worker_cache(fresh=True)  # cold, like a new worker
    t0 = time.perf_counter()
    for j in jobs:
        r = batch.write_result(out, j, batch.run_shot(batch.job_payload(j)), batch.output_options())
        assert r.status == "ok", r.error
    return time.perf_counter() - t0


def on_dask(jobs, out: Path, workers: int):
    t0 = time.perf_counter()
    client = batch.start_local_cluster(workers, dashboard_address=None)
    start = time.perf_counter() - t0
    try:
        t1 = time.perf_counter()
        results = batch.run_batch(jobs, out, client=client)
        run = time.perf_counter() - t1
    finally:
        cluster = client.cluster
        client.close()
        cluster.close()
    assert all(r.status == "ok" for r in results), [r.error for r in results if r.error]
    return time.perf_counter() - t0, start, run


def task_cpu(out: Path) -> float:
    """CPU seconds the shots took in their tasks (from the manifests): load-independent work."""
    return sum(json.loads(m.read_text())["cpu_seconds"] for m in out.glob("*/manifest.json"))


def main():
    tmp = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    try:
        jobs = shots(tmp)
        frames = 0
        ref = loop(jobs, tmp / "loop")
        for r in batch.read_results(tmp / "loop").values():
            frames += r.metrics["frames"]
        for n in (1, 2):
            ours, start, run = on_dask(jobs, tmp / f"dask{n}", n)
            case = f"batch_{n}worker{'s' if n > 1 else ''}"
            print(f"BENCH {case} ours_s={ours:.2f} ref_s={ref:.2f} ratio={ref / ours:.2f} "
                  f"shots_per_min={60 * len(jobs) / ours:.1f} ref_shots_per_min={60 * len(jobs) / ref:.1f} "
                  f"start_s={start:.2f} run_s={run:.2f} task_cpu_s={task_cpu(tmp / f'dask{n}'):.2f} "
                  f"ref_task_cpu_s={task_cpu(tmp / 'loop'):.2f} shots={len(jobs)} frames={frames} "
                  f"load1={os.getloadavg()[0]:.1f} ref_kind=python_loop_same_task", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
