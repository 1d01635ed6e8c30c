"""A common time base for four magnetometers on their own clocks.

Each sensor samples at its own instants (its stamps are the true sample times). A sample
set is formed by resampling every sensor's stream to the *reference instants* (sensor 1's
stamps by default, or a regular grid), interpolating between the neighbouring samples of
each sensor, never across a gap longer than ``max_gap_periods`` of that sensor's own sample
period; such sets are skipped and counted. The same :class:`Resampler` serves the offline
readers (batches of thousands of samples) and the live tensor node (one message at a time):
a reference instant is resolved as soon as every sensor has a sample at or after it, so the
added latency is the wait for the latest sensor's next sample: up to one of its sample
periods (one more per message of it lost, up to the gap limit) plus the transport delay.

Interpolation: quadratic through the two samples before the instant and the one after (the
latency stays one period); an instant without two earlier samples within the gap limit (the
first one of a stream, the first one after a long gap) is skipped, not degraded. Why
quadratic: linear interpolation errs by ``h^2/8 |B''|``, at 50 Hz on a trim
manoeuvre (``|B''| ~ omega^2 |B|``, omega 0.25 rad/s, 50 000 nT) about 0.15 nT per sensor,
which differencing over a 0.5 m array turns into ~0.3 nT/m, several times the noise floor;
the quadratic's ``~0.1 h^3 |B'''|`` is below 1e-3 nT (see ``test/core/test_timebase.py``).
An instant that coincides with a sample's stamp takes that sample exactly, so synchronous
streams give exactly the readings a stamp matcher would pair.

Clock estimate: for every resolved instant, each sensor's nearest stamp minus the instant
(within half the sensor's period: beyond, the sample that belonged there was lost); its
running mean is the sensor's clock offset against the reference and its standard deviation
the jitter against the reference (it includes the reference's own jitter). With unequal
rates the "offset" is the mean phase and the "jitter" mostly the beat between the clocks.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .plausibility import MAX_FIELD_T, plausible_reading, plausible_readings
from .streams import StreamReport
from .units import NS_PER_S, S_PER_NS

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

N_SENSORS = 4
#: Sample intervals kept per sensor for its period estimate (running median).
PERIOD_HISTORY = 64
#: The median is recomputed after this many new intervals (the period is steady; a median
#: per message was a third of the live path's time).
PERIOD_REFRESH = 16
#: Methods of forming sets: resampling (default), or pairing the nearest stamps within a
#: tolerance (``io/matching.StampMatcher``) for sensors sampled together by one clock whose
#: stamps carry transport jitter (arrival times): interpolating at such stamps would add
#: ``jitter x dB/dt``, while pairing takes the simultaneous samples.
SYNC_METHODS = ('interpolate', 'nearest')


@dataclass(frozen=True)
class TimeBase:
    """How the four streams become sample sets.

    Attributes
    ----------
    sync : 'interpolate' (resample to the reference instants) or 'nearest' (pair stamps
        within ``tolerance_s``; see :data:`SYNC_METHODS`)
    reference_rate_hz : 0: sensor 1's stamps are the reference instants; > 0: a regular
        grid at this rate (multiples of its period since the epoch), Hz
    max_gap_periods : never interpolate across a gap longer than this many of the sensor's
        own sample periods (running median of its last intervals)
    tolerance_s : largest spread of the four stamps of a set, s ('nearest' only)
    """

    sync: str = 'interpolate'
    reference_rate_hz: float = 0.0
    max_gap_periods: float = 3.0
    tolerance_s: float = 2e-3

    def __post_init__(self) -> None:
        if self.sync not in SYNC_METHODS:
            raise InputError(f'sync must be one of {SYNC_METHODS}, got {self.sync!r}')
        if not (np.isfinite(self.reference_rate_hz) and self.reference_rate_hz >= 0):
            raise InputError(f'reference_rate_hz must be >= 0, got {self.reference_rate_hz}')
        if not (np.isfinite(self.max_gap_periods) and self.max_gap_periods >= 1):
            raise InputError(f'max_gap_periods must be >= 1, got {self.max_gap_periods}')
        if not (np.isfinite(self.tolerance_s) and self.tolerance_s > 0):
            raise InputError(f'tolerance_s must be > 0, got {self.tolerance_s}')

    @property
    def text(self) -> str:
        """One line for summaries."""
        if self.sync == 'nearest':
            return f'nearest stamps within {self.tolerance_s * 1e3:g} ms'
        reference = (
            f'a {self.reference_rate_hz:g} Hz grid'
            if self.reference_rate_hz
            else "sensor 1's stamps"
        )
        return f'resampled to {reference} (gaps > {self.max_gap_periods:g} periods skipped)'


#: The default: resample to sensor 1's stamps, skipping gaps over 3 periods.
DEFAULT_TIMEBASE = TimeBase()


@dataclass
class ResampleCounters:
    """Running counts of a :class:`Resampler`.

    Attributes
    ----------
    sets : sets emitted
    skipped_gap : reference instants skipped: a sensor had a gap longer than the limit there
    skipped_start : reference instants before some sensor's first sample
    skipped_end : reference instants after some sensor's last sample (a stream that stopped;
        counted by :meth:`Resampler.finish` at the end of a recording)
    out_of_order : messages refused because their stamp did not increase on their sensor
    evicted : reference instants dropped unresolved because a sensor stayed silent for more
        than ``max_pending`` of them
    streams : the streams' faults found before the sets were formed (offline reads)
    """

    sets: int = 0
    skipped_gap: int = 0
    skipped_start: int = 0
    out_of_order: int = 0
    evicted: int = 0
    skipped_end: int = 0
    streams: StreamReport = field(default_factory=StreamReport)

    @property
    def skipped(self) -> int:
        return self.skipped_gap + self.skipped_start + self.skipped_end + self.evicted

    def text(self) -> str:
        """For summaries: '2 sets skipped (0 at gaps, 2 at stream starts, 0 at stream ends,
        0 evicted), 0 out of order'."""
        return (
            f'{self.skipped} sets skipped ({self.skipped_gap} at gaps, {self.skipped_start} at '
            f'stream starts, {self.skipped_end} at stream ends, {self.evicted} evicted), '
            f'{self.out_of_order} out of order'
        ) + (f'; {self.streams.text()}' if self.streams.faults else '')

    def as_dict(self) -> dict[str, Any]:
        """Calibration-file diagnostics."""
        return self.streams.as_dict() | {
            'sets_resampled': self.sets,
            'sets_skipped_gap': self.skipped_gap,
            'sets_skipped_start': self.skipped_start,
            'sets_evicted': self.evicted,
            'sets_skipped_end': self.skipped_end,
            'messages_out_of_order': self.out_of_order,
        }


