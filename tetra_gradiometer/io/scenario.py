"""Scenario files (YAML) -> :class:`~tetra_gradiometer.core.Scenario`.

Units are in the key names (``_m``, ``_nT``, ``_deg``, ``_s``); the core gets SI. The
Earth field is either given (``earth_field: {enu_nT: [e, n, u]}``) or computed from IGRF-14
with ppigrf (``earth_field: {igrf: {latitude_deg, longitude_deg, date, altitude_m}}``);
ppigrf is a maintained pure-Python IGRF, so we do not carry our own coefficients.

Example::

    seed: 7
    sample_rate_hz: 10
    noise_nT: 0.05
    geometry: {regular_edge_m: 0.5}          # or {sensor_positions_m: [12 floats]}
    earth_field: {enu_nT: [0, 20000, -45000]}
    dipoles: [{position_m: [0, 0, -80], moment_Am2: [3.0e4, 1.0e4, -2.0e4]}]
    interference: {random: {k_scale: 0.005, b_scale_nT: 150, reference_clean: false}}
    segments:
      - trim: {duration_s: 300, center_m: [3000, 3000, -50]}
      - line: {start_m: [-200, 30, -50], end_m: [200, 30, -50], speed_m_s: 2}
    effects: {}                                # see EFFECT_KEYS; e.g.
                                               # vehicle_current: {nT_per_A: 4x3xm}
    current:                                   # the vehicle's currents, A (negative:
      base_a: -3                               # discharging): the hotel load, plus
      step_amplitude_a: 1                      # one channel per thruster (its own
      step_s: 30                               # BatteryState topic; see THRUSTER_KEYS)
      thrusters:
        - {topic: /thruster_1/battery_state, speed_a_per_m2_s2: -2.5}
        - {topic: /thruster_2/battery_state, turn_a_per_deg_s: -0.1}
    regional_gradient_nT_per_m: [[0.5, 0.2, 0], [0.2, -0.3, 0.1], [0, 0.1, -0.2]]
                                               # symmetric, traceless; default zero
    clocks: {offset_ms: [0, 0.5, 2, 4], jitter_ms: 0.2, drift_ppm: [0, 20, -30, 50],
             rate_hz: [100, 100, 100, 100], loss_fraction: 0.005}
                                               # see CLOCK_KEYS; a number or 4 per key;
                                               # no clocks: the sensors sample together
"""

from __future__ import annotations

import copy
import datetime as _dt
import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .._optional import require
from ..core import (
    CurrentProfile,
    Dipole,
    Effects,
    Scenario,
    SensorClocks,
    SensorInterference,
    SurveyLine,
    TemperatureProfile,
    TetraGeometry,
    Thruster,
    TrimManoeuvre,
    check_gradient_tensor,
    random_interference,
)
from ..core.simulator import EFFECT_SPECS
from ..core.units import S_PER_MS, T_PER_NT
from ..errors import InputError, ScenarioError
from . import conversions as cv
from ._yaml import read_yaml

#: effect name -> (key in the file, factor to SI)
#: Scenario file keys of the effects: ``{effect: (key, factor to SI)}``, from the simulator's
#: one table (:data:`~tetra_gradiometer.core.simulator.EFFECT_SPECS`).
EFFECT_KEYS = {
    name: (spec.scenario_key, spec.scenario_factor) for name, spec in EFFECT_SPECS.items()
}

#: Scenario file keys of a thruster under ``current: {thrusters: [...]}`` (A and the units in
#: the names; see :mod:`tetra_gradiometer.core.vehicle_signals`); ``topic`` is required.
THRUSTER_KEYS = tuple(Thruster.__dataclass_fields__)
#: Topics a thruster's BatteryState may not take: the data contract's other topics.
RESERVED_TOPICS = frozenset((*cv.BAG_MAG_TOPICS, cv.ODOM_TOPIC, cv.TEMPERATURE_TOPIC))

