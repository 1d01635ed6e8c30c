"""``target`` node: magnetic targets located live from the compensated tensor and odometry.

Subscribes to ``gradient/compensated`` (the compensator's tetra_gradiometer_msgs/GradientTensor,
T/m, body frame) and
``odom`` (nav_msgs/Odometry: relative, the driver's ``/tetra/odom``; on a vehicle remap it to
the navigation's, ``-r odom:=/odom``, as the calibrator). The track (nodes/track.py): tensors
averaged over ``1 / sample_rate_hz`` (anti-alias: the detector and the fit need no more than
10 Hz at survey speeds), the odometry pose interpolated onto each (position linear,
orientation slerped; a sample whose nearest odometry is more than 0.5 s away is dropped and
counted), bounded to the last ``history_s``. Non-finite tensors, stamps not after the
previous one, malformed messages: dropped and counted on ``/diagnostics``.

When to search (``core.targets.locate`` with the offline ``locate`` command's settings: the
detector's defaults but ``false_alarms_per_hour``): when a pass completes (a straight leg of
at least 60 s ends: the heading leaves the leg's first heading by more than 15 degrees, a
gap over 2 s or a jump over 10 m, as the detector cuts legs), and every ``update_period_s``
(node clock; 0: on completed passes only) while new samples arrive. The search runs on a
copy of the track in a background thread (an hour at 10 Hz takes tens of seconds), never
two at once; the callbacks keep buffering meanwhile, and each result replaces the previous
one on every output. Too little track (no straight leg of 60 s yet) is not an error: the
outputs keep the last result and ``/diagnostics`` says "nothing to search yet". (The leg
length and turn are not parameters: on legs much shorter than 60 s the detector does not
hold its stated false-alarm rate.)

Outputs, all reliable and transient local (latched: a late subscriber gets the latest), in
the frame of the odometry messages (``odom``), stamped with the last searched sample:

* ``targets`` (geometry_msgs/PoseArray): a pose per target at its fitted position; the
  orientation rotates +x onto the target's moment (RViz's arrow points along the moment);
* ``targets/markers`` (visualization_msgs/MarkerArray): DELETEALL, then per target a sphere
  of 3-sigma half-axes (at least 0.1 m wide) and a label with the moment's magnitude;
* ``targets/json`` (std_msgs/String): the ``targets.json`` record of io/targets.py (the same
  document as ``locate``'s: positions, moments, their 1-sigma, times, fit RMS);
* ``detections`` (geometry_msgs/PoseArray): the vehicle's pose at the peak of every
  detection of the search (on the survey's own tensors, before any target is taken out).

A target whose fit holds a non-finite value is left out of every output and counted.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from nav_msgs.msg import Odometry
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from ..core import TetraGeometry
from ..core.targets import DetectorSettings, LocatorSettings, locate
from ..core.units import S_PER_NS
from ..errors import InputError, MessageError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..pipelines.window_check import MAX_ODOM_GAP_S
from . import target_messages as tm
from .common import (
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
    status,
)
from .managed import ManagedNode
from .process import spin_node
from .stamps import AHEAD_SPEC
from .track import SurveyTrack, TrackSnapshot

#: The outputs (relative: ``/tetra/targets`` ...).
TARGETS_TOPIC = 'targets'
MARKERS_TOPIC = 'targets/markers'
JSON_TOPIC = 'targets/json'
DETECTIONS_TOPIC = 'detections'
#: Period of the work between messages: resolving poses, starting a search, publishing, s.
TICK_S = 0.2

PARAMETERS = [
    POSITIONS_SPEC,
    ParamSpec(
        'false_alarms_per_hour',
        0.1,
        'Detector: design false-alarm rate of the target detection, per hour of straight '
        'legs (1e-6 to 60).',
        float_range=(1e-6, 60.0),
    ),
    ParamSpec(
        'sample_rate_hz',
        10.0,
        'The compensated tensor is averaged over 1/sample_rate_hz before it is kept, Hz '
        '(2 to 100).',
        float_range=(2.0, 100.0),
    ),
    ParamSpec(
        'history_s',
        7200.0,
        'Track kept and searched: the last history_s of samples, s (60 to 14400; a search '
        'of an hour at 10 Hz takes tens of seconds).',
        float_range=(60.0, 14400.0),
    ),
    ParamSpec(
        'update_period_s',
        30.0,
        'Search again at least this often while new samples arrive, s (node clock; 0 to '
        '3600; 0: only when a pass completes).',
        float_range=(0.0, 3600.0),
    ),
    WARN_THROTTLE_SPEC,
    AHEAD_SPEC,
    diagnostics_period_spec(),
]


@dataclass(frozen=True)
class _Outcome:
    """A search's result: ``located`` (None: nothing published), why not (``text``),
    whether that was a bug (``error``), and its duration, s."""

    located: tm.LocatedTargets | None
    text: str
    error: bool
    elapsed_s: float


class _Background:
    """One call at a time in a daemon thread (a search cannot be interrupted: at exit the
    process does not wait for it); the newest finished result is kept until taken, and
    :meth:`abandon` drops the result of the one running."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._result: _Outcome | None = None
        self._epoch = 0

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, work: Callable[[], _Outcome]) -> None:
        epoch = self._epoch

        def run() -> None:
            outcome = work()
            with self._lock:
                if epoch == self._epoch:
                    self._result = outcome

        self._thread = threading.Thread(target=run, name='target_locate', daemon=True)
        self._thread.start()

    def take(self) -> _Outcome | None:
        with self._lock:
            outcome, self._result = self._result, None
        return outcome

    def abandon(self) -> None:
        with self._lock:
            self._epoch += 1
            self._result = None


