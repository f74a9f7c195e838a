"""The one policy for our own threads (core.cores): how many cores other processes leave free."""

import os

import pytest

from core import cores


@pytest.fixture(autouse=True)
def fresh(monkeypatch):
    monkeypatch.setattr(cores, "_SEEN", [float("-inf"), 1])  # no answer to reuse


def test_free_cores_leave_out_what_other_processes_run_now(monkeypatch):
    """The threads use the cores that other processes leave free right now, never fewer than 1;
    the 1-minute load average only where /proc cannot tell."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    for elsewhere, want in ((0, 2), (1, 1), (2, 1), (5, 1)):
        monkeypatch.setattr(cores, "running_elsewhere", lambda samples=3, e=elsewhere: e)
        assert cores.free_cores(max_age=0) == want
    monkeypatch.setattr(cores, "running_elsewhere", lambda samples=3: None)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.2, 1.0, 1.0))  # this process's own 1 and a little
    assert cores.free_cores(max_age=0) == 2
    monkeypatch.setattr(os, "getloadavg", lambda: (2.4, 1.0, 1.0))
    assert cores.free_cores(max_age=0) == 1


def test_free_cores_reuses_a_young_answer(monkeypatch):
    """A spacetime change asks at every active-set step: within max_age the last answer stands."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    seen = []
    monkeypatch.setattr(cores, "running_elsewhere", lambda samples=3: seen.append(1) or 0)
    assert cores.free_cores(max_age=60) == 2
    monkeypatch.setattr(cores, "running_elsewhere", lambda samples=3: seen.append(1) or 5)
    assert cores.free_cores(max_age=60) == 2 and len(seen) == 1  # reused
    assert cores.free_cores(max_age=0) == 1 and len(seen) == 2  # looked again


@pytest.mark.skipif(not os.path.exists("/proc/loadavg"), reason="Linux /proc only")
def test_running_elsewhere_reads_proc():
    n = cores.running_elsewhere()
    assert isinstance(n, int) and n >= 0
