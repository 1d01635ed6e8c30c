"""Exact linear solvers: the paper's objective solved directly, and identification on
data whose true gradient is known (trim manoeuvres), optionally jointly with a constant
regional (world-frame) gradient.

Regional gradient: ``G_w`` (ENU, symmetric, traceless) is seen in the body frame as
``R_n^T G_w R_n``, ``R_n`` the attitude rotating body vectors into ENU. Its 5 coefficients
are ``c = (gxx, gxy, gxz, gyy, gyz)`` of ``G_w`` with ``gzz = -gxx - gyy``
(:data:`REGIONAL_BASIS`).
"""

from __future__ import annotations

import numpy as np

from ...errors import IdentifiabilityError, InputError
from .._validate import as_array, as_tensors, as_vectors, same_length
from ..design import CONSTRAINT_ROWS, constraint_design, constraint_residual, interference_design
from ..geometry import TetraGeometry, to_body
from ..model import InterferenceParameters, interference_tensor, n_parameters
from ..types import ArrayLike, FloatArray
from ..units import NT_PER_T
from ._linear import AffineReduction, LinearSolution, reduce_affine, solve_scaled
from ._selection import PAIR_WHITENER
from .result import TensorCalibration

#: Fewest samples any solver accepts.
MIN_SAMPLES = 10
#: Largest attitude-coverage condition number accepted by ``known_gradient_lstsq``.
MAX_COVERAGE_CONDITION = 1.0e4
#: Samples per chunk of the joint (regional-gradient) solve's TSQR: ``9 x 2000`` rows at once.
TSQR_CHUNK = 2000


def _regional_basis() -> FloatArray:
    """(5, 3, 3): ``G_w = sum_k c_k E_k`` for ``c = (gxx, gxy, gxz, gyy, gyz)``."""
    basis = np.zeros((5, 3, 3))
    for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2))):
        basis[k, i, j] = basis[k, j, i] = 1.0
    basis[0, 2, 2] = basis[3, 2, 2] = -1.0  # traceless: gzz = -gxx - gyy
    return basis


#: The symmetric, traceless world-frame basis of the regional gradient, (5, 3, 3).
REGIONAL_BASIS = _regional_basis()


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
    return geometry.a @ PAIR_WHITENER


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
    orientation_xyzw: ArrayLike | None = None,
) -> TensorCalibration:
    """Identify ``k``, ``b`` where the true gradient is known (zero on a trim manoeuvre), or
    known up to a constant regional gradient when ``orientation_xyzw`` is given.

    Solves ``G_m - G_true = D(theta)`` (eq. 18) by generalised least squares, whitened for
    i.i.d. sensor noise, so that the returned covariance is ``sigma^2 (A^T A)^-1`` with
    ``sigma`` (per-axis sensor noise) estimated from the residual. Noise on ``B_1'`` as a
    regressor is neglected (it matters only for ``|K| ~ 1``).

    With ``orientation_xyzw`` it solves ``G_m - G_true = R_n^T G_w R_n + D(theta)`` jointly
    for ``theta`` and the 5 coefficients of a constant world-frame gradient ``G_w``
    (symmetric, traceless; see the module docstring). The new columns are not linear in
    ``(B_1', 1)``, so :func:`reduce_affine` alone does not apply: a chunked TSQR (QR per
    :data:`TSQR_CHUNK` samples, the triangles stacked and re-factored; memory bounded by a
    chunk) of the whitened ``[B_1' 1 | regional columns | target]`` gives, exactly and by
    orthogonal transformations only, a small system with the whole problem's normal matrix
    (see :func:`_regional_system`), solved by the same scaled SVD. ``G_w`` is signal:
    compensation (eq. 19) does not remove it.

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
    orientation_xyzw : array_like, shape (N, 4), optional
        Attitude quaternions (x, y, z, w; scipy convention) rotating body vectors into ENU.
        Given: also fit the regional gradient (``regional_gradient_enu`` and
        ``regional_gradient_sigma`` of the result, T/m; ``covariance`` stays the P x P
        marginal of ``theta``, and ``sigma^2`` counts the 5 extra parameters).

    Raises
    ------
    IdentifiabilityError
        Too few samples, too little attitude diversity (message gives the condition number),
        or attitudes that cannot separate a regional gradient from the interference.
    InputError
        Arrays of the wrong shape or with non-finite values (for ``orientation_xyzw``: how
        many rows).
    """
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    g_true = np.zeros_like(g_measured) if g_true is None else as_tensors(g_true, 'g_true')
    n = same_length(g_measured=g_measured, b_reference=b_reference, g_true=g_true)
    method = 'known_gradient_lstsq' if symmetric_k else 'known_gradient_lstsq_general'
    quaternions = None if orientation_xyzw is None else _orientations(orientation_xyzw, n, method)
    _check_samples(n, method)
    coverage = _coverage(b_reference, max_coverage_condition, method)
    details = {'attitude_coverage_condition': coverage}
    target = g_measured - g_true
    if quaternions is not None:
        return _regional_calibration(
            target, b_reference, quaternions, geometry, symmetric_k, method, details
        )
    return _affine_calibration(target, b_reference, geometry, symmetric_k, method, details)


