"""Open-world structure in the residual: what the library has no family for, found by a scan
of the current model's residual and then offered to the search like a library effect.

* **Steps** (``hard_iron_step``): a sensor's constant offset changes at a time ``t_s`` (a
  magnetized part picked up or lost). Binary segmentation with the likelihood-ratio
  (CUSUM) statistic of a mean shift in the sensor's three axes: on ~1 s block means, each
  axis whitened by the robust spread of the differences of its block means (so slow
  colour of the residual counts as noise, a step as one outlier); a split is a change when
  its statistic exceeds the chi-square(3) quantile at ``alpha / blocks`` (Bonferroni over
  every possible split: the scan tests them all). The time is then refined on the samples
  around the block boundary. Each side keeps at least :data:`MIN_SEGMENT_S`.
* **Spectral lines** (``periodic_interference``): a rotating magnet (a shaft, a pump)
  adds a sinusoid to the sensors near it. The periodogram of each channel, its power over
  the local noise level (running median over neighbouring frequencies, so a coloured
  residual does not raise false lines); false-alarm probability ``1 - (1 - exp(-z))^M``
  with ``M`` the number of independent frequencies (Scargle 1982). A line is reported on
  the sensors where some axis passes at ``alpha`` (at least ten periods in the run); its
  frequency is refined by least squares on sine and cosine terms. A recorded channel
  (field rate, temperature, current) with a line there too is named with it: the scans
  run only once no library family passes, so the library has no form for it, but a
  missing effect of that channel would look the same (a manoeuvre's band holds many such
  lines; skipping them lost real lines below 0.22 Hz).

Why not the packages the field uses: the core imports numpy and scipy only (``ruptures``,
``astropy.timeseries.LombScargle`` are outside it), and ``scipy.signal.lombscargle`` is
O(samples x frequencies), ~20 s per channel on a 10-minute 10 Hz record; the samples lie
on a regular grid with gaps, where the zero-filled FFT periodogram is the same estimator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy  # submodules load on first use: see core/__init__.py
from numpy.typing import NDArray
from scipy.ndimage import median_filter

from .._distributions import chi2_isf

Array = NDArray[np.float64]

#: A step leaves at least this long a stretch on either side, s.
MIN_SEGMENT_S = 10.0
#: At most this many steps per sensor.
MAX_STEPS = 4
#: Block length of the step scan, s.
STEP_BLOCK_S = 1.0
#: Periodogram oversampling, and the running-median width of the noise level (bins).
OVERSAMPLE = 4
NOISE_WIDTH = 801
#: At most this many lines.
MAX_LINES = 3


@dataclass(frozen=True)
class StepChange:
    """A change of a sensor's offset (0-based ``sensor``) at ``t_s`` (s, the analysis'
    clock), with the scan's statistic and the threshold it passed."""

    sensor: int
    t_s: float
    statistic: float
    threshold: float


@dataclass(frozen=True)
class SpectralLine:
    """A sinusoid at ``frequency_hz`` in ``sensors`` (0-based), with the false-alarm
    probability of the strongest channel, its power over the local noise level and the
    ``recorded`` channels (names) that have a line there too."""

    frequency_hz: float
    sensors: tuple[int, ...]
    false_alarm: float
    power: float
    recorded: tuple[str, ...] = ()


@dataclass(frozen=True)
class OpenWorld:
    """What the scans found so far (the search keeps them: a family is built from them)."""

    steps: tuple[StepChange, ...] = ()
    lines: tuple[SpectralLine, ...] = ()

    def with_steps(self, steps: tuple[StepChange, ...]) -> OpenWorld:
        return OpenWorld(self.steps + steps, self.lines)

    def with_lines(self, lines: tuple[SpectralLine, ...]) -> OpenWorld:
        return OpenWorld(self.steps, self.lines + lines)


