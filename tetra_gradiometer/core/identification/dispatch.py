"""One entry for the solvers by name, shared by the calibrator node and the calibrate command."""

from __future__ import annotations

import numpy as np

from ...errors import IdentifiabilityError, InputError
from ..geometry import TetraGeometry
from .lstsq import (
    MAX_COVERAGE_CONDITION,
    attitude_coverage,
    constraint_lstsq,
    known_gradient_lstsq,
    paper_bounds,
)
from .paper_ga import GENERATIONS, paper_ga
from .result import TensorCalibration

#: Methods whose result is the paper's ``k, b`` (eq. 19), i.e. what a calibration file holds.
METHODS = ('known_gradient_lstsq', 'constraint_lstsq', 'paper_ga')


def identify(
    method: str,
    g_measured: np.ndarray,
    b_reference: np.ndarray,
    geometry: TetraGeometry,
    *,
    symmetric_k: bool = False,
    rng: np.random.Generator | None = None,
    generations: int = GENERATIONS,
    wide_bounds: bool = False,
    max_coverage_condition: float = MAX_COVERAGE_CONDITION,
) -> TensorCalibration:
    """Run the solver ``method`` after the attitude-coverage check every method needs.

    Parameters
    ----------
    method : one of :data:`METHODS`
    g_measured : ndarray, shape (N, 3, 3)
        ``G_m``, T/m.
    b_reference : ndarray, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    symmetric_k : bool
        For ``known_gradient_lstsq`` and ``constraint_lstsq``: the paper's symmetric 27
        parameters, else a general 3x3 per pair (36). ``paper_ga`` is symmetric always.
    rng : numpy.random.Generator
        Required for ``paper_ga``.
    generations, wide_bounds
        ``paper_ga`` options.
    max_coverage_condition : float
        Refuse data whose :func:`attitude_coverage` is larger (the body-frame field must take
        3 non-coplanar directions for ``K`` and ``B^h`` to separate).

    Raises
    ------
    IdentifiabilityError
        Too little attitude diversity (the message gives the condition number) or too few samples.
    ValueError
        An unknown method, or ``paper_ga`` without ``rng``.
    """
    if method not in METHODS:
        raise InputError(f'unknown method {method!r}; choose one of {METHODS}')
    coverage = attitude_coverage(b_reference)
    if not coverage <= max_coverage_condition:
        raise IdentifiabilityError(
            f'too little attitude diversity: the body-frame field spans too few directions (attitude '
            f'coverage condition number {coverage:.3g} > {max_coverage_condition:.3g}; it must take at '
            f'least 3 non-coplanar directions: turn, roll and pitch more)'
        )
    if method == 'known_gradient_lstsq':
        result = known_gradient_lstsq(
            g_measured,
            b_reference,
            geometry,
            symmetric_k=symmetric_k,
            max_coverage_condition=max_coverage_condition,
        )
    elif method == 'constraint_lstsq':
        result = constraint_lstsq(g_measured, b_reference, geometry, symmetric_k=symmetric_k)
    else:
        if rng is None:
            raise InputError('paper_ga needs rng (a seeded numpy.random.Generator)')
        if generations < 1:
            raise InputError(f'paper_ga needs at least 1 generation, got {generations}')
        result = paper_ga(
            g_measured,
            b_reference,
            geometry,
            rng=rng,
            generations=generations,
            bounds=paper_bounds(symmetric=True, wide=wide_bounds),
        )
    result.details.setdefault('attitude_coverage_condition', coverage)
    return result
