"""Every numeric signal a bag records beyond the data contract, as candidate channels for
the discrepancy search and ``calibrate``'s automatic selection: ``signal:TOPIC#FIELD``
(:mod:`.signals`), found in the first message of each other topic.

Topics that place the vehicle in the world (:data:`NAVIGATION_TYPES`: a GNSS fix, an IMU,
a pose, a depth) are not candidates. A field is a candidate when it is a number (not a
header or a stamp), an element of a short array (at most :data:`MAX_ELEMENTS`), or an
element named by a ``name`` array beside it (``sensor_msgs/JointState``:
``position[fin1]``). At most :data:`MAX_SIGNALS` are read; one that never changes on the
run is no regressor and is left out, said with why.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.effects import SIGNAL_PREFIX
from ..errors import BagError
from . import conversions as cv
from .signals import read_signal

if TYPE_CHECKING:
    from .bag import MagneticBag, Series

__all__ = ['MAX_SIGNALS', 'discover_signals', 'numeric_fields', 'signal_topics']

#: Arrays longer than this (an image, a point cloud) are not signals.
MAX_ELEMENTS = 16
#: At most this many signals are read from a bag.
MAX_SIGNALS = 48
#: Fields that place a message, not measure the vehicle.
_SKIPPED = {'header', 'stamp', 'frame_id', 'child_frame_id', 'covariance', 'name'}


def numeric_fields(msg: Any, prefix: str = '') -> list[str]:
    """The paths (:func:`~.signals.field_value`'s) of the numbers in ``msg``."""
    out: list[str] = []
    names = [str(n) for n in getattr(msg, 'name', ())] if hasattr(msg, 'name') else []
    for item in dataclasses.fields(msg) if dataclasses.is_dataclass(msg) else ():
        key = item.name
        if key in _SKIPPED or key.endswith('covariance') or key.startswith('_'):
            continue
        value, path = getattr(msg, key), f'{prefix}{key}'
        if isinstance(value, bool) or isinstance(value, str):
            continue
        if isinstance(value, (int, float, np.number)):
            out.append(path)
        elif isinstance(value, (list, tuple, np.ndarray)):
            numbers = np.asarray(value)
            if numbers.dtype.kind not in 'iuf' or numbers.ndim != 1:
                continue
            if names and len(names) == len(numbers):
                out += [f'{path}[{n}]' for n in names]
            elif 0 < len(numbers) <= MAX_ELEMENTS:
                out += [f'{path}[{i}]' for i in range(len(numbers))]
        elif dataclasses.is_dataclass(value):
            out += numeric_fields(value, f'{path}.')
    return out


#: Topics of the ROS graph's own, never a vehicle signal.
INFRASTRUCTURE = ('/tf', '/tf_static', '/rosout', '/parameter_events', '/diagnostics', '/clock')
#: Messages that place the vehicle in the world or read a field (a position, an attitude, a
#: depth, another magnetometer): offered as regressors they would fit what is fixed to the
#: world (geology, a target, the Earth field turning with the attitude), which is signal,
#: never the vehicle's own interference. The attitude enters through /odom.
NAVIGATION_TYPES = frozenset(
    f'{package}/msg/{name}'
    for package, names in {
        'sensor_msgs': ('NavSatFix', 'Imu', 'MagneticField', 'FluidPressure'),
        'nav_msgs': ('Odometry', 'Path'),
        'geometry_msgs': (
            'PoseStamped',
            'PoseWithCovarianceStamped',
            'TwistStamped',
            'TwistWithCovarianceStamped',
            'QuaternionStamped',
            'PointStamped',
            'TransformStamped',
        ),
        'geographic_msgs': ('GeoPoint', 'GeoPointStamped', 'GeoPoseStamped'),
    }.items()
    for name in names
)


def signal_topics(bag: MagneticBag) -> tuple[str, ...]:
    """The bag's topics beyond the contract, its current channels (BatteryState), the
    graph's own and those of :data:`NAVIGATION_TYPES`: where a vehicle signal may be."""
    skip = {*cv.CONTRACT_TOPICS, *bag.topics_of_type(cv.BATTERY_STATE), *INFRASTRUCTURE}
    skip |= {t for kind in NAVIGATION_TYPES for t in bag.topics_of_type(kind)}
    return tuple(t for t in bag.topics() if t not in skip and not t.startswith(cv.NAMESPACE + '/'))


def discover_signals(bag: MagneticBag) -> tuple[dict[str, Series], list[str]]:
    """The numeric signals of the bag's topics beyond the contract (channel name -> its
    series), and a line per topic or field left out (why)."""
    found: dict[str, Series] = {}
    notes: list[str] = []
    for topic in signal_topics(bag):
        first = _first_message(bag, topic)
        if first is None:
            notes.append(f'{topic}: not decoded (no message definition)')
            continue
        for path in numeric_fields(first):
            if len(found) >= MAX_SIGNALS:
                notes.append(f'{topic}#{path} and further fields: beyond {MAX_SIGNALS} signals')
                return found, notes
            try:
                series = read_signal(bag, topic, path)
            except BagError as error:  # a field only some messages have: a candidate less
                notes.append(f'{topic}#{path}: {error}')
                continue
            if series is None or len(series.stamps_ns) < 3:
                continue
            if np.ptp(series.values[:, 0]) == 0.0:
                notes.append(f'{topic}#{path}: constant on the run (no regressor)')
                continue
            found[f'{SIGNAL_PREFIX}{topic}#{path}'] = series
    return found, notes


def _first_message(bag: MagneticBag, topic: str) -> Any:
    connections = [c for c in bag.reader.connections if bag.topic_of(c.topic) == topic]
    for connection, _, raw in bag.reader.messages(connections):
        try:
            return bag.reader.deserialize(raw, connection.msgtype)
        except Exception:  # a damaged first message, an unknown type: the next one, or none
            continue
    return None
