"""Blocked cross-validation and the noise floor: the residual views, per-block Gram
matrices, their least-squares solves, and the held-out gap every decision is measured by."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy  # submodules load on first use: see core/__init__.py
from numpy.typing import NDArray

from ..identification._selection import held_out_blocks

Array = NDArray[np.float64]
Index = NDArray[np.int_]

ALL_SENSORS = (0, 1, 2, 3)


def solve_fast(gram: Array, rhs: Array) -> Array:
    """Solve a normalised Gram system with a tiny ridge (Cholesky); exactly degenerate
    directions get (nearly) the minimum-norm share. Falls back to the eigen-solve."""
    if not len(rhs):
        return np.zeros(0)
    ridge = 1e-10 * max(float(np.trace(gram)) / len(rhs), 1e-300)
    try:
        factor = scipy.linalg.cho_factor(gram + ridge * np.eye(len(rhs)), check_finite=False)
        solution: Array = scipy.linalg.cho_solve(factor, rhs, check_finite=False)
        return solution
    except np.linalg.LinAlgError:
        return solve(gram, rhs)[0]


def solve(gram: Array, rhs: Array) -> tuple[Array, int]:
    """Eigen-solve with a relative cut-off; returns the solution and the rank."""
    w, v = np.linalg.eigh(gram)
    top = max(float(w[-1]), 1e-300) if len(w) else 1.0
    keep = w > top * 1e-11
    theta = v[:, keep] @ ((v[:, keep].T @ rhs) / w[keep])
    return theta, int(keep.sum())


@dataclass(frozen=True)
class Fit:
    """One fit of :meth:`Gram.evaluate`: coefficients (normalised columns), their rank, the
    full-data residual sum of squares and the cross-validated one, nT^2."""

    theta: Array
    rank: int
    rss: float
    cv: float


class Gram:
    """Per-fold Gram matrices of ``Z`` (N, m, q) with its first ``n_regressors`` columns
    normalised to unit norm over all samples (``usable`` (n_regressors,): the columns not
    all zero), the rest (target and offset vectors) left unscaled. Blocks of ``block_s``
    seconds are dealt to ``n_folds`` folds in turn
    (:func:`~..identification._selection.held_out_blocks`)."""

    def __init__(
        self, z: Array, t: Array, block_s: float, n_folds: int, n_regressors: int
    ) -> None:
        n, m, q = z.shape
        blocks = held_out_blocks(t, block_s, n_folds)
        n_folds = max(2, 1 + max(fold for _, _, fold in blocks))  # one block: one empty fold
        self.folds = np.zeros((n_folds, q, q))
        self.fold_rows = np.zeros(n_folds)
        self.fold_of_sample = np.zeros(n, dtype=int)
        for lo, hi, fold in blocks:
            zb = z[lo:hi].reshape(-1, q)
            self.folds[fold] += zb.T @ zb
            self.fold_rows[fold] += zb.shape[0]
            self.fold_of_sample[lo:hi] = fold
        # Normalised here, on the q x q matrices, not on Z (N m x q, 100s of MB for a long record).
        norm = np.sqrt(self.folds.sum(axis=0).diagonal()[:n_regressors])
        self.usable: NDArray[np.bool_] = norm > 0
        scale = np.ones(q)
        scale[:n_regressors] = 1.0 / np.where(self.usable, norm, 1.0)
        self.folds *= scale[:, None] * scale[None, :]
        self.total = self.folds.sum(axis=0)
        self.n = float(n * m)

    @staticmethod
    def _parts(
        g: Array, cols: Index, targets: Index, weights: Array
    ) -> tuple[Array, Array, float]:
        """Gram of ``cols``, their products with the target ``sum_j weights_j z_targets_j``,
        and the target's square."""
        c = g[np.ix_(cols, targets)] @ weights
        s = float(weights @ g[np.ix_(targets, targets)] @ weights)
        return g[np.ix_(cols, cols)], c, s

    def evaluate(
        self, cols: Index, ty: int, offsets: Sequence[int] = (), add_back: Sequence[int] = ()
    ) -> Fit:
        """Fit ``cols`` to ``z_ty - sum z_offsets + sum z_add_back``: full-data and
        cross-validated residual SS."""
        targets = np.array([ty] + list(offsets) + list(add_back), dtype=int)
        weights = np.array([1.0] + [-1.0] * len(offsets) + [1.0] * len(add_back))
        gg, c, s = self._parts(self.total, cols, targets, weights)
        theta, rank = solve(gg, c) if len(cols) else (np.zeros(0), 0)
        rss = s - 2 * theta @ c + theta @ gg @ theta
        cv: float = 0.0
        for fold in self.folds:
            tg, tc, _ = self._parts(self.total - fold, cols, targets, weights)
            fg, fc, fs = self._parts(fold, cols, targets, weights)
            th = solve_fast(tg, tc)
            cv += float(fs - 2 * th @ fc + th @ fg @ th)
        return Fit(theta, rank, max(float(rss), 0.0), max(float(cv), 1e-300))


