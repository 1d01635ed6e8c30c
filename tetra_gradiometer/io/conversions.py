"""Every message <-> array conversion, for rclpy messages and rosbags messages alike.

Both libraries build messages from the same keyword fields, so each function takes a
:class:`MessageTypes` naming the classes to use (:func:`rclpy_types` for the nodes,
:func:`rosbags_types` for bag files). Nothing here imports rclpy at module import.

Contract (README, "Topics"):

* ``mag1``..``mag4``: ``sensor_msgs/MagneticField``, tesla, body frame (REP 103),
  frames ``tetra_mag1``..``tetra_mag4``, ``header.stamp`` = sample time;
  ``magnetic_field_covariance`` row-major 3 x 3 in T^2, ``diag(sigma^2)`` of the per-axis
  sensor noise when known, -1 in the first element when unknown (REP 145).
* tensors (``gradient/raw``, ``gradient/compensated``, ``gradient/truth``):
  ``tetra_gradiometer_msgs/GradientTensor`` (io/gradient_tensor.py), frame ``tetra_array``;
  bags recorded before it hold ``sensor_msgs/JointState`` with ``name = gxx, gxy, gxz, gyx,
  gyy, gyz, gzx, gzy, gzz``, ``position`` = ``G_ij = dB_i/dx_j`` in T/m (:func:`tensor_msg`,
  :func:`tensor_from_msg`).
* ``/odom``: ``nav_msgs/Odometry``, orientation rotates body vectors into ENU.
* the target node's outputs: ``geometry_msgs/PoseArray`` (m, odom frame) and
  ``visualization_msgs/MarkerArray``, built by nodes/target_messages.py from the classes here.
* ``/tetra/temperature``: ``sensor_msgs/Temperature`` (degC);
  ``/battery_state``: ``sensor_msgs/BatteryState`` (``current`` in A).

The nodes' per-message paths (tensor, compensator, driver) read and write serialized
messages (CDR bytes) with the functions at the end of this module (the tensor's in
io/gradient_tensor.py): rclpy's conversion between
Python message objects and C structs costs 10-15 us per message, a tenth of the budget per set
at 1000 sets/s (bench/bench_chain.py).
"""

from __future__ import annotations

import array
import functools
import importlib
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.units import NS_PER_S
from ..errors import InputError, MessageError

NAMESPACE = '/tetra'
MAG_TOPICS = ('mag1', 'mag2', 'mag3', 'mag4')
MAG_FRAMES = ('tetra_mag1', 'tetra_mag2', 'tetra_mag3', 'tetra_mag4')
ARRAY_FRAME = 'tetra_array'
#: REP 105: the world-fixed frame of odometry and the body frame (REP 103 axes); the sensor
#: frames and the array frame are children of the body frame. Defaults of the nodes'
#: frame-id parameters.
ODOM_FRAME = 'odom'
BASE_FRAME = 'base_link'
TENSOR_NAMES = ('gxx', 'gxy', 'gxz', 'gyx', 'gyy', 'gyz', 'gzx', 'gzy', 'gzz')
#: Odometry in a bag (the bag contract's name, README "Topics").
ODOM_TOPIC = '/odom'
#: Odometry between the nodes: relative, so in the suite's namespace (``/tetra/odom``) where
#: the driver publishes its simulated or replayed vehicle and the calibrator listens. On a
#: vehicle the calibrator is remapped to the navigation's topic (``-r odom:=/odom``); the
#: driver never publishes on the vehicle's own ``/odom``.
ODOM_NODE_TOPIC = 'odom'
#: The compensator's output, relative (``/tetra/gradient/compensated``); the target node's input.
COMPENSATED_NODE_TOPIC = 'gradient/compensated'
TEMPERATURE_TOPIC = '/tetra/temperature'
BATTERY_TOPIC = '/battery_state'
BAG_MAG_TOPICS = tuple(f'{NAMESPACE}/{name}' for name in MAG_TOPICS)

#: The topics of the bag contract (README, "Topics"): what ``remap`` may map to.
CONTRACT_TOPICS = (
    *BAG_MAG_TOPICS,
    f'{NAMESPACE}/gradient/truth',
    ODOM_TOPIC,
    TEMPERATURE_TOPIC,
    BATTERY_TOPIC,
)


