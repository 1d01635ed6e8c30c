"""The one module of shared ROS helpers (no Node class here): QoS profiles, declared and
validated parameters, throttled warnings, diagnostics helpers, stamp pairing, and the
start/stop of nodes (``spin_node``) and of in-process graphs (``interrupt_on_signals``,
``stop_graph``, used by the commands in ``cli/``).

QoS (docs/ros.md has the full table):

* magnetometer subscriptions: sensor-data style (best effort, volatile, keep last
  ``sensor_queue_depth``);
* derived topics (tensors, reference field, metrics): reliable, volatile, keep last
  ``DERIVED_DEPTH`` (1000);
* ``calibration``: reliable, transient local, keep last 1 (latched).
"""

from __future__ import annotations

import math
import os
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

NAMESPACE = '/tetra'

#: Largest plausible magnetometer reading, tesla (the Earth's field is < 7e-5 T).
MAX_FIELD_T = 1.0e-3

DERIVED_DEPTH = 1000


def sensor_qos(depth: int) -> Any:
    """Sensor-data QoS (best effort, volatile) with a queue of ``depth`` messages."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def derived_qos(depth: int = DERIVED_DEPTH) -> Any:
    """Reliable, volatile QoS for derived topics."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def latched_qos() -> Any:
    """Reliable, transient-local, depth 1: late joiners get the last message."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


# --------------------------------------------------------------------------- parameters


def ros_home() -> Path:
    """``$ROS_HOME``, else ``~/.ros`` (where ROS 2 keeps a node's files)."""
    return Path(os.environ.get('ROS_HOME') or Path.home() / '.ros').expanduser()


def resolve_node_path(value: str) -> Path:
    """A file parameter as a path: ``~`` expanded, absolute as given, relative ones under
    :func:`ros_home` (never the working directory, which differs between launches)."""
    path = Path(value).expanduser()
    return path if path.is_absolute() else ros_home() / path


Validator = Callable[[Any], 'str | None']


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: default (its type fixes the ROS type), description (with
    units), an optional numeric range and an optional validator returning an error text."""

    name: str
    default: Any
    description: str
    validate: Validator | None = None
    float_range: tuple[float, float] | None = None
    int_range: tuple[int, int] | None = None
    read_only: bool = False


def _descriptor(spec: ParamSpec, read_only: bool) -> Any:
    from rcl_interfaces.msg import (
        FloatingPointRange,
        IntegerRange,
        ParameterDescriptor,
        ParameterType,
    )

    default = spec.default
    if isinstance(default, bool):
        kind = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        kind = ParameterType.PARAMETER_INTEGER
    elif isinstance(default, float):
        kind = ParameterType.PARAMETER_DOUBLE
    elif isinstance(default, str):
        kind = ParameterType.PARAMETER_STRING
    elif isinstance(default, (list, tuple)) and all(isinstance(v, float) for v in default):
        kind = ParameterType.PARAMETER_DOUBLE_ARRAY
    else:
        raise TypeError(f'parameter {spec.name}: unsupported default {default!r}')
    descriptor = ParameterDescriptor(
        name=spec.name, type=kind, description=spec.description, read_only=read_only
    )
    if spec.float_range is not None:
        descriptor.floating_point_range = [
            FloatingPointRange(
                from_value=float(spec.float_range[0]),
                to_value=float(spec.float_range[1]),
                step=0.0,
            )
        ]
    if spec.int_range is not None:
        descriptor.integer_range = [
            IntegerRange(
                from_value=int(spec.int_range[0]), to_value=int(spec.int_range[1]), step=0
            )
        ]
    return descriptor


def declare_parameters(
    node: Any, specs: list[ParamSpec], dynamic: tuple[str, ...] = ()
) -> dict[str, Any]:
    """Declare ``specs`` on ``node`` with descriptors and validation; return their values.

    Only the parameters named in ``dynamic`` may change at run time (the node reads them
    when it uses them); the others are read-only after start-up.

    The validators also guard later ``set_parameters`` calls (bad values are refused with
    the validator's reason). Raises rclpy's ``InvalidParameterValueException`` (a
    ValueError) when a start-up value (params file, override) is refused.
    """
    from rcl_interfaces.msg import SetParametersResult

    by_name = {spec.name: spec for spec in specs}

    def on_set(parameters: list) -> Any:
        for parameter in parameters:
            spec = by_name.get(parameter.name)
            if spec is None or spec.validate is None:
                continue
            reason = spec.validate(parameter.value)
            if reason:
                return SetParametersResult(successful=False, reason=f'{parameter.name}: {reason}')
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    for spec in specs:
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        read_only = spec.read_only or spec.name not in dynamic
        node.declare_parameter(spec.name, default, _descriptor(spec, read_only))
    return {spec.name: node.get_parameter(spec.name).value for spec in specs}


def positive(value: Any) -> str | None:
    return None if value > 0 and math.isfinite(value) else f'must be > 0, got {value}'


def non_negative(value: Any) -> str | None:
    return None if value >= 0 and math.isfinite(value) else f'must be >= 0, got {value}'


def one_of(*choices: str) -> Validator:
    def check(value: Any) -> str | None:
        return None if value in choices else f'must be one of {list(choices)}, got {value!r}'

    return check


def valid_positions(value: Any) -> str | None:
    """``sensor_positions``: the reason :meth:`TetraGeometry.from_flat` (the one check of
    sensor positions) refuses them, or None."""
    from ..core import TetraGeometry
    from ..errors import InputError

    try:
        TetraGeometry.from_flat(value)
    except InputError as error:
        return str(error)
    return None


#: Regular tetrahedron of 0.5 m edge, sensor 1 at the origin (as config/tetra_gradiometer.yaml).
DEFAULT_POSITIONS = (
    0.0,
    0.0,
    0.0,
    0.5,
    0.0,
    0.0,
    0.25,
    0.4330127018922193,
    0.0,
    0.25,
    0.14433756729740643,
    0.408248290463863,
)

POSITIONS_SPEC = ParamSpec(
    'sensor_positions',
    DEFAULT_POSITIONS,
    'Positions of magnetometers 1..4 in the body frame (x forward, y left, z up), metres, '
    'as x1 y1 z1 x2 ... z4; sensor 1 is the reference. Must not be coplanar.',
    valid_positions,
    read_only=True,
)


#: Shared by the nodes that warn on every dropped message (0: no throttling).
WARN_THROTTLE_SPEC = ParamSpec(
    'warn_throttle_s',
    5.0,
    'Least interval between repeated warnings, s.',
    float_range=(0.0, 3600.0),
)


def diagnostics_period_spec() -> ParamSpec:
    return ParamSpec(
        'diagnostics_period_s',
        1.0,
        'Period of /diagnostics publication, seconds.',
        positive,
        float_range=(0.01, 60.0),
    )


# --------------------------------------------------------------------------- helpers


class Throttle:
    """True at most once per ``period_s`` (wall clock): for throttled warnings."""

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self._last = -math.inf

    def __call__(self) -> bool:
        now = time.monotonic()
        if now - self._last >= self.period_s:
            self._last = now
            return True
        return False


class StampPairer:
    """Joins ``n`` streams on identical header stamps (ns): :meth:`add` returns the tuple of
    values once every stream has delivered that stamp. Bounded: the oldest incomplete
    stamps are evicted beyond ``max_pending`` and counted in :attr:`evicted` (the nodes
    report it on ``/diagnostics``)."""

    def __init__(self, n: int, max_pending: int = 1000) -> None:
        self.n = int(n)
        self.max_pending = int(max_pending)
        self.evicted = 0
        self._pending: OrderedDict[int, list] = OrderedDict()

    def add(self, stream: int, stamp_ns: int, value: Any) -> tuple | None:
        slot = self._pending.get(stamp_ns)
        if slot is None:
            slot = self._pending[stamp_ns] = [None] * self.n
            while len(self._pending) > self.max_pending:
                self._pending.popitem(last=False)
                self.evicted += 1
        slot[stream] = value
        if all(v is not None for v in slot):
            del self._pending[stamp_ns]
            return tuple(slot)
        return None

    def clear(self) -> None:
        """Forget the incomplete stamps (:attr:`evicted` keeps counting)."""
        self._pending.clear()


def key_values(values: dict[str, Any]) -> list:
    """``diagnostic_msgs/KeyValue`` list from a dict (floats to 6 significant digits)."""
    from diagnostic_msgs.msg import KeyValue

    out = []
    for key, value in values.items():
        text = f'{value:.6g}' if isinstance(value, float) else str(value)
        out.append(KeyValue(key=key, value=text))
    return out


def status(name: str, level: int, message: str, hardware_id: str, values: dict[str, Any]) -> Any:
    """A ``diagnostic_msgs/DiagnosticStatus``; ``level`` 0 OK, 1 WARN, 2 ERROR, 3 STALE."""
    from diagnostic_msgs.msg import DiagnosticStatus

    return DiagnosticStatus(
        level=bytes([level]),
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=key_values(values),
    )


OK, WARN, ERROR = 0, 1, 2


def interrupt_on_signals() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread (also when the shell
    started us with SIGINT ignored), for processes that stop their executors themselves
    instead of letting rclpy's handler invalidate the context under running callbacks."""
    import signal

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)


def tensor_or_nan(msg: Any) -> np.ndarray:
    """A tensor JointState as (3, 3) T/m; a malformed one (wrong names or count) as NaN, which
    the callers' non-finite checks drop and count, so one bad message cannot stop a node."""
    from ..io import conversions as cv

    try:
        return cv.tensor_from_msg(msg)
    except cv.MessageError:
        return np.full((3, 3), np.nan)


def spin_node(factory: Callable[[], Any], name: str, args: list[str] | None) -> int:
    """The ``main()`` of every node (the ros2/demos pattern): init, build the node, spin until
    Ctrl-C or an external shutdown, then destroy it and ``rclpy.try_shutdown()``.

    Returns 1 when the node refuses its parameters (a ``ValueError`` naming the reason), else 0.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
    try:
        node = factory()
    except ValueError as error:
        rclpy.logging.get_logger(name).error(f'cannot start: {error}')
        rclpy.try_shutdown()
        return 1
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def stop_graph(executor: Any, spinner: Any, nodes: list[Any]) -> None:
    """Stop an in-process graph (demo, record): the executor, then its spin thread, then the
    nodes and the context, in that order (joining the thread first avoids a crash at exit)."""
    import rclpy

    executor.shutdown(timeout_sec=2)
    if spinner.is_alive():
        spinner.join(timeout=5)
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()
