"""``tetra_gradiometer_msgs/GradientTensor``: one tensor set per message, as arrays and CDR.

The message (``tetra_gradiometer_msgs/msg/GradientTensor.msg``) carries the tensor ``g``
(T/m, 3 x 3 row-major, ``G_ij = dB_i/dx_j``), its 1-sigma ``g_sigma`` (T/m, NaN where
unknown), the reference reading ``B_1'`` of the same set (T) with its covariance (T^2,
3 x 3 row-major, all 0 = unknown), a state (:data:`RAW`, :data:`COMPENSATED`,
:data:`UNCOMPENSATED`) and the ``calibration_id`` that compensated it. The topics
``gradient/raw``, ``gradient/compensated`` and ``gradient/truth`` carry it.

:class:`TensorSet` is its content as arrays; :func:`gradient_tensor_msg` builds the message
for rclpy or rosbags (``conversions.MessageTypes``); :func:`tensor_set_from_msg` reads it,
and reads the tensor ``sensor_msgs/JointState`` (names ``gxx..gzz``) of bags recorded before
the message existed. :class:`GradientTensorCdr` writes and reads the serialized message
directly, for the nodes' per-set path (io/conversions' CDR section says why).
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..core.units import NS_PER_S
from ..errors import MessageError
from . import conversions as cv

GRADIENT_TENSOR = cv.GRADIENT_TENSOR
#: The tensor topics' message types a reader accepts: this one, and the JointState of older
#: recordings.
TENSOR_TYPES = (GRADIENT_TENSOR, cv.JOINT_STATE)
#: Values of ``state`` (the message's constants).
RAW, COMPENSATED, UNCOMPENSATED = 0, 1, 2

#: ``g_sigma`` unknown (9,): NaN; ``reference_field_covariance`` unknown (9,): 0.
UNKNOWN_SIGMA = np.full(9, np.nan)
UNKNOWN_SIGMA.setflags(write=False)
UNKNOWN_COVARIANCE = np.zeros(9)
UNKNOWN_COVARIANCE.setflags(write=False)
#: Doubles after the header: g (9), g_sigma (9), reference_field (3), its covariance (9).
_DOUBLES = 30
_U32 = struct.Struct('<I')


@dataclass(frozen=True)
class TensorSet:
    """The content of one ``GradientTensor``.

    Parameters
    ----------
    stamp_ns : header stamp, integer ns (sensor 1's sample time of the set)
    g : the tensor (3, 3), T/m
    g_sigma : 1-sigma of each element of ``g`` (3, 3), T/m; NaN where unknown
    reference_field : ``B_1'`` (3,), T; NaN when the message has none (an older recording)
    reference_covariance : covariance of ``reference_field`` (9,) row-major, T^2; all 0 =
        unknown
    state : :data:`RAW`, :data:`COMPENSATED` or :data:`UNCOMPENSATED`
    calibration_id : the compensating calibration's ``created_utc``; '' unless COMPENSATED
    frame_id : the array's frame
    """

    stamp_ns: int
    g: np.ndarray
    g_sigma: np.ndarray = field(default_factory=lambda: UNKNOWN_SIGMA.reshape(3, 3))
    reference_field: np.ndarray = field(default_factory=lambda: UNKNOWN_SIGMA[:3])
    reference_covariance: np.ndarray = field(default_factory=lambda: UNKNOWN_COVARIANCE)
    state: int = RAW
    calibration_id: str = ''
    frame_id: str = cv.ARRAY_FRAME


def rclpy_class() -> Any:
    """The compiled message class (the nodes' side; imported on first use)."""
    return cv.rclpy_types()[GRADIENT_TENSOR]


def gradient_tensor_msg(types: cv.MessageTypes, tensor: TensorSet) -> Any:
    """The ``GradientTensor`` of ``tensor``, built from ``types`` (``conversions.rclpy_types``
    or a rosbags typestore's, ``conversions.rosbags_types``)."""
    field_t = np.asarray(tensor.reference_field, dtype=float)
    return types[GRADIENT_TENSOR](
        header=cv.header(types, tensor.stamp_ns, tensor.frame_id),
        g=_nine(tensor.g),
        g_sigma=_nine(tensor.g_sigma),
        reference_field=types['geometry_msgs/msg/Vector3'](
            x=float(field_t[0]), y=float(field_t[1]), z=float(field_t[2])
        ),
        reference_field_covariance=_nine(tensor.reference_covariance),
        state=int(tensor.state),
        calibration_id=tensor.calibration_id,
    )


def _nine(values: Any) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(9)


def tensor_set_from_msg(msg: Any, msgtype: str = GRADIENT_TENSOR) -> TensorSet:
    """The :class:`TensorSet` of a ``GradientTensor`` or, with ``msgtype`` JointState, of a
    tensor JointState (its ``g`` only: the rest unknown, state RAW).

    Raises
    ------
    MessageError
        A JointState that is not a tensor (``conversions.tensor_from_msg``), or a type that
        is neither.
    """
    stamp_ns = cv.stamp_to_ns(msg.header.stamp)
    if msgtype == cv.JOINT_STATE:
        return TensorSet(stamp_ns, cv.tensor_from_msg(msg), frame_id=msg.header.frame_id)
    if msgtype != GRADIENT_TENSOR:
        raise MessageError(f'a tensor topic holds {GRADIENT_TENSOR}, not {msgtype}')
    field_t = msg.reference_field
    return TensorSet(
        stamp_ns,
        _nine(msg.g).reshape(3, 3),
        _nine(msg.g_sigma).reshape(3, 3),
        np.array([field_t.x, field_t.y, field_t.z], dtype=float),
        _nine(msg.reference_field_covariance),
        int(msg.state),
        str(msg.calibration_id),
        str(msg.header.frame_id),
    )


class GradientTensorCdr:
    """Writer and reader of serialized ``GradientTensor`` messages in ``frame_id``:
    everything before the stamp-dependent and value fields is built once.

    Layout (XCDR1 little endian, offsets from the payload's start): the header (stamp,
    ``frame_id``), padding to 8, 30 doubles (``g``, ``g_sigma``, ``reference_field``, its
    covariance), ``state`` (1 byte), padding to 4, ``calibration_id`` (length with its NUL,
    bytes, NUL).
    """

    def __init__(self, frame_id: str) -> None:
        self.frame_id = frame_id
        payload = bytearray(8)  # the stamp
        cv._cdr_string(payload, frame_id)
        cv._cdr_pad(payload, 8)
        self._middle = bytes(payload[8:])

    def write(
        self,
        stamp_ns: int,
        values: np.ndarray,
        state: int = RAW,
        calibration_id: str = '',
    ) -> bytes:
        """The serialized message at ``stamp_ns`` (integer ns) of ``values`` (30,): ``g`` (9,)
        T/m, ``g_sigma`` (9,) T/m, ``reference_field`` (3,) T, its covariance (9,) T^2 (see
        :func:`pack`)."""
        ident = calibration_id.encode()
        # 30 doubles end 8-aligned: the state byte, 3 bytes to the string's 4-alignment.
        tail = bytes((state, 0, 0, 0)) + _U32.pack(len(ident) + 1) + ident + b'\x00'
        data = np.ascontiguousarray(values, dtype='<f8').tobytes()
        return b''.join((cv._CDR_LE, cv._cdr_stamp(stamp_ns), self._middle, data, tail))

    def read(self, data: bytes) -> tuple[int, np.ndarray, int, str]:
        """``(stamp_ns, values (30,) as :meth:`write` takes them, state, calibration_id)`` of a
        serialized ``GradientTensor`` (any frame).

        Raises
        ------
        MessageError
            Not a GradientTensor (rclpy's deserialization fails too).
        """
        if data[:2] == cv._CDR_LE[:2] and len(data) >= 16:
            sec, nanosec = cv._STAMP.unpack_from(data, 4)
            (length,) = _U32.unpack_from(data, 12)
            start = 16 + length
            start += -(start - 4) % 8
            at = start + 8 * _DOUBLES + 4  # after the state and its padding to 4
            if length >= 1 and at + 5 <= len(data):
                (size,) = _U32.unpack_from(data, at)
                # Fast DDS pads a payload it carries between processes to 4 bytes.
                if size >= 1 and 0 <= len(data) - (at + 4 + size) <= 3:
                    values = np.frombuffer(data, '<f8', _DOUBLES, start).astype(float)
                    ident = data[at + 4 : at + 3 + size].decode(errors='replace')
                    return sec * NS_PER_S + nanosec, values, data[at - 4], ident
        tensor = tensor_set_from_msg(_deserialize(data))  # another encoding: the object rule
        return tensor.stamp_ns, pack(tensor), tensor.state, tensor.calibration_id


def pack(tensor: TensorSet) -> np.ndarray:
    """The 30 values of :meth:`GradientTensorCdr.write` from a :class:`TensorSet`."""
    return np.concatenate(
        [
            _nine(tensor.g),
            _nine(tensor.g_sigma),
            np.asarray(tensor.reference_field, dtype=float).reshape(3),
            _nine(tensor.reference_covariance),
        ]
    )


def pack_sets(
    g: np.ndarray, g_sigma: np.ndarray | None, reference_field: np.ndarray
) -> np.ndarray:
    """The values (N, 30) of N sets for :meth:`GradientTensorCdr.write`: tensors (N, 3, 3) T/m,
    their 1-sigma (N, 3, 3) T/m (None: unknown, NaN), ``B_1'`` (N, 3) T (its covariance
    unknown, 0)."""
    n = len(g)
    sigma = np.full((n, 9), np.nan) if g_sigma is None else np.reshape(g_sigma, (n, 9))
    return np.hstack([np.reshape(g, (n, 9)), sigma, reference_field, np.zeros((n, 9))])


def unpack(stamp_ns: int, values: np.ndarray, state: int, calibration_id: str) -> TensorSet:
    """The :class:`TensorSet` of :meth:`GradientTensorCdr.read`'s tuple."""
    return TensorSet(
        stamp_ns,
        values[:9].reshape(3, 3),
        values[9:18].reshape(3, 3),
        values[18:21],
        values[21:30],
        state,
        calibration_id,
    )


def _deserialize(data: bytes) -> Any:
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(data, rclpy_class())
    except Exception as error:  # rclpy raises its C layer's errors
        raise MessageError(f'cannot deserialize a {GRADIENT_TENSOR}: {error}') from None


@functools.cache
def cdr_agrees() -> bool:
    """Whether the RMW serializes ``GradientTensor`` as :class:`GradientTensorCdr` does
    (round trips both ways with rclpy, on frame ids and calibration ids of every alignment;
    checked once per process)."""
    from rclpy.serialization import deserialize_message, serialize_message

    stamp, values = 1_234_567_890_123_456_789, np.arange(1.0, 31.0) * 1e-9
    try:
        for frame in ('', 'a', 'ab', 'abc', 'abcd', cv.ARRAY_FRAME):
            layout, ident = GradientTensorCdr(frame), frame[::-1]
            tensor = unpack(stamp, values, COMPENSATED, ident)
            msg = deserialize_message(
                layout.write(stamp, values, COMPENSATED, ident), rclpy_class()
            )
            read = tensor_set_from_msg(msg)
            if (read.stamp_ns, read.frame_id, read.state, read.calibration_id) != (
                stamp,
                frame,
                COMPENSATED,
                ident,
            ) or not np.array_equal(pack(read), values):
                return False
            original = gradient_tensor_msg(cv.rclpy_types(), replace(tensor, frame_id=frame))
            back = layout.read(serialize_message(original))
            if back[0] != stamp or back[2:] != (COMPENSATED, ident):
                return False
            if not np.array_equal(back[1], values):
                return False
        return True
    except Exception:  # noqa: BLE001 - any disagreement (rclpy raises its C layer's errors)
        return False
