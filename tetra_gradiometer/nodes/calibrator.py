"""``calibrator`` node: identifies the interference parameters ``k``, ``b`` (eqs. 15-18).

Pairs ``gradient/raw`` (``G_m``, T/m) with ``reference_field`` (``B_1'``, T) by identical
stamp and accumulates the pairs while enabled. Services (std_srvs/Trigger):

* ``~/start``: forget earlier samples and collect (fly the trim manoeuvre now);
* ``~/stop``: stop collecting (samples are kept);
* ``~/calibrate``: solve with ``method`` on the collected samples. Too few samples, or a
  body-frame field spanning too few directions (the attitude-coverage condition number is
  given), answer success=false with the reason. On success the parameters are written
  atomically to ``calibration_file`` and published on ``calibration`` (std_msgs/String
  holding the calibration file's YAML text, transient local = latched).
  ``calibration_file`` is read-only after start-up (nobody on the ROS domain can point the
  write elsewhere), relative paths resolve under ``$ROS_HOME`` (default ``~/.ros``), and
  the write replaces only a previous calibration file: any other file there is left
  untouched and the call answers success=false.

``method`` is one of ``core.identification.CALIBRATION_METHODS`` (the registry;
default ``known_gradient_lstsq_general``: the true gradient is taken as zero, a trim far
from targets).
"""

from __future__ import annotations

import threading

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
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
from ..errors import OutputError, TetraError
from ..io import conversions as cv
from ..io.calibration import CalibrationFile, save_calibration
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
        f'Fewest sample sets ~/calibrate accepts (the solvers need >= {MIN_SAMPLES}).',
        int_range=(MIN_SAMPLES, 10_000_000),
    ),
    ParamSpec(
        'max_samples',
        200_000,
        'Most sample sets kept while collecting (older ones are dropped).',
        int_range=(MIN_SAMPLES, 10_000_000),
    ),
    ParamSpec(
        'max_coverage_condition',
        MAX_COVERAGE_CONDITION,
        "Refuse samples whose attitude-coverage condition number (of [B_1' 1], unit columns) "
        'exceeds this: the body-frame field spans too few directions.',
        positive,
        float_range=(1.0, 1e12),
    ),
    ParamSpec('ga_seed', 0, 'paper_ga: random seed.', int_range=(0, 2**31 - 1)),
    ParamSpec('ga_generations', 1000, 'paper_ga: generations.', int_range=(1, 1_000_000)),
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
            ),
        )
        self._geometry = TetraGeometry.from_flat(p['sensor_positions'])
        self._calibration_path = resolve_node_path(p['calibration_file'])
        self._lock = threading.Lock()
        self._collecting = False
        self._g: list[np.ndarray] = []
        self._b: list[np.ndarray] = []
        self._pairer = StampPairer(2)
        self._state = 'idle'
        self._last_result = 'no calibration yet'
        self._last_ok: bool | None = None
        self._calibrations = 0

        self._cal_pub = self.create_publisher(String, 'calibration', latched_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_subscription(JointState, 'gradient/raw', self._on_raw, derived_qos())
        self.create_subscription(
            MagneticField, 'reference_field', self._on_reference, derived_qos()
        )
        self.create_service(Trigger, '~/start', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        self.create_service(Trigger, '~/calibrate', self._on_calibrate)
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
            if pair is None or not all(np.all(np.isfinite(v)) for v in pair):
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
        ok, message = self._calibrate()
        response.success, response.message = ok, message
        self._last_ok, self._last_result = ok, message
        if ok:
            self.get_logger().info(f'calibrate: {message}')
        else:
            self.get_logger().warning(f'calibrate: {message}')
        self._publish_diagnostics()
        return response

    def _calibrate(self) -> tuple[bool, str]:
        """Solve on a snapshot of the samples; write and publish on success."""
        with self._lock:
            g = np.array(self._g).reshape(-1, 3, 3)
            b = np.array(self._b).reshape(-1, 3)
        method = self.get_parameter('method').value
        minimum = int(self.get_parameter('min_samples').value)
        limit = float(self.get_parameter('max_coverage_condition').value)
        if len(g) < minimum:
            return False, (
                f'{len(g)} samples are too few (need at least {minimum}); call ~/start, '
                f'fly the trim manoeuvre, then ~/stop'
            )
        try:
            options = Options(
                rng=np.random.default_rng(self.get_parameter('ga_seed').value),
                generations=int(self.get_parameter('ga_generations').value),
                max_coverage_condition=limit,
            )
            result = identify(method, g, b, self._geometry, options)
        except (TetraError, np.linalg.LinAlgError) as error:
            return False, str(error)
        calibration = CalibrationFile.from_calibration(result, self._geometry)
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
            f'{s["residual_rms_nT_per_m"]:.3g} nT/m; written to {path}'
        )

    def _publish_diagnostics(self) -> None:
        level = WARN if self._last_ok is False else OK
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(
            status(
                'tetra/calibrator: calibration',
                level,
                f'{self._state}: {self._last_result}',
                cv.ARRAY_FRAME,
                {
                    'state': self._state,
                    'samples': self.n_samples,
                    'calibrations': self._calibrations,
                    'unpaired_evicted': self._pairer.evicted,
                    'method': self.get_parameter('method').value,
                    'calibration_file': str(self._calibration_path),
                },
            )
        )
        self._diag_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    """``ros2 run tetra_gradiometer calibrator``; 1 when the node refuses its parameters."""
    return spin_node(CalibratorNode, 'calibrator', args)