@dataclass
class _ClockSums:
    """Welford sums of (nearest stamp - instant), ns, and the sensor's recent intervals."""

    count: int = 0
    mean_ns: float = 0.0
    m2: float = 0.0
    intervals: deque[int] = field(default_factory=lambda: deque(maxlen=PERIOD_HISTORY))
    _period: float | None = None
    _new_intervals: int = 0

    def add_intervals(self, intervals: list[int]) -> None:
        self.intervals.extend(intervals)
        self._new_intervals += len(intervals)

    def add_one(self, delta_ns: float) -> None:
        """:meth:`add` of one delta, in plain Python (the same arithmetic)."""
        total = self.count + 1
        delta = delta_ns - self.mean_ns
        self.mean_ns += delta / total
        self.m2 += delta**2 * self.count / total
        self.count = total

    def add(self, deltas_ns: FloatArray) -> None:
        """Chan et al.'s parallel update with a batch of deltas."""
        n = len(deltas_ns)
        if not n:
            return
        batch_mean = float(np.mean(deltas_ns))
        batch_m2 = float(np.sum((deltas_ns - batch_mean) ** 2))
        total = self.count + n
        delta = batch_mean - self.mean_ns
        self.mean_ns += delta * n / total
        self.m2 += batch_m2 + delta**2 * self.count * n / total
        self.count = total

    def period_ns(self) -> float | None:
        """Median of the recent intervals, refreshed every PERIOD_REFRESH new ones."""
        if self.intervals and (self._period is None or self._new_intervals >= PERIOD_REFRESH):
            self._period, self._new_intervals = float(np.median(self.intervals)), 0
        return self._period


