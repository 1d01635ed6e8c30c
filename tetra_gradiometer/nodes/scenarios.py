"""The driver's built-in sim scenario (the io/scenario.py YAML format, as a dict).

A trim manoeuvre 3 km from the target (true gradient ~1e-5 nT/m there: the calibrator may
take it as zero), then a survey line passing 40 m above a dipole target. Earth field
50 000 nT, a vehicle whose reference sensor is not clean (random soft iron up to 5e-3 and
hard iron up to 150 nT on every sensor, sensor 1 included), 0.1 nT noise, 10 Hz, seeded.
"""
from __future__ import annotations

import copy
from typing import Any

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
        {'line': {'start_m': [-150.0, 5.0, -50.0], 'end_m': [150.0, 5.0, -50.0], 'speed_m_s': 2.0,
                  'roll_amplitude_deg': 3.0, 'pitch_amplitude_deg': 2.0}},
    ],
}


def default_scenario_dict() -> dict[str, Any]:
    """A fresh copy of :data:`DEFAULT_SCENARIO`."""
    return copy.deepcopy(DEFAULT_SCENARIO)


def load(path: str = '') -> tuple[Any, int]:
    """``(Scenario, seed)`` from a scenario YAML file, or the built-in default when ``path`` is empty."""
    from ..io.scenario import load_scenario, scenario_from_dict
    return load_scenario(path) if path else scenario_from_dict(default_scenario_dict())
