"""The one module of shared ROS helpers (no Node class here): QoS profiles, declared and
validated parameters, throttled warnings, diagnostics helpers (starting and stopping nodes:
nodes/process.py).

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
import sys
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ParamsError, TetraError
from ..io import conversions as cv
from ..io import gradient_tensor as gt

NAMESPACE = '/tetra'

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


def latched_qos(depth: int = 1) -> Any:
    """Reliable, transient-local, keep last ``depth``: late joiners get the last messages."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
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
    units), an optional numeric range and an optional validator returning an error text.
    ``string_array``: a string array (needed when the default is empty: ``()``)."""

    name: str
    default: Any
    description: str
    validate: Validator | None = None
    float_range: tuple[float, float] | None = None
    int_range: tuple[int, int] | None = None
    read_only: bool = False
    string_array: bool = False


def _descriptor(spec: ParamSpec, read_only: bool) -> Any:
    from rcl_interfaces.msg import (
        FloatingPointRange,
        IntegerRange,
        ParameterDescriptor,
        ParameterType,
    )

    default = spec.default
    if spec.string_array:
        kind = ParameterType.PARAMETER_STRING_ARRAY
    elif isinstance(default, bool):
        kind = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        kind = ParameterType.PARAMETER_INTEGER
    elif isinstance(default, float):
        kind = ParameterType.PARAMETER_DOUBLE
    elif isinstance(default, str):
        kind = ParameterType.PARAMETER_STRING
    elif isinstance(default, (list, tuple)) and all(isinstance(v, float) for v in default):
        kind = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif isinstance(default, (list, tuple)) and all(isinstance(v, str) for v in default):
        kind = ParameterType.PARAMETER_STRING_ARRAY
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
    the validator's reason).

    Raises
    ------
    ParamsError
        A start-up value (params file, ``-p`` override) is refused: one line naming the
        parameter, the value and the allowed range, type or the validator's reason.
    """
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.exceptions import ParameterException

    by_name = {spec.name: spec for spec in specs}

    def on_set(parameters: list) -> Any:
        for parameter in parameters:
            spec = by_name.get(parameter.name)
            if spec is None or spec.validate is None or parameter.value is None:
                continue  # (None: a string array declared unset, see below)
            reason = spec.validate(parameter.value)
            if reason:
                return SetParametersResult(successful=False, reason=f'{parameter.name}: {reason}')
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    for spec in specs:
        default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
        read_only = spec.read_only or spec.name not in dynamic
        try:
            if spec.string_array and not default:
                _declare_empty_string_array(node, spec, read_only)
            else:
                node.declare_parameter(spec.name, default, _descriptor(spec, read_only))
        except ParameterException as error:
            raise ParamsError(_refusal(node, spec, error)) from None
    return {spec.name: node.get_parameter(spec.name).value for spec in specs}


def _declare_empty_string_array(node: Any, spec: ParamSpec, read_only: bool) -> None:
    """Declare a string array whose default is empty: rclpy types an empty default as a byte
    array (and an empty YAML list ``[]`` arrives unset), so it is declared by type, set to
    ``[]`` when no override gave it a value, and only then made read-only."""
    from rclpy.exceptions import ParameterUninitializedException
    from rclpy.parameter import Parameter

    kind = Parameter.Type.STRING_ARRAY
    node.declare_parameter(spec.name, kind, _descriptor(spec, False))
    try:
        node.get_parameter(spec.name)
    except ParameterUninitializedException:
        node.set_parameters([Parameter(spec.name, kind, [])])
    if read_only:
        node.set_descriptor(spec.name, _descriptor(spec, True))


_TYPE_NAMES = ((bool, 'a boolean'), (int, 'an integer'), (float, 'a double'), (str, 'a string'))


def _type_name(value: Any) -> str:
    for kind, name in _TYPE_NAMES:
        if isinstance(value, kind):
            return name
    return 'an array'


