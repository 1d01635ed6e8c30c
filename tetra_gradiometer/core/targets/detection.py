"""Detection of magnetic anomalies in the compensated tensor at a stated false-alarm rate.

Choices (the literature gives the invariants, not a detector; these are ours):

* Where: on straight legs only. The track is cut into legs where the heading leaves the
  leg's first heading by more than ``max_turn_deg``, where the track jumps (a step over
  ``max_step_m``) or where samples are missing (a gap over ``max_gap_s``); legs shorter
  than ``min_leg_s`` (manoeuvres, turns: a compensation residual that changes with the
  attitude) are not searched.
* What: the tensor in the odom frame minus its background on the leg (the regional
  gradient and a compensation residual that is constant while the attitude is), symmetric
  traceless part (a source-free field's tensor: the antisymmetric part and the trace are
  noise), five components. The statistic ``q`` is their squared Mahalanobis norm under the
  noise covariance (:class:`NoiseModel`, estimated on the quiet samples: the output's
  sigma as it is, sensor noise and residual alike): rotation-invariant, chi-square with 5
  degrees of freedom on Gaussian noise.
* Two passes: the first (running median background, sigma from first differences: robust
  to the anomalies, which cover much of a line over targets) only marks the quiet samples;
  the second takes the background (running mean) and the noise model from them.
* Rate: ``q`` averaged over ``window_s`` is compared with the threshold that the averaged
  statistic crosses upwards ``false_alarms_per_hour`` times per hour of legs on noise
  (:meth:`NoiseModel.threshold`: exact on white noise). A detection is a run of samples
  whose averaged ``q`` exceeds its 99 % point, containing at least one sample over the
  threshold (hysteresis: the span covers the whole anomaly, not only its peak), so every
  false detection holds an upcrossing: the stated rate bounds the false alarms from above.
  (The earlier threshold, the averaged statistic's tail at one test per window length,
  let 0.33 false alarms per hour through at a stated 0.1: a running mean crosses a high
  level several times per window length.) Checked on simulated target-free surveys by
  ``bench/bench_targets.py`` (README).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy  # submodules load on first use: see core/__init__.py

from ...errors import InputError
from .._distributions import chi2_isf
from .._validate import require_positive
from ..geometry import to_world
from ..types import FloatArray, IntArray
from .forward import normalized_source_strength, symmetric_components

#: Two peaks of the normalized source strength are two detections when each stands out of
#: the dip between them by this factor (it falls as R^-4 away from a dipole).
PEAK_PROMINENCE = 2.0
#: 1.4826 MAD: the standard deviation of Gaussian data.
MAD_TO_SIGMA = 1.482602218505602
#: A sample is quiet (noise only: the noise model's and the background's samples) unless a
#: window of the first pass's statistic within two windows of it exceeds its chi-square tail
#: of this probability: rare enough on noise that the quiet noise is not the low part of it.
QUIET_TAIL = 1e-4
#: Fewer quiet samples than this share of the legs (anomalies everywhere, as over a field
#: of targets before any is taken out): the noise is taken as white (``NoiseModel.white``).
QUIET_SHARE = 0.2


@dataclass(frozen=True)
class DetectorSettings:
    """How anomalies are searched (units in the names)."""

    false_alarms_per_hour: float = 0.1
    window_s: float = 2.0
    background_s: float = 300.0
    min_leg_s: float = 60.0
    max_turn_deg: float = 15.0
    max_step_m: float = 10.0
    max_gap_s: float = 2.0

    def __post_init__(self) -> None:
        names = ('false_alarms_per_hour', 'window_s', 'background_s', 'min_leg_s')
        require_positive('DetectorSettings', **{name: getattr(self, name) for name in names})


@dataclass(frozen=True)
class Detection:
    """One anomaly: sample indices ``start`` (first) .. ``stop`` (exclusive), its ``peak``
    sample, the averaged statistic there, and the leg it lies on (``leg_start``,
    ``leg_stop``: sample indices)."""

    start: int
    stop: int
    peak: int
    peak_statistic: float
    leg_start: int
    leg_stop: int


@dataclass(frozen=True)
class DetectionResult:
    """Detections plus what they were made from: the window-averaged statistic (N,) (NaN
    outside the searched legs), the threshold, the ``noise`` model, the residual
    ``anomaly`` (N, 3, 3) T/m in the odom frame (zero outside legs), the legs as
    (start, stop) index pairs, and the settings used."""

    detections: list[Detection]
    statistic: FloatArray
    threshold: float
    noise: NoiseModel
    anomaly: FloatArray
    legs: list[tuple[int, int]]
    settings: DetectorSettings

    @property
    def sigma(self) -> FloatArray:
        """The five components' 1-sigma (5,) T/m."""
        return self.noise.sigma