#: Scenario file keys of ``clocks``: ``{key: (SensorClocks attribute, factor to SI)}``; each
#: takes a number (all sensors) or four.
CLOCK_KEYS = {
    'offset_ms': ('offset_s', S_PER_MS),
    'jitter_ms': ('jitter_s', S_PER_MS),
    'drift_ppm': ('drift_ppm', 1.0),
    'rate_hz': ('rate_hz', 1.0),
    'loss_fraction': ('loss_fraction', 1.0),
}
#: Scenario file key of the regional gradient, nT/m.
REGIONAL_GRADIENT_KEY = 'regional_gradient_nT_per_m'


def igrf_field_enu(
    latitude_deg: float, longitude_deg: float, date: _dt.date | str, altitude_m: float = 0.0
) -> np.ndarray:
    """IGRF-14 main field (3,) in tesla, ENU, at a place and date (ppigrf)."""
    ppigrf = require('ppigrf', 'the IGRF field of a scenario (earth_field: igrf)')

    when = _dt.datetime.fromisoformat(str(date)) if not isinstance(date, _dt.date) else date
    if not isinstance(when, _dt.datetime):
        when = _dt.datetime(when.year, when.month, when.day)
    east, north, up = ppigrf.igrf(longitude_deg, latitude_deg, altitude_m / 1000.0, when)
    return np.array([east.item(), north.item(), up.item()]) * T_PER_NT


def _vec(
    section: dict, key: str, shape: tuple[int, ...], where: str, factor: float = 1.0
) -> np.ndarray:
    if key not in section:
        raise ScenarioError(f'{where}: missing "{key}"')
    try:
        value = np.asarray(section[key], dtype=float)
    except (TypeError, ValueError):
        raise ScenarioError(f'{where}.{key}: not numeric: {section[key]!r}') from None
    if value.shape != shape:
        raise ScenarioError(f'{where}.{key}: expected shape {shape}, got {value.shape}')
    if not np.all(np.isfinite(value)):
        raise ScenarioError(f'{where}.{key}: non-finite value in {section[key]!r}')
    return value * factor


#: Largest ``seed``: the driver node's seed range (int32), as on the command line.
MAX_SEED = 2**31 - 1

#: Top-level keys a scenario file may hold.
TOP_LEVEL_KEYS = {
    'seed',
    'sample_rate_hz',
    'noise_nT',
    'geometry',
    'earth_field',
    'dipoles',
    'interference',
    'segments',
    'effects',
    'temperature',
    'current',
    'description',
    REGIONAL_GRADIENT_KEY,
    'clocks',
}


def _positive(spec: dict, key: str, where: str, *, allow_zero: bool = False) -> None:
    if key not in spec:
        return
    try:
        value = float(spec[key])
    except (TypeError, ValueError):
        raise ScenarioError(f'{where}.{key}: not a number: {spec[key]!r}') from None
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ScenarioError(
            f'{where}.{key} must be {"non-negative" if allow_zero else "positive"}, got {value}'
        )


def _finite(spec: dict, key: str, where: str) -> None:
    if key in spec:
        try:
            value = float(spec[key])
        except (TypeError, ValueError):
            raise ScenarioError(f'{where}.{key}: not a number: {spec[key]!r}') from None
        if not np.isfinite(value):
            raise ScenarioError(f'{where}.{key} must be finite, got {value}')


def _segment(entry: dict, index: int) -> TrimManoeuvre | SurveyLine:
    where = f'segments[{index}]'
    if not isinstance(entry, dict) or len(entry) != 1 or next(iter(entry)) not in ('trim', 'line'):
        raise ScenarioError(
            f'{where}: expected {{trim: {{...}}}} or {{line: {{...}}}}, got {entry!r}'
        )
    kind, spec = next(iter(entry.items()))
    spec = dict(spec or {})
    where = f'{where}.{kind}'
    for key in ('duration_s', 'speed_m_s', 'roll_period_s', 'pitch_period_s', 'sway_period_s'):
        _positive(spec, key, where)
    for key in ('roll_amplitude_deg', 'pitch_amplitude_deg'):
        _positive(spec, key, where, allow_zero=True)
    for key in ('heading_rate_deg_s', 'initial_heading_deg'):
        _finite(spec, key, where)
    if kind == 'trim' and 'duration_s' not in spec:
        raise ScenarioError(f'{where}: missing "duration_s"')
    if kind == 'line' and 'start_m' in spec and 'end_m' in spec:
        if np.allclose(np.asarray(spec['start_m'], float), np.asarray(spec['end_m'], float)):
            raise ScenarioError(f'{where}: start_m and end_m are the same point')
    try:
        if kind == 'trim':
            center = (
                tuple(_vec(spec, 'center_m', (3,), where))
                if 'center_m' in spec
                else (0.0, 0.0, -50.0)
            )
            spec.pop('center_m', None)
            return TrimManoeuvre(center=center, **spec)
        start, end = _vec(spec, 'start_m', (3,), where), _vec(spec, 'end_m', (3,), where)
        spec.pop('start_m'), spec.pop('end_m')
        return SurveyLine(tuple(start), tuple(end), **spec)
    except TypeError as error:
        raise ScenarioError(f'{where}: {error}') from None