def _shown(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if not isinstance(value, (bool, int, float)):
        try:
            return str([v for v in value])
        except TypeError:
            pass
    return str(value)


def range_text(spec: ParamSpec) -> str:
    """``spec``'s declared range as ``[low, high]`` ('' when it has none)."""
    bounds = spec.int_range or spec.float_range
    return f'[{bounds[0]:g}, {bounds[1]:g}]' if bounds else ''


def _refusal(node: Any, spec: ParamSpec, error: Exception) -> str:
    """One line for a refused start-up value: the parameter, the value and why."""
    from rclpy.exceptions import InvalidParameterTypeException

    override = node._parameter_overrides.get(spec.name)  # rclpy keeps no public accessor
    if override is None:  # not an override: should not happen, the defaults are valid
        return f'parameter {spec.name!r} refused: {error}'
    value = override.value
    head = f'parameter {spec.name!r} = {_shown(value)} refused'
    within = f' within {range_text(spec)}' if range_text(spec) else ''
    if isinstance(error, InvalidParameterTypeException):
        expected = 'a string array' if spec.string_array else _type_name(spec.default)
        decimal = _type_name(value) == 'an integer' and expected == 'a double'
        hint = ' (write it with a decimal point)' if decimal else ''
        return f'{head}: {_type_name(value)}, it must be {expected}{within}{hint}'
    bounds = spec.int_range or spec.float_range
    if bounds and not bounds[0] <= value <= bounds[1]:
        return f'{head}: must be{within} ({spec.description.rstrip(".")})'
    reason = spec.validate(value) if spec.validate else None
    return f'{head}: {reason or error}'


def ros_argument_values(args: list[str] | None, flags: tuple[str, ...]) -> list[str]:
    """The values following any of ``flags`` (``-p``, ``--params-file``) in the ROS arguments
    of ``args`` (``sys.argv`` when None): between ``--ros-args`` and ``--``."""
    values: list[str] = []
    ros, expect = False, False
    for token in sys.argv if args is None else args:
        if expect:
            values.append(token)
            expect = False
        elif token in ('--ros-args', '--'):
            ros = token == '--ros-args'
        else:
            expect = ros and token in flags
    return values


def command_line_parameters(args: list[str] | None, node_name: str) -> dict[str, str]:
    """``{name: value text}`` of the ``-p``/``--param [NODE:]NAME:=VALUE`` rules in the ROS
    arguments of ``args`` (``sys.argv`` when None) that address ``node_name`` (no prefix, or
    a prefix ending in it)."""
    rules: dict[str, str] = {}
    for rule in ros_argument_values(args, ('-p', '--param')):
        target, _, text = rule.partition(':=')
        prefix, _, name = target.rpartition(':')
        if not prefix or prefix.rsplit('/', 1)[-1] == node_name:
            rules[name] = text
    return rules


def _parsed(text: str) -> Any:
    """A ``-p`` value as rcl types it (YAML; ``1e-3`` is a double too)."""
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    if isinstance(value, str) and any(c.isdigit() for c in value):
        try:
            return float(value)
        except ValueError:
            pass
    return value


def _descriptor_range(node: Any, name: str) -> str:
    descriptor = node.describe_parameter(name)
    ranges = list(descriptor.integer_range) or list(descriptor.floating_point_range)
    return f' within [{ranges[0].from_value:g}, {ranges[0].to_value:g}]' if ranges else ''


def dropped_command_line_value(node: Any, rules: dict[str, str]) -> str | None:
    """The refusal of a ``-p`` value rcl dropped, or None.

    When a params file gives the same name another type, rcl keeps both values and may hand
    the node the file's (measured: ``-p ga_generations:=abc`` and ``-p ga_generations:=5.0``
    over the file's integer 1000 both gave 1000): refused here, with the type the parameter
    has, instead of being silently ignored."""
    for name, text in rules.items():
        given = _parsed(text)
        if given is None or not node.has_parameter(name):
            continue
        value = node.get_parameter(name).value
        if _type_name(given) != _type_name(value):
            return (
                f'parameter {name!r} = {_shown(given)} refused: {_type_name(given)}, it must '
                f'be {_type_name(value)}{_descriptor_range(node, name)}'
            )
    return None


def unknown_overrides(node: Any, command_line: Collection[str]) -> list[str]:
    """Overrides ``node`` received but does not declare: a ``-p`` name (one node per
    process, so it was meant for this one) or a params-file name no node of the package
    declares (a typo). Not: names another node declares, from a shared ``/**`` file (each
    node takes its own entries); rclpy's built-ins (``use_sim_time``: declared too); entries
    under another node's name (rcl never hands them to this node)."""
    # The package's names from io/params.py's list, which the tests keep equal to the shipped
    # config and that to the nodes' declarations: collecting them from the node modules
    # imported all five at every start (~0.3 s of CPU each, the shared /** file always
    # giving a node names it does not declare).
    from ..io.params import KNOWN_PARAMETERS

    undeclared = [name for name in node._parameter_overrides if not node.has_parameter(name)]
    return sorted(
        name for name in undeclared if name in command_line or name not in KNOWN_PARAMETERS
    )


def params_file_sections(args: list[str] | None) -> list[tuple[str, list[str]]]:
    """(path, its top-level section names) of each ``--params-file PATH`` in the ROS
    arguments of ``args`` (``sys.argv`` when None); an unreadable file is rcl's to refuse."""
    import yaml

    out = []
    for path in ros_argument_values(args, ('--params-file',)):
        try:
            with open(path, encoding='utf-8') as handle:
                document = yaml.safe_load(handle)
        except (OSError, yaml.YAMLError):
            continue
        if isinstance(document, dict):
            out.append((path, [str(key) for key in document]))
    return out


def section_matches(section: str, fully_qualified: str) -> bool:
    """Whether a params-file section (``/**``, ``/tetra/compensator``, ``/*/compensator``,
    ``/**/compensator``, ``compensator``) applies to the node ``fully_qualified``."""
    import re

    if not section.startswith('/'):
        section = '/' + section
    pattern = re.escape(section).replace(r'\*\*', '.*').replace(r'\*', '[^/]*')
    return re.fullmatch(pattern, fully_qualified) is not None


def misnamed_section(node: Any, args: list[str] | None) -> str | None:
    """Why a params file given to ``node`` is refused: none of its sections applies to the
    node while one names it, or nearly (a typo, another namespace: rcl would ignore the
    whole section without a word), or None. A file whose sections all name other nodes (one
    launch file for all) is the node's defaults."""
    import difflib

    fully_qualified = node.get_fully_qualified_name()
    for path, sections in params_file_sections(args):
        if any(section_matches(section, fully_qualified) for section in sections):
            continue
        name = fully_qualified.rsplit('/', 1)[-1]
        for section in sections:
            last = section.rsplit('/', 1)[-1]
            if difflib.SequenceMatcher(None, last, name).ratio() >= 0.8:
                return (
                    f'params file {path} has no section for {fully_qualified} (its sections: '
                    f'{", ".join(sections)}): is {section!r} meant to be {fully_qualified!r}? '
                    '(rcl ignores a section that names another node, without a word)'
                )
    return None


def absolute_topics(value: Any) -> str | None:
    """A string array of absolute topic names (``/thruster1/battery``), none twice."""
    topics = list(value)
    bad = [t for t in topics if not (isinstance(t, str) and t.startswith('/') and ' ' not in t)]
    if bad:
        return f'must be absolute topic names (e.g. /thruster1/battery), got {bad!r}'
    if len(set(topics)) != len(topics):
        return f'names a topic twice: {topics!r}'
    return None


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


def frame_ids(value: Any) -> str | None:
    """Validator of frame ids (a string or a list): non-empty, no leading '/' (tf2's rule)."""
    ids = [value] if isinstance(value, str) else list(value)
    bad = [i for i in ids if not i or i.startswith('/')]
    return f'frame ids must be non-empty without a leading "/", got {bad!r}' if bad else None


#: The tensor and compensator's frame of the gradient tensors (a child of the body frame).
ARRAY_FRAME_SPEC = ParamSpec(
    'array_frame_id',
    cv.ARRAY_FRAME,
    'Frame id of the published gradient tensors (REP 103 body axes; a child of base_link).',
    frame_ids,
    read_only=True,
)

#: Shared by the nodes that warn on every dropped message (0: no throttling).
WARN_THROTTLE_SPEC = ParamSpec(
    'warn_throttle_s',
    5.0,
    'Least interval between repeated warnings, s (0: every one; at most an hour).',
    float_range=(0.0, 3600.0),
)


def diagnostics_period_spec() -> ParamSpec:
    return ParamSpec(
        'diagnostics_period_s',
        1.0,
        'Period of /diagnostics publication, seconds (0.05-60: faster floods the '
        'aggregators, slower and a monitor takes the node for dead).',
        positive,
        float_range=(0.05, 60.0),
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


def key_values(values: dict[str, Any]) -> list:
    """``diagnostic_msgs/KeyValue`` list from a dict (floats to 6 significant digits)."""
    from diagnostic_msgs.msg import KeyValue

    out = []
    for key, value in values.items():
        text = f'{value:.6g}' if isinstance(value, float) else str(value)
        out.append(KeyValue(key=key, value=text))
    return out


def status(
    node: Any, task: str, level: int, message: str, hardware_id: str, values: dict[str, Any]
) -> Any:
    """A ``diagnostic_msgs/DiagnosticStatus`` of ``node``'s check ``task``, named
    ``<node's fully qualified name without the leading slash>: <task>`` (``tetra/tensor:
    matching``: a second instance in another namespace does not collide in an aggregator);
    ``hardware_id`` a device id, ``''`` for a software check; ``level`` 0 OK, 1 WARN, 2 ERROR,
    3 STALE."""
    from diagnostic_msgs.msg import DiagnosticStatus

    return DiagnosticStatus(
        level=bytes([level]),
        name=f'{node.get_fully_qualified_name().lstrip("/")}: {task}',
        message=message,
        hardware_id=hardware_id,
        values=key_values(values),
    )


OK, WARN, ERROR = 0, 1, 2


def check_serialization() -> None:
    """Refuse to configure a node whose per-message path reads and writes serialized messages
    (io/conversions) when the RMW serializes otherwise (never seen: Fast DDS, Cyclone DDS and
    Connext all use XCDR1 little endian for these types).

    Raises
    ------
    TetraError
        The RMW's serialization differs from io/conversions' CDR layout.
    """
    if not (cv.cdr_agrees() and gt.cdr_agrees()):
        rmw = os.environ.get('RMW_IMPLEMENTATION', 'the default RMW')
        raise TetraError(
            f'{rmw} does not serialize sensor_msgs/MagneticField and GradientTensor as plain '
            'CDR (XCDR1, little endian), which this node reads and writes directly '
            '(io/conversions.py, io/gradient_tensor.py); use rmw_fastrtps_cpp or '
            'rmw_cyclonedds_cpp'
        )
