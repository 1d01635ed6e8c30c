"""``calibrator`` node: identifies the interference parameters ``k``, ``b`` (eqs. 15-18).

Reads ``gradient/raw`` (tetra_gradiometer_msgs/GradientTensor: ``G_m``, T/m, with the
reference reading ``B_1'`` of the same set, T) and accumulates the sets while enabled.
Services (std_srvs/Trigger but ``~/calibrate``):

* ``~/start``: forget earlier samples and collect (fly the trim manoeuvre now);
* ``~/stop``: stop collecting (samples are kept);
* ``~/calibrate`` (tetra_gradiometer_msgs/srv/Calibrate; the request's ``window_s``,
  ``force`` and ``effects`` apply to that call: :mod:`.calibrate_call`): solve with
  ``method`` on a snapshot of the samples collected in the window. Too few samples, or a
  body-frame field spanning too few directions (the attitude-coverage condition number is
  given), answer success=false with the reason. The known-gradient methods solve as
  ``calibrate`` does (:func:`~tetra_gradiometer.pipelines.window_check.identify_checked`):
  a regional world-frame gradient jointly when every sample has an ``odom`` attitude (else
  it is assumed zero, as the reply and the file's ``notes`` say), then the test of the fit's
  assumption; samples that fail it (a target, a bad stretch), or whose trim assessment (of
  every sample) predicts more than 2x the noise floor (too little attitude excitation), answer
  success=false with the figures (the failing part in s after the first sample, a passing
  sub-window), and nothing is written, unless ``force`` (then the warning goes into the
  file's ``notes``). On success the parameters are written atomically to
  ``calibration_file`` (with the regional gradient, its 1-sigma, the check, this node's name
  as ``source`` and the first and last sample stamps as ``samples_window_s``), published on
  ``calibration`` (tetra_gradiometer_msgs/Calibration,
  :mod:`~tetra_gradiometer.io.calibration_message`; transient local = latched), and the
  response carries the fit's figures. ``calibration_file`` is read-only after start-up
  (nobody on the ROS domain can point the write elsewhere), relative paths resolve under
  ``$ROS_HOME`` (default ``~/.ros``), and the write replaces only a previous calibration
  file: any other file there is left untouched and the call answers success=false.
* ``~/cancel``: stop a running solve; its ``~/calibrate`` answers success=false
  "cancelled ..." and writes nothing.

The solve runs off the executor (:class:`.solve_worker.SolveWorker`): in a worker thread
(one at a time), while the ``~/calibrate`` callback, in a reentrant callback group, waits
for it and then replies (synchronously, with the result). ``main()`` spins a
MultiThreadedExecutor, so meanwhile the samples, ``~/cancel``, a second ``~/calibrate``
(answered at once: "a solve is already running") and ``/diagnostics`` (state ``solving``,
``solve_elapsed_s``) are served.
``max_solve_s`` bounds the solve: ``paper_ga`` checks it and the cancel flag once per
generation and, at the limit, returns its best individual so far (the reply says after how
many generations); the closed-form methods take about a second per 10^6 samples and
``max_samples`` caps them. On a single-threaded executor (``demo``) the call still works but
blocks the other callbacks until the solve ends.

``method`` is one of ``core.identification.CALIBRATION_METHODS`` (the registry;
default ``known_gradient_lstsq_general``: the true gradient is taken as zero, a trim far
from targets).

Vehicle effects: the node keeps the messages of the channels the effects read
(``/tetra/temperature``, sensor_msgs/Temperature; the ``current`` of sensor_msgs/BatteryState
on ``/battery_state`` and on each of ``current_topics``), whether or not it collects, and
``~/calibrate`` fits the terms ``effects`` asks for (``auto``: those whose channels have
messages and pass the held-out test) jointly with ``k``, ``b``, through the code
``calibrate`` runs on a bag (:func:`.channels.sample_terms`: the channels interpolated onto
the samples' stamps, NaN where stale, never zero); the calibration written and published
carries the terms.

Trim guidance (:mod:`tetra_gradiometer.core.guidance`): while samples arrive, about once a
second (:data:`GUIDANCE_PERIOD_S`) the node publishes on ``~/guidance`` (std_msgs/String,
JSON of ``TrimAssessment.to_dict``, latched) the predicted 1-sigma of every parameter and of
the compensated tensor on a representative survey, the noise floor, the coverage condition
number, the attitudes covered, whether that is *enough* (predicted sigma within 1.1x the
floor) and else the next manoeuvre ("roll ±15° on heading 120–180°"); the key figures also go
on ``/diagnostics``. Per sample it only appends (the sums and the attitude bin of the
samples since the last tick are added in the timer, in its own callback group, or by a
``~/calibrate`` before it); a sample's attitude is the nearest ``odom`` message
(nav_msgs/Odometry: the relative topic, the driver's ``/tetra/odom``; on a vehicle remap it
to the navigation's, ``-r odom:=/odom``) within 0.5 s
(:class:`~tetra_gradiometer.pipelines.window_check.AttitudeHistory`), else unknown (the
coverage is that of the body-frame field direction). The survey and the candidate
manoeuvres are flown in ``earth_field_enu``; the sensor noise is ``sensor_noise_t`` (or
0.1 nT) until the samples estimate their own.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections import deque
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from std_msgs.msg import String
from std_srvs.srv import Trigger

from tetra_gradiometer_msgs.msg import Calibration
from tetra_gradiometer_msgs.srv import Calibrate

from ..core import TetraGeometry
from ..core.effects import parse_declaration
from ..core.guidance import TrimAssessment, TrimStatistics, assess, trim_statistics
from ..core.identification import Options, attitude_coverage
from ..core.plausibility import plausible_readings
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import OutputError, ParamsError, TetraError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..io.calibration import CalibrationFile, CalibrationFileError
from ..io.calibration_message import calibration_fields
from ..io.channels import TEMPERATURE, channel_topic, current_channels
from ..io.outputs import CALIBRATION, atomic_write_text
from ..pipelines.effects_choice import EffectsChoice
from ..pipelines.terms import WindowTerms
from ..pipelines.window_check import (
    KNOWN_GRADIENT_METHODS,
    AttitudeHistory,
    CheckedCalibration,
    identify_checked,
    joint_attitude,
)
from .authentication import key_id, node_key, sign
from .calibrate_call import SUB_WINDOW, CalibrateCall, kept
from .calibrator_params import DEFAULT_NOISE_T, PARAMETERS
from .channels import (
    ChannelHistory,
    channel_message,
    channel_stamp,
    sample_terms,
    subscribe_channels,
)
from .common import OK, WARN, derived_qos, latched_qos, resolve_node_path, status
from .managed import ManagedNode
from .process import spin_node
from .solve_worker import SolveWorker

#: Period of the trim guidance on ``~/guidance`` while samples arrive, s (the issue's ~1 Hz).
GUIDANCE_PERIOD_S = 1.0
#: How a refusal names the override, and how the note of a calibration kept by it starts
#: (pipelines/window_check.forced).
FORCE_NAME = 'force:=true'
FORCED = f'WARNING ({FORCE_NAME})'


class CalibratorNode(ManagedNode):
    """Collects ``(B_1', G_m)`` on demand and identifies the compensation parameters."""

    PARAMETERS = PARAMETERS
    DYNAMIC = (
        *('method', 'min_samples', 'max_samples', 'max_coverage_condition', 'force'),
        *('ga_seed', 'ga_generations', 'max_solve_s', 'earth_field_enu', 'sensor_noise_t'),
        'effects',
    )
    # What is written and how the samples are judged (the guidance's noise and field feed the
    # excitation refusal): all but the solve's time budget.
    LOCKED = tuple(name for name in DYNAMIC if name != 'max_solve_s')

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('calibrator', **kwargs)

    def configure(self, p: dict[str, Any]) -> None:
        """Buffers, the solve worker, publishers, subscriptions and services."""
        if p['min_samples'] > p['max_samples']:
            raise ParamsError(
                f"parameter 'min_samples' = {p['min_samples']} refused: must be at most "
                f'max_samples ({p["max_samples"]})'
            )
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        self._calibration_path = resolve_node_path(p['calibration_file'])
        self._key = node_key(p['calibration_key_file'])  # signs what is written and published
        self._lock = threading.Lock()
        self._collecting = False
        # Deques: dropping the oldest sample beyond max_samples is O(1).
        self._g: deque[np.ndarray] = deque()
        self._b: deque[np.ndarray] = deque()
        self._q: deque[np.ndarray] = deque()  # attitude per sample (NaN: unknown)
        self._t: deque[int] = deque()  # stamp per sample, ns
        self._dropped_implausible = 0
        self._state = 'idle'
        self._last_result = 'no calibration yet'
        self._last_ok: bool | None = None
        self._forced = ''  # the warning of the current calibration, written with force:=true
        self._calibrations = 0
        # The solve: off the executor, one at a time, cancellable.
        self._worker = SolveWorker('calibrator_solve', on_start=self._publish_diagnostics)
        # Trim guidance: recent odom (stamp ns, quaternion), samples not yet in the sums.
        self._odom = AttitudeHistory()
        # The channels' messages (temperature, currents) for the vehicle effects' terms.
        self._current_topics = tuple(p['current_topics'])
        self._signals = tuple(parse_declaration(d).effect_name for d in p['vehicle_signals'])
        self._channels = ChannelHistory(
            (
                TEMPERATURE,
                *current_channels(self._current_topics),
                *EffectsChoice(signals=self._signals).signal_channels,  # installed effects' too
            )
        )
        self._epoch = 0  # counts ~/start: a tick that straddles one discards its work
        # One fold of the guidance's sums at a time: its timer's, or a ~/calibrate's.
        self._guidance_lock = threading.Lock()
        self._assessed = (0, 0)  # (epoch, samples received) the assessment is of
        self._added: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (g, b, q)
        self._removed: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._statistics = TrimStatistics.empty()
        self._first_stamp: int | None = None
        self._last_stamp = 0
        self._n_received = 0
        self._assessment: TrimAssessment | None = None

        self._cal_pub = self.create_lifecycle_publisher(Calibration, 'calibration', latched_qos())
        self._diag_pub = self.diagnostics_publisher()
        self._horizon = self._diag_pub.inputs.watch_stamps(p['max_stamp_ahead_s'])
        gated = self.when_active
        raw = self.create_subscription(
            gt.rclpy_class(), 'gradient/raw', gated(self._on_raw), derived_qos()
        )
        self._diag_pub.inputs.require(raw)
        self.create_service(Trigger, '~/start', gated(self._on_start))
        self.create_service(Trigger, '~/stop', gated(self._on_stop))
        control = ReentrantCallbackGroup()  # served while a ~/calibrate waits for its solve
        self.create_service(
            Calibrate, '~/calibrate', gated(self._on_calibrate), callback_group=control
        )
        self.create_service(Trigger, '~/cancel', gated(self._on_cancel), callback_group=control)
        self.create_diagnostics_timer(p['diagnostics_period_s'], self._publish_diagnostics)
        self._guidance_pub = self.create_lifecycle_publisher(String, '~/guidance', latched_qos())
        # Each beside the samples: the guidance's work, and odom never behind a burst.
        guidance, odom = MutuallyExclusiveCallbackGroup(), MutuallyExclusiveCallbackGroup()
        self.create_timer(GUIDANCE_PERIOD_S, self._publish_guidance, callback_group=guidance)
        self.create_subscription(
            Odometry, cv.ODOM_NODE_TOPIC, gated(self._on_odom), derived_qos(), callback_group=odom
        )
        # The channels the vehicle effects read (nodes/channels.py), beside odom.
        subscribe_channels(self, self._channels.names, self._on_channel, callback_group=odom)

    # ----------------------------------------------------------------- samples

    def _on_raw(self, msg: Any) -> None:
        """One GradientTensor: its ``G_m`` (3, 3) T/m and ``B_1'`` (3,) T, while collecting."""
        tensor = gt.tensor_set_from_msg(msg)
        stamp_ns = tensor.stamp_ns
        if self._horizon.refuse('gradient/raw', stamp_ns) or not self._collecting:
            return
        with self._lock:
            g, b = tensor.g, tensor.reference_field
            if not (np.all(np.isfinite(g)) and plausible_readings(b)):
                self._dropped_implausible += 1  # the offline tools' rule; never fitted
                return
            sample = (g, b, self._odom.at(stamp_ns))
            self._g.append(sample[0])
            self._b.append(sample[1])
            self._q.append(sample[2])
            self._t.append(stamp_ns)
            self._added.append(sample)
            self._first_stamp = stamp_ns if self._first_stamp is None else self._first_stamp
            self._last_stamp, self._n_received = stamp_ns, self._n_received + 1
            while len(self._g) > self.get_parameter('max_samples').value:
                self._removed.append((self._g.popleft(), self._b.popleft(), self._q.popleft()))
                self._t.popleft()

    def _on_odom(self, msg: Odometry) -> None:
        stamp_ns = cv.stamp_to_ns(msg.header.stamp)
        if not self._horizon.refuse(cv.ODOM_NODE_TOPIC, stamp_ns):
            self._odom.add(stamp_ns, cv.odometry_orientation(msg))

    def _on_channel(self, name: str, msg: Any) -> None:
        """A temperature or current message: kept whether or not collecting, as odom."""
        stamp_ns = channel_stamp(msg, self.get_clock().now().nanoseconds)
        if self.active and not self._horizon.refuse(channel_topic(name), stamp_ns):
            self._channels.add(name, stamp_ns, channel_message(name, msg))

    # ----------------------------------------------------------------- guidance

    def _reset_guidance(self) -> None:
        """Forget the sums (``~/start``); the caller holds the lock (or is ``__init__``)."""
        self._added = []
        self._removed = []
        self._statistics = TrimStatistics.empty()
        self._first_stamp = None
        self._last_stamp = 0
        self._n_received = 0
        self._assessment = None

    def _batch(self, samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> TrimStatistics:
        if not samples:
            return TrimStatistics.empty()
        g, b, q = (np.array(column) for column in zip(*samples, strict=True))
        return trim_statistics(b, g, self._geometry, orientation_xyzw=q)

    def _publish_guidance(self) -> None:
        """Fold the new samples into the sums, assess, publish ``~/guidance`` (timer)."""
        with self._guidance_lock:
            assessment = self._fold()
        if assessment is not None:
            document = json.dumps(assessment.to_dict(), allow_nan=False)
            self._guidance_pub.publish(String(data=document))

    def _assessment_of(self, received: int) -> TrimAssessment | None:
        """The guidance's assessment of the samples received up to ``received`` (a snapshot's),
        folded now if its timer has not (else a ~/calibrate right after the last samples meets
        the assessment of the first few); None when samples came after the snapshot."""
        with self._guidance_lock:
            self._fold()
        with self._lock:
            current = self._assessed == (self._epoch, received)
            return self._assessment if current else None

    def _fold(self) -> TrimAssessment | None:
        """Fold the new samples into the sums and assess them: the new assessment, or None
        (nothing new, or it failed); the caller holds the guidance lock."""
        with self._lock:
            added, removed, epoch = self._added, self._removed, self._epoch
            self._added, self._removed = [], []
            span_s = (self._last_stamp - (self._first_stamp or 0)) * S_PER_NS
            rate = (self._n_received - 1) / span_s if span_s > 0 else 1.0
            statistics, received = self._statistics, self._n_received
        if not added and not removed:
            return None
        statistics = statistics.plus(self._batch(added)).minus(self._batch(removed))
        try:
            assessment = assess(
                statistics,
                self._geometry,
                self.get_parameter('earth_field_enu').value,
                sample_rate_hz=rate,
                sensor_noise_t=self.get_parameter('sensor_noise_t').value or DEFAULT_NOISE_T,
                symmetric=self.get_parameter('method').value == 'known_gradient_lstsq',
                max_coverage_condition=self.get_parameter('max_coverage_condition').value,
            )
        except (TetraError, np.linalg.LinAlgError) as error:  # never seen; never fatal
            self.get_logger().warning(f'trim guidance: {error}')
            assessment = None
        with self._lock:
            if epoch != self._epoch:  # a ~/start came meanwhile: these sums are stale
                return None
            self._statistics, self._assessment = statistics, assessment
            self._assessed = (epoch, received)
        return assessment

    def _guidance_values(self) -> dict[str, Any]:
        """The key figures of the last assessment, for /diagnostics."""
        assessment = self._assessment
        if assessment is None:
            return {}
        advice = assessment.advice
        return {
            'guidance': 'enough' if assessment.enough else 'not enough',
            'predicted_sigma_nT_per_m': assessment.predicted_sigma * NT_PER_T,
            'noise_floor_nT_per_m': assessment.noise_floor * NT_PER_T,
            'coverage_condition_number': assessment.condition_number,
            'coverage': assessment.coverage.text,
            'next_manoeuvre': '' if advice is None else advice.text,
        }

    @property
    def n_samples(self) -> int:
        with self._lock:
            return len(self._g)

    # ----------------------------------------------------------------- services

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            discarded = len(self._g)
            self._g, self._b, self._q, self._t = deque(), deque(), deque(), deque()
            self._reset_guidance()
            self._epoch += 1
            self._collecting = True
        self._state = 'collecting'
        response.success = True
        response.message = f'collecting ({discarded} earlier samples discarded)'
        self.get_logger().info(response.message)
        self._publish_diagnostics()
        return response

    def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._collecting = False
        self._state = 'stopped'
        response.success, response.message = True, f'stopped with {self.n_samples} samples'
        self.get_logger().info(response.message)
        self._publish_diagnostics()
        return response

    def _on_calibrate(
        self, request: Calibrate.Request, response: Calibrate.Response
    ) -> Calibrate.Response:
        response.residual_t_per_m = response.residual_over_floor = float('nan')
        result = self._worker.run(lambda: self._calibrate(request, response))
        if result is None:
            response.success, response.message = False, 'a solve is already running'
            return response
        ok, message = result
        response.success, response.message = ok, message
        self._last_ok, self._last_result = ok, message
        if ok:
            self.get_logger().info(f'calibrate: {message}')
        else:
            self.get_logger().warning(f'calibrate: {message}')
        self._publish_diagnostics()
        return response

    def _on_cancel(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self._worker.cancel():
            response.success, response.message = False, 'no solve is running'
            return response
        response.success, response.message = True, 'cancelling the running solve'
        self.get_logger().info(response.message)
        return response

    def deactivated(self) -> None:
        """A running solve is cancelled (its ``~/calibrate`` answers "cancelled"); the
        samples and the calibration file stay."""
        self._worker.cancel()

    def released(self) -> None:
        """Cancel a running solve and wait for its worker (at most one GA generation, or the
        rest of a closed-form solve), so no worker outlives the configuration."""
        self._worker.shutdown()

    def _snapshot(self, call: CalibrateCall) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The samples received so far, and those in ``call``'s window in stamp order, one per
        stamp: stamps (n,) ns, ``G_m`` (n, 3, 3) T/m, ``B_1'`` (n, 3) T."""
        with self._lock:
            t = np.array(self._t, dtype=np.int64)
            g = np.array(self._g).reshape(-1, 3, 3)
            b = np.array(self._b).reshape(-1, 3)
            received = self._n_received
        _, first = np.unique(t, return_index=True)  # sorted; a repeated stamp counts once
        first = first[call.select(t[first])]
        return received, t[first], g[first], b[first]

    def _options(self, method: str, stamps_ns: np.ndarray) -> tuple[Options, tuple[str, ...]]:
        """The solve's options; for the known-gradient methods the attitudes at the samples'
        ``stamps_ns`` for a joint regional gradient when every sample has one, and the note
        saying which."""
        options = Options(
            rng=np.random.default_rng(self.get_parameter('ga_seed').value),
            generations=int(self.get_parameter('ga_generations').value),
            max_coverage_condition=float(self.get_parameter('max_coverage_condition').value),
            deadline_s=time.monotonic() + float(self.get_parameter('max_solve_s').value),
            should_stop=self._worker.should_stop,
        )
        if method not in KNOWN_GRADIENT_METHODS:
            return options, ()
        orientation, note = joint_attitude(self._odom.over(stamps_ns))
        return dataclasses.replace(options, orientation_xyzw=orientation), (note,)

    def _calibrate(
        self, request: Calibrate.Request, response: Calibrate.Response
    ) -> tuple[bool, str]:
        """Solve on a snapshot of the request's samples; write and publish on success (the
        figures into ``response``)."""
        try:
            call = CalibrateCall.parse(request, self.get_parameter)
        except TetraError as error:
            return False, str(error)
        received, t, g, b = self._snapshot(call)
        method = self.get_parameter('method').value
        minimum = int(self.get_parameter('min_samples').value)
        maximum = int(self.get_parameter('max_samples').value)
        if minimum > maximum:
            return False, f'min_samples {minimum} exceeds max_samples {maximum}: lower it'
        if len(g) < minimum:
            return False, (
                f'{call.describe(len(g))} are too few (need at least {minimum}); call '
                '~/start, fly the trim manoeuvre, then ~/stop (or widen window_s)'
            )
        response.samples = len(t)
        options, notes = self._options(method, t)
        try:
            terms = self._terms(method, t, g, b, options, call.effects)
            options = dataclasses.replace(options, terms=terms.candidates)
            checked = identify_checked(
                method,
                t,
                g,
                b,
                self._geometry,
                options,
                window=call.describe(len(t)),
                first_ns=int(t[0]),
                force=call.force,
                force_name=FORCE_NAME,
                sub_window=SUB_WINDOW,
                notes=(*notes, *terms.notes),
                # the guidance's, of every sample: not of a narrower window
                assessment=None if call.window_s is not None else self._assessment_of(received),
                lacking=terms.lacking,
            )
        except (TetraError, np.linalg.LinAlgError) as error:
            return False, str(error)
        return self._keep(checked, method, terms, (t[0] * S_PER_NS, t[-1] * S_PER_NS), response)

    def _terms(
        self, method: str, t: np.ndarray, g: np.ndarray, b: np.ndarray, options: Options,
        effects: str,
    ) -> WindowTerms:
        """The vehicle effects the samples are fitted with (``effects``; the channels'
        messages received), chosen as ``calibrate`` chooses them on a bag; none when the
        samples span too few field directions (the solve refuses them, saying so)."""
        if not attitude_coverage(b) <= options.max_coverage_condition:
            return WindowTerms()
        choice = EffectsChoice.parse(effects, self._current_topics)
        choice = dataclasses.replace(choice, signals=self._signals)
        series = self._channels.series()
        orientation = options.orientation_xyzw
        return sample_terms(method, t, g, b, series, self._geometry, choice, orientation)

    def _keep(
        self,
        checked: CheckedCalibration,
        method: str,
        terms: WindowTerms,
        window_s: tuple[float, float],
        response: Calibrate.Response,
    ) -> tuple[bool, str]:
        """Write and publish a solved calibration (unless cancelled) fitted on the samples
        stamped ``window_s`` (first, last, s); the reply, its figures into ``response``."""
        result = checked.calibration
        generations = int(self.get_parameter('ga_generations').value)
        ran = result.details.get('generations', generations)
        if self._worker.should_stop():
            progress = f' after {ran} of {generations} generations' if method == 'paper_ga' else ''
            return False, f'cancelled (~/cancel){progress}; nothing written'
        budget = float(self.get_parameter('max_solve_s').value)
        stopped = (
            f'; stopped at max_solve_s {budget:g} s after {ran} of {generations} generations'
            if result.details.get('stopped') == 'deadline'
            else ''
        )
        try:
            calibration = CalibrationFile.from_calibration(result, self._geometry)
        except CalibrationFileError as error:  # k or b outside the physical bounds
            return False, str(error)
        diagnostics = {
            **calibration.diagnostics,
            **checked.diagnostics(),
            'effects': terms.diagnostics(),
            'source': self.get_fully_qualified_name(),
            'samples_window_s': [float(v) for v in window_s],
        }
        calibration = dataclasses.replace(calibration, diagnostics=diagnostics)
        path, text = self._calibration_path, calibration.to_yaml()
        text = text if self._key is None else sign(text, self._key)
        try:  # replaces only a previous calibration
            atomic_write_text(path, text, CALIBRATION, force=True)
        except (OSError, OutputError) as error:
            return False, f'solved, but cannot write {path}: {error}'
        message = Calibration(**calibration_fields(text, 'the calibration written'))
        message.header.stamp = self.get_clock().now().to_msg()
        message.header.frame_id = cv.ARRAY_FRAME
        self._cal_pub.publish(message)
        self._forced = next((n for n in checked.notes if n.startswith(FORCED)), '')
        self._calibrations += 1
        self._state = 'calibrated' if not self._collecting else 'collecting'
        return True, kept(response, checked, stopped, path)

    def _publish_diagnostics(self) -> None:
        odom = self._odom.check.report()  # odom messages dropped or normalized since the last
        level = WARN if self._last_ok is False or self._forced or odom else OK
        running = self._worker.running_s
        state, elapsed = self._state, self._worker.last_s
        message = f'{state}: {self._last_result}'
        if self._forced:  # until a calibration that passed its checks replaces it
            message = f'{message}; the calibration in use was forced: {self._forced}'
        if running is not None:
            state, elapsed = 'solving', running
            budget = self.get_parameter('max_solve_s').value
            message = f'solving for {elapsed:.1f} s (max_solve_s {budget:g})'
        message += f'; {odom}' * bool(odom)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(
            status(
                self,
                'calibration',
                level,
                message,
                '',
                {
                    'state': state,
                    'solve_elapsed_s': float(elapsed),
                    'samples': self.n_samples,
                    'calibrations': self._calibrations,
                    'dropped_implausible': self._dropped_implausible,
                    **self._odom.check.values(),
                    'method': self.get_parameter('method').value,
                    'effects': self.get_parameter('effects').value,
                    **{f'{n} messages': count for n, count in self._channels.counts().items()},
                    'calibration_file': str(self._calibration_path),
                    'authentication': 'none: unsigned (no calibration_key_file)'
                    if self._key is None
                    else f'HMAC-SHA256, key id {key_id(self._key)}',
                    **self._guidance_values(),
                },
            )
        )
        self._diag_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer calibrator``; 1 when the node refuses its parameters.

    A MultiThreadedExecutor: one thread for the waiting ``~/calibrate``, one for a second
    ``~/calibrate`` or ``~/cancel``, the others for the samples and ``/diagnostics``."""
    return spin_node(CalibratorNode, 'calibrator', args, threads=4)
