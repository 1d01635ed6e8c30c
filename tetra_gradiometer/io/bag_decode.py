"""Decoding ``sensor_msgs/MagneticField`` CDR with numpy, message by message when a batch
holds a malformed message (io/bag.py's fast path: a bad message costs itself).

Layout: encapsulation header, ``int32 sec``, ``uint32 nanosec``, ``frame_id`` (uint32 length
incl. NUL, bytes), padding to 8 (counted from the end of the 4-byte encapsulation header),
3 float64, 9 float64 covariance; little- and big-endian plain CDR (XCDR1), as rosbags'
deserializer. Malformed: another encapsulation, a payload cut short or longer than its
layout (more than 3 trailing bytes, as rosbags), a frame_id length beyond the payload, a
header nanosec outside [0, 1e9).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.units import NS_PER_S
from . import conversions as cv

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: CDR encapsulation identifiers (first two bytes) of plain CDR (XCDR1).
_CDR_BE, _CDR_LE = b'\x00\x00', b'\x00\x01'


class _UnsupportedEncoding(Exception):
    """A serialized message is malformed or not plain CDR (its text: the reason)."""


def _decode_one(raw: bytes) -> tuple[int, float, float, float]:
    """One MagneticField CDR -> (stamp_ns, x, y, z); raises _UnsupportedEncoding with the
    reason when it is malformed (the checks rosbags' deserializer makes, and the stamp's)."""
    if not isinstance(raw, (bytes, bytearray, memoryview)):
        raise _UnsupportedEncoding(f'no payload ({type(raw).__name__})')
    if len(raw) < 4:
        raise _UnsupportedEncoding(f'payload cut short ({len(raw)} bytes)')
    kind = bytes(raw[:2])
    if kind == _CDR_LE:
        order = '<'
    elif kind == _CDR_BE:
        order = '>'
    else:
        raise _UnsupportedEncoding(f'unknown CDR encapsulation 0x{kind.hex()}')
    if len(raw) < 16:
        raise _UnsupportedEncoding(f'payload cut short ({len(raw)} bytes)')
    sec, nanosec, length = struct.unpack_from(order + 'iII', raw, 4)
    offset = 16 + length
    offset += -(offset - 4) % 8
    if 16 + length > len(raw):
        raise _UnsupportedEncoding(f'frame_id length {length} beyond the payload')
    if offset + 96 > len(raw):
        raise _UnsupportedEncoding(f'payload cut short ({len(raw)} of {offset + 96} bytes)')
    if offset + 96 + 3 < len(raw):
        raise _UnsupportedEncoding(f'payload longer than its layout ({len(raw)} bytes)')
    if nanosec >= NS_PER_S:
        raise _UnsupportedEncoding(f'header stamp nanosec {nanosec} >= 1e9')
    x, y, z = struct.unpack_from(order + '3d', raw, offset)
    return sec * NS_PER_S + nanosec, x, y, z


def _decode_uniform(raws: list[bytes]) -> tuple[IntArray, FloatArray] | None:
    """The vectorised decode when every message shares one length, byte order and frame_id
    length and passes the checks of :func:`_decode_one`; None otherwise."""
    n, size = len(raws), len(raws[0])
    kind = raws[0][:2]
    if size < 16 or kind not in (_CDR_LE, _CDR_BE) or any(len(r) != size for r in raws):
        return None
    order = '<' if kind == _CDR_LE else '>'
    block = np.frombuffer(b''.join(raws), dtype=np.uint8).reshape(n, size)
    length = block[:, 12:16].copy().view(order + 'u4')[:, 0]
    if not (np.all(block[:, :2] == block[0, :2]) and np.all(length == length[0])):
        return None
    offset = 16 + int(length[0])
    offset += -(offset - 4) % 8
    if not offset + 96 <= size <= offset + 99:
        return None
    nanosec = block[:, 8:12].copy().view(order + 'u4')[:, 0].astype(np.int64)
    if np.any(nanosec >= NS_PER_S):
        return None
    sec = block[:, 4:8].copy().view(order + 'i4')[:, 0].astype(np.int64)
    values = block[:, offset : offset + 24].copy().view(order + 'f8').astype(float)
    return sec * NS_PER_S + nanosec, values


def decode_checked(raws: list[bytes]) -> tuple[IntArray, FloatArray, list[tuple[int, str]]]:
    """Stamps (m,) int64 ns and fields (m, 3) T of the well-formed messages among ``raws``,
    and ``(index, reason)`` of the malformed ones (m = n - their number).

    Vectorised when the batch is uniform and clean (the usual case); otherwise message by
    message, so a bad message costs itself, not its batch.
    """
    if not raws:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), []
    try:
        uniform = _decode_uniform(raws)
    except Exception:  # e.g. a row without payload: sorted out below
        uniform = None
    if uniform is not None:
        return uniform[0], uniform[1], []
    good: list[tuple[int, float, float, float]] = []
    bad: list[tuple[int, str]] = []
    for i, raw in enumerate(raws):
        try:
            good.append(_decode_one(raw))
        except _UnsupportedEncoding as error:
            bad.append((i, str(error)))
    return (
        np.array([d[0] for d in good], dtype=np.int64),
        np.array([d[1:] for d in good], dtype=float).reshape(-1, 3),
        bad,
    )


def decode_magnetic_field(raws: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    """Header stamps (n,) int64 ns and fields (n, 3) tesla of serialized MagneticField messages.

    Vectorised when all messages share one length, byte order and frame_id length (the
    usual case: one topic, one frame); message by message otherwise.

    Raises
    ------
    _UnsupportedEncoding
        A message is malformed or not plain CDR (:func:`decode_checked` skips it instead).
    """
    stamps, values, bad = decode_checked(raws)
    if bad:
        raise _UnsupportedEncoding(bad[0][1])
    return stamps, values


def checked_stamp_ns(stamp: Any) -> int:
    """A deserialized ``builtin_interfaces/Time`` -> ns; nanosec outside [0, 1e9) is malformed."""
    if not 0 <= int(stamp.nanosec) < NS_PER_S:
        raise _UnsupportedEncoding(f'header stamp nanosec {stamp.nanosec} >= 1e9')
    return cv.stamp_to_ns(stamp)


def skip_reason(error: Exception) -> str:
    """A short reason for a skipped message."""
    text = str(error).strip() or type(error).__name__
    return text if len(text) <= 120 else text[:117] + '...'


#: The channels decoded without rosbags' generic deserializer (io/bag.py read_series: a
#: 100 Hz channel is 360 000 messages an hour, ~10x faster than rosbags' ~35 us each): the
#: message type -> (strings after the header's frame_id, alignment of the values after them,
#: their struct code, their offset after that alignment, bytes the type's fixed layout takes
#: from that alignment). ``sensor_msgs/Temperature``: float64 ``temperature``, ``variance``;
#: ``sensor_msgs/BatteryState``: float32 ``voltage``, ``temperature``, then ``current``;
#: ``nav_msgs/Odometry``: ``child_frame_id``, then the pose (position x, y, z, orientation x,
#: y, z, w: ``conversions.odometry_pose``), its 36 covariances, the twist and its 36.
CHANNEL_LAYOUTS = {
    cv.TEMPERATURE: (0, 8, 'd', 0, 16),
    cv.BATTERY_STATE: (0, 4, 'f', 8, 12),
    cv.ODOMETRY: (1, 8, '7d', 0, 85 * 8),
}


def decode_channel(raw: bytes, msgtype: str) -> tuple[int, tuple[float, ...]]:
    """One message of a :data:`CHANNEL_LAYOUTS` type -> (stamp_ns, its values: temperature
    degC, current A or the pose (7,)); raises _UnsupportedEncoding when it is not plain CDR of
    that layout (the caller then takes rosbags' deserializer, which names the fault)."""
    strings, align, code, after, size = CHANNEL_LAYOUTS[msgtype]
    if not isinstance(raw, (bytes, bytearray, memoryview)) or len(raw) < 16:
        raise _UnsupportedEncoding('payload cut short')
    kind = bytes(raw[:2])
    if kind not in (_CDR_LE, _CDR_BE):
        raise _UnsupportedEncoding(f'unknown CDR encapsulation 0x{kind.hex()}')
    order = '<' if kind == _CDR_LE else '>'
    sec, nanosec, length = struct.unpack_from(order + 'iII', raw, 4)
    offset = 16 + length
    for _ in range(strings):
        offset += -(offset - 4) % 4
        if offset + 4 > len(raw):
            raise _UnsupportedEncoding('payload cut short')
        offset += 4 + struct.unpack_from(order + 'I', raw, offset)[0]
    offset += -(offset - 4) % align
    if offset + size > len(raw):
        raise _UnsupportedEncoding('payload cut short')
    if nanosec >= NS_PER_S:
        raise _UnsupportedEncoding(f'header stamp nanosec {nanosec} >= 1e9')
    return sec * NS_PER_S + nanosec, struct.unpack_from(order + code, raw, offset + after)
