"""Sensor clocks: when each of the four magnetometers samples, and which of its messages arrive.

A real array samples each sensor on its own clock: a constant offset from sensor 1, white
timing jitter, a small rate error (drift, ppm) or a different rate altogether, and a few
messages lost on the way. :class:`SensorClocks` describes that; :func:`sample_instants` and
:func:`kept_messages` draw one realisation from the caller's generator, and
:class:`SensorStream` holds one sensor's stamped readings. Times are the true sample times, in
seconds from the mission start (header stamps carry them); sensor index 0 is sensor 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from ._validate import as_array, frozen_array
from .types import ArrayLike, FloatArray

#: Largest accepted ``loss_fraction`` (exclusive): beyond it a stream is mostly gaps.
MAX_LOSS_FRACTION = 0.5
#: Jitter tails drawn beyond the mission's ends, in jitter standard deviations: instants
#: whose nominal time is further out than this cannot fall inside the mission.
_JITTER_REACH = 8.0
#: Rounding tolerance at the mission's end, in sample periods: an instant that lands on
#: ``duration`` up to this (nominally the first instant after the mission) is not taken.
_END_TOLERANCE = 1e-9
#: ppm -> relative rate error.
_PER_PPM = 1e-6


def _zeros() -> FloatArray:
    return np.zeros(4)


def _per_sensor(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a read-only (4,) array: a scalar is broadcast to the four sensors."""
    array = np.asarray(value, dtype=float)
    if array.ndim == 0:
        array = np.full(4, float(array))
    return frozen_array(array, f'SensorClocks.{name}', (4,))


@dataclass(frozen=True)
class SensorClocks:
    """Each sensor's sampling clock; every attribute is per sensor, (4,), or a scalar for all.

    Sensor ``s`` samples at ``t_s[k] = offset_s[s] + k / (rate_s (1 + drift_ppm[s] 1e-6))``
    plus Gaussian jitter, for every ``k = 0, 1, ...`` with ``0 <= t_s[k] < duration``.

    Attributes
    ----------
    offset_s : (4,) s
        Each sensor's first instant (``k = 0``) relative to the start of sensor 1's grid, of
        any size and sign: beyond a period it is a late start, and instants before 0 are not
        taken. Default 0.
    jitter_s : (4,) s
        RMS of the white timing jitter of each sample, >= 0. Default 0.
    drift_ppm : (4,) ppm
        Rate error of each clock: its rate is ``rate (1 + drift_ppm 1e-6)``. Default 0.
    rate_hz : (4,) Hz or None
        Nominal rate of each sensor, > 0; None: the scenario's ``sample_rate_hz`` for all.
    loss_fraction : (4,)
        Probability that a message of the sensor is lost, in [0, 0.5). Default 0.

    Raises
    ------
    InputError
        Naming the attribute: a shape other than () or (4,), a non-finite value, negative
        jitter, a non-positive rate (also after drift), or a loss fraction outside [0, 0.5).
    """

    offset_s: FloatArray = field(default_factory=_zeros)
    jitter_s: FloatArray = field(default_factory=_zeros)
    drift_ppm: FloatArray = field(default_factory=_zeros)
    rate_hz: FloatArray | None = None
    loss_fraction: FloatArray = field(default_factory=_zeros)

    def __post_init__(self) -> None:
        for name in ('offset_s', 'jitter_s', 'drift_ppm', 'rate_hz', 'loss_fraction'):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _per_sensor(getattr(self, name), name))
        if np.any(self.jitter_s < 0):
            raise InputError(f'SensorClocks.jitter_s must be >= 0, got {self.jitter_s}')
        if self.rate_hz is not None and not np.all(self.rate_hz > 0):
            raise InputError(f'SensorClocks.rate_hz must be positive, got {self.rate_hz}')
        if not np.all(1.0 + self.drift_ppm * _PER_PPM > 0):
            raise InputError(f'SensorClocks.drift_ppm must be above -1e6, got {self.drift_ppm}')
        loss = self.loss_fraction
        if not np.all((loss >= 0) & (loss < MAX_LOSS_FRACTION)):
            raise InputError(
                f'SensorClocks.loss_fraction must be in [0, {MAX_LOSS_FRACTION}), got {loss}'
            )

    def rates(self, sample_rate_hz: float) -> FloatArray:
        """Actual sampling rate of each sensor (4,) Hz: nominal (``rate_hz``, or
        ``sample_rate_hz`` for all) times ``1 + drift_ppm 1e-6``."""
        nominal = np.full(4, float(sample_rate_hz)) if self.rate_hz is None else self.rate_hz
        return nominal * (1.0 + self.drift_ppm * _PER_PPM)


