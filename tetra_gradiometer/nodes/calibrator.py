"""``calibrator`` node: identifies the interference parameters ``k``, ``b`` (eqs. 15-18).

Pairs ``gradient/raw`` (``G_m``, T/m) with ``reference_field`` (``B_1'``, T) by identical
stamp and accumulates the pairs while enabled. Services (std_srvs/Trigger):

* ``~/start``: forget earlier samples and collect (fly the trim manoeuvre now);
* ``~/stop``: stop collecting (samples are kept);
* ``~/calibrate``: solve with ``method`` on a snapshot of the collected samples. Too few
  samples, or a body-frame field spanning too few directions (the attitude-coverage
  condition number is given), answer success=false with the reason. On success the
  parameters are written atomically to ``calibration_file`` and published on
  ``calibration`` (std_msgs/String holding the calibration file's YAML text, transient
  local = latched).
  ``calibration_file`` is read-only after start-up (nobody on the ROS domain can point the
  write elsewhere), relative paths resolve under ``$ROS_HOME`` (default ``~/.ros``), and
  the write replaces only a previous calibration file: any other file there is left
  untouched and the call answers success=false.
* ``~/cancel``: stop a running solve; its ``~/calibrate`` answers success=false
  "cancelled ..." and writes nothing.

The solve runs off the executor: in a worker thread (one at a time), while the
``~/calibrate`` callback, in a reentrant callback group, waits for it and then replies
(synchronously, with the result). ``main()`` spins a MultiThreadedExecutor, so meanwhile
the samples, ``~/cancel``, a second ``~/calibrate`` (answered at once: "a solve is already
running") and ``/diagnostics`` (state ``solving``, ``solve_elapsed_s``) are served.
``max_solve_s`` bounds the solve: ``paper_ga`` checks it and the cancel flag once per
generation and, at the limit, returns its best individual so far (the reply says after how
many generations); the closed-form methods take about a second per 10^6 samples and
``max_samples`` caps them. On a single-threaded executor (``demo``) the call still works but
blocks the other callbacks until the solve ends.

``method`` is one of ``core.identification.CALIBRATION_METHODS`` (the registry;
default ``known_gradient_lstsq_general``: the true gradient is taken as zero, a trim far
from targets).
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import JointState, MagneticField
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..core import TetraGeometry
from ..core.identification import (
    CALIBRATION_METHODS,
    DEFAULT_METHOD,
    MAX_COVERAGE_CONDITION,
    METHODS,
    MIN_SAMPLES,
    Options,
    identify,
)
from ..core.plausibility import plausible_readings
from ..errors import OutputError, ParamsError, TetraError
from ..io import conversions as cv
from ..io.calibration import CalibrationFile, CalibrationFileError, save_calibration
from .common import (
    NAMESPACE,
    OK,
    POSITIONS_SPEC,
    WARN,
    ParamSpec,
    StampPairer,
    declare_parameters,
    derived_qos,
    diagnostics_period_spec,
    latched_qos,
    one_of,
    positive,
    resolve_node_path,
    spin_node,
    status,
    tensor_or_nan,
)

#: Bounds of ``max_samples`` and ``ga_generations`` (see their descriptions).
MAX_SAMPLES = 500_000
MAX_GENERATIONS = 20_000


def _path(value: str) -> str | None:
    return None if value.strip() else 'must name a file'


PARAMETERS = [
    POSITIONS_SPEC,
    ParamSpec(
        'method',
        DEFAULT_METHOD,
        'Identification method: '
        + '; '.join(f'{name} ({METHODS[name].description})' for name in CALIBRATION_METHODS)
        + '.',
        one_of(*CALIBRATION_METHODS),
    ),
    ParamSpec(
        'calibration_file',
        'calibration.yaml',
        'Where ~/calibrate writes the parameters (YAML, '
        'written atomically; only a previous calibration file is replaced). Read-only after '
        'start-up; "~" is expanded, a relative path is under $ROS_HOME (default ~/.ros).',
        _path,
    ),
    ParamSpec(
        'min_samples',
        100,
        f'Fewest sample sets ~/calibrate accepts (the solvers need >= {MIN_SAMPLES}; at most '
        'max_samples).',
        int_range=(MIN_SAMPLES, MAX_SAMPLES),
    ),
    ParamSpec(
        'max_samples',
        200_000,
        f'Most sample sets kept while collecting (older ones are dropped); at most {MAX_SAMPLES}: '
        '42 min of trim at 200 sets/s, a solve of about 1 s and 0.4 GB.',
        int_range=(MIN_SAMPLES, MAX_SAMPLES),
    ),
    ParamSpec(
        'max_coverage_condition',
        MAX_COVERAGE_CONDITION,
        "Refuse samples whose attitude-coverage condition number (of [B_1' 1], unit columns) "
        'exceeds this: the body-frame field spans too few directions (at most 1e8: beyond, '
        'the solve loses more than half of its 16 digits).',
        positive,
        float_range=(1.0, 1e8),
    ),
    ParamSpec('ga_seed', 0, 'paper_ga: random seed.', int_range=(0, 2**31 - 1)),
    ParamSpec(
        'ga_generations',
        1000,
        f'paper_ga: generations (the paper: 1000; at most {MAX_GENERATIONS}, about 4 s on one '
        'core: more does not lower its objective, which stalls within a few thousand).',
        int_range=(1, MAX_GENERATIONS),
    ),
    ParamSpec(
        'max_solve_s',
        60.0,
        'Time budget of one ~/calibrate solve, s (0.1-600): paper_ga stops at it and returns '
        'its best so far; the closed-form methods take about 1 s per 10^6 samples.',
        positive,
        float_range=(0.1, 600.0),
    ),
    diagnostics_period_spec(),
]


class CalibratorNode(Node):
    """Collects ``(B_1', G_m)`` on demand and identifies the compensation parameters."""

    def __init__(self, **kwargs) -> None:
        kwargs.setdefault('namespace', NAMESPACE)
        super().__init__('calibrator', **kwargs)
        p = declare_parameters(
            self,
            PARAMETERS,
            dynamic=(
                'method',
                'min_samples',
                'max_samples',
                'max_coverage_condition',
                'ga_seed',
                'ga_generations',
                'max_solve_s',
            ),
        )
        if p['min_samples'] > p['max_samples']:
            raise ParamsError(
                f"parameter 'min_samples' = {p['min_samples']} refused: must be at most "
                f'max_samples ({p["max_samples"]})'
            )
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        self._calibration_path = resolve_node_path(p['calibration_file'])
        self._lock = threading.Lock()
        self._collecting = False
        self._g: list[np.ndarray] = []
        self._b: list[np.ndarray] = []
        self._pairer = StampPairer(2)
        self._dropped_implausible = 0
        self._state = 'idle'
        self._last_result = 'no calibration yet'
        self._last_ok: bool | None = None
        self._calibrations = 0
        # The solve: one worker thread; the lock is held while a solve runs.
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix='calibrator_solve')
        self._solving = threading.Lock()
        self._cancel = threading.Event()
        self._solve_started: float | None = None
        self._solve_s = 0.0

        self._cal_pub = self.create_publisher(String, 'calibration', latched_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_subscription(JointState, 'gradient/raw', self._on_raw, derived_qos())
        self.create_subscription(
            MagneticField, 'reference_field', self._on_reference, derived_qos()
        )
        self.create_service(Trigger, '~/start', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        control = ReentrantCallbackGroup()  # served while a ~/calibrate waits for its solve
        self.create_service(Trigger, '~/calibrate', self._on_calibrate, callback_group=control)
        self.create_service(Trigger, '~/cancel', self._on_cancel, callback_group=control)
        self.create_timer(p['diagnostics_period_s'], self._publish_diagnostics)

    # ----------------------------------------------------------------- samples

    def _on_raw(self, msg: JointState) -> None:
        self._add(0, cv.stamp_to_ns(msg.header.stamp), tensor_or_nan(msg))

    def _on_reference(self, msg: MagneticField) -> None:
        self._add(1, cv.stamp_to_ns(msg.header.stamp), cv.magnetic_field_vector(msg))

    def _add(self, stream: int, stamp_ns: int, value: np.ndarray) -> None:
        if not self._collecting:
            return
        with self._lock:
            pair = self._pairer.add(stream, stamp_ns, value)
            if pair is None:
                return
            if not (np.all(np.isfinite(pair[0])) and plausible_readings(pair[1])):
                self._dropped_implausible += 1  # the offline tools' rule; never fitted
                return
            self._g.append(pair[0])
            self._b.append(pair[1])
            if len(self._g) > self.get_parameter('max_samples').value:
                del self._g[0], self._b[0]

    @property
    def n_samples(self) -> int:
        with self._lock:
            return len(self._g)

    # ----------------------------------------------------------------- services

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self._g, self._b = [], []
            self._pairer.clear()
            self._collecting = True
        self._state = 'collecting'
        response.success, response.message = True, 'collecting (earlier samples discarded)'
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
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        if not self._solving.acquire(blocking=False):
            response.success, response.message = False, 'a solve is already running'
            return response
        try:
            self._cancel.clear()
            self._solve_started = time.monotonic()
            self._publish_diagnostics()
            try:
                ok, message = self._worker.submit(self._calibrate).result()
            except RuntimeError:  # the worker was shut down: the node is stopping
                ok, message = False, 'the calibrator is shutting down'
        finally:
            self._solve_s = time.monotonic() - (self._solve_started or time.monotonic())
            self._solve_started = None
            self._solving.release()
        response.success, response.message = ok, message
        self._last_ok, self._last_result = ok, message
        if ok:
            self.get_logger().info(f'calibrate: {message}')
        else:
            self.get_logger().warning(f'calibrate: {message}')
        self._publish_diagnostics()
        return response

    def _on_cancel(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self._solve_started is None:
            response.success, response.message = False, 'no solve is running'
            return response
        self._cancel.set()
        response.success, response.message = True, 'cancelling the running solve'
        self.get_logger().info(response.message)
        return response

    def stop_work(self) -> None:
        """Cancel a running solve and wait for its worker (at most one GA generation, or the
        rest of a closed-form solve); ``spin_node`` calls it before stopping the executor."""
        self._cancel.set()
        self._worker.shutdown(wait=True, cancel_futures=True)

    def destroy_node(self) -> None:
        """Stop the solve first, so no worker outlives the node."""
        self.stop_work()
        super().destroy_node()

    def _calibrate(self) -> tuple[bool, str]:
        """Solve on a snapshot of the samples; write and publish on success."""
        with self._lock:
            g = np.array(self._g).reshape(-1, 3, 3)
            b = np.array(self._b).reshape(-1, 3)
        method = self.get_parameter('method').value
        minimum = int(self.get_parameter('min_samples').value)
        limit = float(self.get_parameter('max_coverage_condition').value)
        budget = float(self.get_parameter('max_solve_s').value)
        generations = int(self.get_parameter('ga_generations').value)
        maximum = int(self.get_parameter('max_samples').value)
        if minimum > maximum:
            return False, f'min_samples {minimum} exceeds max_samples {maximum}: lower it'
        if len(g) < minimum:
            return False, (
                f'{len(g)} samples are too few (need at least {minimum}); call ~/start, '
                f'fly the trim manoeuvre, then ~/stop'
            )
        try:
            options = Options(
                rng=np.random.default_rng(self.get_parameter('ga_seed').value),
                generations=generations,
                max_coverage_condition=limit,
                deadline_s=time.monotonic() + budget,
                should_stop=self._cancel.is_set,
            )
            result = identify(method, g, b, self._geometry, options)
        except (TetraError, np.linalg.LinAlgError) as error:
            return False, str(error)
        ran = result.details.get('generations', generations)
        if self._cancel.is_set():
            progress = f' after {ran} of {generations} generations' if method == 'paper_ga' else ''
            return False, f'cancelled (~/cancel){progress}; nothing written'
        stopped = (
            f'; stopped at max_solve_s {budget:g} s after {ran} of {generations} generations'
            if result.details.get('stopped') == 'deadline'
            else ''
        )
        try:
            calibration = CalibrationFile.from_calibration(result, self._geometry)
        except CalibrationFileError as error:  # k or b outside the physical bounds
            return False, str(error)
        path = self._calibration_path
        try:
            save_calibration(path, calibration, force=True)  # replaces only a previous calibration
        except (OSError, OutputError) as error:
            return False, f'solved, but cannot write {path}: {error}'
        self._cal_pub.publish(String(data=calibration.to_yaml()))
        self._calibrations += 1
        self._state = 'calibrated' if not self._collecting else 'collecting'
        s = result.summary()
        return True, (
            f'{s["method"]}: {s["n_samples"]} samples, {s["n_parameters"]} parameters, rank '
            f'{s["rank"]}, condition number {s["condition_number"]:.3g}, attitude coverage '
            f'{s["attitude_coverage_condition"]:.3g}, fit residual '
            f'{s["residual_rms_nT_per_m"]:.3g} nT/m{stopped}; written to {path}'
        )

    def _publish_diagnostics(self) -> None:
        level = WARN if self._last_ok is False else OK
        started = self._solve_started
        state, elapsed = self._state, self._solve_s
        message = f'{state}: {self._last_result}'
        if started is not None:
            state, elapsed = 'solving', time.monotonic() - started
            budget = self.get_parameter('max_solve_s').value
            message = f'solving for {elapsed:.1f} s (max_solve_s {budget:g})'
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(
            status(
                'tetra/calibrator: calibration',
                level,
                message,
                cv.ARRAY_FRAME,
                {
                    'state': state,
                    'solve_elapsed_s': float(elapsed),
                    'samples': self.n_samples,
                    'calibrations': self._calibrations,
                    'unpaired_evicted': self._pairer.evicted,
                    'dropped_implausible': self._dropped_implausible,
                    'method': self.get_parameter('method').value,
                    'calibration_file': str(self._calibration_path),
                },
            )
        )
        self._diag_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer calibrator``; 1 when the node refuses its parameters.

    A MultiThreadedExecutor: one thread for the waiting ``~/calibrate``, one for a second
    ``~/calibrate`` or ``~/cancel``, the others for the samples and ``/diagnostics``."""
    return spin_node(CalibratorNode, 'calibrator', args, threads=4)