def _search(track: TrackSnapshot, geometry: TetraGeometry, settings: LocatorSettings) -> _Outcome:
    """``locate`` on ``track`` and its outputs (in the background thread: never raises)."""
    started = time.monotonic()
    try:
        targets, detected = locate(track.survey, geometry, settings)
        located = tm.located_targets(
            track,
            targets,
            detected,
            false_alarms_per_hour=settings.detector.false_alarms_per_hour,
        )
    except InputError as error:
        return _Outcome(None, f'nothing to search yet: {error}', False, time.monotonic() - started)
    except Exception:  # a bug: keep its traceback for the log, keep the node running
        return _Outcome(None, traceback.format_exc(), True, time.monotonic() - started)
    return _Outcome(located, '', False, time.monotonic() - started)


class TargetNode(ManagedNode):
    """Buffers the compensated tensor along the track and locates targets in it."""

    PARAMETERS = PARAMETERS

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('target', **kwargs)

    def configure(self, p: dict[str, Any]) -> None:
        """The track, the background search, publishers, subscriptions and timers."""
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        detector = DetectorSettings(false_alarms_per_hour=p['false_alarms_per_hour'])
        self._settings = LocatorSettings(detector=detector)
        self._track = SurveyTrack(
            sample_rate_hz=p['sample_rate_hz'], history_s=p['history_s'], legs=detector
        )
        self._period_s = float(p['update_period_s'])
        self._warn = Throttle(p['warn_throttle_s'])
        self._worker = _Background()
        self._frame = cv.ODOM_FRAME  # the odometry's, once a message came
        self.dropped_malformed = 0
        self._searched = (0, 0)  # track.added and passes at the last search's start
        self._last_start = self._now_s()
        self._runs = 0
        self._last: _Outcome | None = None  # the last search's outcome
        self._published: tm.LocatedTargets | None = None  # what the outputs hold
        self._no_odom_reported = 0

        check_serialization()  # the tensor is read from its serialized message
        self._cdr = gt.GradientTensorCdr(cv.ARRAY_FRAME)
        self._types = cv.rclpy_types()
        self._targets_pub = self.create_lifecycle_publisher(
            PoseArray, TARGETS_TOPIC, latched_qos()
        )
        self._markers_pub = self.create_lifecycle_publisher(
            MarkerArray, MARKERS_TOPIC, latched_qos()
        )
        self._json_pub = self.create_lifecycle_publisher(String, JSON_TOPIC, latched_qos())
        self._detections_pub = self.create_lifecycle_publisher(
            PoseArray, DETECTIONS_TOPIC, latched_qos()
        )
        self._diag_pub = self.diagnostics_publisher()
        self._horizon = self._diag_pub.inputs.watch_stamps(
            p['max_stamp_ahead_s'], p['warn_throttle_s']
        )
        gated = self.when_active
        tensor = self.create_subscription(
            gt.rclpy_class(),
            cv.COMPENSATED_NODE_TOPIC,
            gated(self._on_tensor),
            derived_qos(),
            raw=True,
        )
        odom = self.create_subscription(
            Odometry, cv.ODOM_NODE_TOPIC, gated(self._on_odom), derived_qos()
        )
        self._diag_pub.inputs.require(tensor, odom)
        self.create_timer(TICK_S, self._tick)
        self.create_diagnostics_timer(p['diagnostics_period_s'], self._publish_diagnostics)

    def activated(self) -> None:
        self._last_start = self._now_s()

    def released(self) -> None:
        self._worker.abandon()

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * S_PER_NS

    # ----------------------------------------------------------------- input

    def _on_tensor(self, data: bytes) -> None:
        """A serialized GradientTensor; a malformed or bad one is dropped and counted."""
        try:
            stamp_ns, values, _, _ = self._cdr.read(data)
        except MessageError as error:
            self.dropped_malformed += 1
            self._warn_drop(f'a malformed {cv.COMPENSATED_NODE_TOPIC} ({error})')
            return
        if self._horizon.refuse(cv.COMPENSATED_NODE_TOPIC, stamp_ns):
            return
        reason = self._track.add_tensor(stamp_ns, values[:9].reshape(3, 3))
        if reason is not None:
            self._warn_drop(f'{reason} at stamp {stamp_ns} ns')

    def _on_odom(self, msg: Odometry) -> None:
        stamp_ns = cv.stamp_to_ns(msg.header.stamp)
        if self._horizon.refuse(cv.ODOM_NODE_TOPIC, stamp_ns):
            return
        reason = self._track.add_odom(stamp_ns, cv.odometry_pose(msg))
        if reason is not None:
            self._warn_drop(reason)
        elif msg.header.frame_id:
            self._frame = msg.header.frame_id

    def _warn_drop(self, what: str) -> None:
        if self._warn():
            self.get_logger().warning(f'dropped {what}')

    # ----------------------------------------------------------------- search

    def _tick(self) -> None:
        """Resolve the waiting samples' poses, publish a finished search, start the next."""
        self._track.resolve()
        outcome = self._worker.take()
        if outcome is not None:
            self._finished(outcome)
        if self._worker.busy:
            return
        added, passes = self._track.added, self._track.counts.passes
        if added == self._searched[0]:
            return  # nothing new
        now = self._now_s()
        periodic = self._period_s > 0 and now - self._last_start >= self._period_s
        if passes > self._searched[1] or periodic:
            track = self._track.snapshot()
            if track is not None:
                self._searched, self._last_start = (added, passes), now
                geometry, settings = self._geometry, self._settings
                self._worker.start(lambda: _search(track, geometry, settings))

    def _finished(self, outcome: _Outcome) -> None:
        """Publish a finished search (and say so on ``/diagnostics`` at once)."""
        self._runs, self._last = self._runs + 1, outcome
        if outcome.error:
            self.get_logger().error(f'locate failed:\n{outcome.text}')
        elif outcome.located is not None:
            self._publish(outcome.located, outcome.elapsed_s)
        self._publish_diagnostics()

    def _publish(self, located: tm.LocatedTargets, elapsed_s: float) -> None:
        self._published = located
        types, stamp, frame = self._types, located.stamp_ns, self._frame
        self._targets_pub.publish(
            tm.pose_array_msg(
                types, located.positions, tm.x_axis_onto(located.moments), stamp, frame
            )
        )
        self._markers_pub.publish(
            tm.target_markers_msg(
                types, located.positions, located.position_sigmas, located.moments, stamp, frame
            )
        )
        self._json_pub.publish(String(data=located.document))
        self._detections_pub.publish(
            tm.pose_array_msg(
                types, located.detection_positions, located.detection_orientations, stamp, frame
            )
        )
        self.get_logger().info(
            f'{len(located.positions)} targets, {len(located.detection_positions)} detections '
            f'on {located.samples} samples ({elapsed_s:.1f} s)'
        )

    # ----------------------------------------------------------------- diagnostics

    def _summary(self) -> tuple[int, str]:
        """Level and message of ``tetra/target: targets``."""
        counts, last = self._track.counts, self._last
        if last is not None and last.error:
            return ERROR, 'locate failed (a bug: see the log); the outputs hold an older result'
        if counts.dropped_no_odom > self._no_odom_reported:
            self._no_odom_reported = counts.dropped_no_odom
            return WARN, (
                f'samples without odometry within {MAX_ODOM_GAP_S:g} s are dropped (is '
                f'{cv.ODOM_NODE_TOPIC} remapped to the navigation?)'
            )
        state = f'searching {len(self._track)} samples; ' if self._worker.busy else ''
        if last is None:
            return OK, state + 'no search yet'
        located = self._published
        if last.located is None or located is None:
            return OK, state + last.text
        return OK, state + (
            f'{len(located.positions)} targets, {len(located.detection_positions)} detections '
            f'in the last search ({located.samples} samples, {last.elapsed_s:.1f} s)'
        )

    def _publish_diagnostics(self) -> None:
        level, text = self._summary()
        if odom := self._track.odom_check.report():  # dropped or normalized since the last
            level, text = max(level, WARN), f'{text}; {odom}'
        counts, last, located = self._track.counts, self._last, self._published
        values: dict[str, Any] = {
            'received': counts.received,
            'buffered_samples': len(self._track),
            'pending_samples': self._track.pending,
            'dropped_malformed': self.dropped_malformed,
            'dropped_non_finite': counts.dropped_non_finite,
            'dropped_out_of_order': counts.dropped_out_of_order,
            'dropped_no_odom': counts.dropped_no_odom,
            'odom_dropped': counts.odom_dropped,
            **self._track.odom_check.values(),
            'restarts': counts.restarts,
            'passes': counts.passes,
            'searches': self._runs,
            'searching': self._worker.busy,
            'last_search_s': float('nan') if last is None else last.elapsed_s,
            'targets': 0 if located is None else len(located.positions),
            'detections': 0 if located is None else len(located.detection_positions),
            'searched_samples': 0 if located is None else located.samples,
            'targets_dropped_non_finite': 0 if located is None else located.dropped_non_finite,
        }
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(status(self, 'targets', level, text, '', values))
        self._diag_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer target``; 1 when the node refuses its parameters."""
    return spin_node(TargetNode, 'target', args)