def parse_remap(text: str) -> dict[str, str]:
    """A topic map from ``FROM:=TO`` rules separated by spaces or commas (the form of
    ``ros2 bag play --remap``): the bag's topic ``FROM`` is read as the contract's ``TO``.

    Raises
    ------
    InputError
        A rule without ``:=``, a name that is not absolute, a ``FROM`` given twice, a ``TO``
        that is not a contract topic (:data:`CONTRACT_TOPICS`) or given twice.
    """
    rules: dict[str, str] = {}
    for rule in text.replace(',', ' ').split():
        recorded, sep, contract = rule.partition(':=')
        if not sep or not recorded.startswith('/') or not contract.startswith('/'):
            raise InputError(f'topic map rule {rule!r}: expected /RECORDED_TOPIC:=/CONTRACT_TOPIC')
        if contract not in CONTRACT_TOPICS:
            raise InputError(
                f'topic map rule {rule!r}: {contract} is not a topic of the bag contract '
                f'({", ".join(CONTRACT_TOPICS)})'
            )
        if recorded in rules or contract in rules.values():
            raise InputError(f'topic map rule {rule!r}: {recorded} or {contract} mapped twice')
        rules[recorded] = contract
    return rules


MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
JOINT_STATE = 'sensor_msgs/msg/JointState'
ODOMETRY = 'nav_msgs/msg/Odometry'
TEMPERATURE = 'sensor_msgs/msg/Temperature'
BATTERY_STATE = 'sensor_msgs/msg/BatteryState'
POSE_ARRAY = 'geometry_msgs/msg/PoseArray'
MARKER = 'visualization_msgs/msg/Marker'
MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
COLOR_RGBA = 'std_msgs/msg/ColorRGBA'
#: Ours (tetra_gradiometer_msgs; io/gradient_tensor.py reads and writes it).
GRADIENT_TENSOR = 'tetra_gradiometer_msgs/msg/GradientTensor'


@dataclass(frozen=True)
class MessageTypes:
    """The message classes to build, by ROS name, and how a float64[] field is given."""

    classes: dict[str, Any]
    float_sequence: Callable[[np.ndarray], Any]

    def __getitem__(self, name: str) -> Any:
        return self.classes[name]


@functools.cache
def rclpy_types() -> MessageTypes:
    """Message classes of the rclpy wheels (imports them on first use; built once)."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseArray,
        PoseWithCovariance,
        Quaternion,
        Twist,
        TwistWithCovariance,
        Vector3,
    )
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import BatteryState, JointState, MagneticField, Temperature
    from std_msgs.msg import ColorRGBA, Float64, Header
    from visualization_msgs.msg import Marker, MarkerArray

    classes = {
        'builtin_interfaces/msg/Time': Time,
        'rosgraph_msgs/msg/Clock': Clock,
        'std_msgs/msg/Header': Header,
        'std_msgs/msg/Float64': Float64,
        'geometry_msgs/msg/Vector3': Vector3,
        'geometry_msgs/msg/Point': Point,
        'geometry_msgs/msg/Quaternion': Quaternion,
        'geometry_msgs/msg/Pose': Pose,
        'geometry_msgs/msg/PoseWithCovariance': PoseWithCovariance,
        'geometry_msgs/msg/Twist': Twist,
        'geometry_msgs/msg/TwistWithCovariance': TwistWithCovariance,
        MAGNETIC_FIELD: MagneticField,
        JOINT_STATE: JointState,
        ODOMETRY: Odometry,
        TEMPERATURE: Temperature,
        BATTERY_STATE: BatteryState,
        POSE_ARRAY: PoseArray,
        COLOR_RGBA: ColorRGBA,
        MARKER: Marker,
        MARKER_ARRAY: MarkerArray,
        # By name: to mypy, the checkout's interface sources (tetra_gradiometer_msgs/, no
        # Python) hide the installed package.
        GRADIENT_TENSOR: importlib.import_module('tetra_gradiometer_msgs.msg').GradientTensor,
    }
    return MessageTypes(
        classes, lambda values: array.array('d', np.asarray(values, float).tolist())
    )


def rosbags_types(typestore: Any) -> MessageTypes:
    """Message classes of a rosbags typestore (e.g. ``get_typestore(Stores.ROS2_JAZZY)``)."""
    return MessageTypes(typestore.types, lambda values: np.asarray(values, dtype=np.float64))


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def time_msg(types: MessageTypes, stamp_ns: int) -> Any:
    """A ``builtin_interfaces/Time`` at ``stamp_ns`` (integer nanoseconds)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)


def header(types: MessageTypes, stamp_ns: int, frame_id: str) -> Any:
    """A ``std_msgs/Header`` at ``stamp_ns`` (integer nanoseconds)."""
    return types['std_msgs/msg/Header'](stamp=time_msg(types, stamp_ns), frame_id=frame_id)


