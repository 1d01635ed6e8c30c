"""Eddy currents induced in the conducting hull and pressure housings by the change of the
field they see as the vehicle turns. By Lenz their field opposes the change and, for a hull
whose time constant is short against the manoeuvre, it is proportional to the rate of
change of the body-frame background field: sensor ``s`` reads ``E_s dB^b/dt`` more, with a
general 3x3 ``E_s`` in seconds (the Tolles-Lawson eddy term).

The rate is that of the measured reference reading ``B_1'`` (the paper's ``B^b``), so the
effect needs no recorded channel. A noisy stream is differentiated **causally**, the same
way offline and live: the slope at each sample of a least-squares quadratic through the
samples of the last ``window_s`` seconds (the sample itself included), evaluated at the
sample (no delay for a field whose rate changes linearly over the window; a centred
difference would need the future, which a node does not have). With fewer than three
samples in the window a line is used. The rate is unknown (NaN) where the window holds a
**break**, the same offline and live: the first sample (a recording's, a restarted
replay's), a sample after a loss (:mod:`.losses`: a node's lost set, a gap of the
recording) and, for the reference reading, a jump (a change between two samples faster
than the field can turn, :data:`MAX_TURN_RATE_RAD_S`: a recording joined from pieces, a
glitch). So every rate is a full window's: a window short of its samples errs by
``B'' h / 2`` from a line (2.5-9.6 noise floors on a 20 Hz trim after a lost set, and a
live rate where the offline one had none).

The window is fixed when the term is fitted (its reference value): :data:`WINDOW_PERIODS`
sample periods of the calibration data, at least :data:`MIN_WINDOW_S`. It trades the fit's
error, ~``W^2`` times the field's third derivative (8 periods biased ``E`` by ~5 of its
sigma on a 2-minute trim at 50 Hz; 4 periods by ~1), against the rate's noise, ~6 nT/s at
100 Hz for 0.05 nT sensors, which times ``E`` ~ 3e-4 s is 2e-3 nT: a twentieth of the
sensor noise.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import numpy as np

from ..types import FloatArray
from .base import Channels, Effect, LiveRegressor
from .losses import LOSS_FACTOR, USUAL_INTERVALS, after_loss, usual_interval
from .simulation import EffectSpec, Truth

#: The pseudo-channel of the reference reading's rate (always available: it is computed).
REFERENCE_RATE = 'reference_rate'
#: The fastest the body-frame field can turn, rad/s: a rate above this times ``|B_1'|`` is
#: not the vehicle turning but a jump of the reading (a recording joined from pieces, a
#: glitch) and is unknown (NaN), never an eddy field of thousands of nT.
MAX_TURN_RATE_RAD_S = 2.0
#: The differentiation window in sample periods, and its floor, s.
WINDOW_PERIODS = 4
MIN_WINDOW_S = 0.02


def window_for(t_s: np.ndarray) -> float:
    """The differentiation window for samples at ``t_s`` (N,) s."""
    steps = np.diff(np.asarray(t_s, dtype=float))
    period = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
    return max(MIN_WINDOW_S, WINDOW_PERIODS * period)


def causal_rate(
    t_s: np.ndarray, values: np.ndarray, window_s: float, breaks: np.ndarray | None = None
) -> FloatArray:
    """The causal rate of ``values`` (N, k) at ``t_s`` (N,) s: the slope at each sample of
    the least-squares quadratic through the samples within ``window_s`` before it (itself
    included); units of ``values`` per second; NaN where the window holds a break (the first
    sample, one after a loss, and where ``breaks`` (N,) is True: see the module)."""
    t_s = np.asarray(t_s, dtype=float)
    values = np.asarray(values, dtype=float)
    n = len(t_s)
    start = np.searchsorted(t_s, t_s - window_s, side='right')
    count = np.arange(n) - start + 1
    lags = int(count.max()) if n else 0
    # Sums over the window of tau^p (p = 0..4) and tau^p y (p = 0..2), tau = t - t_n and
    # y = values - values_n (small numbers: no cancellation), one lag at a time.
    s = np.zeros((n, 5))
    r = np.zeros((n, 3, values.shape[1]))
    for lag in range(lags):
        inside = count > lag
        idx = np.flatnonzero(inside)
        tau = t_s[idx - lag] - t_s[idx]
        y = values[idx - lag] - values[idx]
        powers = tau[:, None] ** np.arange(5)
        s[idx] += powers
        r[idx] += powers[:, :3, None] * y[:, None, :]
    rate = _slopes(s, r, count)
    if n:
        flagged = after_loss(t_s)
        flagged[0] = True
        if breaks is not None:
            flagged |= np.asarray(breaks, dtype=bool)
        last_break = np.maximum.accumulate(np.where(flagged, np.arange(n), -1))
        rate[last_break >= start] = np.nan
    return rate


def _slopes(s: np.ndarray, r: np.ndarray, count: np.ndarray) -> FloatArray:
    """The fitted slope at tau = 0 from the window sums (see :func:`causal_rate`)."""
    n, k = len(count), r.shape[2]
    out = np.full((n, k), np.nan)
    quad = count >= 3
    normal = np.stack([s[:, 0:3], s[:, 1:4], s[:, 2:5]], axis=1)  # (n, 3, 3)
    if np.any(quad):
        det = np.linalg.det(normal[quad])
        ok = np.flatnonzero(quad)[np.abs(det) > 0]
        coef = np.linalg.solve(normal[ok], r[ok])  # (m, 3, k)
        out[ok] = coef[:, 1]
    line = (count == 2) | (quad & ~np.isfinite(out[:, 0]))
    if np.any(line):
        # Two samples (or a degenerate quadratic): the line through the window's points.
        cov = s[line, 0] * s[line, 2] - s[line, 1] ** 2
        good = cov > 0
        slope = (s[line, 0, None] * r[line, 1] - s[line, 1, None] * r[line, 0]) / np.where(
            good, cov, 1.0
        )[:, None]
        slope[~good] = np.nan
        out[line] = slope
    return out


def jumps(t_s: np.ndarray, b_reference: np.ndarray) -> np.ndarray:
    """(N,) True where the reading changed from the previous sample faster than the field
    can turn (:data:`MAX_TURN_RATE_RAD_S`): a jump, not a turn."""
    out = np.zeros(len(t_s), dtype=bool)
    if len(t_s) > 1:
        step = np.linalg.norm(np.diff(b_reference, axis=0), axis=1)
        dt = np.diff(t_s)
        limit = MAX_TURN_RATE_RAD_S * np.linalg.norm(b_reference[1:], axis=1) * dt
        out[1:] = step > limit
    return out


class LiveRate:
    """:func:`causal_rate` one sample at a time (a node's path): the samples of the last
    ``window_s`` seconds are kept, and the intervals that judge a loss."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.history: deque[tuple[float, np.ndarray]] = deque()
        self.intervals: deque[float] = deque(maxlen=USUAL_INTERVALS)
        self.last_t: float | None = None
        self.break_t = -np.inf  # the last break's time, s

    def push(self, t_s: float, value: np.ndarray, brk: bool = False) -> FloatArray:
        """The rate (k,) per second at ``t_s`` of ``value`` (k,), this sample included; NaN
        while the window holds a break (``brk``: this sample is one besides a start or a
        loss)."""
        value = np.asarray(value, dtype=float)
        if self.last_t is not None and t_s <= self.last_t:
            self.reset()  # time went back: a restarted replay
        if self.last_t is None:
            brk = True
        else:
            interval = t_s - self.last_t
            previous = np.full((1, USUAL_INTERVALS), np.nan)
            previous[0, : len(self.intervals)] = self.intervals
            brk = brk or bool(interval > LOSS_FACTOR * usual_interval(previous)[0])
            self.intervals.append(interval)
        self.last_t = t_s
        if brk:
            self.break_t = t_s
        self.history.append((t_s, value))
        while self.history and self.history[0][0] <= t_s - self.window_s:
            self.history.popleft()
        if self.break_t > t_s - self.window_s:
            return np.full(len(value), np.nan)
        t = np.array([item[0] for item in self.history])
        tau = t - t_s
        powers = tau[:, None] ** np.arange(5)
        s = powers.sum(axis=0)[None]
        values = np.array([item[1] for item in self.history])
        r = (powers[:, :3, None] * (values - value)[:, None, :]).sum(axis=0)[None]
        return _slopes(s, r, np.array([len(t)]))[0]

    def reset(self) -> None:
        self.history.clear()
        self.intervals.clear()
        self.last_t, self.break_t = None, -np.inf


class _Live(LiveRegressor):
    def __init__(self, window_s: float) -> None:
        self.rate = LiveRate(window_s)
        self.last: tuple[float, np.ndarray] | None = None

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        b_reference = np.asarray(b_reference, dtype=float)
        jump = self.last is not None and t_s > self.last[0] and bool(
            jumps(np.array([self.last[0], t_s]), np.stack([self.last[1], b_reference]))[1]
        )
        self.last = (t_s, b_reference)
        return self.rate.push(t_s, b_reference, jump)

    def reset(self) -> None:
        self.rate.reset()
        self.last = None


class EddyCurrent(Effect):
    name = 'eddy_current'
    physics = (
        'Eddy currents induced in the conducting hull and pressure housings by the change of '
        'the field they see as the vehicle turns; by Lenz their field opposes the change and, '
        'for a hull whose time constant is short against the manoeuvre, is proportional to '
        'the rate of change of the body-frame background field: E_i dB^b/dt with a general '
        "3x3 E_i (seconds) per sensor (the Tolles-Lawson eddy term); the rate is B_1''s, "
        'differentiated causally.'
    )
    file_unit = 's'
    file_factor = 1.0
    separated_by = (
        'turns about different axes at different rates (a general 3x3 response to the '
        "field rate; a delay is isotropic and also follows the field's curvature, which "
        'fast, short manoeuvres bring out)'
    )

    def inputs(self, available: tuple[str, ...]) -> tuple[str, ...]:
        return (REFERENCE_RATE,)

    def missing(self, available: tuple[str, ...]) -> str:
        return ''

    def labels(self, inputs: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(f'dB1{axis}/dt_T_per_s' for axis in 'xyz')

    def reference(self, channels: Channels, inputs: tuple[str, ...]) -> tuple[float, ...]:
        return (window_for(channels.t_s),)

    def regressors(
        self, channels: Channels, inputs: tuple[str, ...], reference: tuple[float, ...]
    ) -> FloatArray:
        t_s, b_reference = channels.t_s, channels.b_reference
        return causal_rate(t_s, b_reference, reference[0], jumps(t_s, b_reference))

    def history_s(self, reference: tuple[float, ...]) -> float:
        return reference[0]

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        return _Live(reference[0])

    #: (4, 3, 3) s: sensor, axis of the field, axis of the rate (``E_s``).
    simulation = EffectSpec((4, 3, 3), 's', 'coefficients_s')

    def simulated_regressors(self, truth: Truth) -> FloatArray:
        """The exact rate (N, 3) T/s of the clean background field at sensor 1."""
        return np.asarray(truth.reference_rate(), float)
