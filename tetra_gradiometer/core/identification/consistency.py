"""Does a fit's residual look like sensor noise? A calibration checks its own assumption.

A known-gradient fit (:func:`~.lstsq.known_gradient_lstsq`) assumes the true gradient is
constant over its window (zero, or a regional gradient fitted with it). If that holds, its
residual is sensor noise; if not (a passing dipole, a misfit model), the residual holds
slow signal as well. :func:`fit_consistency` compares the residual's variance with an
independent estimate of the noise variance from high-frequency differences, by an F-test,
over the window and per block of time.

The residual is whitened as the known-gradient fit whitens it (``residual @ W``,
:func:`~.lstsq.noise_whitener`), so i.i.d. sensor noise gives 9 independent components of
equal variance (tesla, per sensor axis). Then:

* residual variance ``s_r^2 = sum r^2 / nu1``, ``nu1 = 9N - P``;
* noise variance from lag-``L`` second differences ``d_n = r_(n+L) - 2 r_n + r_(n-L)``
  (``L = 3``), ``s_d^2 = mean(d^2) / 6``. It is unbiased for any stationary noise whose
  autocovariance ``gamma`` vanishes beyond lag 2 (``E d^2 = 6 gamma_0 - 8 gamma_L +
  2 gamma_2L``), such as the MA(1)/MA(2) noise left by interpolating between neighbouring
  samples; a signal at frequency ``f`` is suppressed by ``~(2 pi f L dt)^2``. A difference
  whose either half spans more than ``2.5 L`` median sample intervals (a gap in the time
  stamps) is dropped; ``N'`` per component remain;
* effective dof of ``s_d^2``: for white Gaussian noise ``Cov(d_n, d_(n+-L)) = -4 sigma^2``,
  ``Cov(d_n, d_(n+-2L)) = sigma^2`` and zero otherwise; with ``Var(d^2) = 2 (6 sigma^2)^2``
  and ``Cov(d_n^2, d_m^2) = 2 Cov(d_n, d_m)^2``, ``Var(mean d^2) = 2 (6 sigma^2)^2
  (1 + 2 ((4/6)^2 + (1/6)^2)) / N'``: a chi-square with ``N' / 1.944`` dof per component,
  ``nu2 = 9 N' / 1.944`` in all;
* test of ``H0: sigma_r <= tolerance sigma_noise``: ``F = s_r^2 / (tolerance^2 s_d^2)`` is
  refused when ``F > F_(1-alpha)(nu1, nu2)``, i.e. when ``ratio = s_r / s_d`` exceeds
  ``threshold_ratio = tolerance sqrt(F_(1-alpha))``. (``s_r`` and ``s_d`` come from the same
  noise and are positively correlated, which makes the test conservative.)
* blocks: each block's ``s_r,block / s_d`` (the window's ``s_d``) under the same test with
  its own ``nu1 = n_block (9 - P / N)`` (the fitted parameters shared out by sample count);
  ``alpha`` applies per block, without correction for the number of blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from .._distributions import f_isf
from .._validate import as_array, as_tensors, same_length
from ..geometry import TetraGeometry
from ..types import ArrayLike, FloatArray
from ..units import NT_PER_T
from .lstsq import noise_whitener

#: Lag ``L`` of the second differences, samples: beyond the MA(1)/MA(2) correlation that
#: interpolating between neighbouring samples gives the noise.
DIFFERENCE_LAG = 3
#: Variance of a second difference ``r_(n+L) - 2 r_n + r_(n-L)`` of white noise, in units
#: of the noise variance: ``1 + 4 + 1``.
DIFFERENCE_GAIN = 6.0
#: Samples per effective degree of freedom of the overlapping second differences (white
#: noise): ``1 + 2 ((4/6)^2 + (1/6)^2) = 35/18 ~ 1.944`` (see :func:`fit_consistency`).
OVERLAP_FACTOR = 1.0 + 2.0 * ((4.0 / 6.0) ** 2 + (1.0 / 6.0) ** 2)
#: A difference whose either half spans more than this many nominal lags (``L`` median
#: sample intervals) straddles a gap and is dropped.
MAX_SPAN_FACTOR = 2.5
#: Default blocks: the window in this many parts, each at least :data:`MIN_BLOCK_S` and
#: :data:`MIN_BLOCK_SAMPLES` median intervals long.
BLOCKS_PER_WINDOW = 20
MIN_BLOCK_S = 5.0
MIN_BLOCK_SAMPLES = 50
#: Fewest valid second differences (per component) the noise estimate accepts.
MIN_DIFFERENCES = 10
#: A whitened residual below this RMS is floating-point roundoff of a noise-free fit (ratio
#: 0, passes), tesla: 100x below the quietest magnetometers' noise (SQUIDs, ~1e-15 T).
ROUNDOFF_T = 1.0e-17


@dataclass(frozen=True)
class Block:
    """One block of time of :class:`FitConsistency`.

    Attributes
    ----------
    t0_s, t1_s : float
        Its edges in the time base of ``t_s``, s (clipped to the window; consecutive blocks
        share an edge).
    ratio : float
        ``sigma_residual,block / sigma_noise`` (the window's noise estimate), whitened.
    passed : bool
        The block's F-test (its own ``nu1``) does not refuse it.
    n_samples : int
    threshold_ratio : float
        The largest ``ratio`` it passes with.
    """

    t0_s: float
    t1_s: float
    ratio: float
    passed: bool
    n_samples: int
    threshold_ratio: float


@dataclass(frozen=True)
class FitConsistency:
    """The residual of a fit against the sensor noise (see :func:`fit_consistency`).

    Attributes
    ----------
    residual_rms : float
        ``sqrt(sum r^2 / (9N - P))`` of the residual tensor itself, T/m.
    noise_rms : float
        The noise estimate from second differences of the residual tensor itself, T/m.
    sensor_noise : float
        The same estimate on the whitened residual: per-axis sensor noise, tesla.
    ratio : float
        ``s_r / s_d`` of the whitened residual (the test statistic's square root; the
        un-whitened ``residual_rms / noise_rms`` agrees for i.i.d. sensor noise only).
    threshold_ratio : float
        ``tolerance * sqrt(F_(1-alpha)(nu1, nu2))``: the largest ``ratio`` that passes.
    passed : bool
        ``ratio <= threshold_ratio``.
    alpha, tolerance : float
        As given.
    dof_residual, dof_noise : float
        ``nu1 = 9N - P`` and ``nu2 = 9 N' / 1.944``.
    n_samples : int
    blocks : tuple of Block
        In time order; blocks without samples are left out.
    """

    residual_rms: float
    noise_rms: float
    sensor_noise: float
    ratio: float
    threshold_ratio: float
    passed: bool
    alpha: float
    tolerance: float
    dof_residual: float
    dof_noise: float
    n_samples: int
    blocks: tuple[Block, ...]

    def _runs(self, passed: bool) -> list[tuple[float, float]]:
        """Spans of consecutive blocks (sharing an edge) whose ``passed`` is ``passed``, s."""
        runs: list[tuple[float, float]] = []
        for block in self.blocks:
            if block.passed != passed:
                continue
            if runs and runs[-1][1] == block.t0_s:
                runs[-1] = (runs[-1][0], block.t1_s)
            else:
                runs.append((block.t0_s, block.t1_s))
        return runs

    def failing_spans(self) -> list[tuple[float, float]]:
        """Spans of consecutive failing blocks, (t0, t1) in s of ``t_s``."""
        return self._runs(False)

    def longest_passing_span(self) -> tuple[float, float] | None:
        """The longest run of consecutive passing blocks, (t0, t1) in s of ``t_s``; None
        when no block passes. Consecutive means sharing an edge: a block without samples
        (a gap) ends a run. Ties go to the earliest."""
        runs = self._runs(True)
        if not runs:
            return None
        return max(runs, key=lambda run: (run[1] - run[0], -run[0]))

    @property
    def text(self) -> str:
        """One line, e.g. ``residual 2.14 nT/m is 17.8x the noise 0.12 nT/m (limit 1.23x,
        alpha 0.001); fails in 410.0-520.0 s`` (times in the time base of ``t_s``)."""
        line = (
            f'residual {self.residual_rms * NT_PER_T:.3g} nT/m is {self.ratio:.3g}x the noise '
            f'{self.noise_rms * NT_PER_T:.3g} nT/m (limit {self.threshold_ratio:.3g}x, '
            f'alpha {self.alpha:g})'
        )
        spans = ', '.join(f'{t0:.1f}-{t1:.1f} s' for t0, t1 in self.failing_spans())
        if spans:
            verdict = 'fails' if not self.passed else 'passes, but blocks fail'
            return f'{line}; {verdict} in {spans}'
        return f'{line}; {"passes" if self.passed else "fails"}'

    def to_dict(self) -> dict:
        """Plain JSON-safe types: tensor figures in nT/m, the sensor noise in nT, times in s,
        non-finite ratios as None."""
        span = self.longest_passing_span()
        return {
            'passed': bool(self.passed),
            'ratio': _finite(self.ratio),
            'threshold_ratio': _finite(self.threshold_ratio),
            'tolerance': float(self.tolerance),
            'alpha': float(self.alpha),
            'residual_rms_nT_per_m': float(self.residual_rms * NT_PER_T),
            'noise_rms_nT_per_m': float(self.noise_rms * NT_PER_T),
            'sensor_noise_nT': float(self.sensor_noise * NT_PER_T),
            'dof_residual': float(self.dof_residual),
            'dof_noise': float(self.dof_noise),
            'n_samples': int(self.n_samples),
            'blocks': [
                {
                    't0_s': float(b.t0_s),
                    't1_s': float(b.t1_s),
                    'ratio': _finite(b.ratio),
                    'threshold_ratio': _finite(b.threshold_ratio),
                    'passed': bool(b.passed),
                    'n_samples': int(b.n_samples),
                }
                for b in self.blocks
            ],
            'longest_passing_span_s': None if span is None else [float(span[0]), float(span[1])],
            'text': self.text,
        }


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def fit_consistency(
    residual: ArrayLike,
    t_s: ArrayLike,
    geometry: TetraGeometry,
    n_parameters: int,
    *,
    tolerance: float = 1.2,
    alpha: float = 1.0e-3,
    block_s: float | None = None,
) -> FitConsistency:
    """Test whether a fit's residual is sensor noise, ``H0: sigma_r <= tolerance sigma_noise``,
    over the window and per block (the statistics are in the module docstring).

    Parameters
    ----------
    residual : array_like, shape (N, 3, 3)
        The fit's residual (e.g. :func:`~.lstsq.calibration_residual`), T/m, in time order.
    t_s : array_like, shape (N,)
        Sample times, s, strictly increasing (gaps allowed).
    geometry : TetraGeometry
    n_parameters : int
        ``P``, parameters the fit took from this residual (27, 36; plus 5 with a regional
        gradient).
    tolerance : float
        How much larger than the noise the residual may be (model error, sensor noise
        that is not i.i.d.); 1.2 by default.
    alpha : float
        Probability of refusing a residual exactly ``tolerance`` times the noise.
    block_s : float, optional
        Block length, s. Default: a 20th of the window, but at least 5 s and 50 median
        sample intervals.

    Returns
    -------
    FitConsistency

    Raises
    ------
    InputError
        Wrong shapes, non-finite values, ``t_s`` not strictly increasing, bad options, or
        too few samples for the noise estimate (fewer than 10 valid differences).
    """
    residual = as_tensors(residual, 'residual')
    t_s = as_array(t_s, 't_s', (None,))
    n = same_length(residual=residual, t_s=t_s)
    _check_options(t_s, n_parameters, tolerance, alpha, block_s)
    whitened = (residual @ noise_whitener(geometry)).reshape(n, 9)
    valid = _valid_differences(t_s)
    n_differences = int(valid.sum())
    if n_differences < MIN_DIFFERENCES:
        raise InputError(
            f'fit_consistency: {n_differences} valid second differences (lag '
            f'{DIFFERENCE_LAG}, no gaps) are too few for a noise estimate (need '
            f'{MIN_DIFFERENCES}); give more samples'
        )
    nu1 = 9.0 * n - n_parameters
    nu2 = 9.0 * n_differences / OVERLAP_FACTOR
    noise2 = _difference_variance(whitened, valid)
    ratio = _ratio(float(np.sum(whitened**2)) / nu1, noise2)
    threshold = tolerance * float(np.sqrt(f_isf(alpha, nu1, nu2)))
    if block_s is None:
        median_dt = float(np.median(np.diff(t_s)))
        duration = float(t_s[-1] - t_s[0])
        block_s = max(duration / BLOCKS_PER_WINDOW, MIN_BLOCK_S, MIN_BLOCK_SAMPLES * median_dt)
    return FitConsistency(
        residual_rms=float(np.sqrt(np.sum(residual**2) / nu1)),
        noise_rms=float(np.sqrt(_difference_variance(residual.reshape(n, 9), valid))),
        sensor_noise=float(np.sqrt(noise2)),
        ratio=ratio,
        threshold_ratio=threshold,
        passed=bool(ratio <= threshold),
        alpha=float(alpha),
        tolerance=float(tolerance),
        dof_residual=nu1,
        dof_noise=nu2,
        n_samples=n,
        blocks=_blocks(whitened, t_s, noise2, nu2, n_parameters, tolerance, alpha, block_s),
    )


def _check_options(
    t_s: FloatArray, n_parameters: int, tolerance: float, alpha: float, block_s: float | None
) -> None:
    n = len(t_s)
    if isinstance(n_parameters, bool) or not isinstance(n_parameters, (int, np.integer)):
        raise InputError(f'n_parameters must be an int, got {n_parameters!r}')
    if not 0 <= n_parameters < 9 * n:
        raise InputError(
            f'n_parameters must be in [0, 9N) = [0, {9 * n}) for {n} samples, got {n_parameters}'
        )
    if not (np.isfinite(tolerance) and tolerance > 0.0):
        raise InputError(f'tolerance must be a positive number, got {tolerance}')
    if not 0.0 < alpha < 1.0:
        raise InputError(f'alpha must be in (0, 1), got {alpha}')
    if block_s is not None and not (np.isfinite(block_s) and block_s > 0.0):
        raise InputError(f'block_s must be a positive number of seconds, got {block_s}')
    steps = np.diff(t_s)
    if np.any(steps <= 0.0):
        raise InputError(
            f't_s must increase strictly; it does not at index {int(np.argmax(steps <= 0.0)) + 1}'
        )


def _valid_differences(t_s: FloatArray) -> np.ndarray:
    """Which centres ``n = L .. N-L-1`` give a second difference that spans no gap, (N-2L,)."""
    lag = DIFFERENCE_LAG
    if len(t_s) < 2 * lag + 1:
        return np.zeros(0, dtype=bool)
    limit = MAX_SPAN_FACTOR * lag * float(np.median(np.diff(t_s)))
    centre = t_s[lag:-lag]
    return (t_s[2 * lag :] - centre <= limit) & (centre - t_s[: -2 * lag] <= limit)


def _difference_variance(values: FloatArray, valid: np.ndarray) -> float:
    """``mean(d^2) / 6`` over the valid lag-L second differences of ``values`` (N, 9)."""
    lag = DIFFERENCE_LAG
    d = values[2 * lag :] - 2.0 * values[lag:-lag] + values[: -2 * lag]
    d = d[valid]
    return float(np.sum(d**2)) / (DIFFERENCE_GAIN * d.size)


def _ratio(residual2: float, noise2: float) -> float:
    """``sqrt(residual2 / noise2)``; 0 for a residual within roundoff
    (:data:`ROUNDOFF_T`), inf for zero noise only."""
    if residual2 <= ROUNDOFF_T**2:
        return 0.0
    return float(np.sqrt(residual2 / noise2)) if noise2 > 0.0 else float('inf')


def _blocks(
    whitened: FloatArray,
    t_s: FloatArray,
    noise2: float,
    nu2: float,
    n_parameters: int,
    tolerance: float,
    alpha: float,
    block_s: float,
) -> tuple[Block, ...]:
    """Each non-empty block of ``block_s`` (from ``t_s[0]``) tested against ``noise2``."""
    n = len(t_s)
    start, end = float(t_s[0]), float(t_s[-1])
    n_blocks = max(1, int(np.ceil((end - start) / block_s - 1e-9)))
    index = np.minimum(((t_s - start) / block_s).astype(int), n_blocks - 1)
    counts = np.bincount(index, minlength=n_blocks)
    sums = np.bincount(index, weights=np.sum(whitened**2, axis=1), minlength=n_blocks)
    blocks = []
    for k in np.flatnonzero(counts):
        nu1 = counts[k] * (9.0 - n_parameters / n)
        ratio = _ratio(float(sums[k]) / nu1, noise2)
        threshold = tolerance * float(np.sqrt(f_isf(alpha, nu1, nu2)))
        blocks.append(
            Block(
                t0_s=float(start + k * block_s),
                t1_s=float(min(start + (k + 1) * block_s, end)),
                ratio=ratio,
                passed=bool(ratio <= threshold),
                n_samples=int(counts[k]),
                threshold_ratio=threshold,
            )
        )
    return tuple(blocks)