def _check_document(document: dict[str, Any]) -> None:
    """The top level's keys and the types of its sections."""
    if not isinstance(document, dict):
        raise ScenarioError('a scenario must be a mapping')
    unknown = set(document) - TOP_LEVEL_KEYS
    if unknown:
        raise ScenarioError(f'unknown key(s) {sorted(unknown)}; known: {sorted(TOP_LEVEL_KEYS)}')
    for key in (
        'geometry',
        'earth_field',
        'interference',
        'effects',
        'temperature',
        'current',
        'clocks',
    ):
        if document.get(key) is not None and not isinstance(document[key], dict):
            raise ScenarioError(f'{key}: expected a mapping, got {document[key]!r}')
    if not isinstance(document.get('segments') or [], list):
        raise ScenarioError('segments: expected a list of {trim: ...} / {line: ...}')
    if not isinstance(document.get('dipoles') or [], list):
        raise ScenarioError('dipoles: expected a list of {position_m, moment_Am2}')


def _geometry(geometry_spec: dict[str, Any]) -> TetraGeometry:
    try:
        if 'sensor_positions_m' in geometry_spec:
            geometry = TetraGeometry.from_flat(geometry_spec['sensor_positions_m'])
        else:
            geometry = TetraGeometry.regular(float(geometry_spec.get('regular_edge_m', 0.5)))
    except (TypeError, ValueError) as error:
        raise ScenarioError(f'geometry: {error}') from None
    return geometry


def _earth_field(earth: dict[str, Any]) -> npt.NDArray[np.float64]:
    if 'igrf' in earth:
        spec = earth['igrf']
        try:
            latitude, longitude = float(spec['latitude_deg']), float(spec['longitude_deg'])
            if not (-90.0 <= latitude <= 90.0 and -180.0 <= longitude <= 360.0):
                raise InputError(f'latitude {latitude} / longitude {longitude} out of range')
            earth_field = igrf_field_enu(
                latitude,
                longitude,
                spec.get('date', '2026-01-01'),
                float(spec.get('altitude_m', 0.0)),
            )
        except KeyError as error:
            raise ScenarioError(f'earth_field.igrf: missing {error}') from None
        except (TypeError, ValueError) as error:
            raise ScenarioError(f'earth_field.igrf: {error}') from None
    else:
        earth_field = _vec(earth, 'enu_nT', (3,), 'earth_field', T_PER_NT)
    return earth_field


def _interference(interference_spec: dict[str, Any], seed: int) -> SensorInterference:
    if 'random' in interference_spec:
        spec = interference_spec['random'] or {}
        _positive(spec, 'k_scale', 'interference.random', allow_zero=True)
        _positive(spec, 'b_scale_nT', 'interference.random', allow_zero=True)
        interference = random_interference(
            np.random.default_rng([seed, 1]),
            k_scale=float(spec.get('k_scale', 5e-3)),
            b_scale_t=float(spec.get('b_scale_nT', 150.0)) * T_PER_NT,
            reference_clean=bool(spec.get('reference_clean', True)),
        )
    elif interference_spec:
        interference = SensorInterference(
            _vec(interference_spec, 'k_soft', (4, 3, 3), 'interference'),
            _vec(interference_spec, 'b_hard_nT', (4, 3), 'interference', T_PER_NT),
        )
    else:
        interference = SensorInterference.zero()
    return interference