def legs(
    t_s: FloatArray, positions: FloatArray, rotations: FloatArray, settings: DetectorSettings
) -> list[tuple[int, int]]:
    """Straight legs (start, stop) of at least ``min_leg_s`` (see the module docstring).

    ``t_s`` (N,) s, ``positions`` (N, 3) m, ``rotations`` (N, 3, 3) body -> odom."""
    heading = headings(rotations)
    out: list[tuple[int, int]] = []
    start = 0
    n = len(t_s)
    for i in range(1, n + 1):
        cut = i == n or ends_leg(
            settings,
            float(heading[i] - heading[start]),
            float(np.linalg.norm(positions[i] - positions[i - 1])),
            float(t_s[i] - t_s[i - 1]),
        )
        if cut:
            if t_s[i - 1] - t_s[start] >= settings.min_leg_s:
                out.append((start, i))
            start = i
    return out


def headings(rotations: FloatArray) -> FloatArray:
    """Heading (N,) rad of the body x axis in the odom frame, from east towards north;
    ``rotations`` (N, 3, 3) body -> odom."""
    return np.asarray(np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0]))


def ends_leg(settings: DetectorSettings, turned_rad: float, step_m: float, gap_s: float) -> bool:
    """Whether a sample ends the straight leg: its heading ``turned_rad`` off the leg's first
    one by more than ``max_turn_deg``, a step of ``step_m`` from the previous sample over
    ``max_step_m`` or a gap ``gap_s`` over ``max_gap_s`` (:func:`legs`, and the target
    node's live track)."""
    return bool(
        np.cos(turned_rad) < np.cos(np.radians(settings.max_turn_deg))
        or step_m > settings.max_step_m
        or gap_s > settings.max_gap_s
    )


def detect(
    t_s: FloatArray,
    tensors: FloatArray,
    positions: FloatArray,
    rotations: FloatArray,
    settings: DetectorSettings | None = None,
) -> DetectionResult:
    """Anomalies in the body-frame tensors (N, 3, 3) T/m at times ``t_s`` (N,) s, with the
    body origin at ``positions`` (N, 3) m and attitudes ``rotations`` (N, 3, 3) body ->
    odom.

    Raises
    ------
    InputError
        No straight leg of ``min_leg_s`` (nothing could be searched), or non-finite input.
    """
    settings = settings or DetectorSettings()
    for name, value in (('t_s', t_s), ('tensors', tensors), ('positions', positions)):
        if not np.all(np.isfinite(value)):
            raise InputError(f'detect: {name} has non-finite values')
    found = legs(t_s, positions, rotations, settings)
    if not found:
        raise InputError(
            f'no straight leg of {settings.min_leg_s:g} s or more in {t_s[-1] - t_s[0]:.1f} s '
            'of track: nothing to search (manoeuvres and turns are not searched)'
        )
    rate_hz = (len(t_s) - 1) / max(t_s[-1] - t_s[0], 1e-9)
    window = max(1, int(round(settings.window_s * rate_hz)))
    world = symmetric_components(to_world(tensors, rotations))
    size = max(3, round(settings.background_s * rate_hz))
    # Pass 1: a background over all samples, sigma from first differences (an anomaly is
    # smooth over one sample period); it only marks the quiet samples.
    components = _background_removed(world, None, found, size)
    sigma = noise_sigma(components, found)
    q = np.sum((components / sigma) ** 2, axis=1)
    low = float(chi2_isf(QUIET_TAIL, 5 * window) / window)
    averaged = scipy.ndimage.uniform_filter1d(q, window, mode='nearest')  # marks only
    quiet = scipy.ndimage.binary_erosion(
        averaged < low, np.ones(4 * window + 1, bool), border_value=1
    )
    # Pass 2: background and noise model from the quiet samples (anomalies cover much of a
    # line over targets and would bias both).
    components = _background_removed(world, quiet, found, size)
    noise = NoiseModel.fit(components, quiet, found, window)
    q = noise.statistic(components)
    threshold = noise.threshold(settings.false_alarms_per_hour, rate_hz)
    low = noise.point(0.01)
    anomaly = _tensors_from_components(components)
    statistic = np.full(len(t_s), np.nan)
    detections: list[Detection] = []
    for start, stop in found:
        averaged = window_mean(q[start:stop], window)
        statistic[start:stop] = averaged
        smooth = scipy.ndimage.uniform_filter1d(
            anomaly[start:stop], window, axis=0, mode='nearest'
        )
        strength = normalized_source_strength(smooth)
        detections += _runs(averaged, strength, (threshold, low, window), start, stop)
    return DetectionResult(detections, statistic, threshold, noise, anomaly, found, settings)


