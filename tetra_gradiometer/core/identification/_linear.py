"""Column-scaled least squares with rank and conditioning reported (shared by the solvers)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Singular values below this fraction of the largest count as zero. Structural null
#: directions sit at ~1e-15; genuinely weak but observable ones well above 1e-9.
RANK_RTOL = 1.0e-9


@dataclass(frozen=True)
class LinearSolution:
    theta: np.ndarray  # (P,) solution, unscaled units
    rank: int
    condition_number: float  # over the retained singular values
    residual: np.ndarray  # (M,) y - A theta
    covariance_unit: np.ndarray  # (P, P) (A^T A)^+ in unscaled units (times sigma^2 = covariance)


def solve_scaled(design: np.ndarray, target: np.ndarray) -> LinearSolution:
    """Minimum-norm (in scaled coordinates) least squares ``design @ theta ~ target``.

    Columns are scaled to unit norm first, because ``K`` (dimensionless) and ``b``
    (tesla) differ by ~1e8 and rank must be judged on comparable columns.

    Parameters
    ----------
    design : ndarray, shape (M, P)
    target : ndarray, shape (M,)
    """
    scale = np.linalg.norm(design, axis=0)
    scale[scale == 0.0] = 1.0
    u, s, vt = np.linalg.svd(design / scale, full_matrices=False)
    keep = s > RANK_RTOL * s[0]
    rank = int(keep.sum())
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    theta_scaled = vt.T @ (inv_s * (u.T @ target))
    theta = theta_scaled / scale
    cov_scaled = (vt.T * inv_s**2) @ vt
    covariance_unit = cov_scaled / np.outer(scale, scale)
    return LinearSolution(
        theta=theta,
        rank=rank,
        condition_number=float(s[0] / s[keep][-1]),
        residual=target - design @ theta,
        covariance_unit=covariance_unit,
    )


@dataclass(frozen=True)
class AffineReduction:
    """A tall least-squares problem whose rows are linear in per-sample regressors, reduced
    exactly to 4 rows per output (see :func:`reduce_affine`)."""

    regressors: np.ndarray  # (4, 4) R: upper-triangular, X^T X = R^T R, X = [B_1' 1]
    targets: np.ndarray  # (4, Q) Q_x^T T: the targets projected on span(X)


def reduce_affine(b_reference: np.ndarray, targets: np.ndarray) -> AffineReduction:
    """Reduce ``sum_n |t_n - H(x_n) theta|^2`` with ``x_n = (B_1', 1)`` to 4 pseudo-samples.

    Every design in this package is linear in ``x_n``: row block ``n`` is
    ``sum_c x_n[c] H_c``. With the thin QR ``X = Q_x R`` of ``X = [B_1' 1]`` (N x 4),
    ``sum_n |t_n - sum_c x_n[c] H_c theta|^2 = sum_m |z_m - sum_c R[m, c] H_c theta|^2 + const``
    with ``z = Q_x^T T``. So the design evaluated at the 4 rows of ``R`` (the offset column
    weighted by ``R[m, 3]`` instead of 1) against targets ``z`` has exactly the same normal
    matrix, right-hand side, singular values and solution as the full design, computed by
    an orthogonal factorisation (no squaring of the condition number) in O(N (4 + Q)^2).

    Parameters
    ----------
    b_reference : ndarray, shape (N, 3)
    targets : ndarray, shape (N, Q)
        The per-sample targets ``t_n``, in the row order of ``H``.
    """
    n = len(b_reference)
    augmented = np.column_stack([b_reference, np.ones(n), targets.reshape(n, -1)])
    # Scale columns before the QR (B in tesla vs 1): Householder QR is not affected in
    # exact arithmetic, but this keeps the tiny entries of R well represented.
    scale = np.linalg.norm(augmented, axis=0)
    scale[scale == 0.0] = 1.0
    r = np.linalg.qr(augmented / scale, mode='r') * scale
    if r.shape[0] < 4:  # fewer than 4 samples: pad with zero rows (they add nothing)
        r = np.vstack([r, np.zeros((4 - r.shape[0], r.shape[1]))])
    return AffineReduction(regressors=r[:4, :4], targets=r[:4, 4:])
