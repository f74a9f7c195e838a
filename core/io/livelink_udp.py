"""Live Link Face UDP packets: what Epic's iPhone app streams to a Live Link target.

The packet (version 6, big-endian, as the app has sent it since Unreal 4.26; no length prefix,
one packet per UDP datagram)::

    uint8    version              6
    int32    device id length     n       then n bytes of UTF-8 (the app's device UUID)
    int32    subject name length  m       then m bytes of UTF-8 (the subject's name, e.g. "iPhone")
    int32    frame number                 FQualifiedFrameTime: the frame (timecode frames)
    float32  subframe                     the fraction of a frame
    int32    rate numerator               e.g. 60
    int32    rate denominator             e.g. 1
    uint8    blend shape count    61      (absent in a frame without a face: see below)
    float32  x 61                         52 ARKit shapes in EARFaceBlendShape order, then head
                                          yaw, pitch, roll and left/right eye yaw, pitch, roll

A packet of the app is therefore 1 + 4 + n + 4 + m + 16 + 1 + 244 bytes: 319 for a 36-character
device UUID and the subject ``Ahmeds_iPhone``, as in a netcat capture of the app's stream
(aelzeiny/Animoji, ``experimentation/livelink.udp``, 567 datagrams: 560 of 319 bytes and 7 of
74). The frame number is the timecode's frame of the day at the rate (1,095,835: 05:04:24 at
60 fps) and the subframe is not 0 (0.345, 0.347, ...: the capture clock's phase
within the timecode frame).

The time of a packet is ``(frame + subframe) * denominator / numerator`` seconds. Sources read
(docs/live.md lists them with their addresses): Epic's receiver and sender in
``AppleARKitLiveLinkSource.cpp`` of the Unreal plugin AppleARKitFaceSupport (versions 1-5 of the
packet, the version history in its comments, and the receiver's rule that a packet whose count
is not 61 is dropped); the version-6 readers and writers ``FaceFrame`` of think-biq's
``llv.py`` and JimWest/PyLiveLinkFace (both: uint8 version, two int32-prefixed strings, the
16-byte frame time, uint8 count, big-endian floats).

The channel order of the packet is Unreal's ``EARFaceBlendShape`` enum (``JawLeft`` before
``JawRight``, ``MouthLeft`` before ``MouthRight``), *not* the order of the app's CSV header
(:data:`core.io.livelink.LIVELINK_CHANNELS`); channels are therefore always handled by name.

Tracking loss: the app sends a frame without a face as the header and the frame time alone, no
count byte and no values (the 74-byte datagrams of the capture above, 7 frames in a row in the
middle of the stream, their frame times continuing the others'; Unreal's receiver drops them as
shorter than its minimum packet size, VRCFaceTracking's LiveLink module as shorter than 244
bytes). In its CSV takes the app marks such a frame by a blend-shape count of 0 and no values
(:mod:`core.io.livelink`); a packet with count 0 is read the same way, and so is a packet whose
52 ARKit values are all exactly 0 (what a sender that zero-fills a lost face sends; a tracked
face never gives 52 exact zeros). All three are :attr:`FacePacket.tracking_lost`; :func:`encode`
writes the app's form.

Anything else — a datagram that ends inside a field, another version, a count other than 0 or
61, string lengths that run past the end, non-UTF-8 names, bytes left over — raises
:class:`PacketError` with the reason (``truncated``, ``version``, ``count``, ``garbage``); a
receiver counts and skips them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Optional

import numpy as np

from core.io.livelink import ROTATION_COLUMNS

__all__ = ["VERSION", "CHANNELS", "ARKIT_CHANNELS", "FacePacket", "PacketError", "decode", "encode"]

#: The packet version this reads and writes.
VERSION = 6
#: The 52 ARKit shapes in the packet's order (Unreal's EARFaceBlendShape enum).
ARKIT_CHANNELS = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawLeft", "JawRight", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthLeft", "MouthRight", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
#: All 61 values of a packet, in order: the ARKit shapes, then the head and eye rotations.
CHANNELS = ARKIT_CHANNELS + ROTATION_COLUMNS
N_VALUES = len(CHANNELS)  # 61

_FRAME_TIME = struct.Struct(">ifii")
_VALUES = struct.Struct(f">{N_VALUES}f")
_INT = struct.Struct(">i")


class PacketError(ValueError):
    """A datagram that is not a Live Link Face packet; ``reason`` is ``truncated``, ``version``,
    ``count`` or ``garbage``."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason


