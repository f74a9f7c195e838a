"""Live retargeting (``face-retarget live``, core/live.py): latency and load on real sockets.

* ``live_latency``: the S07 take (ICT driven by Live Link Face curves -> Rocketbox, 165 solver
  shapes, the default method ``auto``: per frame, bounded, pulled towards the namesake
  channels) sent as Live Link Face packets at 60 Hz to a listener on 127.0.0.1 that answers
  every packet with an OSC bundle to a receiver socket. ``ours_s`` = p95 of packet arrival (the
  kernel's timestamp: time queued counts) -> OSC bundle sent (wall clock); ``ref_s`` = p95 of the same frames' solve done naively (the
  per-frame system rebuilt and solved cold for each frame: no precomputed Hessian, no warm
  start), measured in the same run. ``cpu_p95_ms``: the retargeting's own thread CPU time,
  which the machine's load (``load1``) does not inflate.
* ``live_three_streams``: three subjects at 60 Hz each (180 packets/s) to one listener;
  ``dropped`` = packets not answered + frames the streams counted as missing; ``ref_s`` = the
  one-stream p95 above.
* ``live_shape_map``: the same take to Rocketbox with every shape renamed (no shared names: live
  maps each packet through auto's shape map, ``clip(M G x, lo, hi)``, no solve), one stream at
  60 Hz on sockets; ``ours_s`` = p95 wall latency as above, ``cpu_p95_ms`` its thread CPU time;
  ``ref_s`` = p95 wall latency of the per-frame bounded solve on the same renamed rig (what live
  ran there before it took auto's map; covariance map, ridge 1e-2), streamed in the same run.
  The first run on a machine pays the rig pair's registration (then cached on disk).
"""

import os
import socket
import sys
import threading
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core.io.livelink import read_livelink  # noqa: E402
from core.io.livelink_udp import ARKIT_CHANNELS, encode  # noqa: E402
from core.live import LiveRetargeter, LiveSession, OscOut, listen  # noqa: E402
from core.pipeline import Pipeline, StageCache  # noqa: E402
from core.solvers.baselines import RangePFPrecompute  # noqa: E402

TAKE = ROOT / "data/performances/livelinkface_take_s07.csv"
FILES = dict(source=str(TAKE), source_rig=str(ROOT / "data/rigs/ict_facekit.glb"),
             target_rig=str(ROOT / "data/rigs/rocketbox_female_adult_02.glb"))


def stream_values(perf):
    col = {c.lower(): i for i, c in enumerate(perf.names)}
    arkit = np.column_stack([perf.data[:, col[c.lower()]] for c in ARKIT_CHANNELS])
    rot = np.hstack([perf.extras[k] for k in ("head_rotation", "eye_rotation_left", "eye_rotation_right")])
    return np.nan_to_num(np.hstack([arkit, rot]))


def run_stream(rt, X, subjects, rate=60.0):
    """Replay ``X`` at ``rate`` Hz per subject to a listener; returns (latencies s, cpu s, session, OSC bundles got)."""
    session = LiveSession(rt)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 23)
    rx.settimeout(0.2)
    osc = OscOut("127.0.0.1", rx.getsockname()[1], rt.target_names)
    lat, cpu, got = [], [], [0]
    stop, bound = threading.Event(), []
    ready = threading.Event()

    def on_frame(frame, latency):
        lat.append(latency)

    orig = session.receive  # timed: the CPU time of decode + solve per packet

    def receive(data, arrival=None):
        c = time.thread_time()
        out = orig(data, arrival)
        cpu.append(time.thread_time() - c)
        return out

    session.receive = receive

    def serve():
        listen(session, "127.0.0.1", 0, [osc], stop, on_frame, lambda h, p: (bound.append(p), ready.set()))

    def drain():
        while not stop.is_set():
            try:
                rx.recv(65536)
                got[0] += 1
            except socket.timeout:
                pass

    th, dr = threading.Thread(target=serve), threading.Thread(target=drain)
    th.start()
    dr.start()
    ready.wait(10)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start = time.perf_counter()
    for i in range(len(X)):
        for k, s in enumerate(subjects):
            at = start + (i + k / len(subjects)) / rate
            while time.perf_counter() < at:
                time.sleep(0.0003)
            tx.sendto(encode(s, i, X[i]), ("127.0.0.1", bound[0]))
    t_end = time.perf_counter() + 10.0  # let the listener answer what is queued (it counts in the latency)
    while session.received < len(X) * len(subjects) and time.perf_counter() < t_end:
        time.sleep(0.05)
    time.sleep(0.3)
    stop.set()
    th.join()
    dr.join()
    tx.close()
    rx.close()
    osc.close()
    return np.array(lat), np.array(cpu), session, got[0]


