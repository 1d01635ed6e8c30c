"""A recorded run as arrays: simulated missions into bags, and bags back into arrays.

``write_mission_bag`` writes a :class:`~tetra_gradiometer.core.MissionData` per the data
contract; ``read_recording`` reads a bag's matched sets with the optional topics
(``/odom``, ``/tetra/temperature``, ``/battery_state`` and any further BatteryState topic,
one per thruster say) interpolated onto the set stamps.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core import MissionData, SensorStream
from ..core.attitude import UNTESTED_ATTITUDE, attitude_verdict, world_frame_fault
from ..core.geometry import interp_orientation
from ..core.odometry import COSTS, OdometryCheck, check_odometry
from ..core.plausibility import DroppedSets, plausible_sets
from ..core.streams import StreamReport
from ..core.timebase import DEFAULT_TIMEBASE, TimeBase
from ..core.types import FloatArray
from ..core.units import NS_PER_S, S_PER_NS
from ..errors import BagError, InputError
from . import conversions as cv
from .bag import BagWriter, MagneticBag
from .channels import ChannelSeries
from .progress import progress_bar


def mission_stamps_ns(mission: MissionData, start_ns: int) -> np.ndarray:
    """Header stamps (N,) int64 ns of a mission starting at ``start_ns``."""
    return _stamps_ns(mission.t, start_ns, 'mission stamps')


def _stamps_ns(t_s: np.ndarray, start_ns: int, what: str) -> np.ndarray:
    """``start_ns + round(t_s 1e9)``, int64 ns; InputError if they do not increase."""
    stamps = start_ns + np.round(t_s * NS_PER_S).astype(np.int64)
    if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
        raise InputError(f'{what} must increase (sample period below 1 ns?)')
    return stamps


def write_mission_bag(
    path: str | os.PathLike,
    mission: MissionData,
    *,
    start_ns: int = 1_767_225_600 * NS_PER_S,
    storage: str = 'sqlite3',
    odom: bool = True,
    temperature: bool = True,
    battery: bool = True,
    progress: bool | None = None,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    command: str = '',
) -> Path:
    """Write the four magnetometers (and the optional topics) of ``mission`` to a bag.

    Without ``mission.streams`` the four sensors are written together at ``t``. With them
    (sensors on their own clocks) each ``/tetra/magN`` carries its sensor's stream, stamped
    ``start_ns + round(t 1e9)``, and all messages are logged in stamp order as a recorder
    would; the optional topics stay at sensor 1's instants ``t``.

    Parameters
    ----------
    path : target rosbag2 folder, written atomically; refused if it exists and is not a bag
        this package wrote (:class:`~tetra_gradiometer.io.bag.BagWriter`)
    mission : MissionData
    start_ns : header stamp of the first sample, ns (default 2026-01-01T00:00:00Z)
    storage : 'sqlite3' or 'mcap'
    odom, temperature, battery : write ``/odom``, ``/tetra/temperature``, the current
        channels (``/battery_state`` and each of ``mission.current_topics`` after it, one
        ``sensor_msgs/BatteryState`` per channel)
    progress : tqdm bar on stderr (None: only on a terminal and for long missions)
    force, inputs, command : as for :class:`~tetra_gradiometer.io.bag.BagWriter`

    Raises
    ------
    InputError
        If the stamps of ``t`` or of a stream do not increase once rounded to ns.
    """
    stamps = mission_stamps_ns(mission, start_ns)
    extras = _Extras(mission, odom, temperature, battery)
    with BagWriter(path, storage=storage, force=force, inputs=inputs, command=command) as writer:
        if mission.streams is None:
            bar = progress_bar(len(stamps) * 4, progress, 'writing bag')
            for i, stamp in enumerate(stamps):
                stamp = int(stamp)
                if i % 1000 == 999:
                    bar.update(4000)
                writer.write_sample(stamp, mission.fields_measured[i])
                extras.write(writer, i, stamp)
        else:
            bar = _write_streams(writer, mission.streams, stamps, start_ns, extras, progress)
    bar.close()
    return Path(path)


@dataclass(frozen=True)
class _Extras:
    """The optional topics of a mission: which to write, and how, at sample ``i``."""

    mission: MissionData
    odom: bool
    temperature: bool
    battery: bool

    def __bool__(self) -> bool:
        return self.odom or self.temperature or self.battery

    def write(self, writer: BagWriter, i: int, stamp: int) -> None:
        """Write the chosen optional topics of sample ``i`` at header and log stamp ``stamp``."""
        mission = self.mission
        if self.odom:
            writer.write_raw(
                cv.ODOM_TOPIC,
                cv.ODOMETRY,
                cv.odometry_cdr(mission.position_enu[i], mission.orientation_xyzw[i], stamp),
                stamp,
            )
        if self.temperature:
            writer.write_raw(
                cv.TEMPERATURE_TOPIC,
                cv.TEMPERATURE,
                cv.temperature_cdr(mission.temperature_c[i], stamp),
                stamp,
            )
        if self.battery:
            currents = [(cv.BATTERY_TOPIC, mission.current_a[i])] + [
                (topic, mission.currents_a[i, j])
                for j, topic in enumerate(mission.current_topics[1:], start=1)
            ]
            for topic, current in currents:
                writer.write_raw(
                    topic, cv.BATTERY_STATE, cv.battery_cdr(float(current), stamp), stamp
                )


def _write_streams(
    writer: BagWriter,
    streams: tuple[SensorStream, ...],
    stamps: np.ndarray,
    start_ns: int,
    extras: _Extras,
    progress: bool | None,
) -> Any:
    """Write each sensor's stream to its topic and the optional topics at ``stamps`` (ns),
    every message in stamp order (at equal stamps: sensor 1 to 4, then the optional topics).
    Returns the progress bar (still open)."""
    events: list[tuple[np.ndarray, int]] = []  # (stamps ns, source: sensor index or 4)
    for sensor, stream in enumerate(streams):
        stream_stamps = _stamps_ns(stream.t, start_ns, f'the stamps of sensor {sensor + 1}')
        events.append((stream_stamps, sensor))
    if extras:
        events.append((stamps, len(streams)))
    all_stamps = np.concatenate([e[0] for e in events])
    source = np.concatenate([np.full(len(e[0]), e[1]) for e in events])
    index = np.concatenate([np.arange(len(e[0])) for e in events])
    order = np.lexsort((source, all_stamps))
    bar = progress_bar(len(order), progress, 'writing bag')
    for count, (stamp, sensor, i) in enumerate(
        zip(all_stamps[order].tolist(), source[order].tolist(), index[order].tolist(), strict=True)
    ):
        if count % 4000 == 3999:
            bar.update(4000)
        if sensor == len(streams):
            extras.write(writer, i, stamp)
            continue
        field_t = streams[sensor].fields[i]
        message = cv.magnetic_field_cdr(field_t, stamp, cv.MAG_FRAMES[sensor])
        writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, message, stamp)
    return bar


@dataclass(frozen=True)
class Recording:
    """A bag's matched samples with the optional topics on the same stamps.

    Attributes
    ----------
    stamps_ns : (N,) int64, header stamps of sensor 1
    fields : (N, 4, 3) tesla, body frame
    orientation_xyzw : (N, 4) body -> ENU, or None without ``/odom``
    position_m : (N, 3) m, the body origin in the odom frame (ENU), or None without ``/odom``
    temperature_c : (N,) degC, or None without ``/tetra/temperature``
    current_a : (N,) A, or None without ``/battery_state``
    extra_currents : BatteryState topic -> (N,) A: every further current channel of the bag
        (one per thruster, say), by topic; a topic whose ``current`` is never known (NaN)
        is left out and named in ``missing``
    missing : topic -> why it is unavailable
    signals : ``signal:TOPIC#FIELD`` -> (N,) values: every further numeric signal the bag
        records (``discover``: :mod:`.discovery`), NaN where stale; ``signal_notes`` what
        was left out, and why
    dropped : sets dropped as implausible (:mod:`~tetra_gradiometer.core.plausibility`)
    skipped_messages : messages skipped as undecodable or unreadable (``MagneticBag.skipped``)
    streams : the magnetometer streams' faults (:mod:`~tetra_gradiometer.core.streams`)
    """

    stamps_ns: np.ndarray
    fields: np.ndarray
    orientation_xyzw: np.ndarray | None = None
    position_m: np.ndarray | None = None
    temperature_c: np.ndarray | None = None
    current_a: np.ndarray | None = None
    extra_currents: dict[str, np.ndarray] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    signals: dict[str, np.ndarray] = field(default_factory=dict)
    signal_notes: tuple[str, ...] = ()
    dropped: DroppedSets = field(default_factory=DroppedSets)
    skipped_messages: int = 0
    streams: StreamReport = field(default_factory=StreamReport)

    def input_counts(self) -> dict[str, int]:
        """What was not analysed, for reports: sets dropped by reason, messages skipped, sets
        lost to the streams' faults."""
        return {
            **self.dropped.as_dict(),
            'messages_skipped_undecodable': self.skipped_messages,
            'stream_faults': len(self.streams.faults),
            'sets_lost_stream_faults': self.streams.sets_lost,
        }

    @property
    def t_s(self) -> np.ndarray:
        """Seconds from the first sample, (N,)."""
        return (self.stamps_ns - self.stamps_ns[0]) * S_PER_NS

    def __len__(self) -> int:
        return len(self.stamps_ns)


