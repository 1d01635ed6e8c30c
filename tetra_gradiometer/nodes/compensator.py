"""``compensator`` node: ``G = G_m - D`` (eq. 19) on every measured tensor.

Loads ``calibration_file`` on configure (corrupt, or of another array: configuration refused,
nodes/managed.py) and follows the latched ``calibration`` topic (tetra_gradiometer_msgs/
Calibration, io/calibration_message.py); without one, or with a refused one, it runs uncompensated
(``gradient/compensated`` = ``gradient/raw``) or on the one it has, WARN on ``/diagnostics``.

Reads ``gradient/raw`` (tetra_gradiometer_msgs/GradientTensor: ``G_m``, T/m, with ``B_1'``,
T) and publishes ``gradient/compensated`` (GradientTensor, state COMPENSATED with the
calibration's ``created_utc`` as ``calibration_id``, or UNCOMPENSATED; ``g_sigma`` the 1-sigma
of each component, T/m: core/uncertainty.py, from ``sensor_noise_t`` or else the
calibration's noise estimate, and the calibration's covariance; uncompensated without a
noise figure, the raw message's; else NaN) and ``gradient/norm`` (Float64, nT/m). With
``gradient/truth`` at the same stamp it publishes the running ``epsilon`` (eq. 24) and
``compensated_percent``; a new calibration or ``~/reset_metrics`` restarts them.
``track_calibration`` follows the calibration's drift and steps online as ``compensate
--track-calibration`` (.calibration_tracking).

Vehicle effects: a calibration with terms (``D = (k B_1' + b + sum W x) a^-1``) makes the
node read the channels they read (:mod:`.channels`: temperature, currents, declared
signals), interpolated onto each set's stamp (a set arriving before a channel's message at
or after its stamp waits for it, bounded), as ``compensate`` does. A channel missing or
stale at a set is never taken as zero: the set is dropped, counted, WARN naming it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from tetra_gradiometer_msgs.msg import Calibration

from ..core import InterferenceParameters, TetraGeometry, compensate
from ..core.health import MIN_SOURCE_RANGE_EDGES, HealthConfig, HealthMonitor
from ..core.metrics import epsilon_terms
from ..core.plausibility import plausible_readings
from ..core.tracking import handed_over
from ..core.uncertainty import SigmaModel
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import InputError, MessageError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..io.calibration import (
    CalibrationFile,
    CalibrationFileError,
    check_positions,
    load_calibration,
)
from ..io.calibration_message import calibration_from_message
from ..io.channels import channel_topic
from ..io.matching import StampPairer
from ..pipelines.health import alarm_cause
from ..pipelines.tracking import learn_after_ns
from .authentication import CalibrationGate, Refused, key_file_spec, node_key
from .calibration_tracking import LiveTracking
from .channels import LiveEffects, channel_message, channel_stamp, subscribe_channels
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
    latched_qos,
    non_negative,
    resolve_node_path,
    status,
)
from .managed import ManagedNode, steady_clock
from .process import spin_node
from .publishers import InputPublishers, resolve_node_name
from .stamps import AHEAD_SPEC

PARAMETERS = [
    POSITIONS_SPEC,
    ParamSpec(
        'calibration_file',
        'calibration.yaml',
        'Calibration loaded on configure (YAML, as the calibrator writes it); "~" is expanded, '
        'a relative path is under $ROS_HOME (default ~/.ros). Missing: run uncompensated until '
        'the calibration topic brings one; corrupt or of another array: configure refused.',
    ),
    ParamSpec(
        'calibration_publisher',
        'calibrator',
        'The node whose calibrations the calibration topic may bring (a relative name is in '
        "this node's namespace: /tetra/calibrator); one that arrives while another node "
        'publishes the topic is refused (WARN naming it). Read-only.',
        lambda name: None if name.strip('/') and ' ' not in name else 'must name a node',
        read_only=True,
    ),
    key_file_spec('verifies'),
    ParamSpec(
        'max_pending',
        1000,
        'Bound of the buffer pairing gradient/compensated with gradient/truth by stamp, '
        'messages (at most 100000, 8 min at 200 sets/s).',
        int_range=(1, 100_000),
    ),
    ParamSpec(
        'sensor_noise_t',
        0.0,
        'White noise per axis of each magnetometer, tesla RMS (0 to 1e-6), propagated into '
        "gradient/compensated's g_sigma; 0 = the loaded calibration's estimate (none: NaN). "
        '(The driver and calibrator read the same value.)',
        non_negative,
        float_range=(0.0, 1e-6),
    ),
    ParamSpec(
        'health_false_alarms_per_hour',
        0.01,
        'Health monitor (core/health.py): design false-alarm rate, per hour (1e-6 to 60).',
        float_range=(1e-6, 60.0),
    ),
    ParamSpec(
        'health_min_source_range_edges',
        20.0,
        'Health monitor: sources closer than this many longest edges may raise an alarm '
        '(their differencing asymmetry is not bounded); 14 to 1000.',
        float_range=(MIN_SOURCE_RANGE_EDGES, 1000.0),
    ),
    ParamSpec(
        'track_calibration',
        True,
        "Follow the calibration's drift and steps online (core/tracking.py, with odom's "
        'attitude when heard by the first set) and add its variance to g_sigma; '
        'false: the calibration as loaded. Read-only.',
        read_only=True,
    ),
    ARRAY_FRAME_SPEC,
    WARN_THROTTLE_SPEC,
    AHEAD_SPEC,
    diagnostics_period_spec(),
]
#: Seconds between feeds of the health monitor (it works on chunks; ~1 ms per call).
HEALTH_PERIOD_S = 0.1
#: Seconds between checks of the sets held for a channel message (when the sets stop).
HOLD_CHECK_S = 0.05


class CompensatorNode(ManagedNode):
    """Applies the current calibration to the measured tensor stream."""

    PARAMETERS = PARAMETERS

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('compensator', **kwargs)

    def configure(self, p: dict[str, Any]) -> None:
        """Publishers, subscriptions and the calibration file (a corrupt one, or one of
        another array, refuses the configuration; a missing one: uncompensated until the
        ``calibration`` topic brings one)."""
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        self._array_frame = p['array_frame_id']
        self._truth = StampPairer(2, p['max_pending'])  # (raw, compensated), truth
        self._warn = Throttle(p['warn_throttle_s'])
        # Not ``_parameters``: rclpy's Node keeps its declared parameters under that name.
        self._interference: InterferenceParameters | None = None
        self._source = ''
        self._problem = 'no calibration loaded yet'
        self._created = ''  # created_utc of the calibration in use
        self._forced = ''  # its warning when it was written with force
        topic = self.resolve_topic_name('calibration')
        publisher = resolve_node_name(self, p['calibration_publisher'])
        self._watch = InputPublishers(self, {topic: publisher})
        self._gate = CalibrationGate(
            self._watch, topic, publisher, node_key(p['calibration_key_file'])
        )
        self._waiting: tuple[float, Calibration] | None = None  # publisher not named yet
        self._noise = float(p['sensor_noise_t'])
        self._sigma: SigmaModel | None = None
        self._sigma_text = ''
        self._health_config = HealthConfig(
            false_alarms_per_hour=p['health_false_alarms_per_hour'],
            min_source_range_edges=p['health_min_source_range_edges'],
        )
        self._health: HealthMonitor | None = None
        self._tracking: LiveTracking | None = None
        self._health_text = 'off: no calibration'
        self._health_first_s = 0.0  # the monitor's first sample, s
        self._health_buffer: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._health_sent: dict[int, bool] = {}  # alarm index -> settled when published
        self._effects: LiveEffects | None = None
        self._channel_subscriptions: dict[str, Any] = {}
        self._set_sigma(None)
        self.published = 0
        self.compensated = 0  # of those published, with a calibration
        self.dropped_non_finite = 0
        self._reset_metrics()

        # The per-sample path reads and writes serialized messages (io/conversions).
        check_serialization()
        self._cdr = gt.GradientTensorCdr(self._array_frame)
        publish, data = self.create_lifecycle_publisher, derived_qos()
        self._comp_pub = publish(gt.rclpy_class(), cv.COMPENSATED_NODE_TOPIC, data)
        self._norm_pub = publish(Float64, 'gradient/norm', data)
        self._eps_pub = publish(Float64, 'epsilon', data)
        self._pct_pub = publish(Float64, 'compensated_percent', data)
        self._alarm_pub = publish(String, 'health/alarm', latched_qos(depth=100))
        self._diag_pub = self.diagnostics_publisher(self._watch)
        self._horizon = self._watch.watch_stamps(p['max_stamp_ahead_s'], p['warn_throttle_s'])
        if p['track_calibration']:
            self._tracking = LiveTracking(self, self.when_active, self._horizon)
        self._load_file(resolve_node_path(p['calibration_file']))
        gated = self.when_active
        on_calibration = gated(self._on_calibration)
        self.create_subscription(Calibration, 'calibration', on_calibration, latched_qos())
        tensor = gt.rclpy_class()
        raw = self.create_subscription(
            tensor, 'gradient/raw', gated(self._on_raw), derived_qos(), raw=True
        )
        self._diag_pub.inputs.require(raw)
        self.create_subscription(
            tensor, 'gradient/truth', gated(self._on_truth), derived_qos(), raw=True
        )
        self.create_service(Trigger, '~/reset_metrics', gated(self._on_reset))
        self.create_diagnostics_timer(p['diagnostics_period_s'], self._publish_diagnostics)
        self.create_timer(HEALTH_PERIOD_S, self._feed_health, clock=steady_clock())  # not /clock's
        self.create_timer(0.2, self._judge_waiting, clock=steady_clock())
        self.create_timer(HOLD_CHECK_S, self._release_held, clock=steady_clock())  # sets that stop

    # ----------------------------------------------------------------- calibration

    @property
    def compensating(self) -> bool:
        return self._interference is not None

    def _load_file(self, path: Path) -> None:
        """Apply the calibration file ``path``; a missing one is waited for on the topic.

        Raises
        ------
        CalibrationFileError
            The file exists but is unreadable, corrupt, implausible or of another array.
        """
        if not path.exists():
            self._refuse(f'no calibration file {path} yet (waiting for the calibration topic)')
            return
        calibration = load_calibration(path)
        self._gate.check_file(path.read_text(encoding='utf-8'), str(path))  # with a key
        self._apply(calibration, f'file {path}')

    def _on_calibration(self, msg: Calibration) -> None:
        self._judge(msg, time.monotonic())

    def _judge_waiting(self) -> None:
        if self._waiting is not None:
            self._judge(self._waiting[1], self._waiting[0])

    def _judge(self, msg: Calibration, arrived: float) -> None:
        """Adopt a calibration from the topic when the gate admits it (its publisher, its
        signature) and it is not older than the one in use under a key (a replay)."""
        self._waiting = None
        try:
            if not self._gate.admit(msg.document, time.monotonic() - arrived):
                self._waiting = (arrived, msg)  # the graph has not named the publisher yet
                return
            calibration = calibration_from_message(msg, 'the calibration topic')
            if self._gate.key is not None and calibration.created_utc < self._created:
                raise Refused(
                    f'a signed calibration from {self._gate.publisher} created '
                    f'{calibration.created_utc}, before the one in use ({self._created}): '
                    'a replay'
                )
            self._apply(calibration, f'topic calibration from {self._gate.publisher}')
        except CalibrationFileError as error:
            self._refuse(str(error))

    def _apply(self, calibration: CalibrationFile, source: str) -> None:
        check_positions(
            calibration, self._geometry, source=source, target='sensor_positions of this node'
        )
        self._release_held(flush=True)  # the held sets with the calibration they arrived under
        self._set_sigma(calibration)
        self._interference = calibration.parameters
        self._follow_channels(calibration)
        self._source = f'{source} ({calibration.method}, {calibration.created_utc})'
        self._created = calibration.created_utc
        self._forced = next(iter(calibration.forced_warnings()), '')
        self._problem = ''
        self._reset_metrics()
        self.get_logger().info(f'compensating with {self._source}')
        self._publish_diagnostics()

    def _follow_channels(self, calibration: CalibrationFile) -> None:
        """The calibration's terms, live, and the subscriptions to the channels they read
        (those no term reads any more are dropped; the messages of the others are kept)."""
        terms = calibration.parameters.terms
        kept = {} if self._effects is None else self._effects.channels
        self._effects = LiveEffects(terms, kept) if terms else None
        names = set(self._effects.channels) if self._effects is not None else set()
        for name in set(self._channel_subscriptions) - names:
            self.destroy_subscription(self._channel_subscriptions.pop(name))
        new = sorted(names - set(self._channel_subscriptions))
        self._channel_subscriptions.update(subscribe_channels(self, new, self._on_channel))
        if self._effects is not None:
            self.get_logger().info(
                f'terms {self._effects.names}: reading '
                + ', '.join(f'{b.name} ({b.topic})' for b in self._effects.channels.values())
            )

    def _on_channel(self, name: str, msg: Any) -> None:
        """A channel message (ignored while inactive, as the sets are)."""
        if self.active and self._effects is not None and name in self._effects.channels:
            stamp_ns = channel_stamp(msg, self.get_clock().now().nanoseconds)
            if not self._horizon.refuse(channel_topic(name), stamp_ns):  # a later stamp
                self._effects.add(name, stamp_ns, channel_message(name, msg))  # would reset it
                self._release_held()

    def _set_sigma(self, calibration: CalibrationFile | None) -> None:
        """The 1-sigma model of ``calibration`` (None: the raw tensor's) and its description."""
        noise = self._noise or (None if calibration is None else calibration.sensor_noise_t)
        if noise is None or noise <= 0:
            self._sigma = None
            self._sigma_text = 'none: sensor noise unknown (sensor_noise_t 0 and ' + (
                'no calibration)' if calibration is None else 'no estimate in the calibration)'
            )
            return
        source = 'sensor_noise_t' if self._noise else 'the calibration'
        if calibration is None:
            self._sigma = SigmaModel.build(self._geometry, noise)
            terms = 'sensor noise (raw tensor)'
        else:
            self._sigma = SigmaModel.build(
                self._geometry, noise, calibration.parameters, calibration.covariance
            )
            terms = 'sensor noise' + (
                ' and parameter covariance' if calibration.covariance is not None else ' only'
            )
        self._sigma_text = f'{terms}, {noise * NT_PER_T:.3g} nT from {source}'
        self._start_health(calibration, noise)

    def _start_health(self, calibration: CalibrationFile | None, noise: float) -> None:
        """A fresh monitor and tracker for ``calibration`` (a new one clears every alarm)."""
        self._health_buffer, self._health_sent = [], {}
        self._health, self._health_text, parameters = None, 'off: no calibration', None
        if calibration is not None:
            parameters, covariance = calibration.parameters, calibration.covariance
            if parameters.terms:  # the monitor's model is k, b: their block of the covariance,
                parameters = parameters.without_terms()  # the general 36 lead full_vector
                covariance = None if covariance is None else covariance[:36, :36]
            self._health = HealthMonitor(
                self._geometry, parameters, noise, covariance, self._health_config
            )
            self._health_text = 'watching'
        if self._tracking is not None:
            fitted = None if calibration is None else learn_after_ns(calibration.diagnostics)
            self._tracking.start(self._geometry, parameters, noise, fitted)

    def _feed_health(self) -> None:
        """Feed the buffered samples to the monitor; publish new (and newly settled) alarms."""
        monitor, buffered = self._health, self._health_buffer
        if monitor is None or not buffered:
            return
        self._health_buffer = []
        t_s, g, b = (np.array(column) for column in zip(*buffered, strict=True))
        if not monitor.samples:
            self._health_first_s = float(t_s[0])
        try:
            for t, sensors in handed_over(monitor.update(t_s, g, b).alarms):
                if self._tracking is not None:
                    self._tracking.step(sensors, t)
        except InputError as error:  # stamps that do not advance: the monitor stops
            self._health, self._health_text = None, f'off: {error}'
            self.get_logger().warning(f'health monitor stopped: {error}')
            return
        for index, alarm in enumerate(monitor.alarms):
            if self._health_sent.get(index) == alarm.settled:
                continue
            self._health_sent[index] = alarm.settled
            document = alarm.to_dict()
            self._alarm_pub.publish(String(data=json.dumps(document)))
            self.get_logger().error(
                f'health alarm: {alarm.kind} at t={alarm.t_s:.3f} s, sensors {list(alarm.sensors)}'
                f' (statistic {alarm.statistic:.1f} > {alarm.threshold:.1f})'
                + ('' if alarm.settled else '; attribution to be confirmed')
            )

    def _refuse(self, reason: str) -> None:
        self._problem = reason
        state = f'keeping {self._source}' if self.compensating else 'running UNCOMPENSATED'
        self.get_logger().warning(f'calibration refused: {reason}; {state}')
        self._publish_diagnostics()

    # ----------------------------------------------------------------- samples

    def _on_raw(self, data: bytes) -> None:
        """A serialized GradientTensor; a malformed one is dropped and counted."""
        try:
            stamp_ns, values, _, _ = self._cdr.read(data)
        except MessageError as error:
            self._drop(None, f'a malformed gradient/raw ({error})')
            return
        if self._horizon.refuse('gradient/raw', stamp_ns):
            return
        if self._effects is None:
            self._compensate(stamp_ns, values)
            return
        for held in self._effects.submit(stamp_ns, (stamp_ns, values), time.monotonic()):
            self._compensate(*held)  # in order, once its channels reached its stamp

    def _release_held(self, flush: bool = False) -> None:
        """Compensate the sets held for a channel message that need wait no longer."""
        if self._effects is not None:
            for held in self._effects.release(time.monotonic(), flush=flush):
                self._compensate(*held)

    def _compensate(self, stamp_ns: int, values: np.ndarray) -> None:
        """Eq. 19 on one set: ``values`` (30,) as io/gradient_tensor.GradientTensorCdr reads
        them (``G_m`` T/m, its 1-sigma T/m, ``B_1'`` T, its covariance T^2)."""
        g_raw, b_reference = values[:9].reshape(3, 3), values[18:21]
        if not (np.all(np.isfinite(g_raw)) and plausible_readings(b_reference)):
            self._drop(stamp_ns, 'a non-finite, implausible or malformed input')
            return
        x = None
        if self._effects is not None:  # the terms' regressors; None: a channel is unknown
            x = self._effects.regressors(stamp_ns, b_reference)
            if x is None:
                if self._warn():
                    self.get_logger().warning(
                        f'dropped the set at stamp {stamp_ns} ns: {self._effects.reason} '
                        '(never compensated with zero)'
                    )
                return
        if self._interference is None:
            g = g_raw
        else:
            regressors = None if x is None else x[None]
            g = compensate(
                g_raw[None], b_reference[None], self._interference, self._geometry, regressors
            )[0]
        variance = np.zeros(9)
        if self._tracking is not None:
            g, variance = self._tracking.one(stamp_ns, g)
        norm_nt = float(np.linalg.norm(g) * NT_PER_T)
        if not (np.all(np.isfinite(g)) and np.isfinite(norm_nt)):  # never publish inf or NaN
            self._drop(stamp_ns, 'a non-finite compensated tensor')
            return
        if self._sigma is not None:  # overflow of an absurd covariance: NaN, unknown
            sigma = np.sqrt(self._sigma.one(b_reference, x).reshape(9) ** 2 + variance)
            sigma[~np.isfinite(sigma)] = np.nan
        else:  # uncompensated, the raw tensor's own sigma holds
            sigma = gt.UNKNOWN_SIGMA if self.compensating else values[9:18]
        out = np.concatenate((g.reshape(9), sigma, values[18:]))
        if self.compensating:
            self._comp_pub.publish(self._cdr.write(stamp_ns, out, gt.COMPENSATED, self._created))
        else:
            self._comp_pub.publish(self._cdr.write(stamp_ns, out, gt.UNCOMPENSATED))
        self._norm_pub.publish(cv.float64_cdr(norm_nt))
        if self._health is not None:
            self._health_buffer.append((stamp_ns * S_PER_NS, g, b_reference))
        self.published += 1
        self.compensated += self._interference is not None
        self._pair_truth(0, stamp_ns, (g_raw, g))

    def _drop(self, stamp_ns: int | None, what: str) -> None:
        self.dropped_non_finite += 1
        if self._warn():
            where = '' if stamp_ns is None else f' at stamp {stamp_ns} ns'
            self.get_logger().warning(f'dropped {what}{where}')

    def _on_truth(self, data: bytes) -> None:
        """A serialized ``gradient/truth``; a malformed one cannot be scored: its sample stays
        unscored (evicted, counted as ``unscored_evicted``)."""
        try:
            stamp_ns, values, _, _ = self._cdr.read(data)
        except MessageError:
            return
        if not self._horizon.refuse('gradient/truth', stamp_ns):
            self._pair_truth(1, stamp_ns, values[:9].reshape(3, 3))

    def _pair_truth(self, stream: int, stamp_ns: int, value: Any) -> None:
        """Join ``(G_m, G)`` (stream 0) with ``gradient/truth`` (stream 1) and score the pair."""
        matched = self._truth.add(stream, stamp_ns, value)
        if matched is not None:
            (g_before, g_after), g_true = matched
            self._score(g_before, g_after, g_true)

    def _score(self, g_before: np.ndarray, g_after: np.ndarray, g_true: np.ndarray) -> None:
        """Running mean of the eq. 24 terms (a sample where it is undefined is skipped)."""
        term = float(epsilon_terms(g_before[None], g_after[None], g_true[None])[0])
        if not np.isfinite(term):
            return
        self._eps_sum += term
        self._eps_count += 1
        eps = self._eps_sum / self._eps_count
        self._eps_pub.publish(Float64(data=float(eps)))
        self._pct_pub.publish(Float64(data=float(100.0 * (1.0 - eps))))

    def _reset_metrics(self) -> None:
        self._eps_sum, self._eps_count = 0.0, 0

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._reset_metrics()
        response.success, response.message = True, 'running epsilon restarted'
        return response

    def _publish_diagnostics(self) -> None:
        channel_level, channel_text, channel_values = self._channels_status()
        if self.compensating:
            level = WARN if self._problem else OK
            text = f'compensating with {self._source}' + (
                f'; refused a newer one: {self._problem}' if self._problem else ''
            )
            if self._gate.key is None:
                text += '; unauthenticated (no calibration_key_file)'
            if self._forced:  # written although its samples failed a check (force)
                level, text = WARN, f'{text}; the calibration was forced: {self._forced}'
            if channel_level == WARN:
                level, text = WARN, f'{text}; {channel_text}'
        else:
            level, text = WARN, f'UNCOMPENSATED: {self._problem}'
        eps = self._eps_sum / self._eps_count if self._eps_count else float('nan')
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(
            status(
                self,
                'compensation',
                level,
                text,
                '',
                {
                    'compensating': self.compensating,
                    'sigma': self._sigma_text,
                    'published': self.published,
                    'dropped_non_finite': self.dropped_non_finite,
                    'epsilon': float(eps),
                    'scored_samples': self._eps_count,
                    'unscored_evicted': self._truth.evicted,
                    'authentication': self._gate.authentication,
                    'calibration_publisher': self._gate.publisher,
                },
            )
        )
        channels = status(self, 'channels', channel_level, channel_text, '', channel_values)
        array.status.extend((channels, self._health_status()))
        self._diag_pub.publish(array)

    def _channels_status(self) -> tuple[int, str, dict[str, Any]]:
        """``tetra/compensator: channels`` as (level, message, values)
        (:meth:`~.channels.LiveEffects.report`; OK without terms)."""
        if self._effects is None:
            return OK, 'no terms: no channel read', {}
        warn, text, values = self._effects.report()
        return (WARN if warn else OK), text, values

    def _health_status(self) -> Any:
        """``tetra/compensator: health``: ERROR after an alarm (until a new calibration), WARN
        when the statistic passes half the threshold or the monitor is off, else OK."""
        monitor = self._health
        if monitor is None:
            return status(self, 'health', WARN, self._health_text, '', {})
        values: dict[str, Any] = {
            'statistic': monitor.last_glr,
            'drift_statistic': monitor.last_drift,
            'threshold': monitor.threshold,
            'alarms': len(monitor.alarms),
            'noise_scale': monitor.noise_scale,
            'samples': monitor.samples,
            **({} if self._tracking is None else self._tracking.values()),
        }
        if monitor.alarms:
            alarm = monitor.alarms[-1]
            values.update(kind=alarm.kind, sensors=str(list(alarm.sensors)), t_s=alarm.t_s)
            text = (
                f'ALARM: {alarm.kind} at t={alarm.t_s:.1f} s, sensors {list(alarm.sensors)}: '
                'the calibration no longer holds; '
                + alarm_cause(monitor.alarms[0].t_s - self._health_first_s, 'run')
            )
            return status(self, 'health', ERROR, text, '', values)
        rising = max(monitor.last_glr, monitor.last_drift) > 0.5 * monitor.threshold
        level = WARN if rising else OK
        text = 'statistic above half the threshold' if rising else self._health_text
        return status(self, 'health', level, text, '', values)


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer compensator``; 1 when the node refuses its parameters."""
    return spin_node(CompensatorNode, 'compensator', args)
