"""Detection of magnetic anomalies in the compensated tensor at a stated false-alarm rate.

Choices (the literature gives the invariants, not a detector; these are ours):

* Where: on straight legs only. The track is cut into legs where the heading leaves the
  leg's first heading by more than ``max_turn_deg``, where the track jumps (a step over
  ``max_step_m``) or where samples are missing (a gap over ``max_gap_s``); legs shorter
  than ``min_leg_s`` (manoeuvres, turns: a compensation residual that changes with the
  attitude) are not searched.
* What: the tensor in the odom frame minus its background (the running median over
  ``background_s`` within the leg: the regional gradient and a compensation residual that
  is constant while the attitude is), symmetric traceless part (a source-free field's
  tensor: the antisymmetric part and the trace are noise), its five components whitened by
  their robust spread over all searched legs (1.4826 MAD: the output's sigma as it is,
  sensor noise and residual alike). The statistic ``q`` is the sum of the five squared
  whitened components: rotation-invariant (its value is the squared Frobenius norm in
  sigma units), chi-square with 5 degrees of freedom on Gaussian noise.
* Rate: ``q`` averaged over ``window_s`` is compared with the chi-square threshold of
  ``5 w`` degrees of freedom (``w`` samples) whose tail probability is
  ``false_alarms_per_hour * window_s / 3600`` (one test per window length: the stated
  rate). A detection is a run of samples whose averaged ``q`` exceeds the chi-square
  99 % point, containing at least one sample over the threshold (hysteresis: the span
  covers the whole anomaly, not only its peak).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import ndimage, signal, stats

from ...errors import InputError
from ..geometry import to_world
from ..types import FloatArray, IntArray
from .forward import normalized_source_strength, symmetric_components

#: Two peaks of the normalized source strength are two detections when each stands out of
#: the dip between them by this factor (it falls as R^-4 away from a dipole).
PEAK_PROMINENCE = 2.0
#: 1.4826 MAD: the standard deviation of Gaussian data.
MAD_TO_SIGMA = 1.482602218505602


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
        for name in ('false_alarms_per_hour', 'window_s', 'background_s', 'min_leg_s'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f'detector setting {name} must be > 0, got {value}')


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
    """Detections plus what they were made from: the statistic (N,) (NaN outside the
    searched legs), the threshold, the whitened residual's ``sigma`` (5,) T/m, the
    residual ``anomaly`` (N, 3, 3) T/m in the odom frame (zero outside legs), and the legs
    as (start, stop) index pairs."""

    detections: list[Detection]
    statistic: FloatArray
    threshold: float
    sigma: FloatArray
    anomaly: FloatArray
    legs: list[tuple[int, int]]


def legs(
    t_s: FloatArray, positions: FloatArray, rotations: FloatArray, settings: DetectorSettings
) -> list[tuple[int, int]]:
    """Straight legs (start, stop) of at least ``min_leg_s`` (see the module docstring).

    ``t_s`` (N,) s, ``positions`` (N, 3) m, ``rotations`` (N, 3, 3) body -> odom."""
    forward = rotations[:, :, 0]
    heading = np.arctan2(forward[:, 1], forward[:, 0])
    out: list[tuple[int, int]] = []
    start = 0
    n = len(t_s)
    cos_turn = np.cos(np.radians(settings.max_turn_deg))
    for i in range(1, n + 1):
        cut = i == n
        if not cut:
            step = np.linalg.norm(positions[i] - positions[i - 1])
            turned = np.cos(heading[i] - heading[start]) < cos_turn
            cut = bool(
                turned or step > settings.max_step_m or t_s[i] - t_s[i - 1] > settings.max_gap_s
            )
        if cut:
            if t_s[i - 1] - t_s[start] >= settings.min_leg_s:
                out.append((start, i))
            start = i
    return out


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
    p_window = settings.false_alarms_per_hour * settings.window_s / 3600.0
    threshold = float(stats.chi2.isf(p_window, 5 * window) / window)
    low = float(stats.chi2.ppf(0.99, 5 * window) / window)
    world = symmetric_components(to_world(tensors, rotations))
    size = max(3, round(settings.background_s * rate_hz))
    # Two passes: the second background is the median of the samples the first found
    # quiet (anomalies cover much of a line over targets and would bias the median).
    quiet = np.ones(len(t_s), bool)
    for _ in range(2):
        components = _background_removed(world, quiet, found, size)
        sigma = noise_sigma(components, found)
        q = np.sum((components / sigma) ** 2, axis=1)
        averaged = ndimage.uniform_filter1d(q, window, mode='nearest')
        quiet = ndimage.binary_erosion(
            averaged < low, np.ones(4 * window + 1, bool), border_value=1
        )
    anomaly = _tensors_from_components(components)
    statistic = np.full(len(t_s), np.nan)
    detections: list[Detection] = []
    for start, stop in found:
        averaged = ndimage.uniform_filter1d(q[start:stop], window, mode='nearest')
        statistic[start:stop] = averaged
        smooth = ndimage.uniform_filter1d(anomaly[start:stop], window, axis=0, mode='nearest')
        strength = normalized_source_strength(smooth)
        detections += _runs(averaged, strength, (threshold, low, window), start, stop)
    return DetectionResult(detections, statistic, threshold, sigma, anomaly, found)


def _background_removed(
    world: FloatArray, quiet: npt.NDArray[np.bool_], found: list[tuple[int, int]], size: int
) -> FloatArray:
    """``world`` (N, 5) minus, on each leg, the running median over ``size`` samples of its
    ``quiet`` samples (interpolated across the others); zero off the legs."""
    out = np.zeros_like(world)
    for start, stop in found:
        index = np.arange(start, stop)
        keep = index[quiet[start:stop]]
        if len(keep) < max(10, (stop - start) // 4):
            keep = index  # too little quiet: the plain median
        # Thinned to ~100 samples per median window: the background is slow, and a median
        # over thousands of samples at every sample is the cost of the whole detector.
        keep = keep[:: max(1, size // 100)]
        window = min(max(3, size * len(keep) // max(stop - start, 1)), len(keep))
        background = ndimage.median_filter(world[keep], size=(window, 1), mode='nearest')
        for c in range(world.shape[1]):
            out[start:stop, c] = world[start:stop, c] - np.interp(index, keep, background[:, c])
    return out


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
    peaks = signal.find_peaks(padded, prominence=np.log(PEAK_PROMINENCE))[0] - 1
    cuts = [first]
    for left, right in zip(peaks[:-1], peaks[1:], strict=True):
        cuts.append(first + left + int(np.argmin(log_s[left:right])))
    cuts.append(last)
    return list(zip(cuts[:-1], cuts[1:], strict=True))