@dataclass(frozen=True)
class ClockEstimate:
    """One sensor's clock as estimated against the reference instants (the simulator's clocks
    are :class:`~tetra_gradiometer.core.clocks.SensorClocks`).

    Attributes
    ----------
    offset_s : mean of (nearest own stamp - reference instant), s
    jitter_s : its standard deviation, s
    rate_hz : 1 / the median of the sensor's recent sample intervals (0 before two samples)
    n : instants it was measured over
    """

    offset_s: float
    jitter_s: float
    rate_hz: float
    n: int

    def to_dict(self) -> dict[str, float]:
        return {
            'offset_ms': self.offset_s * 1e3,
            'jitter_ms': self.jitter_s * 1e3,
            'rate_hz': self.rate_hz,
            'instants': self.n,
        }


def clocks_text(clocks: tuple[ClockEstimate, ...]) -> str:
    """'sensor clocks vs reference: 2 +1.98 ms (jitter 0.28 ms, 50.0 Hz), ...'"""
    parts = [
        f'{i + 1} {c.offset_s * 1e3:+.2f} ms '
        f'(jitter {c.jitter_s * 1e3:.2f} ms, {c.rate_hz:.1f} Hz)'
        for i, c in enumerate(clocks)
    ]
    return 'sensor clocks vs reference: ' + ', '.join(parts)


def _lagrange_weights(x: Any, xa: Any, x1: Any) -> tuple[Any, Any, Any]:
    """Quadratic Lagrange weights on the nodes ``(x1, 0, xa)`` at ``x`` (floats or arrays,
    ns relative to the sample before): those of the samples before-before, before, after."""
    w1 = x * (x - xa) / (x1 * (x1 - xa))
    w0 = (x - x1) * (x - xa) / (x1 * xa)
    wa = (x - x1) * x / ((xa - x1) * xa)
    return w1, w0, wa


