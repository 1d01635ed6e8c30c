"""Exact linear solvers: the paper's objective solved directly, and identification on
data whose true gradient is known (trim manoeuvres)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from ...errors import IdentifiabilityError
from .._validate import as_tensors, as_vectors, same_length
from ..design import CONSTRAINT_ROWS, constraint_design, constraint_residual, interference_design
from ..geometry import TetraGeometry
from ..model import InterferenceParameters, interference_tensor, n_parameters
from ..types import ArrayLike, FloatArray
from ..units import NT_PER_T
from ._linear import AffineReduction, reduce_affine, solve_scaled
from .result import TensorCalibration

#: Fewest samples any solver accepts.
MIN_SAMPLES = 10
#: Largest attitude-coverage condition number accepted by ``known_gradient_lstsq``.
MAX_COVERAGE_CONDITION = 1.0e4


def paper_bounds(*, symmetric: bool = True, wide: bool = False) -> tuple[FloatArray, FloatArray]:
    """Bounds of eq. 23 in SI: ``0 <= k <= 0.01``, ``0 <= b <= 10 nT``.

    ``wide=True`` gives ``|k| <= 1``, ``|b| <= 1000 nT`` instead (the printed bounds exclude
    the printed truth: ``K_2 - K_1`` has 0.451 on its diagonal).
    """
    n_k = n_parameters(symmetric=symmetric) - 9
    k_lo, k_hi, b_lo, b_hi = (-1.0, 1.0, -1000e-9, 1000e-9) if wide else (0.0, 0.01, 0.0, 10e-9)
    lower = np.concatenate([np.full(n_k, k_lo), np.full(9, b_lo)])
    upper = np.concatenate([np.full(n_k, k_hi), np.full(9, b_hi)])
    return lower, upper


def attitude_coverage(b_reference: ArrayLike) -> float:
    """Condition number of ``[B_1' 1]`` with unit-norm columns: how well the body-frame field
    directions (and the offset) are separated. Near 1-10: rich trim manoeuvre; infinite: one
    direction only (``K`` and ``B^h`` inseparable).

    Parameters
    ----------
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla.
    """
    b_reference = as_vectors(b_reference, 'b_reference')
    regressors = np.column_stack([b_reference, np.ones(len(b_reference))])
    norms = np.linalg.norm(regressors, axis=0)
    if np.any(norms == 0.0):
        return float('inf')
    singular = np.linalg.svd(regressors / norms, compute_uv=False)
    return float('inf') if singular[-1] == 0.0 else float(singular[0] / singular[-1])


def noise_whitener(geometry: TetraGeometry) -> FloatArray:
    """Right-multiplier making each tensor row's noise white for i.i.d. sensor noise.

    A tensor row is ``e a^-1`` with ``e = (n_2 - n_1, n_3 - n_1, n_4 - n_1)`` per axis,
    covariance ``sigma^2 (I + 1 1^T)``; ``(I + 1 1^T)^(-1/2) = I - 1 1^T / 6``.
    """
    return geometry.a @ (np.eye(3) - np.ones((3, 3)) / 6.0)


def reduced_design(
    reduction: AffineReduction, geometry: TetraGeometry, *, symmetric: bool
) -> FloatArray:
    """The interference design (eq. 18) at the 4 pseudo-samples of ``reduction``, (4, 9, P):
    the offset columns weighted by the pseudo-samples' 4th regressor instead of 1."""
    r = reduction.regressors
    design = interference_design(r[:, :3], geometry, symmetric=symmetric).copy()
    n_k = design.shape[2] - 9
    design[:, :, n_k:] *= r[:, 3, None, None]
    return design


def _check_samples(n: int, method: str) -> None:
    if n < MIN_SAMPLES:
        raise IdentifiabilityError(
            f'{method}: {n} samples are too few (need at least {MIN_SAMPLES})'
        )


def known_gradient_lstsq(
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    *,
    g_true: ArrayLike | None = None,
    symmetric_k: bool = True,
    max_coverage_condition: float = MAX_COVERAGE_CONDITION,
) -> TensorCalibration:
    """Identify ``k``, ``b`` where the true gradient is known (zero on a trim manoeuvre).

    Solves ``G_m - G_true = D(theta)`` (eq. 18) by generalised least squares, whitened for
    i.i.d. sensor noise, so that the returned covariance is ``sigma^2 (A^T A)^-1`` with
    ``sigma`` (per-axis sensor noise) estimated from the residual. Noise on ``B_1'`` as a
    regressor is neglected (it matters only for ``|K| ~ 1``).

    Parameters
    ----------
    g_measured : array_like, shape (N, 3, 3)
        Measured tensor ``G_m``, T/m.
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla, body frame.
    geometry : TetraGeometry
    g_true : array_like, shape (N, 3, 3), optional
        Known true tensor, T/m; zero (uniform field) when omitted.
    symmetric_k : bool
        True: the paper's 27 parameters. False: a general 3x3 per pair (36), exact when
        sensor 1 carries its own interference (effective ``K_i1 (I + K_1)^-1``).
    max_coverage_condition : float
        Refuse data whose :func:`attitude_coverage` exceeds this.

    Raises
    ------
    IdentifiabilityError
        Too few samples, or too little attitude diversity (message gives the condition number).
    """
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    g_true = np.zeros_like(g_measured) if g_true is None else as_tensors(g_true, 'g_true')
    n = same_length(g_measured=g_measured, b_reference=b_reference, g_true=g_true)
    method = 'known_gradient_lstsq' if symmetric_k else 'known_gradient_lstsq_general'
    _check_samples(n, method)
    coverage = attitude_coverage(b_reference)
    if not coverage <= max_coverage_condition:
        raise IdentifiabilityError(
            f'{method}: the body-frame field spans too few directions (attitude coverage '
            f'condition number {coverage:.3g} > {max_coverage_condition:.3g}); '
            'turn, roll and pitch more'
        )
    whitener = noise_whitener(geometry)
    target_w = (g_measured - g_true) @ whitener  # (N, 3, 3): rows of G, whitened columns
    # The whitened design is linear in x_n = (B_1', 1): reduce the 9N x P problem exactly to
    # 36 x P (see reduce_affine) and solve that by the same scaled SVD.
    reduction = reduce_affine(b_reference, target_w.reshape(n, 9))
    design = reduced_design(reduction, geometry, symmetric=symmetric_k)
    n_par = design.shape[2]
    design_w = np.einsum('nRjp,jk->nRkp', design.reshape(4, 3, 3, n_par), whitener).reshape(
        -1, n_par
    )
    solution = solve_scaled(design_w, reduction.targets.reshape(-1))
    parameters = InterferenceParameters.from_vector(solution.theta, symmetric=symmetric_k)
    residual = g_measured - g_true - interference_tensor(b_reference, parameters, geometry)
    residual_w = residual @ whitener
    dof = max(residual.size - solution.rank, 1)
    sigma2 = float(np.sum(residual_w**2)) / dof
    return TensorCalibration(
        method=method,
        n_samples=n,
        n_parameters=n_par,
        rank=solution.rank,
        condition_number=solution.condition_number,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        details={
            'attitude_coverage_condition': coverage,
            'sensor_noise_nT': float(np.sqrt(sigma2) * NT_PER_T),
        },
        parameters=parameters,
        symmetric=symmetric_k,
        covariance=sigma2 * solution.covariance_unit,
    )


def constraint_objective(
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    *,
    symmetric_k: bool = True,
) -> tuple[FloatArray, FloatArray]:
    """The linear system behind eqs. 21-22: ``F(theta) = |A theta - y|^2``.

    Returns
    -------
    design : ndarray, shape (4N, P)
        T/m per unit parameter.
    target : ndarray, shape (4N,)
        Asymmetry and trace of ``G_m``, T/m.
    """
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    same_length(g_measured=g_measured, b_reference=b_reference)
    design = constraint_design(b_reference, geometry, symmetric=symmetric_k)
    return design.reshape(-1, design.shape[2]), constraint_residual(g_measured).reshape(-1)


def constraint_lstsq(
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    *,
    symmetric_k: bool = True,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> TensorCalibration:
    """The paper's objective (eqs. 21-22) solved exactly as the linear least squares it is.

    The design has rank at most 15 of 27: the symmetric, traceless part of ``D`` is
    invisible to symmetry and trace conditions. Unbounded, the minimum-norm solution (in
    column-scaled coordinates) is returned; with ``bounds`` (SI, e.g. :func:`paper_bounds`)
    the bounded problem is solved with :func:`scipy.optimize.lsq_linear`.

    Parameters
    ----------
    g_measured : array_like, shape (N, 3, 3)
        T/m.
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    symmetric_k : bool
    bounds : (lower, upper), each shape (P,), optional
        SI units of the parameter vector.
    """
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    n = same_length(g_measured=g_measured, b_reference=b_reference)
    _check_samples(n, 'constraint_lstsq')
    # Same reduction as known_gradient_lstsq: 4N x P -> 16 x P with the same normal matrix,
    # right-hand side and singular values (the objective differs by a constant).
    reduction = reduce_affine(b_reference, constraint_residual(g_measured))
    reduced = reduced_design(reduction, geometry, symmetric=symmetric_k)
    design = np.einsum('kq,nqp->nkp', CONSTRAINT_ROWS, reduced).reshape(-1, reduced.shape[2])
    target = reduction.targets.reshape(-1)
    solution = solve_scaled(design, target)
    theta = solution.theta
    details: dict = {'bounded': bounds is not None}
    if bounds is not None:
        scale = np.linalg.norm(design, axis=0)
        scale[scale == 0.0] = 1.0
        lower, upper = (np.asarray(b, dtype=float) for b in bounds)
        bounded = lsq_linear(
            design / scale,
            target,
            bounds=(lower * scale, upper * scale),
            method='bvls',
            lsmr_tol='auto',
        )
        theta = bounded.x / scale
    parameters = InterferenceParameters.from_vector(theta, symmetric=symmetric_k)
    # Residual of eq. 21 on every sample: the asymmetry and trace left after compensation.
    residual = constraint_residual(
        g_measured - interference_tensor(b_reference, parameters, geometry)
    )
    details['objective_F'] = float(np.sum(residual**2))
    return TensorCalibration(
        method='constraint_lstsq',
        n_samples=n,
        n_parameters=design.shape[1],
        rank=solution.rank,
        condition_number=solution.condition_number,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        details=details,
        parameters=parameters,
        symmetric=symmetric_k,
    )