def _coverage(b_reference: FloatArray, max_coverage_condition: float, method: str) -> float:
    """:func:`attitude_coverage`, or :class:`IdentifiabilityError` above the limit."""
    coverage = attitude_coverage(b_reference)
    if not coverage <= max_coverage_condition:
        raise IdentifiabilityError(
            f'{method}: the body-frame field spans too few directions (attitude coverage '
            f'condition number {coverage:.3g} > {max_coverage_condition:.3g}); '
            'turn, roll and pitch more'
        )
    return coverage


def _affine_calibration(
    target: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    symmetric_k: bool,
    method: str,
    details: dict,
) -> TensorCalibration:
    """The solve without a regional gradient: ``target = G_m - G_true`` against eq. 18."""
    n = len(target)
    whitener = noise_whitener(geometry)
    target_w = target @ whitener  # (N, 3, 3): rows of G, whitened columns
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
    residual = target - interference_tensor(b_reference, parameters, geometry)
    sigma2 = _sigma2(residual @ whitener, solution.rank)
    return _tensor_calibration(
        method, solution, residual, sigma2, parameters, symmetric_k, details
    )


def _sigma2(residual_w: FloatArray, rank: int) -> float:
    """Per-axis sensor noise variance, T^2, from the whitened residual and the fitted rank."""
    dof = max(residual_w.size - rank, 1)
    return float(np.sum(residual_w**2)) / dof


def _tensor_calibration(
    method: str,
    solution: LinearSolution,
    residual: FloatArray,
    sigma2: float,
    parameters: InterferenceParameters,
    symmetric: bool,
    details: dict,
    regional: tuple[FloatArray, FloatArray] | None = None,
) -> TensorCalibration:
    """The known-gradient result; ``regional`` is ``(G_w, its 1-sigma)``, (3, 3) T/m each."""
    n_par = len(parameters.to_vector(symmetric=symmetric))
    return TensorCalibration(
        method=method,
        n_samples=len(residual),
        n_parameters=n_par,
        # Of the interference parameters: the joint solve refuses unless the 5 gradient
        # coefficients are all resolved, so they take exactly 5 of its rank.
        rank=solution.rank - (0 if regional is None else 5),
        condition_number=solution.condition_number,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        details={**details, 'sensor_noise_nT': float(np.sqrt(sigma2) * NT_PER_T)},
        parameters=parameters,
        symmetric=symmetric,
        covariance=sigma2 * solution.covariance_unit[:n_par, :n_par],
        regional_gradient_enu=None if regional is None else regional[0],
        regional_gradient_sigma=None if regional is None else regional[1],
    )


def _orientations(orientation_xyzw: ArrayLike, n: int, method: str) -> FloatArray:
    """Quaternions (N, 4), finite and nonzero, or :class:`InputError` saying how many are not."""
    q = np.asarray(orientation_xyzw, dtype=float)
    if q.shape != (n, 4):
        raise InputError(f'{method}: orientation_xyzw must have shape ({n}, 4), got {q.shape}')
    bad = ~np.all(np.isfinite(q), axis=1)
    if np.any(bad):
        raise InputError(
            f'{method}: orientation_xyzw has {int(bad.sum())} non-finite rows of {n} '
            f'(first at index {int(np.argmax(bad))}); drop those samples'
        )
    zero = np.linalg.norm(q, axis=1) == 0.0
    if np.any(zero):
        raise InputError(
            f'{method}: orientation_xyzw has {int(zero.sum())} zero quaternions of {n} '
            f'(first at index {int(np.argmax(zero))})'
        )
    return q