def read_recording(
    path: str | os.PathLike,
    *,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    window_s: tuple[float, float] | None = None,
    progress: bool | None = None,
    uses: str = 'discrepancy',
    earth_field_enu: FloatArray | None = None,
    discover: bool = False,
) -> Recording:
    """Read a bag per the data contract into a :class:`Recording` (whole, in memory).

    Optional topics are interpolated onto the set stamps (slerp for orientation, linear for
    positions and scalars, held at the ends); an absent topic is named in ``missing``. Sets with an
    implausible reading are dropped and counted in ``dropped``. The streams are checked as
    they are read (against ``earth_field_enu`` (3,) T's norm; :mod:`~tetra_gradiometer.core.
    streams`) and ``/odom`` before it is used (:func:`odometry_at`, its world frame against
    ``earth_field_enu``; ``uses`` names the command, for what going without it costs): an
    unusable pose is left out and named in ``missing``.
    """
    with MagneticBag(path) as bag:
        earth_t = None if earth_field_enu is None else float(np.linalg.norm(earth_field_enu))
        stamps, fields = bag.read_sets(
            timebase=timebase, window_s=window_s, progress=progress, earth_field_t=earth_t
        )
        keep, dropped = plausible_sets(fields)
        if not keep.any():
            raise BagError(f'{path}: every set has an implausible reading ({dropped.text()})')
        stamps, fields = stamps[keep], fields[keep]
        odometry = odometry_at(bag, stamps, fields[:, 0], uses, earth_field_enu)
        extras: dict[str, np.ndarray | None] = {
            'orientation_xyzw': odometry.orientation_xyzw,
            'position_m': odometry.position_m,
        }
        missing: dict[str, str] = {}
        if odometry.orientation_xyzw is None or odometry.position_m is None:
            missing[cv.ODOM_TOPIC] = odometry.reason
        for name, topic in (
            ('temperature_c', cv.TEMPERATURE_TOPIC),
            ('current_a', cv.BATTERY_TOPIC),
        ):
            series = bag.read_series(topic)
            if series is None:
                extras[name] = None
                missing[topic] = bag.unread.get(topic, f'{topic} is not in the bag')
            else:
                extras[name] = np.interp(stamps, series.stamps_ns, series.values[:, 0])
        currents = _extra_currents(bag, stamps, missing)
        signals, signal_notes = _signals(bag, stamps) if discover else ({}, ())
        skipped, streams = bag.skipped_messages, bag.streams
    return Recording(
        stamps,
        fields,
        extra_currents=currents,
        missing=missing,
        signals=signals,
        signal_notes=signal_notes,
        dropped=dropped,
        skipped_messages=skipped,
        streams=streams,
        **extras,
    )