def clock_msg(types: MessageTypes, stamp_ns: int) -> Any:
    """A ``rosgraph_msgs/Clock`` (``/clock``, sim time) at ``stamp_ns`` (integer ns)."""
    return types['rosgraph_msgs/msg/Clock'](clock=time_msg(types, stamp_ns))


def _vector3(types: MessageTypes, values: np.ndarray) -> Any:
    return types['geometry_msgs/msg/Vector3'](
        x=float(values[0]), y=float(values[1]), z=float(values[2])
    )


#: REP 145 "covariance unknown": -1 in the first element (sensor_msgs/MagneticField says 0
#: too, but a zero covariance also reads as a perfect sensor; -1 cannot be mistaken).
UNKNOWN_COVARIANCE = np.r_[-1.0, np.zeros(8)]
UNKNOWN_COVARIANCE.setflags(write=False)


def known_covariance(covariance_t2: np.ndarray) -> bool:
    """Whether a ``magnetic_field_covariance`` (9,) T^2 states a covariance: finite, its first
    element not negative (REP 145's unknown) and not all zero (the older unknown)."""
    values = np.asarray(covariance_t2, dtype=float)
    return bool(np.all(np.isfinite(values)) and values[0] >= 0 and np.any(values))


def noise_covariance(sensor_noise_t: float) -> np.ndarray:
    """``magnetic_field_covariance`` (9,) row-major, T^2, of a reading with independent white
    noise ``sensor_noise_t`` (tesla RMS) on each axis: ``diag(sigma^2)``; 0 (no noise figure)
    gives :data:`UNKNOWN_COVARIANCE`."""
    if sensor_noise_t <= 0:
        return UNKNOWN_COVARIANCE.copy()
    return (np.eye(3) * float(sensor_noise_t) ** 2).reshape(9)


def magnetic_field_msg(
    types: MessageTypes,
    field_t: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    covariance_t2: np.ndarray | None = None,
) -> Any:
    """``sensor_msgs/MagneticField`` from a field (3,) in tesla and its covariance (9,)
    row-major in T^2 (None: :data:`UNKNOWN_COVARIANCE`)."""
    covariance = UNKNOWN_COVARIANCE if covariance_t2 is None else covariance_t2
    return types[MAGNETIC_FIELD](
        header=header(types, stamp_ns, frame_id),
        magnetic_field=_vector3(types, field_t),
        magnetic_field_covariance=np.asarray(covariance, dtype=float).reshape(9),
    )


def magnetic_field_vector(msg: Any) -> np.ndarray:
    """Field (3,) in tesla from a ``sensor_msgs/MagneticField`` (may be non-finite: callers
    check)."""
    field = msg.magnetic_field
    return np.array([field.x, field.y, field.z], dtype=float)


def magnetic_field_covariance(msg: Any) -> np.ndarray:
    """``magnetic_field_covariance`` (9,) row-major, T^2, of a ``sensor_msgs/MagneticField``
    (as recorded: :func:`known_covariance` tells whether it states one)."""
    return np.asarray(msg.magnetic_field_covariance, dtype=float).reshape(9)


def magnetic_field_reading(msg: Any) -> np.ndarray:
    """Field and covariance in one array (12,): the field (3,) in tesla, then the covariance
    (9,) row-major in T^2 (what the tensor node's stamp matcher carries per sensor)."""
    field = msg.magnetic_field
    return np.concatenate(([field.x, field.y, field.z], msg.magnetic_field_covariance))


def tensor_msg(
    types: MessageTypes, g: np.ndarray, stamp_ns: int, frame_id: str = ARRAY_FRAME
) -> Any:
    """The tensor ``sensor_msgs/JointState`` of older recordings: named ``gxx..gzz``,
    positions in T/m."""
    values = np.asarray(g, dtype=float).reshape(9)
    empty = types.float_sequence(np.zeros(0))
    return types[JOINT_STATE](
        header=header(types, stamp_ns, frame_id),
        name=list(TENSOR_NAMES),
        position=types.float_sequence(values),
        velocity=empty,
        effort=empty,
    )


def tensor_from_msg(msg: Any) -> np.ndarray:
    """(3, 3) tensor in T/m from a tensor ``JointState``, in any name order.

    Raises
    ------
    MessageError
        If the names are not exactly ``gxx..gzz`` or the counts differ.
    """
    names = list(msg.name)
    values = np.asarray(msg.position, dtype=float)
    if sorted(names) != sorted(TENSOR_NAMES) or len(values) != 9:
        raise MessageError(
            f'a tensor JointState needs names {TENSOR_NAMES} with 9 positions, '
            f'got names {names} and {len(values)} positions'
        )
    return values[[names.index(n) for n in TENSOR_NAMES]].reshape(3, 3)


