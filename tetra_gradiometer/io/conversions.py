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
  ``sensor_msgs/JointState`` with ``name = gxx, gxy, gxz, gyx, gyy, gyz, gzx, gzy, gzz``,
  ``position`` = ``G_ij = dB_i/dx_j`` in T/m, frame ``tetra_array``.
* ``/odom``: ``nav_msgs/Odometry``, orientation rotates body vectors into ENU.
* ``/tetra/temperature``: ``sensor_msgs/Temperature`` (degC);
  ``/battery_state``: ``sensor_msgs/BatteryState`` (``current`` in A).
"""

from __future__ import annotations

import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.units import NS_PER_S
from ..errors import MessageError

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
ODOM_TOPIC = '/odom'
TEMPERATURE_TOPIC = '/tetra/temperature'
BATTERY_TOPIC = '/battery_state'
BAG_MAG_TOPICS = tuple(f'{NAMESPACE}/{name}' for name in MAG_TOPICS)

MAGNETIC_FIELD = 'sensor_msgs/msg/MagneticField'
JOINT_STATE = 'sensor_msgs/msg/JointState'
ODOMETRY = 'nav_msgs/msg/Odometry'
TEMPERATURE = 'sensor_msgs/msg/Temperature'
BATTERY_STATE = 'sensor_msgs/msg/BatteryState'


@dataclass(frozen=True)
class MessageTypes:
    """The message classes to build, by ROS name, and how a float64[] field is given."""

    classes: dict[str, Any]
    float_sequence: Callable[[np.ndarray], Any]

    def __getitem__(self, name: str) -> Any:
        return self.classes[name]


def rclpy_types() -> MessageTypes:
    """Message classes of the rclpy wheels (imports them on first use)."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseWithCovariance,
        Quaternion,
        Twist,
        TwistWithCovariance,
        Vector3,
    )
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import BatteryState, JointState, MagneticField, Temperature
    from std_msgs.msg import Header

    classes = {
        'builtin_interfaces/msg/Time': Time,
        'rosgraph_msgs/msg/Clock': Clock,
        'std_msgs/msg/Header': Header,
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
    """Tensor carrier: ``sensor_msgs/JointState`` named ``gxx..gzz``, positions in T/m."""
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
    q = np.asarray(orientation_xyzw, dtype=float)
    pose = types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](
            x=float(position_enu[0]), y=float(position_enu[1]), z=float(position_enu[2])
        ),
        orientation=types['geometry_msgs/msg/Quaternion'](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )
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