def _effects(effects_spec: dict[str, Any]) -> Effects:
    unknown = set(effects_spec) - set(EFFECT_KEYS)
    if unknown:
        raise ScenarioError(f'effects: unknown {sorted(unknown)}; known: {sorted(EFFECT_KEYS)}')
    values = {}
    for name, spec in EFFECT_SPECS.items():
        if name not in effects_spec:
            continue
        section, key, where = effects_spec[name], spec.scenario_key, f'effects.{name}'
        if not isinstance(section, dict) or key not in section:
            raise ScenarioError(f'{where}: missing "{key}"')
        try:
            value = np.asarray(section[key], dtype=float) * spec.scenario_factor
        except (TypeError, ValueError):
            raise ScenarioError(f'{where}.{key}: not numeric: {section[key]!r}') from None
        try:
            values[name] = spec.check(value, f'{where}.{key}')
        except InputError as error:
            raise ScenarioError(str(error)) from None
    try:
        return Effects(**values)
    except InputError as error:
        raise ScenarioError(f'effects: {error}') from None


def _current(current_spec: dict[str, Any]) -> CurrentProfile:
    """The current profile: the hotel load's keys and the ``thrusters`` list."""
    spec = dict(current_spec)
    entries = spec.pop('thrusters', None) or []
    if not isinstance(entries, list):
        raise ScenarioError('current.thrusters: expected a list of {topic: ..., ...}')
    thrusters = []
    for i, entry in enumerate(entries):
        where = f'current.thrusters[{i}]'
        if not isinstance(entry, dict) or 'topic' not in entry:
            raise ScenarioError(f'{where}: expected a mapping with a "topic", got {entry!r}')
        unknown = set(entry) - set(THRUSTER_KEYS)
        if unknown:
            raise ScenarioError(
                f'{where}: unknown {sorted(unknown)}; known: {list(THRUSTER_KEYS)}'
            )
        if entry['topic'] in RESERVED_TOPICS:
            raise ScenarioError(f'{where}.topic: {entry["topic"]} is a topic of the data contract')
        try:
            thrusters.append(Thruster(**entry))
        except (TypeError, ValueError) as error:
            raise ScenarioError(f'{where}: {error}') from None
    try:
        return CurrentProfile(**spec, thrusters=tuple(thrusters))
    except (TypeError, ValueError) as error:
        raise ScenarioError(f'current: {error}') from None


def _regional_gradient(document: dict[str, Any]) -> npt.NDArray[np.float64]:
    """The regional gradient (3, 3) T/m, zero when the file has none."""
    if document.get(REGIONAL_GRADIENT_KEY) is None:
        return np.zeros((3, 3))
    value = _vec(document, REGIONAL_GRADIENT_KEY, (3, 3), 'scenario')
    try:
        check_gradient_tensor(value, REGIONAL_GRADIENT_KEY)
    except InputError as error:
        raise ScenarioError(str(error)) from None
    return value * T_PER_NT


def _clocks(clocks_spec: dict[str, Any] | None) -> SensorClocks | None:
    """The sensor clocks, None when the file has none (the sensors sample together)."""
    if clocks_spec is None:
        return None
    unknown = set(clocks_spec) - set(CLOCK_KEYS)
    if unknown:
        raise ScenarioError(f'clocks: unknown {sorted(unknown)}; known: {sorted(CLOCK_KEYS)}')
    values: dict[str, np.ndarray] = {}
    for key, (name, factor) in CLOCK_KEYS.items():
        if key not in clocks_spec:
            continue
        try:
            value = np.asarray(clocks_spec[key], dtype=float)
        except (TypeError, ValueError):
            raise ScenarioError(f'clocks.{key}: not numeric: {clocks_spec[key]!r}') from None
        if value.shape not in ((), (4,)):
            raise ScenarioError(
                f'clocks.{key}: expected a number or 4 numbers, got {clocks_spec[key]!r}'
            )
        try:
            SensorClocks(**{name: value * factor})  # checks this key alone, to name it
        except InputError as error:
            raise ScenarioError(f'clocks.{key} = {clocks_spec[key]!r}: {error}') from None
        values[name] = value * factor
    return SensorClocks(**values)


