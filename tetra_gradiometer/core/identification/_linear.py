"""Column-scaled least squares with rank and conditioning reported (shared by the solvers)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Singular values below this fraction of the largest count as zero. Structural null
#: directions sit at ~1e-15; genuinely weak but observable ones well above 1e-9.
RANK_RTOL = 1.0e-9


@dataclass(frozen=True)
class LinearSolution:
    theta: np.ndarray          # (P,) solution, unscaled units
    rank: int
    condition_number: float    # over the retained singular values
    residual: np.ndarray       # (M,) y - A theta
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
    return LinearSolution(theta=theta, rank=rank, condition_number=float(s[0] / s[keep][-1]),
                          residual=target - design @ theta, covariance_unit=covariance_unit)