def regional_body_tensor(orientation_xyzw: ArrayLike, g_world: ArrayLike) -> FloatArray:
    """A constant world-frame gradient seen in the body frame, ``R_n^T G_w R_n``.

    Parameters
    ----------
    orientation_xyzw : array_like, shape (N, 4)
        Quaternions (x, y, z, w) rotating body vectors into ENU.
    g_world : array_like, shape (3, 3)
        ``G_w``, T/m, ENU.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        T/m, body frame.

    Raises
    ------
    InputError
        Wrong shapes, non-finite or zero quaternions (the message says how many).
    """
    quaternions = np.asarray(orientation_xyzw, dtype=float)
    n = quaternions.shape[0] if quaternions.ndim else 0
    quaternions = _orientations(quaternions, n, 'regional_body_tensor')
    return _body_tensor(quaternions, as_array(g_world, 'g_world', (3, 3)))


def _body_tensor(quaternions: FloatArray, g_world: FloatArray) -> FloatArray:
    """:func:`regional_body_tensor` of validated (N, 4) quaternions and (3, 3) ``G_w``."""
    # Imported here: scipy.spatial loads its k-d tree and sparse modules with it (~0.17 s of
    # CPU), which a compensator node that never fits a regional gradient paid at each start.
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_quat(quaternions).as_matrix().reshape(-1, 3, 3)
    return to_body(np.broadcast_to(g_world, rotation.shape), rotation)


def _regional_columns(
    target_w: FloatArray, b_reference: FloatArray, quaternions: FloatArray, whitener: FloatArray
) -> FloatArray:
    """Per-sample columns ``[B_1' 1 | Z | y]``, shape (m, 58): ``Z`` the whitened body-frame
    regional basis (9 whitened components x 5 coefficients, component-major), ``y`` the
    whitened target (9)."""
    from scipy.spatial.transform import Rotation  # as in _body_tensor

    m = len(b_reference)
    rotation = Rotation.from_quat(quaternions).as_matrix().reshape(m, 1, 3, 3)
    body = np.swapaxes(rotation, 2, 3) @ REGIONAL_BASIS @ rotation  # (m, 5, 3, 3)
    regional_w = np.moveaxis(body @ whitener, 1, 3)  # (m, 3, 3, 5): [n, row, col_w, coef]
    return np.column_stack(
        [b_reference, np.ones(m), regional_w.reshape(m, 45), target_w.reshape(m, 9)]
    )


def _r_factor(matrix: FloatArray) -> FloatArray:
    """``R`` of the Householder QR of ``matrix`` (M, K), shape (min(M, K), K)."""
    return np.asarray(np.linalg.qr(matrix, mode='r'), dtype=float)


def _regional_triangle(
    target_w: FloatArray, b_reference: FloatArray, quaternions: FloatArray, whitener: FloatArray
) -> FloatArray:
    """``R`` (58, 58) of the QR of every sample's :func:`_regional_columns`, by chunked TSQR:
    QR per :data:`TSQR_CHUNK` samples, the triangles stacked and re-factored."""
    scale: FloatArray | None = None
    stacked: FloatArray | None = None
    for start in range(0, len(target_w), TSQR_CHUNK):
        chunk = slice(start, start + TSQR_CHUNK)
        columns = _regional_columns(
            target_w[chunk], b_reference[chunk], quaternions[chunk], whitener
        )
        if scale is None:  # one column scale for all chunks (tesla vs 1 vs T/m)
            scale = np.linalg.norm(columns, axis=0)
            scale[scale == 0.0] = 1.0
        r = _r_factor(columns / scale)
        stacked = r if stacked is None else _r_factor(np.vstack([stacked, r]))
    assert stacked is not None and scale is not None  # at least MIN_SAMPLES samples
    triangle = stacked * scale
    missing = triangle.shape[1] - triangle.shape[0]  # fewer rows than columns: zero rows
    return np.vstack([triangle, np.zeros((missing, triangle.shape[1]))]) if missing else triangle


def _regional_system(
    triangle: FloatArray, geometry: TetraGeometry, whitener: FloatArray, symmetric: bool
) -> tuple[FloatArray, FloatArray]:
    """A small system ``A x ~ y`` (x = theta then c) with the normal matrix, right-hand side
    and singular values of the whole whitened ``9N x (P + 5)`` problem.

    Per whitened component ``r``, the interference columns over the samples are ``X H_r``
    with ``X = [B_1' 1] = Q_x R_x``. So ``|X H_r theta + Z_r c - y_r|^2`` splits exactly into
    the part in span(X), ``R_x H_r theta + Q_x^T (Z_r c - y_r)`` (4 rows: the design at the
    pseudo-samples of :func:`reduce_affine`), and the rest, ``(I - Q_x Q_x^T)(Z_r c - y_r)``,
    which involves ``c`` only. With ``R`` the triangle of ``[X | Z | y]``, ``R[:4]`` is
    ``Q_x^T [X | Z | y]`` and ``R[4:]`` restricted to component ``r``'s columns has the Gram
    matrix of the rest. Rows: 36 in span(X) (pseudo-sample-major) and 9 x 54 outside it.
    """
    reduction = AffineReduction(regressors=triangle[:4, :4], targets=triangle[:4, 49:])
    design = reduced_design(reduction, geometry, symmetric=symmetric)
    n_par = design.shape[2]
    design_w = np.einsum('nRjp,jk->nRkp', design.reshape(4, 3, 3, n_par), whitener)
    regional = triangle[:, 4:49].reshape(-1, 9, 5)
    target = triangle[:, 49:]
    outside = np.swapaxes(regional[4:], 0, 1).reshape(-1, 5)
    system = np.block(
        [
            [design_w.reshape(36, n_par), regional[:4].reshape(36, 5)],
            [np.zeros((len(outside), n_par)), outside],
        ]
    )
    return system, np.concatenate([target[:4].reshape(36), target[4:].T.reshape(-1)])