def naive(rt, X):
    """Per frame: the system rebuilt and solved cold (no precompute, no warm start)."""
    pre = rt.solver_
    ts = []
    for x in X:
        t0 = time.perf_counter()
        lo, hi = pre.lo_, pre.hi_
        Bk = pre.B_.T.reshape(len(lo), -1, 3)
        fresh = RangePFPrecompute(Bk, lo, hi, ridge=rt.ridge_, quadratic=rt.quadratic_, zero=pre.zero_)
        fresh.solve(rt.markers(x), linear=None if rt.pull_ is None else x @ rt.pull_)
        ts.append(time.perf_counter() - t0)
    return np.array(ts)


def main(n_frames=1200, n_ref=60, n_three=600):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rt = LiveRetargeter(Pipeline(cache=StageCache(), **FILES))
    X = stream_values(read_livelink(TAKE))[:n_frames]
    load1 = os.getloadavg()[0]
    lat, cpu, sess, got = run_stream(rt, X, ["iPhone"])
    ref = naive(rt, X[np.linspace(0, len(X) - 1, n_ref).astype(int)])
    p95, ref95 = np.percentile(lat, 95), np.percentile(ref, 95)
    answered = sess.stats()["subjects"]["iPhone"]["answered"]
    print(f"BENCH live_latency ours_s={p95:.5f} ref_s={ref95:.5f} ratio={ref95 / p95:.1f} p95_ms={1e3 * p95:.2f} "
          f"p50_ms={1e3 * np.median(lat):.2f} cpu_p95_ms={1e3 * np.percentile(cpu, 95):.2f} "
          f"answered={answered}/{len(X)} osc_got={got} ref_kind=naive_cold_rebuilt_{n_ref}frames load1={load1:.1f} "
          f"solve={rt.choice.split(':')[0].replace(' ', '_').replace(',', '')}", flush=True)
    subjects = ["iPhone-A", "iPhone-B", "iPhone-C"]
    load1 = os.getloadavg()[0]
    lat3, cpu3, sess3, got3 = run_stream(rt, X[:n_three], subjects)
    st = sess3.stats()["subjects"]
    answered = sum(st[s]["answered"] for s in subjects)
    dropped = 3 * n_three - answered + sum(st[s]["dropped"] for s in subjects)
    p95_3 = np.percentile(lat3, 95)
    print(f"BENCH live_three_streams ours_s={p95_3:.5f} ref_s={p95:.5f} ratio={p95 / p95_3:.2f} p95_ms={1e3 * p95_3:.2f} "
          f"cpu_p95_ms={1e3 * np.percentile(cpu3, 95):.2f} dropped={dropped} answered={answered}/{3 * n_three} "
          f"osc_got={got3} ref_kind=one_stream_p95 load1={load1:.1f}", flush=True)
    shape_map(X[:n_three])


def shape_map(X):
    import tempfile

    from core.io.rigs import write_renamed_rig

    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hidden = str(write_renamed_rig(FILES["target_rig"], Path(tmp) / "rocketbox_hidden.glb"))
        files = {**FILES, "target_rig": hidden}
        rt = LiveRetargeter(Pipeline(cache=StageCache(), **files))
        ref_rt = LiveRetargeter(Pipeline(cache=StageCache(), method="bounded", motion_scale="covariance", ridge=1e-2,
                                         **files))
    assert rt.shape_map_ is not None, rt.choice
    load1 = os.getloadavg()[0]
    lat, cpu, sess, got = run_stream(rt, X, ["iPhone"])
    ref_lat, ref_cpu, _, _ = run_stream(ref_rt, X, ["iPhone"])
    p95, ref95 = np.percentile(lat, 95), np.percentile(ref_lat, 95)
    answered = sess.stats()["subjects"]["iPhone"]["answered"]
    print(f"BENCH live_shape_map ours_s={p95:.5f} ref_s={ref95:.5f} ratio={ref95 / p95:.1f} p95_ms={1e3 * p95:.2f} "
          f"p50_ms={1e3 * np.median(lat):.2f} cpu_p95_ms={1e3 * np.percentile(cpu, 95):.3f} "
          f"ref_cpu_p95_ms={1e3 * np.percentile(ref_cpu, 95):.3f} answered={answered}/{len(X)} osc_got={got} "
          f"ref_kind=bounded_per_frame_same_rig load1={load1:.1f} shapes={len(rt.lo_)}", flush=True)


if __name__ == "__main__":
    main()
