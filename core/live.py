"""Live retargeting: a Live Link Face stream retargeted packet by packet as it arrives.

The per-frame system is built once from a shot's pipeline (:class:`LiveRetargeter`): the
pipeline's own stages give the source rig and layout, the shared markers, the calibrated (and,
when asked, personalised) target marker blendshapes ``B`` (K, M, 3), the range-of-motion scale
and the per-shape controls. A packet's 61 values ``x`` then become source marker deltas through
the source rig, linearly::

    s = A x,      A (3M, 61) = the source rig's marker deltas of each channel (through the name
                  map, :func:`core.retarget.source_markers`), each marker's mapped by the
                  calibrate stage's motion map (:func:`live_alignment`: the 3×3 map per marker,
                  or the range-of-motion scale; linear, so folded into A once)

and target weights by the bounded per-frame solve of the ``bounded`` method (Seol et al. 2012,
§7 Range PF with the controls' per-shape bounds, active shapes, symmetry term and ridge)::

    w_t = argmin ||B w - s_t||^2 + rho ||w||^2 + sigma^2 w^T Q w   s.t.  lower <= w <= upper

With the default method ``auto`` (which solves the whole take at once offline) live does what
:func:`core.stages.methods.auto_choice` picks for the pair, in its per-packet form, with the
motion map auto's calibrate stage made (``matched``: fitted on the shot's take when it has a
recorded one; on the neutral placeholder take of a shot without one that fit has nothing to fit
and is the covariance map of the two rigs' shapes, which live then names):

* the target has the take's ARKit names: the per-frame solve with auto's ridge and its name prior
  ``c sigma^2 ||w_N - G_N x||^2`` (each named shape pulled towards its namesake channel, ``c`` =
  ``AUTO_NAMED["name_weight"]``), the other shapes held at zero as auto holds them;
* no shared names and a source rig (auto's shape map over the rigs' dense correspondence): no
  solve at all, each packet's source-rig weights mapped through the sparse shape map ``M`` the
  solve stage made (taken from its cached result, :func:`core.stages.methods._shape_mapped`)::

      w_t = clip(M G x_t, lower, upper)          (M G: one (K, 61) matrix, a few microseconds)

* otherwise the per-frame solve with auto's ridge, by geometry alone.

solved exactly by :class:`core.solvers.baselines.RangePFPrecompute` (the Hessian built once,
each frame warm-started from the previous one), then the causal One Euro filter
(:class:`core.controls.filters.OneEuro`, Casiez et al. 2012) when the shot's ``weights_filter``
is ``one_euro``, then the controls' gain and offset (as the pipeline's synthesize stage).

Streams (:class:`LiveStream`, one per subject name) are ordered by the packets' frame time:
a packet not later than the last one answered is a repeat (same time) or out of order (earlier)
and is counted and ignored (a causal retargeter cannot go back); a jump of more than one frame
step counts the frames between as dropped. A tracking-loss packet
(:attr:`core.io.livelink_udp.FacePacket.tracking_lost`) holds the last pose and is flagged.

:class:`LiveSession` routes datagrams to the streams and counts the bad ones;
:func:`listen` runs a session on a UDP socket and hands each answered frame to the outputs
(:class:`OscOut`: VRChat/VRCFaceTracking OSC, :class:`LiveLinkOut`: Live Link Face packets).
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from pythonosc import osc_bundle_builder, osc_message_builder

from .controls import default_table, merge_table, resolve
from .controls.filters import OneEuro
from .io.livelink import ROTATIONS, arkit_curves, write_livelink
from .io.livelink_udp import ARKIT_CHANNELS, CHANNELS, PacketError, decode, encode
from .model import Performance
from .retarget import drive_rig, source_markers
from .solvers.baselines import RangePFPrecompute
from .names import NameMap
from .motion_alignment import apply_alignment
from .stages.methods import _shape_mapped, auto_choice, method_of, shape_map_phrase
from .stages.retarget import auto_maps_shapes

__all__ = ["LiveRetargeter", "LiveStream", "LiveSession", "LiveFrame", "OscOut", "LiveLinkOut", "listen",
           "parse_address", "neutral_take"]

#: the frames a stream keeps for Record (10 minutes at 60 Hz)
RECORD_LIMIT = 36000


def parse_address(text: str, default_host: str = "127.0.0.1") -> tuple:
    """``"HOST:PORT"`` (or ``":PORT"``, ``"PORT"``) -> ``(host, port)``.

    Raises
    ------
    ValueError
        No port, or a port outside 0-65535.
    """
    host, _, port = str(text).rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"address {text!r}: expected HOST:PORT, e.g. 0.0.0.0:11111") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"address {text!r}: port {p} outside 0-65535")
    return (host or default_host), p


def neutral_take(path) -> Path:
    """Write a neutral Live Link Face CSV at ``path`` (64 frames: just over a second, so the
    reader can tell the timecode rate): the take a live shot without a recorded take runs its
    stages on (with a source rig the take only sets the frame range; the source's neutral is the
    rig's own)."""
    perf = Performance.curves(np.zeros((64, len(ARKIT_CHANNELS))), ARKIT_CHANNELS, 60.0, name="live")
    write_livelink(path, perf)
    return Path(path)


def live_alignment(calibrate, posed: bool = False) -> tuple:
    """``(map (M, 3, 3) or None, kind)``: the calibrate stage's motion map a live stream is
    aligned by, computed once before the stream. ``matched`` is fitted on a take: the shot's
    recorded take when it has one (its curves move), else (a neutral placeholder take, on which
    the refit has nothing to fit and returns its start) the covariance map of the two rigs'
    shapes, said as such; ``covariance``, ``rom`` (the scale as a diagonal map) and ``none`` as
    the stage ran them. ``posed``: auto with example poses solves on the covariance map
    (:func:`core.stages.methods.covariance_inputs`), and so does live."""
    mode = calibrate.get("alignment")
    if mode == "matched" and posed:
        return calibrate["covariance_map"], "covariance"
    if mode == "matched":
        W = calibrate["source"].source_weights
        if W is not None and np.nan_to_num(np.asarray(W)).any():
            return calibrate["source_map"], "matched"
        return calibrate["covariance_map"], "covariance"
    return calibrate.get("source_map"), (mode or "none")


def alignment_phrase(kind: str, take: str = "", frames=None, instead: str = "") -> str:
    """How a live stream's motion is matched to the character's (:func:`live_alignment`), in words;
    ``instead``: why the covariance map stands for the shot's matched one."""
    if kind == "matched":
        span = f", frames {frames['first']}–{frames['stop'] - 1}" if frames else ""
        return (f"the actor's motion space aligned to the character's by the 3×3 map per point fitted on the shot's "
                f"take ({take}{span})")
    if kind == "covariance":
        return ("the actor's motion space aligned to the character's (a 3×3 map per point from the two rigs' shapes"
                + (f"; {instead})" if instead else ")"))
    if kind == "rom":
        return "the actor's range of motion matched to the character's"
    return "the actor's motion as captured"


class LiveRetargeter:
    """The per-frame system of a shot, built once (module docstring).

    Parameters
    ----------
    pipeline : core.pipeline.Pipeline
        The shot (rigs, layouts, correspondence, calibration, personalisation, controls,
        ridge, bounds, One Euro settings). Its source must be weight curves on a source rig
        (any take: only the source rig's channels and the calibration are read).

    Attributes
    ----------
    channels : the 61 stream channels (:data:`core.io.livelink_udp.CHANNELS`)
    target_names : the target rig's shape names (the weights :meth:`solve` returns)
    source_names : the source rig's shape names (:meth:`source_weights`)
    choice : what it does per packet, one sentence in auto's style (the CLI prints it, the page shows it)
    A_ : (61, 3M) stream values -> source marker deltas (metres, motion-mapped)
    G_ : (61, K_source) stream values -> source rig weights
    motion_map_ : (M, 3, 3) or None, the calibrate stage's motion map folded into ``A_``
    alignment_ : "matched", "covariance", "rom" or "none": which map (:func:`live_alignment`)
    shape_map_ : (61, K_solver) or None, ``(M G)ᵀ`` when auto maps the curves through its shape map
    solver_ : RangePFPrecompute over the solver's shapes
    lo_, hi_ : (K_solver,) the controls' bounds
    shape_index_ : (K_solver,) int, the solver's shapes among the target's

    Raises
    ------
    ValueError
        No source rig (a live stream is ARKit weights: they need the rig they drive), or a
        dense (transfer) method.
    """

    def __init__(self, pipeline):
        cfg = pipeline.config()
        if method_of(cfg).dense:
            raise ValueError("live: the transfer method builds a new rig offline; choose a per-frame method "
                             "(--method bounded or auto)")
        # auto's shape map needs the rig pair's dense correspondence (decided from the files, as the solve stage does)
        maps = auto_maps_shapes(cfg)
        res = pipeline.results(["load", "frames", "correspond", "shapes", "calibrate", "personalize", "vocabulary"]
                               + (["dense_correspondence"] if maps else []))
        ld, cor, sh, cal = res["load"], res["correspond"], res["shapes"], res["calibrate"]
        rig = ld["source_rig"]
        if rig is None or cor["source_layout"] is None:
            raise ValueError("live: the Live Link Face stream is ARKit weights; give the rig they drive "
                             "(--source-rig, e.g. data/rigs/ict_facekit.glb)")
        C = len(CHANNELS)
        # each channel alone at 1 (and the neutral): the source rig's markers of each, by the
        # same function the pipeline's stabilize stage uses
        probe = Performance.curves(np.vstack([np.zeros(C), np.eye(C)]), CHANNELS, 60.0, name="live")
        sm = source_markers(probe, rig, cor["source_layout"], ld["name_map"])
        idx = [sm.names.index(n) for n in sh["names"]]
        D = sm.deltas[:, idx]  # (1 + C, M, 3)
        D = D[1:] - D[:1]
        # the calibrate stage's motion map, per marker (linear: folded into A once)
        # under example poses auto solves on the covariance map unless its base is the shape map
        posed = method_of(cfg).chooses and bool(cfg.solve.example_poses) and not maps
        self.motion_map_, self.alignment_ = live_alignment(cal, posed)
        if self.motion_map_ is not None:
            D = apply_alignment(self.motion_map_, D)
        B = np.asarray(res["personalize"]["deltas"], dtype=np.float64)
        w = sh.get("weights")
        if w is not None:  # dense correspondence: each point's rows weighted (as methods.weighted_markers)
            r = np.sqrt(w)[:, None]
            B, D = B * r[None], D * r[None]
        self.A_ = D.reshape(C, -1)
        Wsrc, _ = drive_rig(probe, rig, ld["name_map"])
        self.G_ = np.nan_to_num(Wsrc[1:] - Wsrc[:1])
        s = cfg.solve
        names = list(sh["rig"].names)
        ctl = resolve(merge_table(s.controls or {}, default_table(names, s.lower, s.upper)), names)
        lo, hi = ctl.bounds()
        K = len(names)
        Q = ctl.symmetry_matrix(s.symmetry_weight) if s.symmetry_weight > 0 and len(ctl.symmetry) else np.zeros((K, K))
        zero = ctl.zero() if (~ctl.active).any() else None
        ridge, self.pull_, self.shape_map_ = s.ridge, None, None
        instead = "" if cal["alignment"] == self.alignment_ else (
            "auto's base under example poses" if posed else "no recorded take to fit the take's map on")
        aligned = alignment_phrase(self.alignment_, ld["source"].name, res["frames"], instead)
        self.choice = f"{cfg.solve.method}: frame by frame within the bounds, {aligned}, by geometry alone"
        if method_of(cfg).chooses:  # auto: what it would choose for this pair, per packet
            run, chosen, sentence = auto_choice(res, zero)
            why = sentence.rpartition(" — ")[2]
            ridge = chosen["ridge"]
            if run is _shape_mapped:
                # the map the solve stage made (cached by the pipeline, content-keyed); none when a
                # negative lower bound sent it to the per-frame solve
                info = pipeline.results(["solve"])["solve"]["info"]
                if info.get("shape_map") is not None:
                    self.shape_map_ = self.G_ @ np.asarray(info["shape_map"], dtype=np.float64).T  # (61, K): M (G x)
                    self.choice = (f"auto, live: each packet's curves {shape_map_phrase(info['dense_points'], info.get('gaze', False))}, "
                                   f"no per-frame solve — {why}")
            if "name_weight" in chosen:
                # each shape pulled towards its namesake channel, c sigma^2 ||w_N - G_N x||^2
                # (auto's name prior, per frame), the other shapes held at zero as auto holds them
                G = NameMap.automatic(CHANNELS, names, vocabularies=res["vocabulary"]["vocabularies"]).matrix(
                    CHANNELS, names)  # (K, 61)
                N = np.abs(G).sum(1) > 0
                c = chosen["name_weight"]
                Q = Q + c * np.diag(N.astype(float))
                self.pull_ = (c, np.where(N[:, None], G, 0.0).T)  # (61, K)
                zero = chosen["zero"]
                self.choice = (f"auto, live: frame by frame within the bounds, {aligned}, each shape pulled towards its "
                               f"namesake channel ({int(N.sum())} of {K} shapes), the others at zero")
            elif self.shape_map_ is None:
                self.choice = f"auto, live: frame by frame within the bounds, {aligned}, by geometry alone — {why}"
        if posed:
            self.choice += "; the shot's example poses are learned over a whole take (offline auto), not per packet"
        self.ridge_, self.quadratic_ = ridge, (Q if Q.any() else None)
        self.solver_ = RangePFPrecompute(B, lo, hi, ridge=ridge, quadratic=self.quadratic_, zero=zero)
        self.lo_, self.hi_ = self.solver_.lo_, self.solver_.hi_
        if self.pull_ is not None:
            self.pull_ = self.pull_[1] * (self.pull_[0] * self.solver_.smax2_)
        self.controls_ = ctl
        self.remap_ = bool((ctl.gain != 1).any() or (ctl.offset != 0).any())
        self.shape_index_ = np.asarray(sh["shape_index"])
        self.channels = CHANNELS
        self.target_names = tuple(ld["target_rig"].names)
        self.source_names = tuple(rig.names)
        self.filter_ = (s.filter_min_cutoff, s.filter_beta) if s.weights_filter == "one_euro" else None
        self.neutral_ = np.zeros(len(self.target_names))
        self.neutral_[self.shape_index_] = self.solve(np.zeros(C))[0] if self.shape_map_ is not None else self.solver_.held_

    def markers(self, values) -> np.ndarray:
        """(M, 3) source marker deltas of one packet's 61 values (``s = A x``)."""
        return (np.asarray(values, dtype=np.float64) @ self.A_).reshape(-1, 3)

    def source_weights(self, values) -> np.ndarray:
        """(K_source,) the source rig's weights the packet drives (for showing the actor)."""
        return np.asarray(values, dtype=np.float64) @ self.G_

    def solve(self, values, warm=None) -> tuple:
        """The bounded solve of one frame: ``(w (K_solver,), u)``, ``u`` to pass as the next
        frame's ``warm`` (:meth:`core.solvers.baselines.RangePFPrecompute.solve`)."""
        x = np.asarray(values, dtype=np.float64)
        if self.shape_map_ is not None:  # auto's shape map: clip(M w_source, lower, upper), no solve
            return np.clip(x @ self.shape_map_, self.lo_, self.hi_), warm
        W, u = self.solver_.solve(self.markers(x), warm=warm, linear=None if self.pull_ is None else x @ self.pull_)
        return W[0], u

    def full(self, w_solver) -> np.ndarray:
        """(K_target,) weights for every target shape: the solver's after the controls' gain
        and offset (clamped), the others 0 (as the pipeline's synthesize stage)."""
        w = self.controls_.remap(w_solver[None])[0] if self.remap_ else w_solver
        out = np.zeros(len(self.target_names))
        out[self.shape_index_] = w
        return out

    def stream(self, subject: str = "") -> "LiveStream":
        return LiveStream(self, subject)


@dataclass
class LiveFrame:
    """One answered packet: ``weights`` (K_target,) of the target, ``values`` (61,) received
    (None on tracking loss), ``held`` True when the pose is the last one held (tracking loss)."""

    subject: str
    frame: int
    time: float
    weights: np.ndarray
    values: Optional[np.ndarray]
    held: bool
    arrival: float = 0.0


@dataclass
class StreamCounts:
    answered: int = 0
    repeated: int = 0
    out_of_order: int = 0
    dropped: int = 0
    tracking_lost: int = 0


class LiveStream:
    """One subject's stream: causal, ordered by frame time (module docstring)."""

    def __init__(self, retargeter: LiveRetargeter, subject: str = ""):
        self.rt = retargeter
        self.subject = subject
        self.counts = StreamCounts()
        self.last_time = None
        self.step = None  # smallest positive frame-time step seen (s)
        self.warm = None
        self.euro = None
        self.weights = retargeter.neutral_.copy()
        self.values = None
        self.recorded = []  # (time, values or None)
        self.recording = False

    def update(self, packet, arrival: float = 0.0) -> Optional[LiveFrame]:
        """The frame of ``packet`` (a :class:`~core.io.livelink_udp.FacePacket` of this
        subject), or None when it is a repeat or out of order (counted)."""
        t = packet.time
        c = self.counts
        if self.last_time is not None:
            dt = t - self.last_time
            if dt <= 0:
                if dt == 0:
                    c.repeated += 1
                else:
                    c.out_of_order += 1
                return None
            if self.step is None or dt < 0.75 * self.step:
                self.step = dt
            else:
                c.dropped += max(0, int(round(dt / self.step)) - 1)
        self.last_time = t
        if self.recording and len(self.recorded) < RECORD_LIMIT:
            self.recorded.append((t, None if packet.tracking_lost else packet.values))
        if packet.tracking_lost:
            c.tracking_lost += 1
            c.answered += 1
            return LiveFrame(self.subject, packet.frame, t, self.weights, None, True, arrival)
        w, self.warm = self.rt.solve(packet.values, self.warm)
        if self.rt.filter_ is not None:
            if self.euro is None:
                self.euro = OneEuro(packet.fps or 60.0, *self.rt.filter_)
            w = self.euro.step(w)
        self.weights = self.rt.full(w)
        self.values = packet.values
        c.answered += 1
        return LiveFrame(self.subject, packet.frame, t, self.weights, packet.values, False, arrival)

    def take(self, fps: Optional[float] = None) -> Performance:
        """What was recorded as a Live Link Face take (curves of the 52 ARKit channels, the
        rotations in ``extras``, tracking loss as invalid frames), times from 0.

        Raises
        ------
        ValueError
            Nothing recorded.
        """
        if not self.recorded:
            raise ValueError(f"subject {self.subject!r}: nothing recorded (press Record while the stream comes)")
        times = np.array([t for t, _ in self.recorded])
        vals = np.array([np.full(len(CHANNELS), np.nan) if v is None else v for _, v in self.recorded], dtype=np.float64)
        fps = fps or (1.0 / self.step if self.step else 60.0)
        extras, at = {}, len(ARKIT_CHANNELS)
        for key, cols in ROTATIONS.items():
            extras[key] = vals[:, at:at + len(cols)]
            at += len(cols)
        return Performance.curves(vals[:, :len(ARKIT_CHANNELS)], ARKIT_CHANNELS, fps, times=times - times[0],
                                  name=self.subject or "live", extras=extras)


class LiveSession:
    """Datagrams in, frames out: decodes, counts the bad ones by reason, routes each packet to
    its subject's :class:`LiveStream`. Thread-safe (:meth:`stats` from another thread)."""

    def __init__(self, retargeter: LiveRetargeter, record: bool = False):
        self.rt = retargeter
        self.streams: dict = {}
        self.bad: dict = {}
        self.received = 0
        self.record = record
        self.lock = threading.Lock()
        self.started = time.monotonic()

    def receive(self, data: bytes, arrival: Optional[float] = None) -> Optional[LiveFrame]:
        """The frame of one datagram, or None (bad, repeated or out of order: counted)."""
        arrival = time.perf_counter() if arrival is None else arrival
        with self.lock:
            self.received += 1
            try:
                packet = decode(data)
            except PacketError as e:
                self.bad[e.reason] = self.bad.get(e.reason, 0) + 1
                return None
            st = self.streams.get(packet.subject)
            if st is None:
                st = self.streams[packet.subject] = self.rt.stream(packet.subject)
                st.recording = self.record
            return st.update(packet, arrival)

    def set_recording(self, on: bool) -> None:
        """Start (clearing what was kept) or stop recording every stream."""
        with self.lock:
            self.record = on
            for st in self.streams.values():
                if on:
                    st.recorded = []
                st.recording = on

    def stats(self) -> dict:
        """Counts: ``received``, ``bad`` {reason: n}, and per subject ``answered``, ``dropped``,
        ``repeated``, ``out_of_order``, ``tracking_lost``, ``recorded``."""
        with self.lock:
            return {"received": self.received, "bad": dict(self.bad),
                    "subjects": {k: {**vars(st.counts), "recorded": len(st.recorded)} for k, st in self.streams.items()}}


class OscOut:
    """Each frame's target weights as one OSC bundle of ``/avatar/parameters/<shape>`` floats
    (the VRChat / VRCFaceTracking convention), over UDP with python-osc.

    The bundle is built once by python-osc (timetag "immediately", one float message per
    shape): every frame's bundle has the same bytes but for the floats, so a frame only writes
    its K big-endian floats at their offsets (python-osc's builder takes ~3 ms a frame for 175
    shapes; this 20 us)."""

    def __init__(self, host: str, port: int, names, prefix: str = "/avatar/parameters/"):
        self.address = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addresses = [prefix + str(n) for n in names]
        b = osc_bundle_builder.OscBundleBuilder(osc_bundle_builder.IMMEDIATELY)
        for a in self.addresses:
            m = osc_message_builder.OscMessageBuilder(address=a)
            m.add_arg(0.0, "f")
            b.add_content(m.build())
        self.template = bytearray(b.build().dgram)
        # a message's float is its last 4 bytes; each element is int32 size + message
        ends, at = [], 16  # "#bundle\0" + 8-byte timetag
        for _ in self.addresses:
            (n,) = struct.unpack_from(">i", self.template, at)
            at += 4 + n
            ends.append(at)
        self.offsets = np.asarray(ends) - 4

    def bundle(self, weights) -> bytes:
        """The OSC bundle of one frame's weights (K,)."""
        buf = np.frombuffer(bytes(self.template), dtype=np.uint8).copy()
        vals = np.asarray(weights, dtype=">f4").view(np.uint8).reshape(-1, 4)
        buf[self.offsets[:, None] + np.arange(4)[None]] = vals
        return buf.tobytes()

    def send(self, frame: LiveFrame) -> None:
        self.sock.sendto(self.bundle(frame.weights), self.address)

    def close(self) -> None:
        self.sock.close()


class LiveLinkOut:
    """The target's ARKit-named shapes re-sent as Live Link Face packets (an Unreal or Blender
    Live Link receiver drives the character from them); ARKit channels the target lacks are 0."""

    def __init__(self, host: str, port: int, names, subject_suffix: str = ""):
        # (K, 52): each shape's ARKit channel weights, by the automatic name map of arkit_curves
        perf, _ = arkit_curves(np.eye(len(names)), names, 60.0)
        self.G = perf.data
        self.arkit = [str(n) for n in perf.names]
        self.suffix = subject_suffix
        self.address = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def packet(self, frame: LiveFrame) -> bytes:
        values = dict(zip(self.arkit, (frame.weights @ self.G).tolist()))
        if frame.values is not None:  # the head and eyes as they came
            values.update(zip(CHANNELS[len(ARKIT_CHANNELS):], frame.values[len(ARKIT_CHANNELS):].tolist()))
        return encode((frame.subject or "face-retarget") + self.suffix, frame.frame, values)

    def send(self, frame: LiveFrame) -> None:
        self.sock.sendto(self.packet(frame), self.address)

    def close(self) -> None:
        self.sock.close()


def listen(session: LiveSession, host: str, port: int, outputs=(), stop: Optional[threading.Event] = None,
           on_frame: Optional[Callable] = None, ready: Optional[Callable] = None, timeout: float = 0.1) -> tuple:
    """Receive datagrams on ``host:port`` until ``stop`` is set; each answered frame goes to
    every output's ``send`` and then to ``on_frame(frame, latency_s)`` (latency: the kernel's
    arrival time of the datagram, where the platform gives it (Linux ``SO_TIMESTAMPNS``), to
    the outputs sent; so time spent queued behind other packets counts). ``ready(host, port)``
    is called once bound (port 0: the port chosen).

    Returns the bound ``(host, port)``.
    """
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    stamped = hasattr(socket, "SO_TIMESTAMPNS")
    if stamped:  # the kernel's arrival time: the wait in the socket's queue counts in the latency
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_TIMESTAMPNS, 1)
    sock.bind((host, port))
    sock.settimeout(timeout)
    bound = sock.getsockname()[:2]
    stop = stop or threading.Event()
    try:
        if ready is not None:
            ready(*bound)
        while not stop.is_set():
            try:
                data, anc, _, _ = sock.recvmsg(65536, socket.CMSG_SPACE(16) if stamped else 0)
            except socket.timeout:
                continue
            arrival = time.perf_counter()
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == socket.SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, ns = struct.unpack("qq", raw[:16])
                    arrival -= max(0.0, time.time() - (sec + 1e-9 * ns))
            frame = session.receive(data, arrival)
            if frame is None:
                continue
            for out in outputs:
                out.send(frame)
            if on_frame is not None:
                on_frame(frame, time.perf_counter() - arrival)
    finally:
        sock.close()
    return bound
