"""The one registry of identification methods: name -> solver, description, parameter count.

Every consumer reads :data:`METHODS`: ``identify()`` (and through it the calibrator node's
``method`` parameter and the ``calibrate`` command's ``--method``), the paper reproduction
and the docs table. Adding a solver is one module in this package plus one :class:`Method`
entry here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

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
from .pei_yeo import pei_yeo_2009
from .result import Calibration
from .terms import Candidate, fit_with_terms

FloatArray = NDArray[np.float64]

__all__ = ['CALIBRATION_METHODS', 'DEFAULT_METHOD', 'METHODS', 'Method', 'Options', 'identify']


@dataclass(frozen=True)
class Options:
    """Options a solver may use; each method reads the ones it needs.

    Attributes
    ----------
    rng : numpy.random.Generator or None
        ``paper_ga``: the seeded generator (required).
    generations : int
        ``paper_ga``: generations.
    wide_bounds : bool
        ``paper_ga``: ``|k| <= 1``, ``|b| <= 1000 nT`` instead of the printed bounds (eq. 23).
    max_coverage_condition : float
        Refuse data whose attitude-coverage condition number is larger.
    g_true : ndarray, shape (N, 3, 3), or None
        Known true tensor, T/m (known-gradient methods, Pei & Yeo); zero when None.
    fields_measured : ndarray, shape (N, 4, 3), or None
        The four raw readings, tesla (Pei & Yeo's per-sensor maps need them).
    deadline_s : float or None
        A ``time.monotonic()`` instant: an iterative solver (``paper_ga``) starts no step
        after it and returns its best result so far, its ``details`` saying so (``stopped``,
        ``generations`` run). The closed-form solvers run to the end (they take about a
        second per 10^6 samples).
    should_stop : callable or None
        Asked once per step of an iterative solver; True ends it like ``deadline_s``
        (cancellation: the caller, which knows why, discards or keeps the result).
    orientation_xyzw : ndarray, shape (N, 4), or None
        Attitude quaternions (x, y, z, w) rotating body vectors into ENU. The known-gradient
        methods then fit a constant regional (world-frame) gradient jointly with ``k``, ``b``
        (the result's ``regional_gradient_enu``); the others ignore it.
    terms : tuple of terms.Candidate
        Vehicle effects to fit jointly (their regressors on the same samples):
        ``known_gradient_lstsq_general`` only (:func:`~.terms.fit_with_terms`); the result's
        parameters carry them.
    """

    rng: np.random.Generator | None = None
    generations: int = GENERATIONS
    wide_bounds: bool = False
    max_coverage_condition: float = MAX_COVERAGE_CONDITION
    g_true: FloatArray | None = None
    fields_measured: FloatArray | None = field(default=None, repr=False)
    deadline_s: float | None = None
    should_stop: Callable[[], bool] | None = field(default=None, repr=False)
    orientation_xyzw: FloatArray | None = field(default=None, repr=False)
    terms: tuple[Candidate, ...] = field(default=(), repr=False)


Solver = Callable[[FloatArray, FloatArray, TetraGeometry, Options], Calibration]


@dataclass(frozen=True)
class Method:
    """One identification method.

    Attributes
    ----------
    name : str
        The one spelling used by the CLI, the node parameter, files and docs.
    solve : callable
        ``solve(g_measured (N,3,3) T/m, b_reference (N,3) T, geometry, options) -> Calibration``.
    description : str
        One line for help texts and the docs table.
    n_parameters : int
        Parameters it identifies.
    calibration_file : bool
        Its result is the paper's ``k, b`` (eq. 19), i.e. what a calibration file holds and
        the calibrator node can publish (Pei & Yeo's per-sensor maps are not).
    """

    name: str
    solve: Solver
    description: str
    n_parameters: int
    calibration_file: bool = True


def _known_gradient(symmetric: bool) -> Solver:
    def solve(g: FloatArray, b: FloatArray, geometry: TetraGeometry, o: Options) -> Calibration:
        if o.terms:
            if symmetric:
                raise InputError(
                    'vehicle-effect terms are fitted with known_gradient_lstsq_general '
                    '(a general K_i1), not with the symmetric known_gradient_lstsq'
                )
            return fit_with_terms(
                g, b, geometry, o.terms, g_true=o.g_true, orientation_xyzw=o.orientation_xyzw
            )
        return known_gradient_lstsq(
            g,
            b,
            geometry,
            g_true=o.g_true,
            symmetric_k=symmetric,
            max_coverage_condition=o.max_coverage_condition,
            orientation_xyzw=o.orientation_xyzw,
        )

    return solve


def _constraint(g: FloatArray, b: FloatArray, geometry: TetraGeometry, o: Options) -> Calibration:
    return constraint_lstsq(g, b, geometry, symmetric_k=True)


def _paper_ga(g: FloatArray, b: FloatArray, geometry: TetraGeometry, o: Options) -> Calibration:
    if o.rng is None:
        raise InputError('paper_ga needs rng (a seeded numpy.random.Generator)')
    if o.generations < 1:
        raise InputError(f'paper_ga needs at least 1 generation, got {o.generations}')
    bounds = paper_bounds(symmetric=True, wide=o.wide_bounds)
    return paper_ga(
        g,
        b,
        geometry,
        rng=o.rng,
        generations=o.generations,
        bounds=bounds,
        deadline=o.deadline_s,
        should_stop=o.should_stop,
    )


def _pei_yeo(g: FloatArray, b: FloatArray, geometry: TetraGeometry, o: Options) -> Calibration:
    if o.fields_measured is None:
        raise InputError("pei_yeo_2009 needs the four sensors' readings (Options.fields_measured)")
    return pei_yeo_2009(o.fields_measured, geometry=geometry, g_true=o.g_true)


#: In the order of the paper's comparison: its own GA and objective, then the known-gradient
#: solves, then the reference method.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            'paper_ga',
            _paper_ga,
            "the paper's genetic algorithm as printed (section 5, bounds of eq. 23), seeded",
            27,
        ),
        Method(
            'constraint_lstsq',
            _constraint,
            "the paper's objective (symmetric, traceless, eqs. 20-22) solved exactly: rank <= 15",
            27,
        ),
        Method(
            'known_gradient_lstsq',
            _known_gradient(symmetric=True),
            "the same with the paper's symmetric K_i1",
            27,
        ),
        Method(
            'known_gradient_lstsq_general',
            _known_gradient(symmetric=False),
            'known (zero) gradient on a trim manoeuvre, a general 3x3 K_i1 per sensor pair: '
            "all parameters observable, exact also with sensor 1's own interference",
            36,
        ),
        Method(
            'pei_yeo_2009',
            _pei_yeo,
            'Pei & Yeo 2009: per-sensor affine maps onto sensor 1, then differencing',
            36,
            calibration_file=False,
        ),
    )
}

#: Names whose result a calibration file holds (the node's ``method``, ``calibrate --method``).
CALIBRATION_METHODS = tuple(name for name, m in METHODS.items() if m.calibration_file)
DEFAULT_METHOD = 'known_gradient_lstsq_general'


def identify(
    method: str,
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    options: Options | None = None,
) -> Calibration:
    """Run the registered solver ``method`` after the attitude-coverage check every method needs.

    Parameters
    ----------
    method : str
        A key of :data:`METHODS`.
    g_measured : ndarray, shape (N, 3, 3)
        ``G_m``, T/m.
    b_reference : ndarray, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    options : Options, optional

    Returns
    -------
    Calibration
        Its ``method`` is the registry name; ``details['attitude_coverage_condition']`` is set.
        With ``options.deadline_s`` or ``options.should_stop``, an iterative solver may have
        stopped early: ``details['stopped']`` (``'deadline'``, ``'should_stop'``) says so.

    Raises
    ------
    IdentifiabilityError
        Too little attitude diversity (the message gives the condition number) or too few samples.
    InputError
        An unknown method, or a method's missing option (``paper_ga`` without ``rng``).
    """
    options = options or Options()
    entry = METHODS.get(method)
    if entry is None:
        raise InputError(f'unknown method {method!r}; choose one of {list(METHODS)}')
    coverage = attitude_coverage(b_reference)
    if not coverage <= options.max_coverage_condition:
        raise IdentifiabilityError(
            'too little attitude diversity: the body-frame field spans too few directions '
            f'(attitude coverage condition number {coverage:.3g} > '
            f'{options.max_coverage_condition:.3g}; it must take at least 3 non-coplanar '
            'directions: turn, roll and pitch more)'
        )
    result = entry.solve(g_measured, b_reference, geometry, options)
    result.details.setdefault('attitude_coverage_condition', coverage)
    return replace(result, method=method)