#: A discovered signal stale (NaN) on more than this share of the sets is left out: the
#: sets it would cost are more than it can explain.
MAX_STALE_SHARE = 0.05


def _signals(
    bag: MagneticBag, stamps: np.ndarray
) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """Every further numeric signal of the bag on ``stamps`` (:func:`.discovery.
    discover_signals`), and what was left out."""
    from .discovery import discover_signals

    found, notes = discover_signals(bag)
    out = {}
    for name, series in found.items():
        values = ChannelSeries(name, series.stamps_ns, series.values[:, 0]).on(stamps)
        stale = float(np.mean(~np.isfinite(values)))
        if stale > MAX_STALE_SHARE:
            notes.append(f'{name.removeprefix("signal:")}: stale on {stale:.0%} of the sets')
            continue
        out[name] = values
    return out, tuple(notes)


def _extra_currents(
    bag: MagneticBag, stamps: np.ndarray, missing: dict[str, str]
) -> dict[str, np.ndarray]:
    """Every BatteryState topic's current but ``/battery_state``'s on ``stamps`` (linear,
    held at the ends); a topic with no known current is named in ``missing`` instead."""
    out = {}
    for topic in bag.topics_of_type(cv.BATTERY_STATE):
        if topic == cv.BATTERY_TOPIC:
            continue
        series = bag.read_series(topic)
        known = None if series is None else np.isfinite(series.values[:, 0])
        if series is None or known is None or not known.any():
            missing[topic] = f'{topic} has no known current'
            continue
        out[topic] = np.interp(stamps, series.stamps_ns[known], series.values[known, 0])
    return out


