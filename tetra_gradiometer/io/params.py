"""ROS 2 parameter files (``/**: ros__parameters:``) as the offline tools read them.

Read strictly: a repeated key is refused; in the package's own sections (``/**``
and the sections of its nodes) an unknown name is refused with the closest known one
(:data:`KNOWN_PARAMETERS`, the nodes' declarations as ``config/tetra_gradiometer.yaml``
holds them; a test keeps the two equal); ``sensor_positions`` and ``earth_field_enu`` must be
numbers (a boolean or a quoted number is refused, not read as 0/1 or parsed).
"""

from __future__ import annotations

import difflib
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..core import TetraGeometry
from ..core.effects import parse_declaration
from ..core.plausibility import MAX_FIELD_T, plausible_readings
from ..errors import InputError, ParamsError
from ._yaml import dumps, read_yaml

#: Every parameter the package's nodes declare (``config/tetra_gradiometer.yaml``'s names),
#: and ROS 2's own ``use_sim_time``: the names a section of the package may hold.
KNOWN_PARAMETERS = frozenset(
    """array_frame_id autostart bag base_frame_id calibration_file
    calibration_key_file calibration_publisher current_topics
    diagnostics_period_s earth_field_enu effects false_alarms_per_hour force ga_generations
    ga_seed health_false_alarms_per_hour health_min_source_range_edges history_s
    hold_between_segments jump_back_s loop max_coverage_condition max_duration_s max_field_t
    max_gap_periods max_stamp_ahead_s max_pending max_samples max_solve_s
    method min_samples min_subscribers mode odom_frame_id publish_clock publisher_depth
    rate
    reference_rate_hz
    replay_remap sample_rate_hz scenario seed sensor_frame_ids sensor_noise_t sensor_positions
    sensor_queue_depth stale_timeout_s stamp_tolerance_s start_paused sync track_calibration
    update_period_s
    vehicle_signals warn_throttle_s use_sim_time""".split()
)
#: The package's nodes: a section named after one (``/tetra/calibrator``, ``calibrator``) is
#: the package's own, its names checked like ``/**``'s.
NODE_NAMES = ('driver', 'tensor', 'calibrator', 'compensator', 'target')


def _own_section(name: Any) -> bool:
    return name == '/**' or str(name).rstrip('/').rsplit('/', 1)[-1] in NODE_NAMES


def _check_names(path: Path, document: dict[Any, Any]) -> None:
    """Refuse an unknown name in one of the package's sections, naming the closest known."""
    for name, section in document.items():
        parameters = section.get('ros__parameters') if isinstance(section, dict) else None
        if not _own_section(name) or not isinstance(parameters, dict):
            continue
        for key in parameters:
            if key not in KNOWN_PARAMETERS:
                close = difflib.get_close_matches(str(key), sorted(KNOWN_PARAMETERS), n=1)
                hint = f'; did you mean {close[0]!r}?' if close else ''
                raise ParamsError(
                    f'params file {path}: unknown parameter {key!r} in "{name}"{hint} '
                    '(docs/ros.md lists the parameters)'
                )


def _numbers(values: Any, name: str, source: str, count: int, unit: str) -> list[float]:
    """``values`` as ``count`` numbers: a YAML number each (int or float), not a boolean or
    a quoted string (which would be read as 0/1, or parsed)."""
    items = values if isinstance(values, list) else [values]
    wrong = [v for v in items if isinstance(v, bool) or not isinstance(v, int | float)]
    if wrong:
        raise ParamsError(
            f'{source}: {name} must be {count} numbers ({unit}), got {wrong[0]!r} '
            f'({type(wrong[0]).__name__}) among {values!r}'
        )
    return [float(v) for v in items]


def load_params(path: str | os.PathLike, node: str = '/**') -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` (default the wildcard ``/**``) in ``path``.

    Falls back to the only node section when ``node`` is absent, so a file written for one
    named node also works.

    Raises
    ------
    ParamsError
        Unreadable, not YAML, a repeated key, no such section, or an unknown name in one of
        the package's sections (with the closest known name).
    """
    path = Path(path)
    document = read_yaml(path, 'params', ParamsError, unique_keys=True)
    if not isinstance(document, dict) or not document:
        raise ParamsError(
            f'params file {path} has no node sections (expected "/**: ros__parameters:")'
        )
    section = document.get(node)
    if section is None and len(document) == 1:
        section = next(iter(document.values()))
    if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
        raise ParamsError(f'params file {path}: no "{node}: ros__parameters:" mapping')
    _check_names(path, document)
    return section['ros__parameters']


def geometry_from_params(params: dict[str, Any], source: str = 'params') -> TetraGeometry:
    """The tetrahedron from ``sensor_positions`` (12 floats, metres, sensor 1 first).

    :meth:`TetraGeometry.from_flat` checks the values; its error is relabelled with
    ``source``.

    Raises
    ------
    ParamsError
        ``sensor_positions`` is missing or is not a usable tetrahedron.
    """
    values = params.get('sensor_positions')
    if values is None:
        raise ParamsError(f'{source}: sensor_positions is missing (12 floats, metres, body frame)')
    values = _numbers(values, 'sensor_positions', source, 12, 'metres')
    try:
        return TetraGeometry.from_flat(values)
    except InputError as error:
        raise ParamsError(f'{source}: {error}') from error


def earth_field_from_params(params: dict[str, Any], source: str = 'params') -> np.ndarray | None:
    """``earth_field_enu`` (3 finite floats, tesla, ``|B| <= MAX_FIELD_T``) or None when
    absent."""
    values = params.get('earth_field_enu')
    if values is None:
        return None
    values = _numbers(values, 'earth_field_enu', source, 3, 'tesla')
    try:
        field = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError):  # text, nested lists of unequal length, mappings
        field = np.full(1, np.nan)
    if field.size != 3 or not np.all(np.isfinite(field)):
        raise ParamsError(
            f'{source}: earth_field_enu must be 3 finite floats (tesla), got {values!r}'
        )
    if not plausible_readings(field):  # the readings' bound (core/plausibility)
        raise ParamsError(
            f'{source}: earth_field_enu must be tesla with |B| <= {MAX_FIELD_T:g} T '
            f'(the Earth field is ~5e-5 T), got {values!r}'
        )
    return field


def vehicle_signals_from_params(params: dict[str, Any], source: str = 'params') -> tuple[str, ...]:
    """The effect names of ``vehicle_signals`` (a list of ``TOPIC#FIELD:BASIS``,
    :mod:`~tetra_gradiometer.core.effects.recorded_signal`), () when absent.

    Raises
    ------
    ParamsError
        Not a list of strings, or a declaration that is not one (named).
    """
    values = params.get('vehicle_signals') or []
    if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
        raise ParamsError(
            f'{source}: vehicle_signals must be a list of TOPIC#FIELD:BASIS strings, got '
            f'{values!r}'
        )
    try:
        names = [parse_declaration(v, f'{source}: vehicle_signals').effect_name for v in values]
    except InputError as error:
        raise ParamsError(str(error)) from None
    return tuple(dict.fromkeys(names))


def params_document(params: dict[str, Any]) -> str:
    """YAML text of a ``/**: ros__parameters:`` file holding ``params``."""
    return dumps({'/**': {'ros__parameters': params}})
