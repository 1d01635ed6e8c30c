"""The driver's frame sources: a recorded rosbag2 folder or a simulated mission, as timed
frames of messages ready to publish (built with a :class:`~.conversions.MessageTypes`).

* :func:`iter_frames` replays a bag: one frame per recorded message (the magnetometers, and
  ``/tetra/gradient/truth`` and ``/odom`` when recorded, and the channels of the vehicle
  effects: ``/tetra/temperature`` and every ``sensor_msgs/BatteryState`` topic, as
  ``calibrate`` reads them), with its recorded header stamp, paced by log time. Messages of
  one log time go channels first: a simulated bag records a set's temperature and currents
  at the set's own instant, and the live compensator takes a channel's value from the
  messages it has when the set arrives (nodes/channels.py), as a vehicle's channel measured
  at that instant would be there before the set has gone through the tensor node. It opens
  the bag's other topics, where the vehicle's own signals are (``io/discovery.signal_topics``:
  fin angles, a power board's currents), are played as recorded (serialized, any type whose
  package is installed), as ``ros2 bag play`` would. The driver opens
  the bag in a ``with`` block, so closing the generator (or exhausting it) closes the bag.
  A message that does not decode and an unreadable storage chunk are skipped (as
  :meth:`~.bag.MagneticBag.iter_sets` does), counted and logged.
  A magnetometer message keeps its recorded ``magnetic_field_covariance`` when that is
  known (``conversions.known_covariance``: finite, not REP 145's -1, not all zero);
  otherwise it gets ``diag(sensor_noise_t^2)`` (REP 145's unknown, -1 first, when
  ``sensor_noise_t`` is 0).
* :func:`simulate` runs the core mission simulator on a scenario and returns the frames of
  its samples (four magnetometers, the true gradient, odometry), paced by sample time; the
  magnetometers' covariance is ``diag(noise^2)`` of the scenario's sensor noise.

Nothing here imports rclpy: the caller passes the message classes.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Generator, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .._optional import require
from ..core import MissionData
from ..core.units import NS_PER_S, S_PER_NS
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..io.bag_decode import checked_stamp_ns, skip_reason
from ..io.bag_skips import SkippedMessage, guarded_messages
from ..io.bag_skips import summary as bag_summary

LOG = logging.getLogger(__name__)

if TYPE_CHECKING:
    from ..io.bag import MagneticBag

#: Publisher keys of a frame's messages: magnetometer ``sensor`` 0..3, truth, odometry, a
#: vehicle effect's channel (``sensor``: its index in :func:`channel_topics`) and a recorded
#: signal's topic (its index in :func:`signal_topics`; the message stays serialized).
MAG, TRUTH, ODOM, CHANNEL, SIGNAL = 'mag', 'truth', 'odom', 'channel', 'signal'

#: Replayed topics -> (key, sensor).
REPLAY_TOPICS: dict[str, tuple[str, int]] = {
    **{topic: (MAG, i) for i, topic in enumerate(cv.BAG_MAG_TOPICS)},
    f'{cv.NAMESPACE}/gradient/truth': (TRUTH, 0),
    cv.ODOM_TOPIC: (ODOM, 0),
}


@dataclass
class Frame:
    """Messages to publish together.

    Attributes
    ----------
    pace_ns : int
        Time of the frame relative to the first one, ns (sample time or log time).
    clock_ns : int
        The frame's absolute time, ns (the log time in replay, the sample stamp in sim): what
        the driver publishes on ``/clock``.
    segment : int
        Scenario segment (sim) or 0 (replay).
    mag1_stamp : int or None
        Header stamp (ns) of magnetometer 1 when the frame holds its reading: one set.
    items : list of (key, sensor, message)
        ``key`` is :data:`MAG`, :data:`TRUTH`, :data:`ODOM` or :data:`CHANNEL`.
    """

    pace_ns: int
    clock_ns: int
    segment: int
    mag1_stamp: int | None
    items: list[tuple[str, int, Any]]


# --------------------------------------------------------------------------- replay


def describe_bag(
    path: str | os.PathLike, remap: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """Check a bag's contract and describe it: ``messages`` (magnetometer messages),
    ``topics`` (the replayed topics present, comma separated, as recorded), ``channels``
    (the channel topics replayed, :func:`channel_topics`, comma separated, as published) and
    ``signals`` (:func:`signal_topics`: ``(topic, message type)`` pairs).

    ``remap``: the bag's topic -> the contract's (``conversions.parse_remap``).

    Raises
    ------
    BagError
        The bag cannot be opened, lacks a magnetometer topic or holds no messages.
    """
    with _open_bag(path, remap) as bag:
        count = bag.check_contract()
        replayed = _replayed(bag)
        topics = sorted(
            {c.topic for c in bag.reader.connections if bag.topic_of(c.topic) in replayed}
        )
        channels = channel_topics(bag)
        signals = signal_topics(bag)
    return {
        'messages': count,
        'topics': ', '.join(topics),
        'channels': ', '.join(channels),
        'signals': signals,
    }


def channel_topics(bag: MagneticBag) -> tuple[str, ...]:
    """The channel topics of ``bag`` the driver replays, as the contract names them (after
    ``remap``): ``/tetra/temperature`` when it holds ``sensor_msgs/Temperature``, then every
    ``sensor_msgs/BatteryState`` topic (``/battery_state``, a thruster's: ``calibrate`` reads
    them all), sorted."""
    temperature = cv.TEMPERATURE_TOPIC in bag.topics_of_type(cv.TEMPERATURE)
    return (cv.TEMPERATURE_TOPIC,) * temperature + bag.topics_of_type(cv.BATTERY_STATE)


def signal_topics(bag: MagneticBag) -> tuple[tuple[str, str], ...]:
    """The bag's topics where a vehicle signal may be (``io/discovery.signal_topics``), each
    with its message type (``package/msg/Name``), sorted."""
    from ..io.discovery import signal_topics as topics

    recorded = {bag.topic_of(c.topic): c.msgtype for c in bag.reader.connections}
    return tuple((topic, recorded[topic]) for topic in topics(bag))


def _replayed(bag: MagneticBag) -> dict[str, tuple[str, int]]:
    """Replayed topic (the contract's name) -> (key, sensor): :data:`REPLAY_TOPICS`, the
    bag's channels and its signal topics."""
    channels = {topic: (CHANNEL, i) for i, topic in enumerate(channel_topics(bag))}
    signals = {topic: (SIGNAL, i) for i, (topic, _) in enumerate(signal_topics(bag))}
    return {**REPLAY_TOPICS, **channels, **signals}


def iter_frames(
    path: str | os.PathLike,
    types: cv.MessageTypes,
    *,
    max_duration_s: float = 0.0,
    sensor_noise_t: float = 0.0,
    skipped: list[SkippedMessage] | None = None,
    remap: Mapping[str, str] | None = None,
) -> Generator[Frame, None, None]:
    """Yield one frame per recorded message of :data:`REPLAY_TOPICS`, of the bag's channels
    (:func:`channel_topics`) and of its signal topics (:func:`signal_topics`, serialized), in
    log-time order (channels and signals first within one log time).

    Parameters
    ----------
    path : rosbag2 folder (sqlite3 or mcap)
    types : the message classes to build (``conversions.rclpy_types()`` for a node)
    max_duration_s : stop after this much log time, s (0: the whole bag)
    sensor_noise_t : per-axis sensor noise, tesla RMS, for magnetometer messages recorded
        without a covariance (unknown, all zero or non-finite); 0 marks them unknown (-1)
    skipped : if given, receives the skipped messages and chunks as they happen (they are
        also logged: the first few one by one, the count when the replay ends)
    remap : the bag's topic -> the contract's, for a bag recorded under other names

    Raises
    ------
    BagError
        As :func:`describe_bag`, on the first ``next()``.
    """
    with _open_bag(path, remap) as bag:
        bag.check_contract()
        reader = bag.reader
        replayed = _replayed(bag)
        connections = [c for c in reader.connections if bag.topic_of(c.topic) in replayed]

        def on_skip(record: SkippedMessage) -> None:
            bag.record_skip(record)
            if skipped is not None:
                skipped.append(record)
            if len(bag.skipped) <= 3:
                LOG.warning('replay of %s skips %s', path, summary_of([record]))

        def summary_of(records: list[SkippedMessage]) -> str:
            return bag_summary(records, reader.start_time)

        first = None
        default_covariance = cv.noise_covariance(sensor_noise_t)
        held: list[Frame] = []  # the frames of one log time, yielded channels first
        try:
            for connection, log_ns, raw in guarded_messages(reader, connections, on_skip):
                try:
                    topic = bag.topic_of(connection.topic)
                    key, sensor = replayed[topic]
                    log_ns = int(log_ns)
                    if key == SIGNAL:  # as recorded: any type, a stamp or none
                        stamp, frame_msg = log_ns, bytes(raw)
                    else:
                        msg: Any = reader.deserialize(raw, connection.msgtype)
                        stamp = checked_stamp_ns(msg.header.stamp)
                        frame_msg = _rebuild(
                            types, key, (msg, connection.msgtype), stamp, default_covariance, topic
                        )
                except Exception as error:  # a malformed message costs itself
                    on_skip(SkippedMessage(connection.topic, log_ns, skip_reason(error)))
                    continue
                first = log_ns if first is None else first
                if max_duration_s > 0 and (log_ns - first) * S_PER_NS > max_duration_s:
                    break
                if held and held[0].clock_ns != log_ns:
                    yield from _channels_first(held)
                    held = []
                mag1 = stamp if (key == MAG and sensor == 0) else None
                held.append(Frame(log_ns - first, log_ns, 0, mag1, [(key, sensor, frame_msg)]))
            yield from _channels_first(held)
        finally:
            if bag.skipped:
                LOG.warning('replay of %s: %s', path, bag.skipped_summary())


def _channels_first(frames: list[Frame]) -> list[Frame]:
    """``frames`` of one log time with the channels' and signals' first (else in recorded
    order)."""
    return sorted(frames, key=lambda frame: frame.items[0][0] not in (CHANNEL, SIGNAL))


def _rebuild(
    types: cv.MessageTypes,
    key: str,
    recorded: tuple[Any, str],
    stamp: int,
    default_covariance: np.ndarray,
    topic: str,
) -> Any:
    """A recorded (rosbags) message and its type as one of ``types``: a tensor (a
    GradientTensor, or the JointState of older recordings) as a GradientTensor; a
    magnetometer without a usable recorded covariance gets ``default_covariance`` (9,) T^2.
    A channel keeps what the
    effects read: a temperature (degC, its variance) or a BatteryState's ``current`` (A; the
    rest unknown, NaN), with the recorded stamp and frame."""
    msg, msgtype = recorded
    if key == MAG:
        covariance = cv.magnetic_field_covariance(msg)
        if not cv.known_covariance(covariance):
            covariance = default_covariance
        return cv.magnetic_field_msg(
            types, cv.magnetic_field_vector(msg), stamp, msg.header.frame_id, covariance
        )
    if key == TRUTH:
        tensor = gt.tensor_set_from_msg(msg, msgtype)
        return gt.gradient_tensor_msg(types, replace(tensor, stamp_ns=stamp))
    if key == CHANNEL:
        if topic == cv.TEMPERATURE_TOPIC:
            out = cv.temperature_msg(types, msg.temperature, stamp, msg.header.frame_id)
            out.variance = float(msg.variance)
            return out
        out = cv.battery_msg(types, msg.current, stamp)
        out.header.frame_id = msg.header.frame_id
        return out
    p = msg.pose.pose.position
    return cv.odometry_msg(
        types,
        np.array([p.x, p.y, p.z]),
        cv.odometry_orientation(msg),
        stamp,
        frame_id=msg.header.frame_id,
        child_frame_id=msg.child_frame_id,
    )


# --------------------------------------------------------------------------- simulator


def simulate(
    scenario_path: str,
    seed: int,
    types: cv.MessageTypes,
    *,
    start_ns: int,
    max_duration_s: float = 0.0,
    frame_ids: FrameIds | None = None,
) -> tuple[Generator[Frame, None, None], dict[str, Any]]:
    """Simulate a mission and return its frames and a description.

    Parameters
    ----------
    scenario_path : scenario YAML (io/scenario.py); '' = the built-in default
    seed : noise seed; -1 = the scenario's own
    types : the message classes to build
    start_ns : header stamp of the first sample, ns (stamps are ``start_ns`` + sample time)
    max_duration_s : keep the samples before this sample time, s (0: all)
    frame_ids : the messages' frame ids (default :class:`FrameIds`: REP 105 names)

    Returns
    -------
    frames : one frame per sample: the four magnetometers (T), the true gradient (T/m)
        and odometry, paced by sample time
    info : ``samples``, ``segments`` (segment kinds), ``sample_rate_hz``, ``dipoles``,
        ``sensor_noise_t`` (the scenario's per-axis noise, T), ``sensor_positions`` (the
        scenario's array, flat (12,), m)
    """
    from ..core import simulate as simulate_mission
    from ..io.scenario import load_scenario_or_default

    scenario, scenario_seed = load_scenario_or_default(scenario_path)
    mission = simulate_mission(
        scenario, np.random.default_rng(scenario_seed if seed < 0 else seed)
    )
    n = len(mission)
    if max_duration_s > 0:
        n = int(np.searchsorted(mission.t, max_duration_s, side='left'))
    info = {
        'samples': n,
        'segments': ', '.join(type(s).__name__ for s in scenario.segments),
        'sample_rate_hz': scenario.sample_rate_hz,
        'dipoles': len(scenario.dipoles),
        'sensor_noise_t': float(scenario.noise_t),
        'sensor_positions': scenario.geometry.to_flat(),
    }
    covariance = cv.noise_covariance(scenario.noise_t)
    frames = _mission_frames(mission, n, types, start_ns, covariance, frame_ids or FrameIds())
    return frames, info


@dataclass(frozen=True)
class FrameIds:
    """Frame ids of the simulated messages (REP 105; the driver's frame-id parameters)."""

    odom: str = cv.ODOM_FRAME
    base: str = cv.BASE_FRAME
    sensors: tuple[str, ...] = cv.MAG_FRAMES


def _mission_frames(
    mission: MissionData,
    n: int,
    types: cv.MessageTypes,
    start_ns: int,
    covariance: np.ndarray,
    frame_ids: FrameIds,
) -> Generator[Frame, None, None]:
    sensors = frame_ids.sensors
    for i in range(n):
        pace = int(round(mission.t[i] * NS_PER_S))
        stamp = start_ns + pace
        fields = mission.fields_measured[i]
        items: list[tuple[str, int, Any]] = [
            (MAG, s, cv.magnetic_field_msg(types, fields[s], stamp, sensors[s], covariance))
            for s in range(4)
        ]
        truth = gt.TensorSet(stamp, mission.g_true[i])
        items.append((TRUTH, 0, gt.gradient_tensor_msg(types, truth)))
        odom = cv.odometry_msg(
            types,
            mission.position_enu[i],
            mission.orientation_xyzw[i],
            stamp,
            frame_id=frame_ids.odom,
            child_frame_id=frame_ids.base,
        )
        items.append((ODOM, 0, odom))
        yield Frame(pace, stamp, int(mission.segment[i]), stamp, items)


def _open_bag(path: str | os.PathLike[str], remap: Mapping[str, str] | None) -> MagneticBag:
    """The bag at ``path`` (io/bag.py), imported only here: ``rosbags`` is an offline-only
    package, and a driver in ``sim`` mode on a rosdep install must start without it."""
    require('rosbags', 'replaying a bag (driver mode replay)')
    from ..io.bag import MagneticBag

    return MagneticBag(path, remap=remap)
