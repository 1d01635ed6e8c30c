"""Identification of the interference parameters.

==============================  ==========================================================
``paper_ga``                    the paper's GA as printed (section 5)
``constraint_lstsq``            the same objective solved exactly (rank <= 15 of 27)
``known_gradient_lstsq``        true gradient known (trim manoeuvre): all parameters
``pei_yeo_2009``                reference [8]: sensors mapped onto sensor 1, then differenced
==============================  ==========================================================

``registry.METHODS`` names them all (with ``known_gradient_lstsq_general``, the 36-parameter
known-gradient solve); ``identify(method, ...)`` runs one by name after the attitude-coverage
check. Given attitudes, the known-gradient solves also fit a constant regional gradient;
``calibration_residual`` is what a fit leaves and ``fit_consistency`` tests it against the
sensor noise.
"""

from ...errors import IdentifiabilityError
from .consistency import Block, FitConsistency, fit_consistency
from .lstsq import (
    MAX_COVERAGE_CONDITION,
    MIN_SAMPLES,
    REGIONAL_BASIS,
    attitude_coverage,
    calibration_residual,
    constraint_lstsq,
    constraint_objective,
    known_gradient_lstsq,
    paper_bounds,
    regional_body_tensor,
)
from .paper_ga import paper_ga
from .pei_yeo import pei_yeo_2009
from .registry import CALIBRATION_METHODS, DEFAULT_METHOD, METHODS, Method, Options, identify
from .result import Calibration, ReferenceSensorCalibration, TensorCalibration

__all__ = [
    'CALIBRATION_METHODS',
    'DEFAULT_METHOD',
    'MAX_COVERAGE_CONDITION',
    'METHODS',
    'MIN_SAMPLES',
    'REGIONAL_BASIS',
    'Block',
    'Calibration',
    'FitConsistency',
    'Method',
    'Options',
    'IdentifiabilityError',
    'ReferenceSensorCalibration',
    'TensorCalibration',
    'attitude_coverage',
    'calibration_residual',
    'constraint_lstsq',
    'constraint_objective',
    'fit_consistency',
    'identify',
    'known_gradient_lstsq',
    'paper_bounds',
    'paper_ga',
    'pei_yeo_2009',
    'regional_body_tensor',
]
