"""Targets: the array's view of a point dipole, anomaly detection at a stated false-alarm
rate, dipole localization with uncertainties, and the survey pipeline joining them."""

from ..geometry import to_body, to_world
from .detection import Detection, DetectionResult, DetectorSettings, detect, legs
from .forward import array_tensor, reference_points, sensor_points
from .localization import DipoleFit, Pass, fit_dipole, fit_dipoles
from .survey import LocatorSettings, Survey, Target, locate

__all__ = [
    'Detection',
    'DetectionResult',
    'DetectorSettings',
    'DipoleFit',
    'LocatorSettings',
    'Pass',
    'Survey',
    'Target',
    'array_tensor',
    'detect',
    'fit_dipole',
    'fit_dipoles',
    'legs',
    'locate',
    'reference_points',
    'sensor_points',
    'to_body',
    'to_world',
]
