"""How many cores this process may use right now: the one policy behind our own threads.

The solvers' and the dense transfer's second threads (:mod:`core.solvers.bounded_spacetime`'s
worker, the Taubin filter's column blocks, the detail stage's solves beside the next chunk, the
mesh-only work of :func:`core.transfer.transfer_sequence`) only help when a core is idle: on
the shared 2-core machine with two other busy processes the threaded Taubin and detail stages
ran 8-16 % slower than one thread (more CPU for the same work, and the pipeline waiting on a
starved worker), with a free core 25-45 % faster. Every such use is arithmetic-identical either
way (tested), so this decides speed only, never a number.

"Right now", not the 1-minute load average: that lags a minute behind a process that starts
or stops, and counts this process's own threads, so back-to-back runs that had used two
threads saw a load of ~2 and took one core on an idle machine (and a spacetime setting change,
a fraction of a second, switched its thread off every other minute).
"""

from __future__ import annotations

import os
import time

__all__ = ["affinity", "free_cores", "running_elsewhere"]

#: how long an answer of :func:`free_cores` is reused (s): a spacetime change asks at every
#: active-set step, and a look costs ~1 ms (a dense change is ~0.15 s: one look, not two)
MAX_AGE = 0.5

_SEEN = [float("-inf"), 1]  # (monotonic time of the last look, its answer)


def affinity() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def free_cores(max_age: float = MAX_AGE) -> int:
    """The cores of this process's affinity less the threads of other processes running now
    (:func:`running_elsewhere`; where ``/proc`` does not tell, the 1-minute load average less
    this process's own 1), at least 1. An answer younger than ``max_age`` seconds is reused."""
    now = time.monotonic()
    if now - _SEEN[0] < max_age:
        return _SEEN[1]
    n = affinity()
    busy = running_elsewhere()
    if busy is None:
        try:
            busy = max(0.0, os.getloadavg()[0] - 1.0)
        except OSError:  # no load average on this platform
            busy = 0.0
    free = max(1, min(n, int(n - busy + 0.5)))
    _SEEN[:] = [now, free]
    return free


def running_elsewhere(samples: int = 3) -> "int | None":
    """Threads of other processes running or waiting for a core (Linux: the running count of
    ``/proc/loadavg`` less this process's threads in state R), the largest of ``samples``
    readings 0.5 ms apart; None where ``/proc`` does not tell."""
    try:
        most = 0
        for i in range(samples):
            if i:
                time.sleep(0.0005)
            with open("/proc/loadavg") as f:
                running = int(f.read().split()[3].split("/")[0])
            own = 0
            for tid in os.listdir("/proc/self/task"):
                try:
                    with open(f"/proc/self/task/{tid}/stat") as f:
                        st = f.read()
                except OSError:  # the thread ended
                    continue
                own += st[st.rindex(")") + 2] == "R"
            most = max(most, running - own)
        return most
    except (OSError, ValueError, IndexError):
        return None
