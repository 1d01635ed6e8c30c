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
samples in the window a line is used, with one the rate is unknown (NaN: the first sample
of a recording, and the first after a gap longer than the window), and so is the rate of
every sample whose window holds a jump: a change between two samples faster than the field
can turn (:data:`MAX_TURN_RATE_RAD_S`; a recording joined from pieces, a glitch).

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


def causal_rate(t_s: np.ndarray, values: np.ndarray, window_s: float) -> FloatArray:
    """The causal rate of ``values`` (N, k) at ``t_s`` (N,) s: the slope at each sample of
    the least-squares quadratic through the samples within ``window_s`` before it (itself
    included); units of ``values`` per second; NaN where unknown (see the module)."""
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
    return _slopes(s, r, count)


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


def jump_free_rate(t_s: np.ndarray, b_reference: np.ndarray, window_s: float) -> FloatArray:
    """:func:`causal_rate` of ``b_reference`` with NaN where the window holds a jump
    (:func:`jumps`): the rate across it would be the jump's, not the vehicle's."""
    rate = causal_rate(t_s, b_reference, window_s)
    start = np.searchsorted(t_s, t_s - window_s, side='right')
    flagged = np.concatenate([[0], np.cumsum(jumps(t_s, b_reference))])
    # A jump at sample j lies in the window of n when start[n] < j <= n.
    inside = flagged[np.arange(len(t_s)) + 1] - flagged[np.minimum(start + 1, len(t_s))] > 0
    rate[inside] = np.nan
    return rate


class LiveRate:
    """:func:`causal_rate` one sample at a time (a node's path): the samples of the last
    ``window_s`` seconds are kept."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.history: deque[tuple[float, np.ndarray]] = deque()

    def push(self, t_s: float, value: np.ndarray) -> FloatArray:
        """The rate (k,) per second at ``t_s`` of ``value`` (k,), this sample included."""
        value = np.asarray(value, dtype=float)
        if self.history and t_s <= self.history[-1][0]:
            self.history.clear()  # time went back: a restarted replay
        self.history.append((t_s, value))
        while self.history and self.history[0][0] <= t_s - self.window_s:
            self.history.popleft()
        t, values = self.window()
        tau = t - t_s
        powers = tau[:, None] ** np.arange(5)
        s = powers.sum(axis=0)[None]
        r = (powers[:, :3, None] * (values - value)[:, None, :]).sum(axis=0)[None]
        return _slopes(s, r, np.array([len(t)]))[0]

    def window(self) -> tuple[np.ndarray, np.ndarray]:
        """The kept samples: times (n,) s and values (n, k)."""
        return (
            np.array([item[0] for item in self.history]),
            np.array([item[1] for item in self.history]),
        )

    def reset(self) -> None:
        self.history.clear()


class _Live(LiveRegressor):
    def __init__(self, window_s: float) -> None:
        self.rate = LiveRate(window_s)

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        rate = self.rate.push(t_s, b_reference)
        if np.any(jumps(*self.rate.window())[1:]):
            rate[:] = np.nan
        return rate

    def reset(self) -> None:
        self.rate.reset()


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
        return jump_free_rate(channels.t_s, channels.b_reference, reference[0])

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        return _Live(reference[0])

    #: (4, 3, 3) s: sensor, axis of the field, axis of the rate (``E_s``).
    simulation = EffectSpec((4, 3, 3), 's', 'coefficients_s')

    def simulated_regressors(self, truth: Truth) -> FloatArray:
        """The exact rate (N, 3) T/s of the clean background field at sensor 1."""
        return np.asarray(truth.reference_rate(), float)
