"""A writer process for tests/test_store.py: a burst of changes, each acknowledged after its commit.

    python tests/store_writer.py DATA_DIR SHOT_ID LABEL COUNT [wait]

Each of COUNT iterations adds a spacetime edit and then a note through :meth:`core.store.Store.apply`,
based on the version this process last saw (stale when another writer is at work: rebased), and
prints ``ACK <label> <i> edit <version>`` / ``ACK <label> <i> note <version> <note_id>`` only after
``apply`` returned (committed). With ``wait`` it prints ``READY`` and starts when a line arrives
on stdin (so two writers really overlap). Exits after COUNT iterations (or when stdin closes
before the start), so it always stops by itself.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.store import Store  # noqa: E402


def main(data, shot_id, label, count, wait=False):
    store = Store(data)
    _, version = store.get(shot_id)  # read before the start: two waiting writers begin from the same version
    print(f"READY {label}", flush=True)
    if wait and not sys.stdin.readline():
        return
    for i in range(count):
        edit = {"frame": i, "weights": {"jawOpen": 0.5}, "writer": label, "i": i}
        version = store.apply(shot_id, {"kind": "edit", "editor": "spacetime", "op": "add", "edit": edit}, version, label).version
        print(f"ACK {label} {i} edit {version}", flush=True)
        a = store.apply(shot_id, {"kind": "note", "op": "add", "frame": i, "text": f"{label} {i}"}, version, label)
        version = a.version
        print(f"ACK {label} {i} note {version} {a.change['note_id']}", flush=True)
    store.close()
    print(f"DONE {label}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), wait=sys.argv[5:] == ["wait"])