def scenario_from_dict(document: dict[str, Any]) -> tuple[Scenario, int]:
    """Build the scenario and return it with its seed."""
    _check_document(document)
    seed = document.get('seed', 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise ScenarioError(f'seed must be an integer from 0 to {MAX_SEED}, got {seed!r}')
    _positive(document, 'sample_rate_hz', 'scenario')
    _positive(document, 'noise_nT', 'scenario', allow_zero=True)
    geometry = _geometry(document.get('geometry') or {'regular_edge_m': 0.5})
    earth_field = _earth_field(document.get('earth_field') or {'enu_nT': [0.0, 20000.0, -45000.0]})
    dipoles = [
        Dipole(
            _vec(d, 'position_m', (3,), f'dipoles[{i}]'),
            _vec(d, 'moment_Am2', (3,), f'dipoles[{i}]'),
        )
        for i, d in enumerate(document.get('dipoles', []))
    ]
    interference = _interference(document.get('interference', {}), seed)
    effects = _effects(document.get('effects') or {})
    segments = [_segment(entry, i) for i, entry in enumerate(document.get('segments') or [])]
    regional_gradient = _regional_gradient(document)
    clocks = _clocks(document.get('clocks'))
    current = _current(document.get('current') or {})
    try:
        scenario = Scenario(
            geometry=geometry,
            earth_field_enu=earth_field,
            segments=tuple(segments),
            sample_rate_hz=float(document.get('sample_rate_hz', 10.0)),
            dipoles=tuple(dipoles),
            interference=interference,
            noise_t=float(document.get('noise_nT', 0.1)) * T_PER_NT,
            effects=effects,
            temperature=TemperatureProfile(**document.get('temperature', {})),
            current=current,
            regional_gradient_enu=regional_gradient,
            clocks=clocks,
        )
    except (TypeError, ValueError) as error:
        raise ScenarioError(f'scenario: {error}') from None
    return scenario, seed


def load_scenario(path: str | os.PathLike) -> tuple[Scenario, int]:
    """Read a scenario file; see the module docstring for the format."""
    path = Path(path)
    document = read_yaml(path, 'scenario', ScenarioError)
    try:
        return scenario_from_dict(document)
    except ScenarioError as error:
        raise ScenarioError(f'{path}: {error}') from None


#: The built-in scenario of the sim driver and the demo: a trim manoeuvre 3 km from the
#: target (true gradient ~1e-5 nT/m there: the calibrator may take it as zero), then a
#: survey line 40 m above a dipole target. Earth field 50 000 nT, a vehicle whose reference
#: sensor is not clean (random soft iron up to 5e-3 and hard iron up to 150 nT on every
#: sensor, sensor 1 included), 0.1 nT noise, 10 Hz, seeded.
DEFAULT_SCENARIO: dict[str, Any] = {
    'seed': 7,
    'sample_rate_hz': 10.0,
    'noise_nT': 0.1,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 20000.0, -45000.0]},
    'dipoles': [{'position_m': [0.0, 0.0, -90.0], 'moment_Am2': [4.0e6, 0.0, 0.0]}],
    'interference': {'random': {'k_scale': 0.005, 'b_scale_nT': 150.0, 'reference_clean': False}},
    'segments': [
        {'trim': {'duration_s': 120.0, 'center_m': [3000.0, 3000.0, -50.0]}},
        {
            'line': {
                'start_m': [-150.0, 5.0, -50.0],
                'end_m': [150.0, 5.0, -50.0],
                'speed_m_s': 2.0,
                'roll_amplitude_deg': 3.0,
                'pitch_amplitude_deg': 2.0,
            }
        },
    ],
}


def load_scenario_or_default(path: str | os.PathLike = '') -> tuple[Scenario, int]:
    """``(Scenario, seed)`` from a scenario file, or :data:`DEFAULT_SCENARIO` when ``path``
    is empty."""
    return load_scenario(path) if path else scenario_from_dict(copy.deepcopy(DEFAULT_SCENARIO))