@dataclass(frozen=True)
class FacePacket:
    """One decoded packet.

    Attributes
    ----------
    subject : str
        The subject name (one stream per subject).
    device_id : str
    frame : int
        Frame number at ``rate``.
    subframe : float
        Fraction of a frame, in [0, 1).
    rate : (int, int)
        Frame rate numerator and denominator.
    values : (61,) float32 or None
        :data:`CHANNELS`' values; None when the packet carried none (count 0).
    """

    subject: str
    device_id: str
    frame: int
    subframe: float
    rate: tuple
    values: Optional[np.ndarray]

    @property
    def time(self) -> float:
        """Seconds: ``(frame + subframe) * denominator / numerator`` (0 rate: the frame number)."""
        num, den = self.rate
        return (self.frame + self.subframe) * den / num if num > 0 and den > 0 else float(self.frame + self.subframe)

    @property
    def fps(self) -> float:
        num, den = self.rate
        return num / den if num > 0 and den > 0 else 0.0

    @property
    def tracking_lost(self) -> bool:
        """No face in this frame: no values, or all 52 ARKit values exactly 0 (module docstring)."""
        return self.values is None or not np.any(self.values[:len(ARKIT_CHANNELS)])

    @property
    def arkit(self) -> dict:
        """``{ARKit channel: value}`` (empty without values)."""
        return {} if self.values is None else dict(zip(CHANNELS, self.values.tolist()))


def _string(data: bytes, at: int, what: str) -> tuple:
    if at + 4 > len(data):
        raise PacketError("truncated", f"{len(data)} bytes end before the {what}'s length")
    (n,) = _INT.unpack_from(data, at)
    at += 4
    if n < 0 or n > 1024:
        raise PacketError("garbage", f"{what} length {n}")
    if at + n > len(data):
        raise PacketError("truncated", f"{what} of {n} bytes runs past the end ({len(data)} bytes)")
    try:
        return data[at:at + n].decode("utf-8"), at + n
    except UnicodeDecodeError:
        raise PacketError("garbage", f"{what} is not UTF-8") from None


def decode(data: bytes) -> FacePacket:
    """The :class:`FacePacket` of one datagram (layout: module docstring).

    Raises
    ------
    PacketError
        ``truncated`` (ends inside a field; ending right after the frame time is the app's
        frame without a face), ``version`` (not 6), ``count`` (neither 0 nor 61),
        ``garbage`` (impossible string length, non-UTF-8 names, bytes left over, non-finite values).
    """
    data = bytes(data)
    if not data:
        raise PacketError("truncated", "empty datagram")
    if data[0] != VERSION:
        raise PacketError("version", f"packet version {data[0]}, this reads version {VERSION}")
    device, at = _string(data, 1, "device id")
    subject, at = _string(data, at, "subject name")
    if at + _FRAME_TIME.size > len(data):
        raise PacketError("truncated", f"{len(data)} bytes end inside the frame time")
    frame, subframe, num, den = _FRAME_TIME.unpack_from(data, at)
    at += _FRAME_TIME.size
    count = data[at] if at < len(data) else 0  # the app's frame without a face ends here
    at = min(at + 1, len(data))
    if count == 0:
        values = None
    elif count == N_VALUES:
        if at + _VALUES.size > len(data):
            raise PacketError("truncated", f"{len(data)} bytes end inside the {N_VALUES} values")
        values = np.array(_VALUES.unpack_from(data, at), dtype=np.float32)
        at += _VALUES.size
        if not np.isfinite(values).all():
            raise PacketError("garbage", "non-finite values")
    else:
        raise PacketError("count", f"{count} values, expected {N_VALUES} (or 0: tracking lost)")
    if at != len(data):
        raise PacketError("garbage", f"{len(data) - at} bytes after the packet")
    if not np.isfinite(subframe):
        raise PacketError("garbage", "non-finite subframe")
    return FacePacket(subject, device, int(frame), float(subframe), (int(num), int(den)), values)


def encode(subject: str, frame: int, values=None, subframe: float = 0.0, rate=(60, 1),
           device_id: str = "face-retarget") -> bytes:
    """One version-6 packet: ``values`` (61,) in :data:`CHANNELS` order, a ``{channel: value}``
    dict (missing channels 0; names in any case, CSV or ARKit spelling), or None for a
    tracking-loss packet as the app sends it (header and frame time, no count, no values).

    Raises
    ------
    ValueError
        ``values`` of the wrong length, or a dict with a name that is not a channel.
    """
    if isinstance(values, dict):
        key = {c.lower(): i for i, c in enumerate(CHANNELS)}
        arr = np.zeros(N_VALUES, dtype=np.float32)
        for name, v in values.items():
            i = key.get(str(name).lower())
            if i is None:
                raise ValueError(f"values: {name!r} is not a Live Link Face channel; channels: {', '.join(CHANNELS[:4])}, ...")
            arr[i] = v
        values = arr
    d, s = device_id.encode("utf-8"), subject.encode("utf-8")
    head = (bytes([VERSION]) + _INT.pack(len(d)) + d + _INT.pack(len(s)) + s
            + _FRAME_TIME.pack(int(frame), float(subframe), int(rate[0]), int(rate[1])))
    if values is None:
        return head
    arr = np.asarray(values, dtype=np.float32).ravel()
    if arr.shape != (N_VALUES,):
        raise ValueError(f"values: expected {N_VALUES} floats ({', '.join(CHANNELS[:3])}, ...), got {arr.shape}")
    return head + bytes([N_VALUES]) + arr.astype(">f4").tobytes()
