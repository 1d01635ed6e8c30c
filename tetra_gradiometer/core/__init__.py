"""ROS-free core: geometry, fields, the interference model, identification, metrics and
the mission simulator. Imports numpy and scipy only. SI units (T, T/m, m, s).

scipy's heavier submodules (``stats``, ``optimize``, ``signal``, ``special``, ``integrate``,
``fft``, ``linalg``) are reached as ``scipy.stats`` after a plain ``import scipy``, which loads
each on first use: importing them (scipy 1.17 parses their docstrings) cost every process that
imported the core ~0.8 s of CPU, each node start and CLI command included, used or not."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .clocks import SensorClocks, SensorStream
    from .fields import MU0_OVER_4PI, dipole_field, dipole_gradient, uniform_field
    from .geometry import GeometryError, TetraGeometry, difference_tensor, sensor_differences
    from .identification import (
        Calibration,
        FitConsistency,
        IdentifiabilityError,
        ReferenceSensorCalibration,
        TensorCalibration,
        attitude_coverage,
        calibration_residual,
        constraint_lstsq,
        fit_consistency,
        known_gradient_lstsq,
        paper_bounds,
        paper_ga,
        pei_yeo_2009,
    )
    from .metrics import (
        compensated_percent,
        epsilon,
        improvement_ratio,
        noise_floor,
        rms_residual,
        summarize,
    )
    from .model import (
        InterferenceParameters,
        SensorInterference,
        compensate,
        compensate_fields,
        interference_tensor,
        n_parameters,
    )
    from .simulator import (
        CurrentProfile,
        Dipole,
        Effects,
        MissionData,
        Scenario,
        SurveyLine,
        TemperatureProfile,
        Thruster,
        TrimManoeuvre,
        check_gradient_tensor,
        random_interference,
        simulate,
    )

#: Public name -> the submodule that defines it. Loaded on first use (PEP 562), so that
#: ``from tetra_gradiometer.core import TetraGeometry`` in an on-vehicle node does not load
#: the solvers, the simulator and scipy.stats (1.3 s of a node's 1.7 s import).
_LAZY = {
    'Calibration': '.identification',
    'CurrentProfile': '.simulator',
    'Dipole': '.simulator',
    'Effects': '.simulator',
    'FitConsistency': '.identification',
    'GeometryError': '.geometry',
    'IdentifiabilityError': '.identification',
    'InterferenceParameters': '.model',
    'MU0_OVER_4PI': '.fields',
    'MissionData': '.simulator',
    'ReferenceSensorCalibration': '.identification',
    'Scenario': '.simulator',
    'SensorClocks': '.clocks',
    'SensorInterference': '.model',
    'SensorStream': '.clocks',
    'SurveyLine': '.simulator',
    'TemperatureProfile': '.simulator',
    'TensorCalibration': '.identification',
    'TetraGeometry': '.geometry',
    'Thruster': '.simulator',
    'TrimManoeuvre': '.simulator',
    'attitude_coverage': '.identification',
    'calibration_residual': '.identification',
    'check_gradient_tensor': '.simulator',
    'compensate': '.model',
    'compensate_fields': '.model',
    'compensated_percent': '.metrics',
    'constraint_lstsq': '.identification',
    'difference_tensor': '.geometry',
    'dipole_field': '.fields',
    'dipole_gradient': '.fields',
    'epsilon': '.metrics',
    'fit_consistency': '.identification',
    'improvement_ratio': '.metrics',
    'interference_tensor': '.model',
    'known_gradient_lstsq': '.identification',
    'n_parameters': '.model',
    'noise_floor': '.metrics',
    'paper_bounds': '.identification',
    'paper_ga': '.identification',
    'pei_yeo_2009': '.identification',
    'random_interference': '.simulator',
    'rms_residual': '.metrics',
    'sensor_differences': '.geometry',
    'simulate': '.simulator',
    'summarize': '.metrics',
    'uniform_field': '.fields',
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    'MU0_OVER_4PI',
    'Calibration',
    'CurrentProfile',
    'Dipole',
    'Effects',
    'FitConsistency',
    'GeometryError',
    'IdentifiabilityError',
    'InterferenceParameters',
    'MissionData',
    'ReferenceSensorCalibration',
    'Scenario',
    'SensorClocks',
    'SensorInterference',
    'SensorStream',
    'SurveyLine',
    'TemperatureProfile',
    'TensorCalibration',
    'TetraGeometry',
    'Thruster',
    'TrimManoeuvre',
    'attitude_coverage',
    'calibration_residual',
    'check_gradient_tensor',
    'compensate',
    'compensate_fields',
    'compensated_percent',
    'constraint_lstsq',
    'difference_tensor',
    'dipole_field',
    'dipole_gradient',
    'epsilon',
    'fit_consistency',
    'improvement_ratio',
    'interference_tensor',
    'known_gradient_lstsq',
    'n_parameters',
    'noise_floor',
    'paper_bounds',
    'paper_ga',
    'pei_yeo_2009',
    'random_interference',
    'rms_residual',
    'sensor_differences',
    'simulate',
    'summarize',
    'uniform_field',
]