def flat(arr: Array, sensors: tuple[int, ...]) -> Array:
    """Full-sensor array (N, 4, 3, ...) -> the residual view (N, 3 len(sensors), ...).

    Absolute view (sensors 0-3): as is. Pair view (sensors 1-3): the differences
    ``sensor_i - sensor_1``, so a term of sensor 1 enters every pair with a minus sign.
    """
    if tuple(sensors) == ALL_SENSORS:
        sub = arr
    else:
        sub = arr[:, list(sensors)] - arr[:, :1]
    return sub.reshape(sub.shape[0], 3 * len(sensors), *sub.shape[3:])


def noise_floor(residual: Array) -> tuple[float, Array]:
    """White-noise RMS of ``residual`` (N, c) nT: the RMS over channels and the per-channel
    sigmas (c,).

    Per channel the smaller of two estimates, each unbiased on white noise and spoiled by a
    different thing: the 4th difference (``var(diff^4 n) = 70 sigma^2``, a smooth signal
    suppressed by ``(omega dt)^4``; its MAD ignores steps and spikes, but a spectral line
    near Nyquist passes almost whole: 15.6 x its power at 0.46 of the sampling rate), and
    the median of the periodogram's upper half (a line is a few bins of thousands, but a
    step's power spreads there too).
    """
    d4 = np.diff(residual, 4, axis=0)
    mad = np.median(np.abs(d4 - np.median(d4, axis=0)), axis=0)
    sigma_d4 = 1.4826 * mad / np.sqrt(70.0)
    # |FFT|^2 / N of white noise is exponential with mean sigma^2: its median is ln 2 of it.
    power = np.abs(np.fft.rfft(residual - residual.mean(axis=0), axis=0)) ** 2 / len(residual)
    upper = power[len(power) // 2 : len(power) - 1]
    sigma = sigma_d4
    if len(upper) >= 10:
        sigma = np.minimum(sigma_d4, np.sqrt(np.median(upper, axis=0) / np.log(2.0)))
    return float(np.sqrt(np.mean(sigma**2))), sigma


def lstsq_view(
    sensors: tuple[int, ...],
    cols: Array,
    target: Array,
    rows: NDArray[np.bool_] | None = None,
) -> Array:
    """Least squares of ``target`` (N, 4, 3) nT on ``cols`` (N, 4, 3, p) in the view
    (normal equations on normalised columns): physical coefficients (p,). On all samples an
    eigen-solve with a rank cut-off; on the samples ``rows`` (bool, N) the ridge solve."""
    if rows is not None and not rows.all():  # (all rows: no copy of the columns)
        cols, target = cols[rows], target[rows]
    a = flat(cols, sensors)
    a = a.reshape(-1, a.shape[-1])
    y = flat(target, sensors).reshape(-1)
    gram = a.T @ a
    norm = np.sqrt(np.diag(gram)).copy()
    norm[norm == 0] = 1.0
    gram, rhs = gram / np.outer(norm, norm), (a.T @ y) / norm
    coef = solve(gram, rhs)[0] if rows is None else solve_fast(gram, rhs)
    result: Array = coef / norm
    return result


def block_length(t: Array, block_s: float | None) -> float:
    """Cross-validation block length, s: ``block_s``, else duration / 40 within [5, 30] s."""
    return block_s or float(np.clip(float(t[-1] - t[0]) / 40.0, 5.0, 30.0))