@dataclass(frozen=True)
class SensorStream:
    """One sensor's messages as logged: stamps and readings.

    Attributes
    ----------
    t : (n,) s
        True sample instants from the mission start (the header stamps), increasing.
    fields : (n, 3) T
        The sensor's readings at ``t``, body frame (measured: interference, effects, noise).
    """

    t: FloatArray
    fields: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, 't', as_array(self.t, 'SensorStream.t', (None,)))
        object.__setattr__(self, 'fields', as_array(self.fields, 'SensorStream.fields', (None, 3)))
        if len(self.t) != len(self.fields):
            raise InputError(
                f'SensorStream: {len(self.t)} instants but {len(self.fields)} readings'
            )

    def __len__(self) -> int:
        return len(self.t)

    def within(self, start_s: float, end_s: float) -> SensorStream:
        """The messages with ``start_s <= t <= end_s`` (s)."""
        keep = (self.t >= start_s) & (self.t <= end_s)
        return SensorStream(self.t[keep], self.fields[keep])


def sample_instants(
    clocks: SensorClocks, sample_rate_hz: float, duration_s: float, rng: np.random.Generator
) -> tuple[FloatArray, ...]:
    """The true sample instants of the four sensors within ``[0, duration_s)``.

    Parameters
    ----------
    clocks : SensorClocks
    sample_rate_hz : float
        Nominal rate, Hz, of the sensors whose ``clocks.rate_hz`` is None.
    duration_s : float
        Mission length, s.
    rng : numpy.random.Generator
        Source of the jitter (drawn for sensor 1, 2, 3, 4 in turn; nothing is drawn for a
        sensor without jitter).

    Returns
    -------
    tuple of four (n_s,) arrays, s, strictly increasing
    """
    instants = []
    for rate, offset, jitter in zip(
        clocks.rates(sample_rate_hz), clocks.offset_s, clocks.jitter_s, strict=True
    ):
        reach = _JITTER_REACH * jitter
        first = max(0, int(np.ceil((-reach - offset) * rate)))
        last = int(np.floor((duration_s + reach - offset) * rate))
        k = np.arange(first, last + 1, dtype=float)
        t = offset + k / rate
        if jitter > 0:
            # Sorted, not clipped: the set of instants keeps its Gaussian jitter and only the
            # labels k of two swapped instants change (never, for jitter << period); clipping
            # would pile instants up at the clip bounds. Ties have probability zero.
            t = np.sort(t + rng.normal(0.0, jitter, len(t)))
        instants.append(t[(t >= 0.0) & (t < duration_s - _END_TOLERANCE / rate)])
    return tuple(instants)


def kept_messages(
    clocks: SensorClocks, counts: tuple[int, ...], rng: np.random.Generator
) -> tuple[npt.NDArray[np.bool_], ...]:
    """Which messages of each sensor arrive: each of the ``counts[s]`` is lost independently
    with probability ``clocks.loss_fraction[s]`` (nothing is drawn for a loss-free sensor).

    Returns
    -------
    tuple of four bool (counts[s],) arrays, True where the message arrives
    """
    return tuple(
        rng.random(n) >= loss if loss > 0 else np.ones(n, dtype=bool)
        for loss, n in zip(clocks.loss_fraction, counts, strict=True)
    )


def select_streams(
    streams: tuple[SensorStream, ...], t: FloatArray, selected: FloatArray
) -> tuple[SensorStream, ...]:
    """The streams' messages within the span of the ``selected`` instants of sensor 1, widened
    by half of sensor 1's median period (taken on all its instants ``t``, s); no messages when
    nothing is selected."""
    if len(selected) == 0:
        return tuple(stream.within(np.inf, -np.inf) for stream in streams)
    half = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    start, end = float(np.min(selected)) - half, float(np.max(selected)) + half
    return tuple(stream.within(start, end) for stream in streams)
