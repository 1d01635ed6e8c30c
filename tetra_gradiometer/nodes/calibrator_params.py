"""The calibrator node's parameters (:mod:`.calibrator`): the declarations, their bounds
and validators (docs/ros.md, *Parameters*, and config/tetra_gradiometer.yaml list them)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..core.effects import parse_declaration
from ..core.identification import (
    CALIBRATION_METHODS,
    DEFAULT_METHOD,
    MAX_COVERAGE_CONDITION,
    METHODS,
    MIN_SAMPLES,
)
from ..core.plausibility import MAX_FIELD_T, plausible_readings
from ..errors import InputError
from ..pipelines.effects_choice import EffectsChoice
from .authentication import key_file_spec
from .common import (
    POSITIONS_SPEC,
    ParamSpec,
    absolute_topics,
    diagnostics_period_spec,
    non_negative,
    one_of,
    positive,
)
from .stamps import AHEAD_SPEC

#: Bounds of ``max_samples`` and ``ga_generations`` (see their descriptions).
MAX_SAMPLES = 500_000
MAX_GENERATIONS = 20_000
#: The guidance's sensor noise before the samples estimate it, with ``sensor_noise_t`` 0, T.
DEFAULT_NOISE_T = 1.0e-10


def _path(value: str) -> str | None:
    return None if value.strip() else 'must name a file'


def _field_enu(value: Any) -> str | None:
    field = np.asarray(value, dtype=float)
    if field.shape != (3,) or not plausible_readings(field):
        return f'must be 3 finite floats, tesla ENU, with |B| <= {MAX_FIELD_T:g} T, got {value!r}'
    return None


def _signals(value: Any) -> str | None:
    try:
        for declaration in value:
            parse_declaration(declaration)
    except InputError as error:
        return str(error)
    return None


def _effects(value: Any) -> str | None:
    try:
        EffectsChoice.parse(value)
    except InputError as error:
        return str(error).removeprefix('--effects ')
    return None


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
    ParamSpec(
        'force',
        False,
        '~/calibrate keeps a calibration whose samples fail the test of its assumption '
        "(residual vs sensor noise), warning in the file's notes (false: refused, not written); "
        "the default of the request's force, which a call's true overrides.",
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
    ParamSpec(
        'earth_field_enu',
        (0.0, 2.0e-5, -4.5e-5),
        "The site's Earth field, tesla, ENU (east, north, up): the trim guidance flies its "
        'survey attitudes and candidate manoeuvres in it (the offline tools read it too).',
        _field_enu,
    ),
    ParamSpec(
        'sensor_noise_t',
        0.0,
        'White noise per axis of each magnetometer, tesla RMS (0 to 1e-6), that the trim '
        f'guidance assumes until {MIN_SAMPLES} samples estimate their own (the fit residual); '
        f'0 = unknown ({DEFAULT_NOISE_T:g} T then). (The driver and compensator read the same '
        'value.)',
        non_negative,
        float_range=(0.0, 1e-6),
    ),
    ParamSpec(
        'effects',
        'auto',
        'Vehicle effects ~/calibrate fits with k, b (known_gradient_lstsq_general only) when its '
        'request leaves effects empty: '
        '"auto" (those whose channels have messages, kept when they pass the held-out test), '
        '"none" (k, b only) or effect names separated by commas (vehicle_current, '
        'eddy_current, thermal_drift; refused when a channel they read has no message), as '
        'calibrate --effects.',
        _effects,
    ),
    ParamSpec(
        'current_topics',
        (),
        'Further sensor_msgs/BatteryState topics whose current the vehicle_current effect '
        'reads, besides /battery_state (absolute names, e.g. /thruster1/battery; empty: none), '
        'as calibrate --current-topics. Read-only after start-up.',
        absolute_topics,
        string_array=True,
    ),
    ParamSpec(
        'vehicle_signals',
        (),
        "The vehicle's own recorded signals fitted as effects, TOPIC#FIELD:BASIS (bases: "
        'linear, harmonic, onoff, rate; e.g. /joint_states#position[fin1]:harmonic), as the '
        "params file's vehicle_signals for calibrate; each topic's type is the graph's at "
        'configure. Read-only after start-up.',
        _signals,
        string_array=True,
    ),
    key_file_spec('signs'),
    AHEAD_SPEC,
    diagnostics_period_spec(),
]