def window_mean(values: FloatArray, window: int) -> FloatArray:
    """The mean (n,) of ``values`` (n,) over ``window`` samples centred on each sample; near
    the ends, that of the first (last) whole window. Every value is a mean of ``window``
    samples, so one null distribution holds everywhere (a window padded by repeating the
    end sample weighs it up to half: a much heavier tail at the ends of every leg)."""
    n = len(values)
    if n <= window:
        return np.full(n, float(np.mean(values)))
    total = np.concatenate([[0.0], np.cumsum(values)])
    whole = (total[window:] - total[:-window]) / window  # whole[j]: values[j : j + window]
    return whole[np.clip(np.arange(n) - window // 2, 0, n - window)]


def _background_removed(
    world: FloatArray, quiet: npt.NDArray[np.bool_] | None, found: list[tuple[int, int]], size: int
) -> FloatArray:
    """``world`` (N, 5) minus its background on each leg; zero off the legs.

    Without ``quiet`` (nothing known yet) the background is the running median over
    ``size`` samples (robust to the anomalies), thinned to ~100 samples per window: the
    background is slow, and a median over thousands of samples at every sample would cost
    more than the whole detector. With ``quiet`` it is the running mean of the quiet samples
    over ``size`` samples (the anomalies are out; a mean of ``size`` samples adds a
    ``1 / size`` of the noise's variance, a thinned median ``pi / 200``: enough to double
    the false alarms at the threshold's tail)."""
    out = np.zeros_like(world)
    for start, stop in found:
        index = np.arange(start, stop)
        piece = world[start:stop]
        if quiet is not None and np.count_nonzero(quiet[start:stop]) >= max(
            10, (stop - start) // 4
        ):
            weight = quiet[start:stop].astype(float)
            window = min(size, stop - start)
            total = scipy.ndimage.uniform_filter1d(
                piece * weight[:, None], window, axis=0, mode='mirror'
            )
            count = scipy.ndimage.uniform_filter1d(weight, window, mode='mirror')
            out[start:stop] = piece - total / np.maximum(count, 1e-12)[:, None]
            continue
        keep = index[:: max(1, size // 100)]
        window = min(max(3, size * len(keep) // max(stop - start, 1)), len(keep))
        background = scipy.ndimage.median_filter(world[keep], size=(window, 1), mode='mirror')
        for c in range(world.shape[1]):
            out[start:stop, c] = piece[:, c] - np.interp(index, keep, background[:, c])
    return out


@dataclass(frozen=True)
class NoiseModel:
    """The background-removed components' noise on the quiet samples: their covariance
    ``covariance`` (5, 5) (T/m)^2, and ``eigenvalues`` (w,) of the whitened components'
    autocorrelation over a window of ``w`` samples (all ones on white noise; coloured noise,
    a compensation residual or a sensor's 1/f, has fewer independent samples per window).

    The window's sum of ``q`` is then ``sum_i lambda_i chi2_5`` (each eigenvalue five times,
    one per component): its tail is taken from the chi-square with the same mean, variance
    and skewness (Pearson 1959; exact on white noise)."""

    covariance: FloatArray
    eigenvalues: FloatArray

    @property
    def sigma(self) -> FloatArray:
        """Per-component 1-sigma (5,) T/m."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def window(self) -> int:
        return len(self.eigenvalues)

    @property
    def dof(self) -> float:
        """The window's effective number of independent samples (``w`` on white noise)."""
        return float(np.sum(self.eigenvalues) ** 2 / np.sum(self.eigenvalues**2))

    @classmethod
    def fit(
        cls,
        components: FloatArray,
        quiet: npt.NDArray[np.bool_],
        found: list[tuple[int, int]],
        window: int,
    ) -> NoiseModel:
        """From ``components`` (N, 5) at the ``quiet`` samples of the legs ``found``: the
        autocorrelation at lags below ``window``, averaged over the whitened components and
        over the pairs of quiet samples of one leg."""
        mask = np.zeros(len(components), bool)
        for start, stop in found:
            mask[start:stop] = quiet[start:stop]
        searched = sum(stop - start for start, stop in found)
        if np.count_nonzero(mask) < max(20 * window, QUIET_SHARE * searched):
            return cls.white(components, found, window)
        covariance = np.cov(components[mask], rowvar=False)
        covariance += np.eye(5) * np.finfo(float).tiny
        whiten = np.linalg.inv(np.linalg.cholesky(covariance))
        # Legs laid end to end with ``window`` empty samples between: no lag crosses legs.
        gap = np.zeros((window, 5))
        z = np.concatenate(
            [
                part
                for a, b in found
                for part in (np.where(mask[a:b, None], components[a:b] @ whiten.T, 0.0), gap)
            ]
        )
        valid = np.concatenate(
            [part for a, b in found for part in (mask[a:b], np.zeros(window, bool))]
        )
        correlation = np.zeros(window)
        correlation[0] = 1.0
        for lag in range(1, window):
            pairs = np.count_nonzero(valid[:-lag] & valid[lag:])
            if pairs < 10:
                break
            correlation[lag] = np.sum(z[:-lag] * z[lag:]) / (5.0 * pairs)
        eigenvalues = np.maximum(scipy.linalg.eigvalsh(scipy.linalg.toeplitz(correlation)), 0.0)
        return cls(covariance, eigenvalues)

    @classmethod
    def white(
        cls, components: FloatArray, found: list[tuple[int, int]], window: int
    ) -> NoiseModel:
        """White noise whose covariance is that of the legs' second differences over 6 (an
        anomaly's curvature over one sample period is far below the noise): for surveys
        whose anomalies leave too few quiet samples, where nothing tells the noise's colour.
        """
        steps = np.concatenate([np.diff(components[a:b], n=2, axis=0) for a, b in found])
        covariance = np.cov(steps, rowvar=False) / 6.0 + np.eye(5) * np.finfo(float).tiny
        return cls(covariance, np.ones(window))

    def statistic(self, components: FloatArray) -> FloatArray:
        """Squared Mahalanobis norm (N,) of ``components`` (N, 5): chi-square with 5
        degrees of freedom on the noise, rotation-invariant once whitened."""
        z = np.linalg.solve(np.linalg.cholesky(self.covariance), components.T)
        return np.asarray(np.sum(z**2, axis=0))

    def _powers(self) -> list[float]:
        """``5 sum(lambda^r)`` for r = 1, 2, 3: the window sum's mean, half its variance and
        an eighth of its third central moment."""
        return [5.0 * float(np.sum(self.eigenvalues**r)) for r in (1, 2, 3)]

    def _pearson(self) -> tuple[float, float, float]:
        """The window's sum of ``q`` as ``mean + scale (X - nu)``, X chi-square with ``nu``
        degrees of freedom (mean, variance and skewness matched): (mean, scale, nu)."""
        power = self._powers()
        mean, variance = power[0], 2.0 * power[1]
        nu = power[1] ** 3 / power[2] ** 2  # the skewness sqrt(8 / nu) of 8 p3 / (2 p2)^1.5
        return mean, float(np.sqrt(variance / (2.0 * nu))), nu

    def point(self, tail: float) -> float:
        """The window-averaged statistic's level exceeded with probability ``tail``."""
        mean, scale, nu = self._pearson()
        return float((mean + scale * (chi2_isf(tail, nu) - nu)) / self.window)

    def threshold(self, false_alarms_per_hour: float, rate_hz: float) -> float:
        """The window-averaged statistic's level crossed upwards ``false_alarms_per_hour``
        times per hour on average, at ``rate_hz`` samples per second.

        One step of the running sum keeps a shared part and swaps one sample: on white noise
        ``w - 1`` samples of ``q`` (chi-square 5 each) are shared, and the sum crosses ``x``
        upwards when they sum to ``r`` with ``q_old <= x - r < q_new`` (:func:`upcrossing`:
        exact). On coloured noise, in the units of the Pearson chi-square (``nu`` degrees of
        freedom), the swapped parts are chi-square ``k`` with ``k / nu`` the consecutive
        sums' decorrelation ``var(q_new - q_old) / (2 var(sum))`` (``q`` taken independent
        ``w`` samples apart). On simulated AR(1) noise (20 h at 10 Hz) the crossings ran
        3 % over the stated rate for a coefficient of 0.3 and 35 % over for 0.6 (10
        independent samples per window); test_targets checks white and 0.3 within 15 %.
        """
        mean, scale, nu = self._pearson()
        swapped = nu * 5.0 / self._powers()[1]  # var(q_new - q_old) = 20, var(sum) = 2 p2
        steps_per_hour = 3600.0 * rate_hz

        def excess(x: float) -> float:
            rate = steps_per_hour * upcrossing(x, nu, swapped)
            return float(np.log(max(rate, 1e-300)) - np.log(false_alarms_per_hour))

        low, high = nu, float(chi2_isf(1e-16, nu))
        if excess(low) <= 0.0:
            x = nu
        else:
            x = float(scipy.optimize.brentq(excess, low, high, xtol=1e-9))
        return float((mean + scale * (x - nu)) / self.window)


def upcrossing(x: float, nu: float, swapped: float) -> float:
    """The probability that a running sum, chi-square ``nu``, crosses ``x`` upwards at one
    step that keeps a chi-square ``nu - swapped`` part (at least 1 degree of freedom) and
    swaps a chi-square ``swapped`` one: the shared part is ``x - y`` with the part leaving
    at most ``y`` and the one entering more. Integrated over ``y`` up to where the swapped
    part's tail is below 1e-19."""
    shared = max(nu - swapped, 1.0)
    top = min(x, float(scipy.special.chdtri(swapped, 1e-19)))
    # scipy.stats.chi2's pdf, cdf and sf are these special functions; called directly, the
    # integrand costs microseconds instead of the frozen distributions' ~0.3 ms, and quad
    # calls it hundreds of times per threshold.
    log_norm = scipy.special.gammaln(shared / 2.0) + np.log(2.0) * shared / 2.0

    def integrand(y: float) -> float:
        z = x - y
        pdf = np.exp(scipy.special.xlogy(shared / 2.0 - 1.0, z) - z / 2.0 - log_norm)
        return float(pdf * scipy.special.chdtr(swapped, y) * scipy.special.chdtrc(swapped, y))

    return float(scipy.integrate.quad(integrand, 0.0, top, epsabs=0.0, limit=200)[0])


def _tensors_from_components(components: FloatArray) -> FloatArray:
    """Symmetric traceless tensors (N, 3, 3) from their five components (inverse of
    :func:`symmetric_components`)."""
    a, b, xy, xz, yz = (components / np.array([np.sqrt(2.0), np.sqrt(6.0), *[np.sqrt(2.0)] * 3])).T
    xx = a + b
    yy = -a + b
    zz = -2.0 * b
    return np.stack(
        [np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2
    )


def noise_sigma(components: FloatArray, found: list[tuple[int, int]]) -> FloatArray:
    """Per-component white-noise 1-sigma (5,) of ``components`` (N, 5) on the legs: 1.4826
    MAD of first differences over root 2 (an anomaly is smooth over one sample period; a
    median of the values themselves would count the anomalies, which cover much of a
    survey over targets)."""
    steps = np.concatenate([np.diff(components[start:stop], axis=0) for start, stop in found])
    sigma = (
        MAD_TO_SIGMA * np.median(np.abs(steps - np.median(steps, axis=0)), axis=0) / np.sqrt(2.0)
    )
    return np.maximum(sigma, np.finfo(float).tiny)


def _runs(
    averaged: FloatArray,
    strength: FloatArray,
    limits: tuple[float, float, int],
    start: int,
    stop: int,
) -> list[Detection]:
    """Runs of ``averaged > low`` on one leg, cut between targets (:func:`_split`), that
    hold a sample over ``threshold`` and last at least ``window`` samples."""
    threshold, low, window = limits
    above = np.concatenate([[False], averaged > low, [False]])
    edges: IntArray = np.flatnonzero(np.diff(above.astype(np.int8)))
    out = []
    for first, last in zip(edges[::2], edges[1::2], strict=True):
        for a, b in _split(strength, int(first), int(last)):
            peak = a + int(np.argmax(averaged[a:b]))
            if averaged[peak] > threshold and b - a >= window:
                out.append(
                    Detection(
                        start + a, start + b, start + peak, float(averaged[peak]), start, stop
                    )
                )
    return out


def _split(strength: FloatArray, first: int, last: int) -> list[tuple[int, int]]:
    """A run cut at the lowest point of the normalized source strength between each two
    of its peaks that stand out by a factor :data:`PEAK_PROMINENCE` (two targets whose
    anomalies overlap are two detections; one dipole's strength has a single peak)."""
    log_s = np.log(np.maximum(strength[first:last], 1e-300))
    padded = np.concatenate([[-np.inf], log_s, [-np.inf]])
    peaks = scipy.signal.find_peaks(padded, prominence=np.log(PEAK_PROMINENCE))[0] - 1
    cuts = [first]
    for left, right in zip(peaks[:-1], peaks[1:], strict=True):
        cuts.append(first + left + int(np.argmin(log_s[left:right])))
    cuts.append(last)
    return list(zip(cuts[:-1], cuts[1:], strict=True))
