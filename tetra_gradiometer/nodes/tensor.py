"""``tensor`` node: the four magnetometers -> the measured gradient tensor ``G_m`` (eq. 7).

Subscribes ``mag1``..``mag4`` (sensor_msgs/MagneticField, T, sensor-data QoS) and forms
sets as the offline tools do: by default each sensor is resampled to sensor 1's stamps
(:class:`~tetra_gradiometer.core.timebase.Resampler`, ``sync: interpolate``; a set leaves
when every sensor has a sample at or after its instant: the added latency is the wait for
the latest sensor's next sample, up to one sample period, one more per message of it lost),
or stamps are paired within ``stamp_tolerance_s`` (``sync: nearest``,
:class:`~tetra_gradiometer.io.matching.StampMatcher`). It drops and counts incomplete
sets and sets with a non-finite or implausible reading (``|B| > max_field_t`` on any
sensor), and publishes, for every good set, ``gradient/raw``
(tetra_gradiometer_msgs/GradientTensor, reliable, stamped with the set's reference instant,
state RAW): ``G_m`` (T/m); its 1-sigma (T/m) from the four readings' covariances through the
geometry (core/uncertainty.readings_sigma), NaN unless all four are known; and ``B_1'``, the
reference reading of the same set (T), with that ``mag1`` reading's covariance (T^2; 0 when
unknown or non-finite).

``/diagnostics``: per sensor rate (Hz), staleness (s since its last message; both on the
node's clock, so ``/clock`` under ``use_sim_time``: a replay at any rate gives the bag's), invalid
readings, clock offset and jitter against the reference (resampling); a sensor silent for
``stale_timeout_s`` is ERROR and no tensor is published until it is back.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict
from functools import partial
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import MagneticField

from ..core import TetraGeometry, difference_tensor
from ..core.live_streams import LiveStreamCheck
from ..core.plausibility import MAX_FIELD_T, plausible_readings
from ..core.timebase import SYNC_METHODS, Resampler, TimeBase
from ..core.uncertainty import noise_jacobian, readings_sigma
from ..core.units import NS_PER_S, S_PER_NS
from ..errors import MessageError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..io.matching import StampMatcher
from .common import (
    ARRAY_FRAME_SPEC,
    ERROR,
    OK,
    POSITIONS_SPEC,
    WARN,
    WARN_THROTTLE_SPEC,
    ParamSpec,
    Throttle,
    check_serialization,
    derived_qos,
    diagnostics_period_spec,
    one_of,
    positive,
    sensor_qos,
    status,
)
from .managed import ManagedNode
from .process import spin_node
from .stamps import AHEAD_SPEC

PARAMETERS = [
    POSITIONS_SPEC,
    ParamSpec(
        'sync',
        'interpolate',
        "How sets are formed: 'interpolate' resamples each sensor to the reference instants "
        "(sensors on their own clocks, stamps = sample times); 'nearest' pairs stamps within "
        'stamp_tolerance_s (sensors sampled together, stamps = arrival times).',
        one_of(*SYNC_METHODS),
    ),
    ParamSpec(
        'reference_rate_hz',
        0.0,
        "Reference instants (interpolate): 0 = sensor 1's stamps; > 0 = a regular grid at "
        'this rate, Hz (0-10000).',
        float_range=(0.0, 10_000.0),
    ),
    ParamSpec(
        'max_gap_periods',
        3.0,
        "Never interpolate across a gap longer than this many of the sensor's sample periods "
        '(1-1000); such sets are skipped and counted.',
        float_range=(1.0, 1000.0),
    ),
    ParamSpec(
        'stamp_tolerance_s',
        2e-3,
        'sync nearest: largest spread of the four header stamps within one set, s (1e-6-1: '
        'it must stay below half the sample period, else neighbouring sets merge).',
        positive,
        float_range=(1e-6, 1.0),
    ),
    ParamSpec(
        'max_field_t',
        MAX_FIELD_T,
        'A reading with |B| above this (tesla) is implausible: its set is dropped. From 1e-4 '
        "(the Earth's field reaches 6.7e-5 T) to core/plausibility's 1e-3 T (the offline tools' "
        'bound).',
        positive,
        float_range=(1e-4, MAX_FIELD_T),
    ),
    ParamSpec(
        'stale_timeout_s',
        1.0,
        "A sensor silent this long (s, the node's clock: /clock under use_sim_time) is ERROR on "
        '/diagnostics and no tensor is published until it returns (0.01-600).',
        positive,
        float_range=(0.01, 600.0),
    ),
    ParamSpec(
        'sensor_queue_depth',
        50,
        'Depth of the magnetometer subscriptions (best effort), messages (at most 10000, '
        '50 s at 200 sets/s).',
        int_range=(1, 10000),
    ),
    ParamSpec(
        'max_pending',
        1000,
        'Per-sensor bound of the stamp matcher queue (nearest), or of the reference instants '
        'waiting for a silent sensor (interpolate), messages (at most 100000, 8 min at '
        '200 sets/s: a longer silence is a stale sensor, not a delay).',
        int_range=(1, 100_000),
    ),
    ParamSpec(
        'jump_back_s',
        1.0,
        "A stamp this much older than its sensor's previous one (s) means the "
        'source restarted (e.g. a new replay): the matcher is reset instead of dropping '
        'everything as out of order (0.01-86400: shorter resets on ordinary jitter).',
        positive,
        float_range=(0.01, 86400.0),
    ),
    ARRAY_FRAME_SPEC,
    WARN_THROTTLE_SPEC,
    AHEAD_SPEC,
    diagnostics_period_spec(),
]


#: The set former's counters (io/matching.MatchCounters, core/timebase.ResampleCounters)
#: -> their /diagnostics keys. A counter not named here is reported as ``matcher_<name>``.
MATCHER_KEYS = {
    'matched': 'sets_matched',
    'dropped_messages': 'messages_dropped_unmatched',
    'evicted_messages': 'messages_evicted',
    'out_of_order': 'messages_out_of_order',
    'sets': 'sets_matched',
    'skipped_gap': 'sets_skipped_gap',
    'skipped_start': 'sets_skipped_start',
    'evicted': 'sets_evicted',
    'skipped_end': 'sets_skipped_end',
}


class TensorNode(ManagedNode):
    """Forms sets of the four magnetometers and publishes ``G_m`` with ``B_1'``."""

    PARAMETERS = PARAMETERS
    DYNAMIC = LOCKED = ('max_field_t', 'stale_timeout_s')

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('tensor', **kwargs)

    def configure(self, p: dict[str, Any]) -> None:
        """The set former, publishers and subscriptions from the parameters ``p``."""
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        self._max_field = float(p['max_field_t'])
        self._array_frame = p['array_frame_id']
        self._jacobian = noise_jacobian(self._geometry)
        self._sigma_of: tuple[bytes, np.ndarray] = (b'', gt.UNKNOWN_SIGMA)  # covariances, sigma
        self._stale_timeout = float(p['stale_timeout_s'])
        self._timebase = TimeBase(
            sync=p['sync'],
            reference_rate_hz=p['reference_rate_hz'],
            max_gap_periods=p['max_gap_periods'],
            tolerance_s=p['stamp_tolerance_s'],
        )
        self._max_pending = int(p['max_pending'])
        self._jump_back_ns = int(round(p['jump_back_s'] * NS_PER_S))
        self._matcher = self._new_former()
        # Stamps and units, before the set former; messages lost in shorter gaps than a
        # silence (stale) are counted.
        self._streams = LiveStreamCheck(silence_s=self._stale_timeout)
        self._missing_mark = [0] * 4  # the missing counts at the previous diagnostics
        self._earlier: dict[str, int] = {}  # counts of the matchers reset before
        self._last_stamp: list[int | None] = [None] * 4
        self.resets = 0
        self._warn = Throttle(p['warn_throttle_s'])
        self._stale_warn = Throttle(p['warn_throttle_s'])

        started = self._now_s()
        self._received = [0] * 4
        self._invalid = [0] * 4
        self._last_arrival = [started] * 4
        self._ever = [False] * 4
        self._stamped = [0] * 4  # readings whose stamps set the rate
        self._rate = [0.0] * 4
        self._rate_mark: list[tuple[int | None, int]] = [(None, 0)] * 4
        self.sets_published = 0
        self.sets_invalid = 0

        check_serialization()
        self._raw_cdr = gt.GradientTensorCdr(self._array_frame)
        self._raw_pub = self.create_lifecycle_publisher(
            gt.rclpy_class(), 'gradient/raw', derived_qos()
        )
        self._diag_pub = self.diagnostics_publisher()
        self._horizon = self._diag_pub.inputs.watch_stamps(
            p['max_stamp_ahead_s'], p['warn_throttle_s']
        )
        qos = sensor_qos(p['sensor_queue_depth'])
        self._subs = [
            self.create_subscription(
                MagneticField, topic, self.when_active(partial(self._on_mag, i)), qos, raw=True
            )
            for i, topic in enumerate(cv.MAG_TOPICS)
        ]
        self._diag_timer = self.create_diagnostics_timer(
            p['diagnostics_period_s'], self._publish_diagnostics
        )
        self.get_logger().info(
            f'sets of {", ".join(cv.MAG_TOPICS)}: {self._timebase.text}; '
            f'array condition number {self._geometry.condition_number:.3g}'
        )

    def activated(self) -> None:
        """Staleness counts from the activation, not from the time spent inactive."""
        self._last_arrival = [self._now_s()] * 4

    # ----------------------------------------------------------------- callbacks

    def _on_mag(self, sensor: int, data: bytes) -> None:
        """One serialized MagneticField (T): queue its reading; publish every set it completes.
        (Serialized: io/conversions reads the bytes, no message object per reading.)"""
        self._received[sensor] += 1
        now_ns = self._now_ns()  # one clock read per message: 10 us each, a set reads 4
        self._last_arrival[sensor] = now_ns * S_PER_NS
        self._ever[sensor] = True
        try:
            # Each reading's covariance travels with its field (12 values) into its set's
            # g_sigma and reference_field_covariance (interpolated on a grid reference).
            stamp, _, reading = cv.magnetic_field_from_cdr(data)
        except MessageError as error:
            self._invalid[sensor] += 1
            if self._warn():
                self.get_logger().warning(f'dropped a malformed {cv.MAG_TOPICS[sensor]}: {error}')
            return
        if self._horizon.refuse(cv.MAG_TOPICS[sensor], stamp):  # never into the set former
            return
        if not self._streams.accept(sensor, stamp, now_ns, *reading[:3].tolist()):
            if self._warn():
                self.get_logger().warning(
                    f'dropped a {cv.MAG_TOPICS[sensor]} reading: {self._stream_text(sensor)}'
                )
            return  # before the restart test: one sensor off the others is no restart
        last = self._last_stamp[sensor]
        if last is not None and stamp < last - self._jump_back_ns:
            self._reset_matcher(sensor, last - stamp)
        self._last_stamp[sensor] = stamp
        self._stamped[sensor] += 1
        sets: Iterable[tuple[int, np.ndarray]]
        if isinstance(self._matcher, Resampler):
            stamps, values = self._matcher.add_one(sensor, stamp, reading)
            sets = zip(stamps.tolist(), values, strict=True)
        else:
            sets = self._matcher.add(sensor, stamp, reading)
        for stamp_ns, readings in sets:
            self._emit(stamp_ns, readings[:, :3], readings[:, 3:])

    def _new_former(self) -> Resampler | StampMatcher:
        """The set former the parameters ask for, empty."""
        if self._timebase.sync == 'nearest':
            tolerance_ns = int(round(self._timebase.tolerance_s * NS_PER_S))
            return StampMatcher(tolerance_ns, max_pending=self._max_pending)
        return Resampler(
            self._timebase, width=12, max_pending=self._max_pending, max_field_t=self._max_field
        )

    def _reset_matcher(self, sensor: int, jump_ns: int) -> None:
        """The source went back in time (a new replay): start matching afresh."""
        self._earlier = self._matcher_counts()
        self._matcher = self._new_former()
        self._last_stamp = [None] * 4
        self._streams.reset()
        self.resets += 1
        self.get_logger().warning(
            f'{cv.MAG_TOPICS[sensor]} jumped back {jump_ns * S_PER_NS:.3g} s in time: '
            f'set forming restarted'
        )

    def _matcher_counts(self) -> dict[str, int]:
        """The stamp matcher's counters, including those of the matchers reset before."""
        counters = {  # the integer counts (the stream report is the offline reads')
            key: value
            for key, value in asdict(self._matcher.counters).items()
            if isinstance(value, int)
        }
        return {key: value + self._earlier.get(key, 0) for key, value in counters.items()}

    def _emit(self, stamp_ns: int, fields: np.ndarray, covariances: np.ndarray) -> None:
        """Check one matched set (4, 3) T and publish ``G_m`` (T/m) with its 1-sigma and
        ``B_1'`` (T), from the readings' covariances (4, 9) T^2. A formed set holds a reading
        of every sensor at its stamp, so none of them is silent there: a silent sensor forms
        no set (and is ERROR on /diagnostics), and the arrival times of a set's readings say
        only how busy this node is: they judge no set."""
        bad = ~plausible_readings(fields, self._max_field)  # the offline tools' rule
        if bad.any():
            self.sets_invalid += 1
            for sensor in np.flatnonzero(bad):
                self._invalid[sensor] += 1
            if self._warn():
                names = [cv.MAG_TOPICS[s] for s in np.flatnonzero(bad)]
                self.get_logger().warning(
                    f'dropped a set at stamp {stamp_ns} ns: non-finite or '
                    f'|B| > {self._max_field:g} T on {", ".join(names)} '
                    f'({self.sets_invalid} sets dropped so far)'
                )
            return
        g = difference_tensor(fields[None], self._geometry)[0]
        if not np.all(np.isfinite(g)):  # cannot happen for finite fields; never publish non-finite
            self.sets_invalid += 1
            return
        reference = (
            covariances[0] if cv.known_covariance(covariances[0]) else gt.UNKNOWN_COVARIANCE
        )
        values = np.concatenate((g.reshape(9), self._sigma(covariances), fields[0], reference))
        self._raw_pub.publish(self._raw_cdr.write(stamp_ns, values))
        self.sets_published += 1

    def _sigma(self, covariances: np.ndarray) -> np.ndarray:
        """The tensor's 1-sigma (9,) T/m from the four covariances (4, 9) T^2; NaN unless
        all four are known. (The covariances seldom change: the last result is kept.)"""
        key = covariances.tobytes()
        if key != self._sigma_of[0]:
            known = all(cv.known_covariance(c) for c in covariances)
            sigma = readings_sigma(self._jacobian, covariances) if known else gt.UNKNOWN_SIGMA
            self._sigma_of = (key, sigma if np.all(np.isfinite(sigma)) else gt.UNKNOWN_SIGMA)
        return self._sigma_of[1]

    def _now_ns(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    def _stream_text(self, sensor: int, with_missing: bool = False) -> str:
        """The sensor's stream faults (core/live_streams.LiveStreamCheck), '' when none;
        ``with_missing``: the messages lost before the node too."""
        counts = self._streams.dropped[sensor]
        what = {
            'zero_stamp': 'with header stamp 0',
            'other_clock': "stamped off the other sensors' clock (another epoch, a jump)",
            'duplicate_stamp': 'repeating a stamp with another reading',
        }
        parts = [f'{n} {what[kind]}' for kind, n in counts.items() if n]
        notes = [
            self._streams.magnitude_text(sensor),
            self._streams.missing_text(sensor, self._received[sensor]) if with_missing else '',
        ]
        dropped = [f'dropped {", ".join(parts)}'] if parts else []
        return '; '.join(dropped + [note for note in notes if note])

    def _now_s(self) -> float:
        """The node's clock, s: ROS time, i.e. ``/clock`` under ``use_sim_time`` (a replay at
        10x real time, or paused, shows the bag's rates and staleness, not the wall clock's)."""
        return self.get_clock().now().nanoseconds * S_PER_NS

    def _stale_sensors(self, now: float | None = None) -> list[int]:
        """The sensors silent beyond ``stale_timeout_s`` at ``now`` (s, default: the clock)."""
        now = self._now_s() if now is None else now
        return [s for s in range(4) if now - self._last_arrival[s] > self._stale_timeout]

    def _update_rates(self) -> None:
        """Each sensor's rate since the previous diagnostics, Hz, on its readings' own stamps:
        the readings accepted over the span of their stamps. (On arrival times a loaded
        executor, or ``/clock`` landing between the data, gives half or twice the rate.)"""
        for s, (mark_stamp, mark_count) in enumerate(self._rate_mark):
            last, count = self._last_stamp[s], self._stamped[s]
            if last is not None and mark_stamp is not None and last > mark_stamp:
                self._rate[s] = (count - mark_count) * NS_PER_S / (last - mark_stamp)
            elif count == mark_count:
                self._rate[s] = 0.0
            self._rate_mark[s] = (last, count)

    def _sensor_status(
        self, s: int, now: float, stale: bool, clocks: dict[str, float], recent_missing: int
    ) -> Any:
        """One sensor's DiagnosticStatus: stale (ERROR), dropped readings or a stream fault
        (WARN: core/live_streams.LiveStreamCheck), else OK."""
        staleness = now - self._last_arrival[s]
        # Lost messages warn while being lost (the count stays in the values).
        invalid, streams = self._invalid[s], self._stream_text(s, bool(recent_missing))
        if stale:
            # The resolved name (after remapping) and who publishes there: a remap to a topic
            # nobody publishes is named, not only its silence.
            topic = self._subs[s].topic_name
            level, text = ERROR, f'no data received on {topic}'
            if not self._ever[s]:
                text += f' ({self.count_publishers(topic)} publishers)'
            else:
                text = f'stale: silent for {staleness:.2f} s (> {self._stale_timeout:g} s)'
        elif invalid or streams:
            level = WARN
            readings = f'{invalid} non-finite, implausible or malformed readings' * bool(invalid)
            text = '; '.join(part for part in (readings, streams) if part)
        else:
            level, text = OK, 'ok'
        values = {
            'rate_hz': float(self._rate[s]),
            'staleness_s': float(staleness),
            'received': self._received[s],
            'dropped_invalid': invalid,
            **{f'dropped_{k}': n for k, n in self._streams.dropped[s].items()},
            'missing_by_stamp': self._streams.missing[s],
            **clocks,
        }
        return status(self, cv.MAG_TOPICS[s], level, text, cv.MAG_FRAMES[s], values)

    def _publish_diagnostics(self) -> None:
        """Per-sensor rate, staleness and drops; the matching counters."""
        now = self._now_s()
        self._update_rates()
        stale = self._stale_sensors()
        clocks: list[dict[str, float]] = [{} for _ in range(4)]
        if isinstance(self._matcher, Resampler):
            clocks = [
                {'clock_offset_ms': c.offset_s * 1e3, 'clock_jitter_ms': c.jitter_s * 1e3}
                for c in self._matcher.clocks()
            ]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        missing = list(self._streams.missing)
        recent = [m - mark for m, mark in zip(missing, self._missing_mark, strict=True)]
        self._missing_mark = missing
        for s in range(len(cv.MAG_TOPICS)):
            array.status.append(self._sensor_status(s, now, s in stale, clocks[s], recent[s]))
        counts = self._matcher_counts()
        dropped = sum(counts.get(k, 0) for k in ('dropped_messages', 'skipped_gap', 'evicted'))
        # Sensor 1's lost messages are sets never formed (its stamps are the sets' instants).
        on_sensor_1 = self._timebase.sync == 'interpolate' and not self._timebase.reference_rate_hz
        never = missing[0] if on_sensor_1 else 0
        lost = bool(never and recent[0])
        level = ERROR if stale else (WARN if self.sets_invalid or dropped or lost else OK)
        text = (
            f'no tensor: stale {", ".join(cv.MAG_TOPICS[s] for s in stale)}'
            if stale
            else f'{self.sets_published} tensors published'
            + (f'; {never} sets never formed: {cv.MAG_TOPICS[0]} messages lost' if never else '')
        )
        array.status.append(
            status(
                self,
                'matching',
                level,
                text,
                '',
                {
                    'sets_published': self.sets_published,
                    'sets_dropped_invalid': self.sets_invalid,
                    'sets_never_formed': never,
                    **{MATCHER_KEYS.get(k, f'matcher_{k}'): v for k, v in counts.items()},
                    'matcher_resets': self.resets,
                    # Matched readers of the outputs (rmw, both sides of discovery done): who
                    # receives the tensors from now on; a reader not yet matched misses them.
                    'gradient/raw subscribers': self._raw_pub.get_subscription_count(),
                },
            )
        )
        self._diag_pub.publish(array)
        silent = [
            s for s in stale if self._ever[s]
        ]  # went quiet after data (not: not started yet)
        if silent and self._stale_warn():
            self.get_logger().warning(
                f'stale sensor(s): {", ".join(cv.MAG_TOPICS[s] for s in silent)}; '
                f'no tensor is published until they return'
            )


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer tensor``; 1 when the node refuses its parameters."""
    return spin_node(TensorNode, 'tensor', args)