def find_steps(t: Array, residual: Array, alpha: float, sensor: int) -> list[StepChange]:
    """Changes of the mean of ``sensor``'s ``residual`` (N, 3) nT over time ``t`` (N,) s,
    by binary segmentation (module docstring); sorted by time."""
    dt = float(np.median(np.diff(t)))
    width = max(1, int(round(STEP_BLOCK_S / dt)))
    count = len(t) // width
    if count < 4:
        return []
    means = residual[: count * width].reshape(count, width, 3).mean(axis=1)
    spread = 1.4826 * np.median(np.abs(np.diff(means, axis=0)), axis=0) / np.sqrt(2.0)
    z = means / np.maximum(spread, 1e-12)
    threshold = float(chi2_isf(alpha / count, 3))
    least = max(2, int(np.ceil(MIN_SEGMENT_S / (width * dt))))
    found: list[StepChange] = []
    segments = [(0, count)]
    while segments and len(found) < MAX_STEPS:
        a, b = segments.pop()
        split = _best_split(z[a:b], least)
        if split is None or split[1] <= threshold:
            continue
        k = a + split[0]
        # A step is one outlier among the block-to-block changes (a drift or a random walk,
        # which CUSUM also splits, is many ordinary ones): the change across the boundary's
        # blocks must pass the same test on its own.
        jump = z[min(k + 1, count - 1)] - z[max(k - 2, 0)]
        if float(np.sum(jump**2)) <= threshold:
            segments += [(a, k), (k, b)]
            continue
        index = _refined(residual, k * width, width)
        found.append(StepChange(sensor, float(t[index]), split[1], threshold))
        segments += [(a, k), (k, b)]
    return sorted(found, key=lambda s: s.t_s)


def _best_split(z: Array, least: int) -> tuple[int, float] | None:
    """The split of ``z`` (n, 3) with the largest mean-shift statistic
    ``k (n - k) / n |mean_left - mean_right|^2``, each side at least ``least`` long."""
    n = len(z)
    if n < 2 * least:
        return None
    k = np.arange(least, n - least + 1)
    left = np.cumsum(z, axis=0)[k - 1]
    total = z.sum(axis=0)
    shift = left / k[:, None] - (total - left) / (n - k)[:, None]
    statistic = k * (n - k) / n * np.sum(shift**2, axis=1)
    best = int(np.argmax(statistic))
    return int(k[best]), float(statistic[best])


def _refined(residual: Array, boundary: int, width: int) -> int:
    """The sample, within two blocks of ``boundary``, where the step best splits
    ``residual`` (the same statistic on samples, the axes weighted alike)."""
    lo = max(1, boundary - 2 * width)
    hi = min(len(residual) - 1, boundary + 2 * width)
    window = residual[max(0, lo - 4 * width) : hi + 4 * width]
    offset = max(0, lo - 4 * width)
    best, best_value = boundary, -np.inf
    for index in range(lo, hi + 1):
        left = window[: index - offset].mean(axis=0)
        right = window[index - offset :].mean(axis=0)
        value = float(np.sum((left - right) ** 2))
        if value > best_value:
            best, best_value = index, value
    return best


def periodogram(t: Array, values: Array) -> tuple[Array, Array]:
    """Frequencies (F,) Hz and power (F, m) of ``values`` (N, m) sampled at ``t`` (N,) s on
    a regular grid with gaps (zero-filled), oversampled :data:`OVERSAMPLE` times."""
    dt = float(np.median(np.diff(t)))
    index = np.round((t - t[0]) / dt).astype(int)
    grid = np.zeros((index[-1] + 1, values.shape[1]))
    grid[index] = values - values.mean(axis=0)
    size = OVERSAMPLE * len(grid)
    spectrum = scipy.fft.rfft(grid, n=size, axis=0)
    power = np.abs(spectrum) ** 2 / len(t)
    return scipy.fft.rfftfreq(size, dt)[1:], power[1:]


def line_power(power: Array) -> Array:
    """Power over the local noise level (running median / ln 2: the median of an
    exponential variable), per column. ``power`` (F, c) or (F,).

    One column at a time: scipy's 1-D median filter has a running-median algorithm, while
    its n-D form with a (width, 1) footprint sorts each window anew; the same values
    (test_line_power.py), over 100 times faster at 12 columns of 40 000 bins."""
    columns = power.reshape(len(power), -1)
    level = np.empty_like(columns)
    for k in range(columns.shape[1]):
        level[:, k] = median_filter(columns[:, k], size=NOISE_WIDTH, mode='reflect')
    level = level.reshape(power.shape) / np.log(2.0)
    out: Array = power / np.maximum(level, 1e-300)
    return out


