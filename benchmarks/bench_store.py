"""Latency of one acknowledged review write (core/store.py): the time from ``Store.apply`` being
called to its change being committed to disk, which is what a reviewer waits for before the
other pages hear of it.

* ``store_edit_write``: ``Store.apply`` of a spacetime edit added to a real shot document (the
  pipeline's shot of the sample take: every stage's settings, ~5 KB of JSON, with 50 edits in its
  lists already), committed before it returns; p50 and p95 over the writes.

  - ours: the store's defaults, ``journal_mode=WAL`` + ``synchronous=FULL`` (one fsync of the WAL
    per commit: durable on a power cut);
  - ref: the same store and the same writes with ``journal_mode=DELETE`` + ``synchronous=FULL``,
    SQLite's default rollback journal (what a plain ``sqlite3.connect`` does);
  - ``wal_normal_p50_s``: WAL + ``synchronous=NORMAL`` (durable against a crash of the process,
    which the kill -9 test checks, but a power cut may lose the last commits);
  - ``note_p50_s``: a note added (ours); ``doc_kb``: the document's size at the end.

  Today's app keeps each tab's state in memory and persists nothing, so it has no write of its own
  to compare with; the reference is the same write under SQLite's default journal.

Writes alternate between the three stores in rounds so that disk noise hits all of them.
"""

import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.store import Store  # noqa: E402

FILES = dict(source=str(ROOT / "data/performances/livelinkface_take_s07.csv"), source_rig=str(ROOT / "data/rigs/ict_facekit.glb"),
             target_rig=str(ROOT / "data/rigs/rocketbox_female_adult_02.glb"))


def pctl(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def bench_edit_write(rounds=20, per_round=10, warm=5):
    pipe = Pipeline(cache=StageCache(), method="spacetime", **FILES)
    for i in range(50):
        pipe.add_edit("spacetime", {"frame": 10 * i, "weights": {"jawOpen": 0.4}, "window": [10 * i - 5, 10 * i + 5]})
    shot = pipe.shot()
    tmp = Path(tempfile.mkdtemp(prefix="bench-store-"))
    try:
        configs = {"ours": dict(journal_mode="WAL", synchronous="FULL"), "ref": dict(journal_mode="DELETE", synchronous="FULL"),
                   "wal_normal": dict(journal_mode="WAL", synchronous="NORMAL")}
        stores = {k: Store(tmp / k, **cfg) for k, cfg in configs.items()}
        state = {}
        for k, s in stores.items():
            sid = s.create_shot(shot, "bench", "bench", import_files=False)
            state[k] = [sid, 1]
        times = {k: [] for k in stores}
        notes = []

        def write(k, i, kind="edit"):
            s, (sid, v) = stores[k], state[k]
            ch = ({"kind": "edit", "editor": "spacetime", "op": "add", "edit": {"frame": i, "weights": {"jawOpen": 0.5}}}
                  if kind == "edit" else {"kind": "note", "op": "add", "frame": i, "text": f"note {i}"})
            t0 = time.perf_counter()
            state[k][1] = s.apply(sid, ch, v, "bench").version
            return time.perf_counter() - t0

        for i in range(warm):
            for k in stores:
                write(k, i)
        for r in range(rounds):
            for k in stores:
                for j in range(per_round):
                    times[k].append(write(k, 1000 + r * per_round + j))
            notes.append(write("ours", r, "note"))
        doc_kb = len(stores["ours"].get(state["ours"][0])[0].to_json(indent=None)) / 1e3
        for s in stores.values():
            s.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    ours, ref = statistics.median(times["ours"]), statistics.median(times["ref"])
    print(f"BENCH store_edit_write ours_s={ours:.5f} ref_s={ref:.5f} ratio={ref / ours:.2f} p95_s={pctl(times['ours'], 0.95):.5f} "
          f"ref_p95_s={pctl(times['ref'], 0.95):.5f} ref_kind=journal_DELETE_sync_FULL "
          f"wal_normal_p50_s={statistics.median(times['wal_normal']):.5f} note_p50_s={statistics.median(notes):.5f} "
          f"writes={len(times['ours'])} doc_kb={doc_kb:.1f}", flush=True)


def main():
    bench_edit_write()


if __name__ == "__main__":
    main()
