"""ROS-free core: geometry, fields, the interference model, identification, metrics and
the mission simulator. Imports numpy and scipy only. SI units (T, T/m, m, s)."""
from .fields import MU0_OVER_4PI, dipole_field, dipole_gradient, uniform_field
from .geometry import GeometryError, TetraGeometry, difference_tensor, sensor_differences
from .identification import (Calibration, IdentifiabilityError, ReferenceSensorCalibration,
                             TensorCalibration, attitude_coverage, constraint_lstsq,
                             known_gradient_lstsq, paper_bounds, paper_ga, pei_yeo_2009)
from .metrics import (compensated_percent, epsilon, improvement_ratio, noise_floor, rms_residual,
                      summarize)
from .model import (InterferenceParameters, SensorInterference, compensate, compensate_fields,
                    interference_tensor, n_parameters)
from .simulator import (CurrentProfile, Dipole, Effects, MissionData, Scenario, SurveyLine,
                        TemperatureProfile, TrimManoeuvre, random_interference, simulate)

__all__ = [
    'MU0_OVER_4PI', 'Calibration', 'CurrentProfile', 'Dipole', 'Effects', 'GeometryError',
    'IdentifiabilityError', 'InterferenceParameters', 'MissionData', 'ReferenceSensorCalibration',
    'Scenario', 'SensorInterference', 'SurveyLine', 'TemperatureProfile', 'TensorCalibration',
    'TetraGeometry', 'TrimManoeuvre', 'attitude_coverage', 'compensate', 'compensate_fields',
    'compensated_percent', 'constraint_lstsq', 'difference_tensor', 'dipole_field', 'dipole_gradient',
    'epsilon', 'improvement_ratio', 'interference_tensor', 'known_gradient_lstsq', 'n_parameters',
    'noise_floor', 'paper_bounds', 'paper_ga', 'pei_yeo_2009', 'random_interference', 'rms_residual',
    'sensor_differences', 'simulate', 'summarize', 'uniform_field',
]
