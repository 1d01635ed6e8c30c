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
    effects: {}                                # see EFFECT_KEYS
"""
from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..core import (CurrentProfile, Dipole, Effects, Scenario, SensorInterference, SurveyLine,
                    TemperatureProfile, TetraGeometry, TrimManoeuvre, random_interference)

NT = 1e-9

#: effect name -> (key in the file, factor to SI)
EFFECT_KEYS = {
    'eddy_current': ('coefficients_s', 1.0),
    'sensor_misalignment': ('rotation_deg', np.pi / 180.0),
    'time_skew_s': ('delay_s', 1.0),
    'thermal_drift': ('nT_per_degC', NT),
    'vehicle_current': ('nT_per_A', NT),
}


class ScenarioError(ValueError):
    """A scenario file is missing a key or has a malformed value."""


def igrf_field_enu(latitude_deg: float, longitude_deg: float, date: _dt.date | str,
                   altitude_m: float = 0.0) -> np.ndarray:
    """IGRF-14 main field (3,) in tesla, ENU, at a place and date (ppigrf)."""
    import ppigrf
    when = _dt.datetime.fromisoformat(str(date)) if not isinstance(date, _dt.date) else date
    if not isinstance(when, _dt.datetime):
        when = _dt.datetime(when.year, when.month, when.day)
    east, north, up = ppigrf.igrf(longitude_deg, latitude_deg, altitude_m / 1000.0, when)
    return np.array([east.item(), north.item(), up.item()]) * NT


def _vec(section: dict, key: str, shape: tuple[int, ...], where: str, factor: float = 1.0) -> np.ndarray:
    if key not in section:
        raise ScenarioError(f'{where}: missing "{key}"')
    try:
        value = np.asarray(section[key], dtype=float)
    except (TypeError, ValueError):
        raise ScenarioError(f'{where}.{key}: not numeric: {section[key]!r}') from None
    if value.shape != shape:
        raise ScenarioError(f'{where}.{key}: expected shape {shape}, got {value.shape}')
    return value * factor


def _segment(entry: dict, index: int) -> TrimManoeuvre | SurveyLine:
    where = f'segments[{index}]'
    if not isinstance(entry, dict) or len(entry) != 1 or next(iter(entry)) not in ('trim', 'line'):
        raise ScenarioError(f'{where}: expected {{trim: {{...}}}} or {{line: {{...}}}}, got {entry!r}')
    kind, spec = next(iter(entry.items()))
    spec = dict(spec or {})
    try:
        if kind == 'trim':
            center = tuple(_vec(spec, 'center_m', (3,), where)) if 'center_m' in spec else (0.0, 0.0, -50.0)
            spec.pop('center_m', None)
            return TrimManoeuvre(center=center, **spec)
        start, end = _vec(spec, 'start_m', (3,), where), _vec(spec, 'end_m', (3,), where)
        spec.pop('start_m'), spec.pop('end_m')
        return SurveyLine(tuple(start), tuple(end), **spec)
    except TypeError as error:
        raise ScenarioError(f'{where}: {error}') from None


def scenario_from_dict(document: dict[str, Any]) -> tuple[Scenario, int]:
    """Build the scenario and return it with its seed."""
    if not isinstance(document, dict):
        raise ScenarioError('a scenario must be a mapping')
    seed = int(document.get('seed', 0))
    geometry_spec = document.get('geometry', {'regular_edge_m': 0.5})
    if 'sensor_positions_m' in geometry_spec:
        geometry = TetraGeometry.from_flat(geometry_spec['sensor_positions_m'])
    else:
        geometry = TetraGeometry.regular(float(geometry_spec.get('regular_edge_m', 0.5)))
    earth = document.get('earth_field', {'enu_nT': [0.0, 20000.0, -45000.0]})
    if 'igrf' in earth:
        spec = earth['igrf']
        earth_field = igrf_field_enu(float(spec['latitude_deg']), float(spec['longitude_deg']),
                                     spec.get('date', '2026-01-01'), float(spec.get('altitude_m', 0.0)))
    else:
        earth_field = _vec(earth, 'enu_nT', (3,), 'earth_field', NT)
    dipoles = [Dipole(_vec(d, 'position_m', (3,), f'dipoles[{i}]'), _vec(d, 'moment_Am2', (3,), f'dipoles[{i}]'))
               for i, d in enumerate(document.get('dipoles', []))]
    interference_spec = document.get('interference', {})
    if 'random' in interference_spec:
        spec = interference_spec['random']
        interference = random_interference(
            np.random.default_rng([seed, 1]), k_scale=float(spec.get('k_scale', 5e-3)),
            b_scale_t=float(spec.get('b_scale_nT', 150.0)) * NT,
            reference_clean=bool(spec.get('reference_clean', True)))
    elif interference_spec:
        interference = SensorInterference(_vec(interference_spec, 'k_soft', (4, 3, 3), 'interference'),
                                          _vec(interference_spec, 'b_hard_nT', (4, 3), 'interference', NT))
    else:
        interference = SensorInterference.zero()
    effects_spec = document.get('effects') or {}
    unknown = set(effects_spec) - set(EFFECT_KEYS)
    if unknown:
        raise ScenarioError(f'effects: unknown {sorted(unknown)}; known: {sorted(EFFECT_KEYS)}')
    shapes = {'eddy_current': (4, 3, 3), 'time_skew_s': (4,)}
    effects = Effects(**{name: _vec(effects_spec[name], key, shapes.get(name, (4, 3)), f'effects.{name}', factor)
                         for name, (key, factor) in EFFECT_KEYS.items() if name in effects_spec})
    segments = [_segment(entry, i) for i, entry in enumerate(document.get('segments') or [])]
    try:
        scenario = Scenario(
            geometry=geometry, earth_field_enu=earth_field, segments=segments,
            sample_rate_hz=float(document.get('sample_rate_hz', 10.0)), dipoles=dipoles,
            interference=interference, noise_t=float(document.get('noise_nT', 0.1)) * NT, effects=effects,
            temperature=TemperatureProfile(**document.get('temperature', {})),
            current=CurrentProfile(**document.get('current', {})))
    except TypeError as error:
        raise ScenarioError(f'scenario: {error}') from None
    return scenario, seed


def load_scenario(path: str | os.PathLike) -> tuple[Scenario, int]:
    """Read a scenario file; see the module docstring for the format."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        raise ScenarioError(f'scenario file not found: {path}') from None
    except yaml.YAMLError as error:
        raise ScenarioError(f'scenario file {path} is not valid YAML: {error}') from None
    try:
        return scenario_from_dict(document)
    except ScenarioError as error:
        raise ScenarioError(f'{path}: {error}') from None
