"""Health of a calibration in use: a sequential change detector on the compensated tensor.

In a source-free region the true gradient tensor is symmetric and traceless, so the four
eq. 20 quantities of the *compensated* tensor, ``e_n = L vec(G_n)`` (T/m, ``L`` =
``design.CONSTRAINT_ROWS``), are pure error:

* **noise**: white, covariance ``Sigma = sigma^2 (L J)(L J)^T`` with ``J`` the (9, 12)
  readings-to-tensor Jacobian (``uncertainty.noise_jacobian``); ``sigma`` is the sensor
  noise, scaled up online (never down) by a running estimate from successive differences
  ``e_n - e_(n-1)`` (they cancel every slow term, a target's signature included);
* **bounded biases** ``s_n`` (T^2/m^2, a variance that averaging does not reduce): the
  calibration parameters' error (``trace(L A_n C A_n^T L^T)``, from the fit's covariance
  ``C``) and the 4-point differencing error of a nearby source, which breaks symmetry by at
  most ``2 (l_max / r) |G|`` (``l_max`` the longest edge, ``r`` the source's range; the
  factor measured 1.7-1.9 over ranges of 3-100 edges) -- so sources closer than
  ``min_source_range_edges`` (default 20 edges: 10 m for a 0.5 m array) may alarm.

A change of the vehicle (a sensor's offset jumps, a part is magnetized) shifts the mean of
``e``. Two detectors test that mean against the calibration's (zero, or the level after an
earlier alarm), never against a tracked level, so a change is always alarmed and never
absorbed:

* **windowed GLR** (Lai 1995): for each window ``w`` (seconds in ``HealthConfig.windows_s``),
  at every ``w / 16``-th sample (the statistic moves little in between; the long windows cost
  as little as the short), the mean ``ebar`` of the last ``w`` samples gives
  ``S = ebar^T (Sigma / n_w + sbar I)^-1 ebar`` (~chi2(4) with no change);
* **drift tracker**: an exponentially weighted mean (time constant
  ``drift_time_constant_s``) of ``e``, i.e. recursive least squares with forgetting on the
  part of the offsets that ``e`` observes, with its own chi2(4) statistic.

The threshold is ``chi2.isf(p, 4)`` with ``p`` = the false-alarm rate per hour spread over
the samples of an hour and the statistics tested per sample (Bonferroni: the tests overlap,
so the real rate is lower). On an alarm the shift is attributed: a jump of sensor ``s``'s
offset moves ``e`` by ``L J_s x`` (``J_s`` its three Jacobian columns, a 3-dimensional
subspace of the 4 dimensions of ``e``); the sensors whose subspace fits the shift
(chi2(1) test at 1 %) are named. The detector then settles: it collects
``settle_s`` seconds, takes their mean as the new level (the alarm stands) and resumes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import InputError
from ._distributions import chi2_isf
from ._filters import exponential_filter
from ._validate import as_array, as_tensors, as_vectors, same_length
from .design import CONSTRAINT_ROWS, constraint_residual
from .geometry import TetraGeometry
from .model import InterferenceParameters
from .types import FloatArray
from .uncertainty import constraint_bias_form, noise_jacobian
from .units import NT_PER_T

__all__ = ['Alarm', 'HealthConfig', 'HealthMonitor', 'HealthTrace', 'alarm_threshold']

#: Samples used to estimate the sampling rate before monitoring starts.
RATE_SAMPLES = 20
#: Consistency of a shift with one sensor's offset signature: chi2(1) at this level.
ATTRIBUTION_P = 0.01
#: Differencing error bound: |e| <= DIFFERENCING_FACTOR (l_max / r) |G|_F (measured <= 1.9).
DIFFERENCING_FACTOR = 2.0
#: Below this range (in longest edges) the differencing bound could mask an offset jump:
#: the jump's asymmetry is >= 1.22 its symmetric part, and (1.22 / (2 / 14))^2 = 73 > the
#: thresholds in use (~40 at 10 Hz, ~45 at 100 Hz).
MIN_SOURCE_RANGE_EDGES = 14.0
#: Per-sample features: y (4), calibration bias variance (1), physical tensor part (9),
#: noise scale (1).
N_FEATURES = 15
PHYSICAL = slice(5, 14)
NOISE_SCALE = 14
#: Successive differences needed before the online noise estimate is used.
MIN_NOISE_DIFFERENCES = 50


@dataclass(frozen=True)
class HealthConfig:
    """Settings of :class:`HealthMonitor` (units in the names)."""

    false_alarms_per_hour: float = 0.01
    windows_s: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
    drift_time_constant_s: float = 300.0
    noise_time_constant_s: float = 120.0
    min_source_range_edges: float = 20.0
    settle_s: float = 64.0

    def __post_init__(self) -> None:
        positive = {
            'false_alarms_per_hour': self.false_alarms_per_hour,
            'drift_time_constant_s': self.drift_time_constant_s,
            'noise_time_constant_s': self.noise_time_constant_s,
            'min_source_range_edges': self.min_source_range_edges,
            'settle_s': self.settle_s,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise InputError(f'HealthConfig.{name} must be positive, got {value}')
        if self.min_source_range_edges < MIN_SOURCE_RANGE_EDGES:
            raise InputError(
                f'HealthConfig.min_source_range_edges must be >= {MIN_SOURCE_RANGE_EDGES:g} '
                f'(closer, the differencing asymmetry could hide an offset jump), got '
                f'{self.min_source_range_edges}'
            )
        if not self.windows_s or not all(np.isfinite(w) and w > 0 for w in self.windows_s):
            raise InputError(f'HealthConfig.windows_s must be positive, got {self.windows_s}')


@dataclass(frozen=True)
class Alarm:
    """One detected change.

    Attributes
    ----------
    t_s : float
        Time of the alarm (the caller's time base), s.
    onset_s : float
        Estimated start of the change, s.
    kind : str
        ``offset_change`` (one or more sensors' offset signature fits), ``calibration_change``
        (none fits) or ``drift`` (raised by the slow tracker).
    sensors : tuple of int
        1-based sensors whose offset change fits the shift (empty: none).
    statistic, threshold : float
        The chi2(4) statistic that crossed the threshold.
    shift_t_per_m : (4,) ndarray
        Estimated shift of ``e`` (two asymmetries, one more, the trace), T/m.
    """

    t_s: float
    onset_s: float
    kind: str
    sensors: tuple[int, ...]
    statistic: float
    threshold: float
    shift_t_per_m: FloatArray
    settled: bool = False

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: times in s, the shift in nT/m."""
        return {
            't_s': float(self.t_s),
            'onset_s': float(self.onset_s),
            'kind': self.kind,
            'sensors': [int(s) for s in self.sensors],
            'statistic': float(self.statistic),
            'threshold': float(self.threshold),
            'shift_nT_per_m': [float(v) * NT_PER_T for v in self.shift_t_per_m],
            'settled': self.settled,
        }


@dataclass
class HealthTrace:
    """Per-sample statistics of one :meth:`HealthMonitor.update` (for plots and reports).

    ``t_s`` (n,) s; ``glr`` (n,) the largest windowed statistic (NaN while the rate is
    estimated or the detector settles); ``drift`` (n,) the tracker's statistic; ``alarms``.
    """

    t_s: FloatArray
    glr: FloatArray
    drift: FloatArray
    alarms: list[Alarm] = field(default_factory=list)


def alarm_threshold(false_alarms_per_hour: float, sample_rate_hz: float, n_tests: int) -> float:
    """The chi2(4) threshold for a false-alarm rate (per hour) over ``n_tests`` per sample."""
    p = false_alarms_per_hour / (3600.0 * sample_rate_hz * n_tests)
    return float(chi2_isf(min(p, 0.5), 4))


#: Each window is tested at this many evenly spaced samples per its length.
WINDOW_TESTS = 16


class HealthMonitor:
    """Sequential change detection on the compensated tensor (see the module docstring).

    Parameters
    ----------
    geometry : TetraGeometry
    parameters : InterferenceParameters
        The calibration in use.
    sensor_noise_t : float
        Per-axis sensor noise, tesla RMS (> 0).
    covariance : (P, P) ndarray, optional
        The calibration's parameter covariance (27 or 36), SI.
    config : HealthConfig
    """

    def __init__(
        self,
        geometry: TetraGeometry,
        parameters: InterferenceParameters,
        sensor_noise_t: float,
        covariance: np.ndarray | None = None,
        config: HealthConfig | None = None,
    ) -> None:
        if not (np.isfinite(sensor_noise_t) and sensor_noise_t > 0):
            raise InputError(f'sensor_noise_t must be positive, got {sensor_noise_t}')
        self.config = config or HealthConfig()
        self._differencing = DIFFERENCING_FACTOR / self.config.min_source_range_edges
        constraint_jacobian = CONSTRAINT_ROWS @ noise_jacobian(geometry, parameters)  # (4, 12)
        noise_cov = sensor_noise_t**2 * constraint_jacobian @ constraint_jacobian.T
        self._eigenvalues, self._basis = np.linalg.eigh(noise_cov)  # Sigma = U diag(D) U^T
        self._signatures = [constraint_jacobian[:, 3 * s : 3 * s + 3] for s in range(4)]
        self._y_signatures = [self._basis.T @ m for m in self._signatures]
        physical = _physical_part_matrix() @ noise_jacobian(geometry, parameters)  # (9, 12)
        self._physical_signatures = [physical[:, 3 * s : 3 * s + 3] for s in range(4)]
        self._bias_form = constraint_bias_form(geometry, covariance)
        self._stamps: list[float] = []
        self._pending: list[tuple[FloatArray, FloatArray, FloatArray]] = []
        self.sample_rate_hz = float('nan')
        self.threshold = float('nan')
        self.alarms: list[Alarm] = []
        self.samples = 0
        self.last_glr = self.last_drift = 0.0
        self.noise_scale = 1.0

    # ------------------------------------------------------------------ public

    def update(
        self, t_s: np.ndarray, g_compensated: np.ndarray, b_reference: np.ndarray
    ) -> HealthTrace:
        """Feed samples in time order: ``t_s`` (n,) s, ``G`` (n, 3, 3) T/m, ``B_1'`` (n, 3) T."""
        t_s = as_array(t_s, 't_s', (None,))
        g_compensated = as_tensors(g_compensated, 'g_compensated')
        b_reference = as_vectors(b_reference, 'b_reference')
        same_length(t_s=t_s, g_compensated=g_compensated, b_reference=b_reference)
        if np.isnan(self.sample_rate_hz):
            return self._buffer(t_s, g_compensated, b_reference)
        return self._run(t_s, g_compensated, b_reference)

    # ------------------------------------------------------------------ start-up

    def _buffer(self, t_s: FloatArray, g: FloatArray, b: FloatArray) -> HealthTrace:
        """Hold samples until the sampling rate is known (from their median interval)."""
        self._pending.append((t_s, g, b))
        self._stamps.extend(t_s.tolist())
        if len(self._stamps) < RATE_SAMPLES:
            n = len(t_s)
            return HealthTrace(t_s, np.full(n, np.nan), np.full(n, np.nan))
        intervals = np.diff(self._stamps)
        interval = float(np.median(intervals[intervals > 0])) if np.any(intervals > 0) else 0.0
        if not interval > 0:
            raise InputError('health monitor: the stamps do not advance; no sampling rate')
        self._start(1.0 / interval)
        held = [np.concatenate(parts) for parts in zip(*self._pending, strict=True)]
        self._pending.clear()
        trace = self._run(*held)
        keep = slice(len(trace.t_s) - len(t_s), None)  # earlier samples were reported as NaN
        return HealthTrace(t_s, trace.glr[keep], trace.drift[keep], trace.alarms)

    def _start(self, sample_rate_hz: float) -> None:
        config = self.config
        self.sample_rate_hz = sample_rate_hz
        self._windows = np.unique(
            np.maximum(1, np.round(np.asarray(config.windows_s) * sample_rate_hz)).astype(int)
        )
        self.threshold = alarm_threshold(
            config.false_alarms_per_hour, sample_rate_hz, 2 * len(self._windows) + 1
        )
        self._forget = float(np.exp(-1.0 / (config.drift_time_constant_s * sample_rate_hz)))
        self._noise_forget = float(np.exp(-1.0 / (config.noise_time_constant_s * sample_rate_hz)))
        self._settle_n = max(1, int(round(config.settle_s * sample_rate_hz)))
        self._level = np.zeros(4)  # the accepted mean of y (after alarms)
        self._level_n = np.inf  # samples behind the level (its own uncertainty)
        self._level_bias = 0.0  # bias variance of the level, (T/m)^2
        self._before = np.zeros((0, N_FEATURES))  # features up to the last alarm
        self._reset_history()
        self._noise_state, self._differences = np.zeros(2), 0
        self._last_y: FloatArray | None = None

    def _reset_history(self) -> None:
        """Forget the samples before now (at start and after an alarm)."""
        self._history = _History(2 * int(self._windows.max()))
        self._drift_state = np.zeros(6)  # weighted sums of y (4), of the bias, the weight
        self._drift_variance = 0.0
        self._settling: list[FloatArray] = []
        self._settle_left = 0

    # ------------------------------------------------------------------ detection

    def _run(self, t_s: FloatArray, g: FloatArray, b: FloatArray) -> HealthTrace:
        """Statistics of every sample; on an alarm, settle and resume after it."""
        n = len(t_s)
        features = self._features(g, b)
        features = np.column_stack([features, self._noise_scales(features[:, :4])])
        trace = HealthTrace(t_s, np.full(n, np.nan), np.full(n, np.nan))
        alarms_before = len(self.alarms)
        start = 0
        while start < n:
            start = self._settle(features, start)
            if start >= n:
                break
            alarm_at = self._detect(t_s, features, trace, start)
            if alarm_at is None:
                break
            start = alarm_at + 1
        self.samples += n
        trace.alarms = self.alarms[alarms_before:]
        return trace

    def _features(self, g: FloatArray, b: FloatArray) -> FloatArray:
        """Per sample (n, N_FEATURES): ``y`` (whitening basis, T/m), the calibration bias
        variance (T/m)^2, and the tensor's physical part (symmetric, traceless) (9) T/m.

        The differencing bound scales with the physical part: a change of the vehicle adds
        as much asymmetry as symmetry (a sensor's offset jump: ``|e| >= 1.22 |sym(dG)|``),
        so it cannot hide behind its own bound."""
        x = np.column_stack([b, np.ones(len(b))])
        calibration = np.einsum('nc,cd,nd->n', x, self._bias_form, x)
        symmetric = 0.5 * (g + np.swapaxes(g, 1, 2))
        trace = np.trace(symmetric, axis1=1, axis2=2)
        physical = symmetric - trace[:, None, None] * np.eye(3) / 3.0
        y = constraint_residual(g) @ self._basis
        return np.column_stack([y, calibration, physical.reshape(len(g), 9)])

    def _noise_scales(self, y: FloatArray) -> FloatArray:
        """Per-sample noise scale (n,): a running estimate from successive differences (an
        exponentially weighted mean of their whitened squares), never below 1, and 1 until
        ``MIN_NOISE_DIFFERENCES`` differences were seen."""
        previous = self._last_y
        stacked = y if previous is None else np.vstack([previous[None], y])
        ratio = np.sum(np.diff(stacked, axis=0) ** 2 / (2 * self._eigenvalues), axis=1) / 4
        if previous is None:  # the very first sample has no difference
            ratio = np.concatenate([[np.nan], ratio])
        valid = np.isfinite(ratio)
        lam = self._noise_forget
        inputs = np.column_stack([np.where(valid, ratio, 0.0), valid]) * (1 - lam)
        state = exponential_filter(lam, inputs, lam * self._noise_state[None])
        self._noise_state = state[-1]
        counts = self._differences + np.cumsum(valid)
        self._differences = int(counts[-1])
        self._last_y = y[-1].copy()
        with np.errstate(invalid='ignore', divide='ignore'):
            estimate = state[:, 0] / state[:, 1]
        scales = np.where(counts >= MIN_NOISE_DIFFERENCES, np.maximum(estimate, 1.0), 1.0)
        self.noise_scale = float(scales[-1])
        return scales

    def _settle(self, features: FloatArray, start: int) -> int:
        """While settling after an alarm, collect samples; the new level is their mean, and
        the alarm's sensors are attributed again on the settled shift (far less noisy)."""
        if self._settle_left == 0:
            return start
        take = features[start : start + self._settle_left]
        self._settling.append(take)
        self._settle_left -= len(take)
        if self._settle_left == 0:
            collected = np.vstack(self._settling)
            mean = collected.mean(axis=0)
            physical_sq = float(np.mean(np.sum(collected[:, PHYSICAL] ** 2, axis=1)))
            self._level, self._level_n = mean[:4], len(collected)
            self._level_bias = mean[4] + self._differencing**2 * physical_sq
            alarm = self.alarms[-1]
            sensors = self._settled_attribution(collected)
            kind = alarm.kind if alarm.kind == 'drift' else _step_kind(sensors)
            self.alarms[-1] = replace(alarm, sensors=sensors, kind=kind, settled=True)
            self._settling, self._before = [], np.zeros((0, N_FEATURES))
        return start + len(take)

    def _settled_attribution(self, after: FloatArray) -> tuple[int, ...]:
        """Sensors whose offset jump explains the jump of ``e`` across the alarm, best first.

        Windows of ``w`` samples (the longest available) just before and after the alarm.
        Each sensor's hypothesis explains part of the physical tensor's jump too (its
        offset jump's symmetric part); what it leaves is a source moving, whose asymmetry
        is bounded by the differencing factor -- so the spread is per hypothesis."""
        w = min(len(after), len(self._before))
        if w < 1:
            return ()
        misfit = self._jump_misfits(after[:w].mean(axis=0), self._before[-w:].mean(axis=0), w)
        limit = chi2_isf(ATTRIBUTION_P, 1)
        return tuple(int(s) + 1 for s in np.argsort(misfit) if misfit[s] < limit)

    def _jump_misfits(self, recent: FloatArray, earlier: FloatArray, w: int) -> FloatArray:
        """chi2(1) misfit (4,) of each sensor's offset-jump hypothesis for the jump between
        two ``w``-sample mean feature rows."""
        jump_y, jump_physical = recent[:4] - earlier[:4], recent[PHYSICAL] - earlier[PHYSICAL]
        noise = (
            self._eigenvalues * (recent[NOISE_SCALE] + earlier[NOISE_SCALE]) / w
            + recent[4]
            + earlier[4]
        )
        misfit = np.zeros(4)
        for s, (design, physical) in enumerate(
            zip(self._y_signatures, self._physical_signatures, strict=True)
        ):
            spread = noise
            for _ in range(2):  # noise-only fit, then with the source bound it leaves
                scale = 1.0 / np.sqrt(spread)
                x = np.linalg.lstsq(design * scale[:, None], jump_y * scale, rcond=None)[0]
                source = jump_physical - physical @ x
                spread = noise + self._differencing**2 * float(source @ source)
            misfit[s] = float(np.sum((jump_y - design @ x) ** 2 / spread))
        return misfit

    def _window_statistics(self, new: FloatArray, held: int) -> tuple[FloatArray, ...]:
        """For each new sample ``new`` (n, N_FEATURES), appended after ``held`` history rows:
        the largest statistic over the level tests and the jump tests, and the window's mean
        shift and spread (n, 4) and its length in samples (negative: a jump test). The tests
        due are computed in one pass (a live call's few samples would cost a loop over the
        windows mostly numpy's per-call time); ties go to the shorter window, level first."""
        n = len(new)
        sums = self._history.sums  # prefix sums of the history and the new rows
        end = np.arange(held + 1, held + n + 1)  # exclusive window ends of the new samples
        # Each window is tested every w // WINDOW_TESTS samples (an alarm later by at most that).
        steps = np.maximum(1, self._windows // WINDOW_TESTS)
        rows, which = np.nonzero(end[:, None] % steps[None, :] == 0)  # by sample, then window
        w, e = self._windows[which], end[rows]
        start, before = np.maximum(e - w, 0), np.maximum(e - 2 * w, 0)
        recent = (sums[e] - sums[start]) / w[:, None]
        earlier = (sums[start] - sums[before]) / w[:, None]
        d = (self._eigenvalues * new[rows, NOISE_SCALE, None]) / w[:, None]  # (p, 4)
        alpha2 = self._differencing**2
        # Level test: the mean against the accepted level.
        physical_sq = np.sum(recent[:, PHYSICAL] ** 2, axis=1)
        level_var = self._eigenvalues / self._level_n + self._level_bias
        level_spread = d + (recent[:, 4] + alpha2 * physical_sq)[:, None] + level_var
        level_stat = np.where(e >= w, np.sum(recent[:, :4] ** 2 / level_spread, axis=1), -np.inf)
        # Jump test: the mean against the window before it (a smooth source barely moves).
        jump = recent[:, :4] - earlier[:, :4]
        change_sq = np.sum((recent[:, PHYSICAL] - earlier[:, PHYSICAL]) ** 2, axis=1)
        jump_spread = 2 * d + (2 * recent[:, 4] + alpha2 * change_sq)[:, None]
        jump_stat = np.where(e >= 2 * w, np.sum(jump**2 / jump_spread, axis=1), -np.inf)
        # The first largest statistic of each sample (level, jump of each window in turn).
        stats = np.column_stack([level_stat, jump_stat]).ravel()
        stats[np.isnan(stats)] = -np.inf  # never chosen
        owner = np.repeat(rows, 2)  # ascending: each sample's candidates are contiguous
        first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if len(owner) else owner
        largest = np.maximum.reduceat(stats, first) if len(owner) else stats
        best = np.full(n, -np.inf)
        best[owner[first]] = largest
        top = np.flatnonzero((stats == np.repeat(largest, np.diff(np.r_[first, len(owner)])))
                             & (stats > -np.inf))
        top = top[np.r_[True, owner[top][1:] != owner[top][:-1]]] if len(top) else top
        pair, is_jump = top // 2, (top % 2 == 1)[:, None]
        sample = rows[pair]
        shift, spread, length = np.zeros((n, 4)), np.ones((n, 4)), np.zeros(n, dtype=int)
        shift[sample] = np.where(is_jump, jump[pair], recent[pair, :4])
        spread[sample] = np.where(is_jump, jump_spread[pair], level_spread[pair])
        length[sample] = np.where(is_jump[:, 0], -w[pair], w[pair])
        return best, shift, spread, length

    def _detect(
        self, t_s: FloatArray, features: FloatArray, trace: HealthTrace, start: int
    ) -> int | None:
        """Statistics of samples ``start:``; the index of the first alarm, or None."""
        new = features[start:].copy()
        new[:, :4] -= self._level
        held = self._history.append(new)
        best, shift, spread, length = self._window_statistics(new, held)
        bias = new[:, 4] + self._differencing**2 * np.sum(new[:, PHYSICAL] ** 2, axis=1)
        drift, drift_variance = self._drift(new[:, :4], bias)
        weight = drift[:, 5]
        drift_mean = drift[:, :4] / weight[:, None]
        drift_spread = (
            self._eigenvalues * new[:, NOISE_SCALE, None] * (drift_variance / weight**2)[:, None]
            + (drift[:, 4] / weight)[:, None]
            + self._eigenvalues / self._level_n
            + self._level_bias
        )
        drift_stat = np.sum(drift_mean**2 / drift_spread, axis=1)
        fired = np.flatnonzero((best > self.threshold) | (drift_stat > self.threshold))
        stop = len(new) if not len(fired) else int(fired[0]) + 1
        trace.glr[start : start + stop] = np.where(np.isfinite(best[:stop]), best[:stop], np.nan)
        trace.drift[start : start + stop] = drift_stat[:stop]
        self.last_glr, self.last_drift = (
            float(trace.glr[start + stop - 1]),
            float(drift_stat[stop - 1]),
        )
        if not len(fired):
            self._drift_state, self._drift_variance = drift[-1], float(drift_variance[-1])
            return None
        j = int(fired[0])
        t_alarm = float(t_s[start + j])
        keep = int(self._windows.max())
        self._before = self._history.rows[max(0, held + j + 1 - keep) : held + j + 1].copy()
        self._before[:, :4] += self._level
        if best[j] > self.threshold:
            w = abs(int(length[j]))
            onset = t_alarm - (w - 1) / self.sample_rate_hz  # the window start
            self._raise(t_alarm, onset, 'step', best[j], shift[j], spread[j])
        else:
            self._raise(t_alarm, t_alarm, 'drift', drift_stat[j], drift_mean[j], drift_spread[j])
        return start + j

    def _drift(self, y: FloatArray, bias: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Exponentially weighted sums over ``y`` (n, 4) and ``bias`` (n,): the state (n, 6)
        (sums of y, of the bias, the weight) and the noise variance sum (n,) (sum of squared
        weights: the mean's variance is ``Sigma`` times it over the weight squared)."""
        lam = self._forget
        inputs = np.column_stack([y, bias, np.ones(len(y))]) * (1 - lam)
        state = exponential_filter(lam, inputs, lam * self._drift_state[None])
        squares = np.full(len(y), (1 - lam) ** 2)
        variance = exponential_filter(lam**2, squares, np.array([lam**2 * self._drift_variance]))
        return state, variance

    def _attribute(self, shift_y: FloatArray, spread: FloatArray) -> tuple[int, ...]:
        """1-based sensors whose offset signature fits ``shift_y`` (chi2(1) at 1 %), best
        first; ``spread`` (4,) is the shift's variance per coordinate of the basis."""
        limit = chi2_isf(ATTRIBUTION_P, 1)
        scale = 1.0 / np.sqrt(spread)
        target = shift_y * scale
        misfit = []
        for signature in self._signatures:
            design = (self._basis.T @ signature) * scale[:, None]
            coefficients = np.linalg.lstsq(design, target, rcond=None)[0]
            misfit.append(float(np.sum((target - design @ coefficients) ** 2)))
        return tuple(int(s) + 1 for s in np.argsort(misfit) if misfit[s] < limit)

    def _raise(
        self,
        t_s: float,
        onset_s: float,
        detector: str,
        statistic: float,
        shift_y: FloatArray,
        spread: FloatArray,
    ) -> None:
        """Record an alarm for the shift ``shift_y`` (whitening basis, variance ``spread``
        per coordinate), name the sensors it fits, and start settling."""
        sensors = self._attribute(shift_y, spread)
        kind = 'drift' if detector == 'drift' else _step_kind(sensors)
        self.alarms.append(
            Alarm(
                t_s=float(t_s),
                onset_s=float(onset_s),
                kind=kind,
                sensors=sensors,
                statistic=float(statistic),
                threshold=self.threshold,
                shift_t_per_m=self._basis @ shift_y,
            )
        )
        self._reset_history()
        self._settle_left = self._settle_n


class _History:
    """The feature rows of at least the last ``keep`` samples and their prefix sums (a zero
    row first), appended in place: O(1) per sample, not a cumsum of the whole history per
    update (at 1000 samples/s: 19 ms per 0.1 s batch of the compensator node). When full it
    keeps the last ``keep`` rows and re-bases their sums (as small as the windows')."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self._rows = np.zeros((0, N_FEATURES))
        self._sums = np.zeros((1, N_FEATURES))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def rows(self) -> FloatArray:
        """(n, N_FEATURES), oldest first."""
        return self._rows[: self._n]

    @property
    def sums(self) -> FloatArray:
        """(n + 1, N_FEATURES): row ``i`` is the sum of the rows before ``i``."""
        return self._sums[: self._n + 1]

    def append(self, new: FloatArray) -> int:
        """Append ``new`` (k, N_FEATURES); return the number of rows before it."""
        if self._n + len(new) > len(self._rows):
            self._compact(len(new))
        held, k = self._n, len(new)
        self._rows[held : held + k] = new
        self._sums[held + 1 : held + k + 1] = self._sums[held] + np.cumsum(new, axis=0)
        self._n = held + k
        return held

    def _compact(self, incoming: int) -> None:
        """Keep the last ``keep`` rows (re-based sums) in a buffer with room for ``incoming``
        rows and as many again (amortized: one copy per ``keep`` samples)."""
        start = max(0, self._n - self.keep)
        kept = self._n - start
        capacity = 2 * (kept + incoming) + self.keep
        rows, sums = np.zeros((capacity, N_FEATURES)), np.zeros((capacity + 1, N_FEATURES))
        rows[:kept] = self._rows[start : self._n]
        sums[: kept + 1] = self._sums[start : self._n + 1] - self._sums[start]
        self._rows, self._sums, self._n = rows, sums, kept


def _step_kind(sensors: tuple[int, ...]) -> str:
    return 'offset_change' if sensors else 'calibration_change'


def _physical_part_matrix() -> FloatArray:
    """(9, 9): ``vec(G)`` -> ``vec`` of its symmetric traceless part."""
    basis = np.eye(9).reshape(9, 3, 3)
    symmetric = 0.5 * (basis + np.swapaxes(basis, 1, 2))
    trace = np.trace(symmetric, axis1=1, axis2=2)
    return (symmetric - trace[:, None, None] * np.eye(3) / 3.0).reshape(9, 9).T