def pose_msg(types: MessageTypes, position: np.ndarray, orientation_xyzw: np.ndarray) -> Any:
    """``geometry_msgs/Pose``: position (3,) m, orientation (4,) x, y, z, w."""
    p, q = np.asarray(position, dtype=float), np.asarray(orientation_xyzw, dtype=float)
    return types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=types['geometry_msgs/msg/Quaternion'](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )


def odometry_msg(
    types: MessageTypes,
    position_enu: np.ndarray,
    orientation_xyzw: np.ndarray,
    stamp_ns: int,
    *,
    frame_id: str = ODOM_FRAME,
    child_frame_id: str = BASE_FRAME,
) -> Any:
    """``nav_msgs/Odometry``: position (3,) m ENU, orientation (4,) x, y, z, w (body -> ENU)."""
    pose = pose_msg(types, position_enu, orientation_xyzw)
    zero = np.zeros(3)
    twist = types['geometry_msgs/msg/Twist'](
        linear=_vector3(types, zero), angular=_vector3(types, zero)
    )
    return types[ODOMETRY](
        header=header(types, stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist, covariance=np.zeros(36)),
    )


def odometry_orientation(msg: Any) -> np.ndarray:
    """Orientation (4,) x, y, z, w from ``nav_msgs/Odometry``."""
    q = msg.pose.pose.orientation
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


#: The columns of :func:`odometry_pose`: position (m, ENU) and orientation (x, y, z, w).
POSE_POSITION = slice(0, 3)
POSE_ORIENTATION = slice(3, 7)


def odometry_pose(msg: Any) -> np.ndarray:
    """Pose (7,) from ``nav_msgs/Odometry``: position x, y, z (m, odom frame) then the
    orientation x, y, z, w (:data:`POSE_POSITION`, :data:`POSE_ORIENTATION`)."""
    p = msg.pose.pose.position
    return np.concatenate([[p.x, p.y, p.z], odometry_orientation(msg)]).astype(float)


def temperature_msg(
    types: MessageTypes, celsius: float, stamp_ns: int, frame_id: str = ARRAY_FRAME
) -> Any:
    """``sensor_msgs/Temperature`` in degC."""
    return types[TEMPERATURE](
        header=header(types, stamp_ns, frame_id), temperature=float(celsius), variance=0.0
    )


def battery_msg(types: MessageTypes, current_a: float, stamp_ns: int) -> Any:
    """``sensor_msgs/BatteryState`` carrying only ``current`` (A); the rest unknown (NaN)."""
    nan = float('nan')
    empty = types.float_sequence(np.zeros(0))
    return types[BATTERY_STATE](
        header=header(types, stamp_ns, 'base_link'),
        voltage=nan,
        temperature=nan,
        current=float(current_a),
        charge=nan,
        capacity=nan,
        design_capacity=nan,
        percentage=nan,
        power_supply_status=0,
        power_supply_health=0,
        power_supply_technology=0,
        present=True,
        cell_voltage=empty,
        cell_temperature=empty,
        location='',
        serial_number='',
    )


# --------------------------------------------------------------------------- serialized (CDR)
# Hand-written, not rosbags' CDR codec (pure Python: slower than rclpy's objects) nor rclpy's
# serialize_message (it takes the message objects whose cost this avoids). Layout: XCDR1
# little endian (encapsulation 00 01, two option bytes), each primitive aligned to its size
# from the start of the payload (after the 4-byte encapsulation): what rosbags writes in a bag
# (the bag writer uses these too) and what the RMWs of ROS 2 put on the wire. A subscription
# created with ``raw=True`` hands its callback these bytes and ``Publisher.publish`` takes
# them. The nodes check once that their RMW agrees (:func:`cdr_agrees`) and refuse to
# configure otherwise; the readers fall back to rclpy's deserialization for any encoding or
# layout they do not recognise.

_CDR_LE = b'\x00\x01\x00\x00'
_STAMP = struct.Struct('<iI')
_U32 = struct.Struct('<I')
_F64 = struct.Struct('<d')


def _cdr_pad(payload: bytearray, size: int) -> None:
    payload.extend(bytes(-len(payload) % size))


def _cdr_string(payload: bytearray, text: str) -> None:
    data = text.encode()
    _cdr_pad(payload, 4)
    payload += _U32.pack(len(data) + 1) + data + b'\x00'


