"""``driver`` node: a stand-in magnetometer source, simulated or replayed.

It has no default source: ``mode`` must be chosen (``sim`` or ``replay``), else its
configuration is refused, so that ``ros2 run tetra_gradiometer driver`` on a vehicle never
fabricates vehicle data. On a vehicle the tensor node takes the real magnetometer driver's
topics instead (docs/ros.md, "Your own magnetometer driver").

``mode: sim`` flies the core mission simulator (``scenario``: a scenario YAML for
io/scenario.py, or the built-in default ``io.scenario.DEFAULT_SCENARIO``: a trim manoeuvre
far from the target, then a survey line over a dipole). It publishes ``mag1``..``mag4``
(sensor_msgs/MagneticField, T, frames tetra_mag1..4, header.stamp = sample time: the start
time plus the simulated time of the sample; ``magnetic_field_covariance`` = ``diag(sigma^2)``
T^2 of the scenario's sensor noise), ``gradient/truth`` (the simulator's ``g_true``,
tetra_gradiometer_msgs/GradientTensor, T/m; its other fields unknown) and ``odom``
(nav_msgs/Odometry, body -> world ENU): every topic relative, so in the suite's namespace
(``/tetra/odom``), never the vehicle's own ``/odom``.

``mode: replay`` plays a rosbag2 folder (sqlite3 or mcap): the magnetometer topics, and
``/tetra/gradient/truth`` and ``/odom`` when recorded (published as ``gradient/truth`` and
``odom`` in the node's namespace), with their recorded stamps; and the channels of the
vehicle effects the bag records, on their own (absolute) topics as the calibrator and
compensator read them: ``/tetra/temperature`` (sensor_msgs/Temperature) and every
sensor_msgs/BatteryState topic (``/battery_state``, a thruster's), the latter carrying only
``current`` (the rest NaN); and the topics where the vehicle's own signals may be (any other
topic: fin angles, a power board's currents) as recorded. A magnetometer message keeps its
recorded covariance; one recorded without (all zero) gets
``diag(sensor_noise_t^2)``, or REP 145's unknown (-1 first) with ``sensor_noise_t`` 0.

Pacing: ``rate`` times real time (by sample time in sim, by log time in replay; a frame
more than ``MAX_CATCH_UP_S`` late, after a stall, restarts the pacing from itself rather
than the backlog going out at once: counted as ``pace_restarts``), or with
``rate: 0`` as fast as the tensor node takes it: at most ``ACK_WINDOW`` sets are published
ahead of the last ``gradient/raw`` received. After ``ACK_TIMEOUT_S`` without one, the driver
moves on and counts a timeout.

``start_paused`` waits for ``~/resume``; ``hold_between_segments`` (sim) pauses after each
scenario segment until ``~/resume`` (so a trim can be calibrated before the survey starts).
State, segment and counts go to ``/diagnostics``. The frames come from nodes/replay.py
(``simulate``, ``iter_frames``); this node only paces them and answers the services.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Generator
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import BatteryState, MagneticField, Temperature
from std_srvs.srv import Trigger

from ..core.units import NS_PER_S
from ..errors import InputError, ParamsError
from ..io import conversions as cv
from . import replay
from .channels import message_class_named
from .common import (
    OK,
    POSITIONS_SPEC,
    WARN,
    ParamSpec,
    derived_qos,
    diagnostics_period_spec,
    frame_ids,
    non_negative,
    status,
)
from .managed import ManagedNode
from .process import spin_node
from .replay import CHANNEL, MAG, ODOM, SIGNAL, TRUTH, Frame

#: rate 0: sets published ahead of the last gradient/raw received (the tensor node's
#: pending queue is far deeper; a small window keeps its readers' queues short).
ACK_WINDOW = 4

#: rate 0: s without a gradient/raw before the driver moves on (counted as ``ack_timeouts``).
ACK_TIMEOUT_S = 0.5

#: Why the driver refuses to configure without a ``mode``.
MODE_UNSET = (
    "parameter 'mode' is not set: choose 'sim' (simulated vehicle data from a scenario) or "
    "'replay' (a recorded bag, with 'bag'); the driver fabricates no data by default"
)


def _mode_error(value: str) -> str | None:
    """Why ``mode`` is refused, or None ('' is accepted here and refused at configure)."""
    return None if value in ('', 'sim', 'replay') else f"must be 'sim' or 'replay', got {value!r}"


def _remap_error(value: str) -> str | None:
    """Why ``replay_remap`` is refused (io/conversions.parse_remap), or None."""
    try:
        cv.parse_remap(value)
    except InputError as error:
        return str(error)
    return None


PARAMETERS = [
    ParamSpec(
        'mode',
        '',
        'Source, to be chosen (no default): "sim" (core mission simulator) or "replay" '
        '(rosbag2 folder); unset, configuration is refused.',
        _mode_error,
    ),
    ParamSpec(
        'scenario',
        '',
        'sim: scenario YAML file (io/scenario.py format); empty: the built-in '
        'default (trim far from the target, then a survey line over it).',
    ),
    ParamSpec(
        'seed', -1, "sim: noise seed; -1 uses the scenario's own seed.", int_range=(-1, 2**31 - 1)
    ),
    ParamSpec('bag', '', 'replay: rosbag2 folder (sqlite3 or mcap).'),
    ParamSpec(
        'replay_remap',
        '',
        'replay: topic map of a bag recorded under other names, FROM:=TO rules separated by '
        'spaces (as ros2 bag play --remap), e.g. "/auv1/tetra/mag1:=/tetra/mag1 '
        '/auv1/odom:=/odom"; TO is a topic of the bag contract (README, Topics).',
        _remap_error,
    ),
    ParamSpec(
        'rate',
        1.0,
        'Speed: multiple of real time; 0 = as fast as the tensor node takes it (paced by '
        'gradient/raw). At most 1000.',
        non_negative,
        float_range=(0.0, 1000.0),
    ),
    ParamSpec('start_paused', False, 'Wait for ~/resume before publishing.'),
    ParamSpec(
        'loop',
        False,
        'Play the source again from its start each time it is played through (as ros2 bag '
        'play --loop; the passes are counted on /diagnostics). False: finished at its end.',
    ),
    ParamSpec(
        'min_subscribers',
        0,
        'Do not publish until every magnetometer topic has at least this many '
        'subscriptions (e.g. 1: wait for the tensor node instead of losing the first sets); '
        'at most 64 (the graph has one subscriber per topic, plus recorders and monitors).',
        int_range=(0, 64),
    ),
    ParamSpec(
        'hold_between_segments', False, 'sim: pause after each scenario segment until ~/resume.'
    ),
    ParamSpec(
        'max_duration_s',
        0.0,
        'Play only this much sample time, s (0: all; at most 1e6 s, 11.6 days of mission).',
        non_negative,
        float_range=(0.0, 1e6),
    ),
    ParamSpec(
        'publisher_depth',
        100,
        'Queue depth of the magnetometer publishers (reliable: the system default, REP 2003), '
        'messages (at most 10000, 50 s at 200 sets/s).',
        int_range=(1, 10000),
    ),
    ParamSpec(
        'sensor_noise_t',
        0.0,
        'replay: white noise per axis of each magnetometer, tesla RMS (0 to 1e-6), for the '
        'covariance of readings recorded without one; 0 = unknown (-1 first, REP 145). sim: the '
        "scenario's noise is used. (The compensator and calibrator read the same value.)",
        non_negative,
        float_range=(0.0, 1e-6),
    ),
    POSITIONS_SPEC,
    ParamSpec('odom_frame_id', cv.ODOM_FRAME, 'sim: /odom header frame (REP 105).', frame_ids),
    ParamSpec('base_frame_id', cv.BASE_FRAME, 'sim: /odom child frame, the body.', frame_ids),
    ParamSpec(
        'sensor_frame_ids',
        cv.MAG_FRAMES,
        'sim: frames of mag1..4 (children of base_frame_id). Replay keeps the recorded ids.',
        lambda ids: f'must name 4 frames, got {list(ids)!r}' if len(ids) != 4 else frame_ids(ids),
    ),
    ParamSpec(
        'publish_clock',
        True,
        'Publish /clock (rosgraph_msgs/Clock): the time of the last frame played (the log time '
        'in replay, the sample time in sim), so nodes with use_sim_time follow the playback '
        '(its rate, its pauses).',
    ),
    diagnostics_period_spec(),
]

#: /clock is published when the played time has advanced this much, ns (1 ms: finer than any
#: node's staleness or rate window, and at most 1000 clock messages per second of playback).
CLOCK_STEP_NS = 1_000_000

#: With ``min_subscribers``: wait this long after the subscriptions appear (s), so that the
#: subscribers' side of the discovery has completed too.
MATCH_SETTLE_S = 0.5

#: rate > 0: a frame due more than this long ago (s of wall time: the driver's process was
#: stalled) restarts the pacing from itself instead of the backlog going out in one tick. A
#: burst of a second's sets overflows best-effort readers' transport queues (a driver stopped
#: for 1 s of an 8x replay: the tensor node received 1092 of 1200 sets and the calibrator's
#: channels 912); restarted, the replay takes longer and nothing is skipped. 0.25 s at 8x is
#: 40 sets of 20 Hz, well within the queues.
MAX_CATCH_UP_S = 0.25


class DriverNode(ManagedNode):
    """Publishes the magnetometers (and truth, odometry) from the simulator or a bag."""

    PARAMETERS = PARAMETERS

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('driver', **kwargs)

    def configure(self, p: dict[str, Any]) -> None:
        """Open the source (simulate the scenario, or open the bag) and create the
        publishers, services and timers."""
        self._rate = float(p['rate'])
        self._hold = bool(p['hold_between_segments'])
        if not p['mode']:
            raise ParamsError(MODE_UNSET)
        self._mode = p['mode']
        self._min_subscribers = int(p['min_subscribers'])
        self._matched_since: float | None = None
        self._types = cv.rclpy_types()
        self._frames, self.info, period = self._open_source(p)
        self._next: Frame | None = next(self._frames, None)
        self._loop, self._source = bool(p['loop']), dict(p)
        self.passes = 1
        self.state = 'paused' if p['start_paused'] else 'playing'
        self.segment = self._next.segment if self._next is not None else -1
        self.sets_published = 0
        self.ack_timeouts = 0
        self.pace_restarts = 0
        self._in_flight: deque[int] = deque()
        self._last_progress = time.monotonic()
        self._origin = (time.monotonic(), self._next.pace_ns if self._next else 0)

        # REP 2003: a sensor driver publishes with the system default (reliable, volatile);
        # consumers (the tensor node) subscribe with sensor-data QoS, and a reliable
        # subscriber (a recorder, a plain depth-10 subscription) gets the data too.
        mag_qos = derived_qos(p['publisher_depth'])
        self._pubs = {
            (MAG, s): self.create_lifecycle_publisher(MagneticField, topic, mag_qos)
            for s, topic in enumerate(cv.MAG_TOPICS)
        }
        tensor = cv.rclpy_types()[cv.GRADIENT_TENSOR]
        self._pubs[(TRUTH, 0)] = self.create_lifecycle_publisher(
            tensor, 'gradient/truth', derived_qos()
        )
        self._pubs[(ODOM, 0)] = self.create_lifecycle_publisher(
            Odometry, cv.ODOM_NODE_TOPIC, derived_qos()
        )
        # A replayed bag's channels (nodes/replay.channel_topics), on the absolute topics the
        # calibrator and compensator subscribe to (best effort: a reliable publisher matches).
        channels = [t for t in str(self.info.get('channels', '')).split(', ') if t]
        for i, topic in enumerate(channels):
            kind = Temperature if topic == cv.TEMPERATURE_TOPIC else BatteryState
            self._pubs[(CHANNEL, i)] = self.create_lifecycle_publisher(kind, topic, derived_qos())
        # Its signal topics, as recorded (serialized): each with its recorded type.
        for i, (topic, msgtype) in enumerate(self.info.get('signals', ())):
            kind = message_class_named(msgtype)
            if kind is None:
                self.get_logger().warning(
                    f'replay: {topic} ({msgtype}) is not played: its '
                    'message package is not installed'
                )
                continue
            self._pubs[(SIGNAL, i)] = self.create_lifecycle_publisher(kind, topic, derived_qos())
        self._diag_pub = self.diagnostics_publisher()
        self._clock_pub = (
            self.create_lifecycle_publisher(Clock, '/clock', 10) if p['publish_clock'] else None
        )
        self._clock_ns = -CLOCK_STEP_NS
        gated = self.when_active
        if self._rate == 0:
            self.create_subscription(tensor, 'gradient/raw', gated(self._on_ack), derived_qos())
        self.create_service(Trigger, '~/resume', gated(self._on_resume))
        self.create_service(Trigger, '~/pause', gated(self._on_pause))
        # Wall-clock (steady) timers: the driver is the source of /clock, so it must not wait
        # for it when the launch gives every node use_sim_time.
        steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(min(max(period, 0.002), 0.05), self._tick, clock=steady)
        self.create_diagnostics_timer(p['diagnostics_period_s'], self._publish_diagnostics)

    def _sim_start_ns(self, scenario: str, max_duration_s: float) -> int:
        """The stamp of the first simulated sample: now (system time even under use_sim_time:
        the driver is /clock), or, played faster than real time, now minus the mission's
        duration, so that no stamp is ever ahead of the clock (the nodes refuse stamps from
        the future: nodes/stamps.py)."""
        from ..io.scenario import load_scenario_or_default  # as replay.simulate imports it

        now = time.time_ns()
        if 0 < self._rate <= 1:
            return now
        duration_s = load_scenario_or_default(scenario)[0].duration_s
        if max_duration_s > 0:
            duration_s = min(duration_s, max_duration_s)
        return now - int(round(duration_s * NS_PER_S))

    def _open_source(
        self, p: dict[str, Any]
    ) -> tuple[Generator[Frame, None, None], dict[str, Any], float]:
        """The frames to play (nodes/replay.py), their description and the tick period, s."""
        types = self._types
        if self._mode == 'sim':
            start_ns = self._sim_start_ns(p['scenario'], float(p['max_duration_s']))
            frames, info = replay.simulate(
                p['scenario'],
                p['seed'],
                types,
                start_ns=start_ns,
                max_duration_s=p['max_duration_s'],
                frame_ids=replay.FrameIds(
                    p['odom_frame_id'], p['base_frame_id'], tuple(p['sensor_frame_ids'])
                ),
            )
            _same_geometry(info['sensor_positions'], p['sensor_positions'], p['scenario'])
            self.get_logger().info(
                f'sim: {info["samples"]} samples at {info["sample_rate_hz"]:g} Hz, segments '
                f'[{info["segments"]}], {info["dipoles"]} dipole(s)'
            )
            rate_hz = info['sample_rate_hz'] * self._rate
            return frames, info, 1.0 / rate_hz if self._rate > 0 else 0.01
        if not p['bag']:
            raise InputError('mode replay needs the parameter "bag" (a rosbag2 folder)')
        path = os.path.expanduser(p['bag'])
        remap = cv.parse_remap(p['replay_remap'])
        info = replay.describe_bag(path, remap)
        self.get_logger().info(
            f'replay: {path}: {info["messages"]} magnetometer messages; topics {info["topics"]}'
            f'; channels published: {info["channels"] or "none"}; signal topics played: '
            f'{", ".join(t for t, _ in info["signals"]) or "none"}'
        )
        frames = replay.iter_frames(
            path,
            types,
            max_duration_s=p['max_duration_s'],
            sensor_noise_t=p['sensor_noise_t'],
            remap=remap,
        )
        return frames, info, 0.005 if self._rate > 0 else 0.01

    # ----------------------------------------------------------------- playing

    def _tick(self) -> None:
        """Publish every frame that is due (rate > 0) or allowed in flight (rate 0)."""
        if self.state != 'playing':
            return
        now = time.monotonic()
        if self._min_subscribers and self._matched_since is None:
            if any(
                self._pubs[(MAG, s)].get_subscription_count() < self._min_subscribers
                for s in range(4)
            ):
                return
            self._matched_since = now
        if self._matched_since is not None and now - self._matched_since < MATCH_SETTLE_S:
            self._origin = (now, self._next.pace_ns if self._next else 0)
            self._last_progress = now
            return
        for _ in range(10_000):
            if self._next is None and self._loop and self.passes < 2**31:
                self._play_again(now)
            frame = self._next
            if frame is None:
                self._set_state('finished')
                return
            if self._hold and frame.segment != self.segment:
                self.segment = frame.segment
                self._set_state('holding')
                return
            if self._rate > 0:
                due_ns = self._origin[1] + (now - self._origin[0]) * self._rate * NS_PER_S
                if frame.pace_ns > due_ns:
                    return
                if frame.pace_ns < due_ns - MAX_CATCH_UP_S * self._rate * NS_PER_S:
                    self._origin = (now, frame.pace_ns)
                    self.pace_restarts += 1
            elif len(self._in_flight) >= ACK_WINDOW:
                if now - self._last_progress < ACK_TIMEOUT_S:
                    return
                self.ack_timeouts += 1
                self._in_flight.clear()
            self._publish(frame)
            self._next = next(self._frames, None)

    def _publish(self, frame: Frame) -> None:
        if self._clock_pub is not None and frame.clock_ns >= self._clock_ns + CLOCK_STEP_NS:
            self._clock_ns = frame.clock_ns  # before the frame: no message is ahead of /clock
            self._clock_pub.publish(cv.clock_msg(self._types, frame.clock_ns))
        for key, sensor, msg in frame.items:
            publisher = self._pubs.get((key, sensor))
            if publisher is not None:  # None: a signal whose type is not installed
                publisher.publish(msg)
        if frame.mag1_stamp is not None:
            self.sets_published += 1
            if self._rate == 0:
                if not self._in_flight:
                    self._last_progress = time.monotonic()
                self._in_flight.append(frame.mag1_stamp)
        self.segment = frame.segment

    def _on_ack(self, msg: Any) -> None:
        """rate 0: a tensor came back; release the sets up to its stamp."""
        stamp = cv.stamp_to_ns(msg.header.stamp)
        while self._in_flight and self._in_flight[0] <= stamp:
            self._in_flight.popleft()
        self._last_progress = time.monotonic()
        self._tick()

    def _play_again(self, now: float) -> None:
        """``loop``: the source from its start (the nodes take the earlier stamps as a
        restarted replay)."""
        self._frames.close()
        self._frames, _, _ = self._open_source(self._source)
        self._next = next(self._frames, None)
        self._origin = (now, self._next.pace_ns if self._next else 0)
        self.passes += 1
        self.get_logger().info(f'loop: pass {self.passes} ({self.sets_published} sets published)')

    def _set_state(self, state: str) -> None:
        if state != self.state:
            self.state = state
            self.get_logger().info(
                f'{state} (segment {self.segment}, {self.sets_published} sets published)'
            )
            self._publish_diagnostics()

    def _on_resume(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.state == 'finished':
            response.success, response.message = False, 'finished: nothing left to play'
            return response
        self._origin = (time.monotonic(), self._next.pace_ns if self._next else 0)
        self._last_progress = time.monotonic()
        self._set_state('playing')
        response.success, response.message = True, f'playing segment {self.segment}'
        return response

    def _on_pause(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.state == 'finished':
            response.success, response.message = False, 'finished'
            return response
        self._set_state('paused')
        response.success, response.message = True, 'paused'
        return response

    def activated(self) -> None:
        """Pacing restarts from the next frame: the time spent inactive is not caught up."""
        self._origin = (time.monotonic(), self._next.pace_ns if self._next else 0)
        self._last_progress = time.monotonic()

    def released(self) -> None:
        """Close the source (a replayed bag)."""
        self._frames.close()

    def _publish_diagnostics(self) -> None:
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(
            status(
                self,
                'playback',
                WARN if self.ack_timeouts else OK,
                f'{self.state} ({self._mode}, segment {self.segment})',
                '',
                {
                    'state': self.state,
                    'mode': self._mode,
                    'segment': self.segment,
                    'sets_published': self.sets_published,
                    'ack_timeouts': self.ack_timeouts,
                    'pace_restarts': self.pace_restarts,
                    'passes': self.passes,
                    'rate': self._rate,
                    **self.info,
                    'signals': ', '.join(t for t, _ in self.info.get('signals', ())),
                    # Matched readers per output (rmw): a reader not yet matched misses what
                    # is played before (volatile), e.g. a node started after the replay.
                    **{
                        f'{publisher.topic_name} subscribers': publisher.get_subscription_count()
                        for publisher in self._pubs.values()
                    },
                },
            )
        )
        self._diag_pub.publish(array)


def _same_geometry(simulated: Any, declared: Any, scenario: str) -> None:
    """One source of the array geometry: the simulated array must be the ``sensor_positions``
    the tensor node differences with (the same params file feeds both)."""
    if not np.allclose(np.asarray(simulated), np.asarray(declared), rtol=0.0, atol=1e-9):
        raise InputError(
            f'the scenario {scenario or "(built-in default)"} simulates the array '
            f'{np.round(simulated, 6).tolist()} m but sensor_positions is '
            f'{np.round(declared, 6).tolist()} m: the tensor node would difference with the '
            'wrong positions; make them agree'
        )


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer driver``; 1 when the node refuses its parameters."""
    return spin_node(DriverNode, 'driver', args)