@dataclass(frozen=True)
class Odometry:
    """``/odom`` on the set stamps, after its check (:mod:`~tetra_gradiometer.core.odometry`).

    Attributes
    ----------
    orientation_xyzw : (N, 4) body -> ENU, or None when absent or unusable
    position_m : (N, 3) m, ENU, or None when absent or unusable
    notes : what was found and what going without it costs, one line each
    check : the checked messages (None without ``/odom``)
    """

    orientation_xyzw: FloatArray | None
    position_m: FloatArray | None
    notes: tuple[str, ...] = ()
    check: OdometryCheck | None = None

    @property
    def reason(self) -> str:
        """Why the pose (or part of it) is not used, for ``Recording.missing``."""
        return '; '.join(self.notes) or f'{cv.ODOM_TOPIC} is not in the bag'


def odometry_at(
    bag: MagneticBag,
    stamps_ns: np.ndarray,
    body_field_t: FloatArray | None,
    command: str,
    earth_field_enu: FloatArray | None = None,
) -> Odometry:
    """``/odom``'s pose on ``stamps_ns`` (N,) ns, checked: zero-norm quaternions dropped,
    unnormalized ones normalized, a frozen orientation or position left out, and the
    orientation tested against ``body_field_t`` (N, 3) T, sensor 1's field (None: not
    tested; :func:`~tetra_gradiometer.core.attitude.attitude_verdict`: another convention, a
    lag or a clock that fits is named) and, with ``earth_field_enu`` (3,) T, its world
    frame against the Earth field's direction. ``command`` names what going without costs
    (``core.odometry.COSTS``)."""
    series = bag.read_series(cv.ODOM_TOPIC)
    cost = COSTS.get(command, '')
    if series is None:
        absent = bag.unread.get(cv.ODOM_TOPIC, f'no {cv.ODOM_TOPIC} in the bag')
        return Odometry(None, None, (f'{absent}: {cost}',))
    check = check_odometry(series.stamps_ns, series.values)
    notes = list(check.faults)
    orientation = position = None
    if check.orientation_ok:
        quats = check.pose[:, cv.POSE_ORIENTATION]
        orientation = interp_orientation(check.stamps_ns, quats, stamps_ns)
        if body_field_t is not None:
            verdict = attitude_verdict(check.stamps_ns, quats, stamps_ns, body_field_t)
            fault = verdict.fault()
            if not verdict.tested:
                notes.append(UNTESTED_ATTITUDE)
            elif fault is None and earth_field_enu is not None and verdict.world_field is not None:
                fault = world_frame_fault(verdict.world_field, earth_field_enu)
            if fault is not None:
                notes.append(fault)
                orientation = None
    if check.position_ok:
        position = np.stack(
            [np.interp(stamps_ns, check.stamps_ns, c) for c in check.pose[:, cv.POSE_POSITION].T],
            axis=1,
        )
    if orientation is None or position is None:
        unused = ' and '.join(
            what
            for what, value in (('orientation', orientation), ('position', position))
            if value is None
        )
        notes.append(f'{cv.ODOM_TOPIC} {unused} not used: {cost}')
    return Odometry(orientation, position, tuple(notes), check)