def _cdr_stamp(stamp_ns: int) -> bytes:
    return _STAMP.pack(*divmod(int(stamp_ns), NS_PER_S))


def magnetic_field_cdr(
    field_t: np.ndarray, stamp_ns: int, frame_id: str, covariance_t2: np.ndarray | None = None
) -> bytes:
    """Serialized :func:`magnetic_field_msg`: field (3,) T, covariance (9,) T^2 (None:
    REP 145 unknown)."""
    covariance = UNKNOWN_COVARIANCE if covariance_t2 is None else covariance_t2
    payload = bytearray(_cdr_stamp(stamp_ns))
    _cdr_string(payload, frame_id)
    _cdr_pad(payload, 8)
    values = np.concatenate((np.ravel(field_t), np.ravel(covariance))).astype('<f8')
    return _CDR_LE + bytes(payload) + values.tobytes()


def magnetic_field_from_cdr(data: bytes) -> tuple[int, str, np.ndarray]:
    """``(stamp_ns, frame_id, reading (12,))`` of a serialized ``sensor_msgs/MagneticField``:
    the reading as :func:`magnetic_field_reading`, field (3,) T then covariance (9,) T^2."""
    try:
        stamp_ns, frame_id, end = _cdr_header(data)
        start = end + (-(end - 4) % 8)
        if start + 96 <= len(data):
            return stamp_ns, frame_id, np.frombuffer(data, '<f8', 12, start).astype(float)
    except MessageError:
        pass
    msg = _deserialize(data, MAGNETIC_FIELD)
    return stamp_to_ns(msg.header.stamp), msg.header.frame_id, magnetic_field_reading(msg)


def float64_cdr(value: float) -> bytes:
    """Serialized ``std_msgs/Float64``."""
    return _CDR_LE + _F64.pack(value)


def stamp_from_cdr(data: bytes) -> int:
    """``header.stamp`` (integer ns) of a serialized message that begins with a header."""
    return _cdr_header(data)[0]


def _cdr_header(data: bytes) -> tuple[int, str, int]:
    """``(stamp_ns, frame_id, offset after the header)`` of a serialized message beginning
    with a ``std_msgs/Header``; MessageError unless little-endian XCDR1 and long enough."""
    if len(data) < 16 or data[:2] != b'\x00\x01':
        raise MessageError('not little-endian CDR')
    sec, nanosec = _STAMP.unpack_from(data, 4)
    (length,) = _U32.unpack_from(data, 12)
    end = 16 + length
    if length < 1 or end > len(data):
        raise MessageError('truncated CDR header')
    return sec * NS_PER_S + nanosec, data[16 : end - 1].decode(errors='replace'), end


def _deserialize(data: bytes, type_name: str) -> Any:
    """rclpy's deserialization of ``data`` as ``type_name``; MessageError when it fails."""
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(data, rclpy_types()[type_name])
    except Exception as error:  # rclpy raises its C layer's errors
        raise MessageError(f'cannot deserialize a {type_name}: {error}') from None


@functools.cache
def cdr_agrees() -> bool:
    """Whether the RMW serializes as the writers here do (checked once per process against
    rclpy's serialize_message and deserialize_message, on frame ids of every alignment)."""
    return _writers_agree()


def _writers_agree() -> bool:
    """Round trips both ways: what the writers write, rclpy reads back equal; what rclpy
    writes, the readers read equal (its padding bytes are not zeroed: no byte comparison)."""
    from rclpy.serialization import deserialize_message, serialize_message

    types = rclpy_types()
    stamp = 1_234_567_890_123_456_789
    reading = np.r_[1e-5, -2e-5, 3e-5, np.arange(9.0) * 1e-20]
    try:
        for frame in ('', 'a', 'ab', 'abc', 'abcd', ARRAY_FRAME):
            data = magnetic_field_cdr(reading[:3], stamp, frame, reading[3:])
            msg = deserialize_message(data, types[MAGNETIC_FIELD])
            if not np.array_equal(magnetic_field_reading(msg), reading):
                return False
            original = magnetic_field_msg(types, reading[:3], stamp, frame, reading[3:])
            stamp_read, frame_read, values = magnetic_field_from_cdr(serialize_message(original))
            if (stamp_read, frame_read) != (stamp, frame) or not np.array_equal(values, reading):
                return False
        float64 = deserialize_message(float64_cdr(2.5), types['std_msgs/msg/Float64'])
        return bool(float64.data == 2.5)
    except Exception:  # noqa: BLE001 - any disagreement (rclpy raises its C layer's errors)
        return False