def false_alarm(z: Array, independent: int) -> Array:
    """False-alarm probability of a normalised power ``z`` among ``independent`` frequencies."""
    single = np.minimum(np.exp(-np.minimum(z, 700.0)), 1.0 - 1e-16)  # z = 0: certain
    out: Array = -np.expm1(independent * np.log1p(-single))
    return out


def find_lines(
    t: Array,
    residual: Array,
    recorded: Array,
    alpha: float,
    known: tuple[SpectralLine, ...] = (),
    recorded_names: tuple[str, ...] = (),
) -> list[SpectralLine]:
    """Lines in ``residual`` (N, s, 3) nT (sensor-major), strongest first, each with the
    ``recorded`` channels (N, r), named by ``recorded_names``, that have a line there too
    (module docstring); none within two independent frequencies of a ``known`` one. Each
    line found is fitted and taken out of the channels before the next search (its
    window's sidelobes are no lines)."""
    channels = residual.reshape(len(t), -1).copy()
    independent = len(t) // 2
    _, recorded_power = periodogram(t, recorded)
    recorded_fap = false_alarm(line_power(recorded_power), independent)
    names = recorded_names or tuple(f'recorded_{k}' for k in range(recorded.shape[1]))
    taken = [k.frequency_hz for k in known]
    lines: list[SpectralLine] = []
    for _ in range(2 * MAX_LINES):
        frequencies, power = periodogram(t, channels)
        bin_hz = float(frequencies[1] - frequencies[0])
        # Not the first bins (ten periods at least: the mean's leakage, and the slow misfit
        # the model's own terms leave) nor the last percent (Nyquist's power has one
        # degree of freedom, not two).
        usable = (frequencies > 10.0 / float(t[-1] - t[0])) & (
            frequencies < 0.99 * frequencies[-1]
        )
        z = line_power(power)
        fap = false_alarm(z, independent * z.shape[1])  # Bonferroni over the channels too
        fap[~usable] = 1.0
        # The strongest bin (by power: the probability underflows to 0 around a strong
        # line, where its first bin would be a sidelobe).
        i = int(np.argmax(np.where(usable, z.max(axis=1), -np.inf)))
        if fap[i].min() >= alpha or len(lines) >= MAX_LINES:
            break
        near = slice(max(0, i - OVERSAMPLE), i + OVERSAMPLE + 1)
        sensors = np.flatnonzero((fap[near].min(axis=0) < alpha).reshape(-1, 3).any(axis=1))
        columns = np.concatenate([np.arange(3 * s, 3 * s + 3) for s in sensors])
        frequency = _refined_frequency(t, channels[:, columns], float(frequencies[i]), bin_hz)
        channels[:, columns] -= _sinusoid(t, channels[:, columns], frequency)
        if any(abs(frequency - f) <= 2 * OVERSAMPLE * bin_hz for f in taken):
            continue  # known
        taken.append(frequency)
        shared = np.flatnonzero(recorded_fap[near].min(axis=0) < alpha)
        lines.append(
            SpectralLine(
                frequency,
                tuple(int(s) for s in sensors),
                float(fap[i].min()),
                float(z[i].max()),
                tuple(names[k] for k in shared),
            )
        )
    return lines


def _sinusoid(t: Array, channels: Array, frequency: float) -> Array:
    """The least-squares sine, cosine and mean of ``channels`` (N, m) at ``frequency`` Hz."""
    phase = 2 * np.pi * frequency * (t - t[0])
    design = np.column_stack([np.sin(phase), np.cos(phase), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(design, channels, rcond=None)
    out: Array = design @ coef
    return out


def _refined_frequency(t: Array, channels: Array, start_hz: float, bin_hz: float) -> float:
    """The frequency (Hz) whose sine and cosine terms explain most of ``channels`` (N, m),
    within two bins of ``start_hz``."""

    def rss(frequency: float) -> float:
        return float(np.sum((channels - _sinusoid(t, channels, frequency)) ** 2))

    result = scipy.optimize.minimize_scalar(
        rss, bounds=(start_hz - 2 * bin_hz, start_hz + 2 * bin_hz), method='bounded'
    )
    return float(result.x)