class Resampler:
    """Streaming resampler of four sensors onto common reference instants.

    Parameters
    ----------
    timebase : TimeBase ('interpolate')
    width : values per reading (3 for a field; more columns, e.g. a covariance, are
        interpolated with the same weights)
    max_pending : bound of the reference instants waiting for a silent sensor (memory)
    max_field_t : a reading (its first 3 values, T) non-finite or larger than this is never
        interpolated (a spike must not leak into its neighbours' sets): the stream is
        interpolated across it as across a lost message, and the instant nearest to it
        gets the reading itself, so that the caller's plausibility check drops and counts
        that one set, as when pairing stamps; settable at run time
    """

    def __init__(
        self,
        timebase: TimeBase,
        *,
        width: int = 3,
        max_pending: int = 10_000,
        max_field_t: float = MAX_FIELD_T,
    ) -> None:
        if timebase.sync != 'interpolate':
            raise InputError(f'Resampler needs sync="interpolate", got {timebase.sync!r}')
        self.timebase = timebase
        self.width = int(width)
        self.max_pending = int(max_pending)
        self.max_field_t = float(max_field_t)
        self.counters = ResampleCounters()
        self._t: list[IntArray] = [np.zeros(0, np.int64) for _ in range(N_SENSORS)]
        self._v: list[FloatArray] = [np.zeros((0, self.width)) for _ in range(N_SENSORS)]
        self._last: list[int | None] = [None] * N_SENSORS
        self._bad_t: list[IntArray] = [np.zeros(0, np.int64) for _ in range(N_SENSORS)]
        self._bad_v: list[FloatArray] = [np.zeros((0, self.width)) for _ in range(N_SENSORS)]
        self._pending: IntArray = np.zeros(0, np.int64)
        self._grid_next: int | None = None  # next grid index (grid mode)
        self._sums = [_ClockSums() for _ in range(N_SENSORS)]

    # ----------------------------------------------------------------- input

    def add(
        self, sensor: int, stamps_ns: npt.ArrayLike, values: npt.ArrayLike
    ) -> tuple[IntArray, FloatArray]:
        """Take readings of one sensor (0..3): ``stamps_ns`` (k,) int ns, ``values`` (k, width);
        return the sets they complete: ``(stamps_ns (m,), values (m, 4, width))``."""
        stamps = np.atleast_1d(np.asarray(stamps_ns, dtype=np.int64))
        values = np.asarray(values, dtype=float).reshape(len(stamps), self.width)
        stamps, values = self._in_order(sensor, stamps, values)
        if not len(stamps):
            return self._resolve()
        self._remember_intervals(sensor, stamps)
        self._last[sensor] = int(stamps[-1])
        self._store(sensor, stamps, values, plausible_readings(values[:, :3], self.max_field_t))
        return self._resolve()

    def add_one(
        self, sensor: int, stamp_ns: int, value: np.ndarray
    ) -> tuple[IntArray, FloatArray]:
        """:meth:`add` of one reading ``value`` (width,) at ``stamp_ns``: the live path (one
        message at a time), the same bookkeeping with Python scalars where numpy's per-call
        overhead made most of the tensor node's time; the same sets."""
        stamp_ns, last = int(stamp_ns), self._last[sensor]
        if last is not None and stamp_ns <= last:
            self.counters.out_of_order += 1
            return self._resolve()
        if last is not None:
            self._sums[sensor].add_intervals([stamp_ns - last])
        self._last[sensor] = stamp_ns
        row = np.asarray(value, dtype=float).reshape(1, self.width)
        x, y, z = row[0, :3].tolist()
        good = np.array([plausible_reading(x, y, z, self.max_field_t)])
        self._store(sensor, np.array([stamp_ns], np.int64), row, good)
        return self._resolve()

    def _store(
        self, sensor: int, stamps: IntArray, values: FloatArray, good: npt.NDArray[np.bool_]
    ) -> None:
        """Keep in-order readings: the plausible ones (``good``) for interpolation, the others
        apart (a set that would take one is dropped by the caller); sensor 1's stamps are the
        reference instants unless on a grid."""
        if sensor == 0 and not self.timebase.reference_rate_hz:
            self._pending = np.concatenate([self._pending, stamps])
        if not good.all():
            self._bad_t[sensor] = np.concatenate([self._bad_t[sensor], stamps[~good]])
            self._bad_v[sensor] = np.concatenate([self._bad_v[sensor], values[~good]])
        if good.any():
            self._t[sensor] = np.concatenate([self._t[sensor], stamps[good]])
            self._v[sensor] = np.concatenate([self._v[sensor], values[good]])

    def _in_order(
        self, sensor: int, stamps: IntArray, values: FloatArray
    ) -> tuple[IntArray, FloatArray]:
        """Drop readings whose stamp does not increase on their sensor (counted)."""
        last = self._last[sensor]
        previous = np.maximum.accumulate(
            np.concatenate([[np.iinfo(np.int64).min if last is None else last], stamps[:-1]])
        )
        keep = stamps > previous
        self.counters.out_of_order += int(len(stamps) - keep.sum())
        return stamps[keep], values[keep]

    def _remember_intervals(self, sensor: int, stamps: IntArray) -> None:
        last = self._last[sensor]
        joined = stamps if last is None else np.concatenate([[last], stamps])
        self._sums[sensor].add_intervals(np.diff(joined)[-PERIOD_HISTORY:].tolist())

    def _bound_pending(self) -> None:
        excess = len(self._pending) - self.max_pending
        if excess > 0:
            self._pending = self._pending[excess:]
            self.counters.evicted += excess

    def _grid_instants(self, until_ns: int) -> IntArray:
        """The grid instants not yet issued up to ``until_ns`` (grid mode)."""
        period = NS_PER_S / self.timebase.reference_rate_hz
        first = self._earliest_buffered()
        if self._grid_next is None:
            self._grid_next = int(np.ceil(first / period))
        last_index = int(np.floor(until_ns / period))
        if last_index < self._grid_next:
            return np.zeros(0, np.int64)
        indices = np.arange(self._grid_next, last_index + 1)
        self._grid_next = last_index + 1
        return np.round(indices * period).astype(np.int64)

    def _earliest_buffered(self) -> int:
        """The earliest stamp buffered (grid origin); only called once all sensors have data."""
        return min(int(t[0]) for t in self._t)

    # ----------------------------------------------------------------- resolving

    def _resolve(self) -> tuple[IntArray, FloatArray]:
        if not all(len(t) for t in self._t):
            self._bound_pending()
            return np.zeros(0, np.int64), np.zeros((0, N_SENSORS, self.width))
        horizon = min(int(t[-1]) for t in self._t)  # every sensor has a good sample at or after
        if not self.timebase.reference_rate_hz and (
            not len(self._pending) or int(self._pending[0]) > horizon
        ):  # no instant ready (the live path's usual case): as below with n_ready 0
            self._bound_pending()
            return np.zeros(0, np.int64), np.zeros((0, N_SENSORS, self.width))
        if self.timebase.reference_rate_hz:
            self._pending = np.concatenate([self._pending, self._grid_instants(horizon)])
        n_ready = int(np.searchsorted(self._pending, horizon, side='right'))
        instants, self._pending = self._pending[:n_ready], self._pending[n_ready:]
        self._bound_pending()  # what still waits for a silent sensor
        if not n_ready:
            return np.zeros(0, np.int64), np.zeros((0, N_SENSORS, self.width))
        out = np.empty((n_ready, N_SENSORS, self.width))
        valid = np.ones(n_ready, bool)
        started = np.ones(n_ready, bool)
        interpolate = self._interpolate_one if n_ready == 1 else self._interpolate
        for sensor in range(N_SENSORS):
            has_before, ok = interpolate(sensor, instants, out[:, sensor])
            started &= has_before
            valid &= ok
        self.counters.skipped_start += int((~started).sum())
        self.counters.skipped_gap += int((started & ~valid).sum())
        self.counters.sets += int(valid.sum())
        self._prune()
        return instants[valid], out[valid]

    def _interpolate(
        self, sensor: int, instants: IntArray, out: FloatArray
    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """Fill ``out`` (m, width) with ``sensor``'s readings at ``instants`` (m,), each at or
        before the sensor's last stamp; return (has a sample at or before, valid)."""
        t, v = self._t[sensor], self._v[sensor]
        after = np.searchsorted(t, instants, side='left')  # first stamp >= instant
        exact = t[after] == instants
        b0, b1 = np.maximum(after - 1, 0), np.maximum(after - 2, 0)
        has_before = exact | (after >= 2)
        period = self._sums[sensor].period_ns()
        max_gap = self.timebase.max_gap_periods * (period if period else np.inf)
        x_after = (t[after] - t[b0]).astype(float)  # relative stamps: exact in float64
        x_b1 = (t[b1] - t[b0]).astype(float)  # < 0
        valid = exact | (has_before & (x_after <= max_gap) & (-x_b1 <= max_gap))
        out[exact] = v[after[exact]]
        q = valid & ~exact
        if np.any(q):
            x = (instants[q] - t[b0[q]]).astype(float)
            w1, w0, wa = _lagrange_weights(x, x_after[q], x_b1[q])
            out[q] = w1[:, None] * v[b1[q]] + w0[:, None] * v[b0[q]] + wa[:, None] * v[after[q]]
        nearest = np.where(exact | (instants - t[b0] > t[after] - instants), after, b0)
        delta = (t[nearest] - instants).astype(float)
        # Beyond half a period the nearest sample is a neighbour of a lost one: not the clock.
        self._sums[sensor].add(delta[valid & (np.abs(delta) <= 0.5 * (period or np.inf))])
        self._pass_bad(sensor, instants, np.abs(delta), out, valid)
        return has_before | valid, valid

    def _interpolate_one(
        self, sensor: int, instants: IntArray, out: FloatArray
    ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
        """:meth:`_interpolate` of one instant in plain Python: the live path (one message at
        a time), where numpy's per-call overhead made it 50x the cost of pairing stamps; the
        same arithmetic in the same order, so the same numbers."""
        t, v, instant = self._t[sensor], self._v[sensor], int(instants[0])
        after = int(t.searchsorted(instant, side='left'))
        t_after, b0, b1 = int(t[after]), max(after - 1, 0), max(after - 2, 0)
        t0 = int(t[b0])
        exact = t_after == instant
        has_before = exact or after >= 2
        period = self._sums[sensor].period_ns()
        max_gap = self.timebase.max_gap_periods * (period if period else np.inf)
        x_after, x_b1 = float(t_after - t0), float(int(t[b1]) - t0)
        valid = exact or (has_before and x_after <= max_gap and -x_b1 <= max_gap)
        if exact:
            out[0] = v[after]
        elif valid:
            w1, w0, wa = _lagrange_weights(float(instant - t0), x_after, x_b1)
            out[0] = w1 * v[b1] + w0 * v[b0] + wa * v[after]
        nearest = after if exact or instant - t0 > t_after - instant else b0
        delta = float(int(t[nearest]) - instant)
        if valid and abs(delta) <= 0.5 * (period or np.inf):
            self._sums[sensor].add_one(delta)
        flags = np.array([valid])
        if len(self._bad_t[sensor]):
            self._pass_bad(sensor, instants, np.array([abs(delta)]), out, flags)
        return np.array([has_before]) | flags, flags

    def _pass_bad(
        self,
        sensor: int,
        instants: IntArray,
        distance: FloatArray,
        out: FloatArray,
        valid: npt.NDArray[np.bool_],
    ) -> None:
        """Where a refused reading lies nearer an instant than every good one, the set takes
        the refused reading (the caller drops and counts it, with its reason)."""
        bad_t = self._bad_t[sensor]
        if not len(bad_t):
            return
        index = np.searchsorted(bad_t, instants)
        left, right = np.clip(index - 1, 0, len(bad_t) - 1), np.clip(index, 0, len(bad_t) - 1)
        left_nearer = np.abs(bad_t[left] - instants) <= np.abs(bad_t[right] - instants)
        pick = np.where(left_nearer, left, right)
        nearer = np.abs(bad_t[pick] - instants) < distance
        out[nearer] = self._bad_v[sensor][pick[nearer]]
        valid[nearer] = True

    def _prune(self) -> None:
        """Forget samples no future instant can need (keep two before the earliest)."""
        if len(self._pending):
            earliest = int(self._pending[0])
        elif self.timebase.reference_rate_hz:
            earliest = int(np.floor(self._grid_next_ns()))
        else:  # the next reference instant is a later stamp of sensor 1
            earliest = int(self._last[0] or 0) + 1
        for sensor in range(N_SENSORS):
            t = self._t[sensor]
            keep_from = max(int(t.searchsorted(earliest, side='left')) - 2, 0)
            if keep_from:
                self._t[sensor], self._v[sensor] = t[keep_from:], self._v[sensor][keep_from:]
            if not len(self._bad_t[sensor]):
                continue
            # A refused reading older than every good sample kept can be no instant's nearest.
            bad_from = int(self._bad_t[sensor].searchsorted(self._t[sensor][0]))
            if bad_from:
                self._bad_t[sensor] = self._bad_t[sensor][bad_from:]
                self._bad_v[sensor] = self._bad_v[sensor][bad_from:]

    def _grid_next_ns(self) -> float:
        return (self._grid_next or 0) * NS_PER_S / self.timebase.reference_rate_hz

    def finish(self) -> None:
        """The recording has ended: the reference instants still waiting (some sensor's stream
        stopped before them) are counted in ``skipped_end`` and forgotten."""
        self.counters.skipped_end += len(self._pending)
        self._pending = np.zeros(0, np.int64)
        lasts = [last for last in self._last if last is not None]
        if self.timebase.reference_rate_hz and self._grid_next is not None and lasts:
            period = NS_PER_S / self.timebase.reference_rate_hz
            self.counters.skipped_end += max(
                int(np.floor(max(lasts) / period)) + 1 - self._grid_next, 0
            )
            self._grid_next = int(np.floor(max(lasts) / period)) + 1

    # ----------------------------------------------------------------- reports

    @property
    def pending(self) -> int:
        """Reference instants waiting for a sensor's next sample."""
        return len(self._pending)

    def clocks(self) -> tuple[ClockEstimate, ...]:
        """Each sensor's offset and jitter against the reference instants, and its rate."""
        result = []
        for sums in self._sums:
            variance = sums.m2 / (sums.count - 1) if sums.count > 1 else 0.0
            period = sums.period_ns()
            result.append(
                ClockEstimate(
                    offset_s=sums.mean_ns * S_PER_NS,
                    jitter_s=float(np.sqrt(variance)) * S_PER_NS,
                    rate_hz=NS_PER_S / period if period else 0.0,
                    n=sums.count,
                )
            )
        return tuple(result)