def _regional_calibration(
    target: FloatArray,
    b_reference: FloatArray,
    quaternions: FloatArray,
    geometry: TetraGeometry,
    symmetric: bool,
    method: str,
    details: dict,
) -> TensorCalibration:
    """Joint solve of ``theta`` and the regional gradient (see :func:`known_gradient_lstsq`)."""
    whitener = noise_whitener(geometry)
    triangle = _regional_triangle(target @ whitener, b_reference, quaternions, whitener)
    system, rhs = _regional_system(triangle, geometry, whitener, symmetric)
    solution = solve_scaled(system, rhs)
    m = system.shape[1]  # P + 5
    if solution.rank < m:
        raise IdentifiabilityError(
            f'{method}: the attitudes cannot separate a regional gradient from the '
            f'interference (rank {solution.rank} of {m - 5} + 5 parameters); roll and pitch '
            'more in the window (--window a span of the trim manoeuvre)'
        )
    n_par = m - 5
    parameters = InterferenceParameters.from_vector(solution.theta[:n_par], symmetric=symmetric)
    g_world = np.einsum('q,qij->ij', solution.theta[n_par:], REGIONAL_BASIS)
    residual = (
        target
        - interference_tensor(b_reference, parameters, geometry)
        - _body_tensor(quaternions, g_world)
    )
    sigma2 = _sigma2(residual @ whitener, solution.rank)
    cov_c = sigma2 * solution.covariance_unit[n_par:, n_par:]
    sigma = np.sqrt(np.einsum('qij,qp,pij->ij', REGIONAL_BASIS, cov_c, REGIONAL_BASIS))
    return _tensor_calibration(
        method, solution, residual, sigma2, parameters, symmetric, details, (g_world, sigma)
    )


def calibration_residual(
    calibration: TensorCalibration,
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    *,
    orientation_xyzw: ArrayLike | None = None,
    regressors: ArrayLike | None = None,
) -> FloatArray:
    """What a known-gradient fit leaves: ``G_m - D(B_1'; theta) - R_n^T G_w R_n``.

    The regional term is subtracted only when ``calibration`` has a regional gradient and
    ``orientation_xyzw`` is given (otherwise the residual of eq. 19 alone, i.e. the
    compensated tensor).

    Parameters
    ----------
    calibration : TensorCalibration
    g_measured : array_like, shape (N, 3, 3)
        ``G_m``, T/m.
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla, body frame.
    geometry : TetraGeometry
    orientation_xyzw : array_like, shape (N, 4), optional
        Quaternions (x, y, z, w) rotating body vectors into ENU.
    regressors : array_like, shape (N, M), optional
        The terms' regressors, required when the calibration has terms (a NaN regressor
        gives a NaN residual).

    Returns
    -------
    ndarray, shape (N, 3, 3)
        T/m, body frame, in the samples' order.

    Raises
    ------
    InputError
        Not a :class:`TensorCalibration`, wrong shapes or non-finite values.
    """
    if not isinstance(calibration, TensorCalibration):
        raise InputError(f'{calibration.method} gives no k, b: no tensor residual to compute')
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    n = same_length(g_measured=g_measured, b_reference=b_reference)
    residual = g_measured - interference_tensor(
        b_reference, calibration.parameters, geometry, regressors
    )
    if calibration.regional_gradient_enu is not None and orientation_xyzw is not None:
        quaternions = _orientations(orientation_xyzw, n, 'calibration_residual')
        residual -= _body_tensor(quaternions, calibration.regional_gradient_enu)
    return residual


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
        from scipy.optimize import lsq_linear  # bounded solves only: 0.1 s of a node's start

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
