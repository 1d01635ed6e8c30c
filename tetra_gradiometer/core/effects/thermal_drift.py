"""Thermal drift: the fluxgates' offsets (and the hard iron near them) change with the
temperature of the electronics and the housing, ``c_s (T - T_ref)`` per sensor ``s`` and
axis, ``c_s`` in T/degC, ``T`` from ``/tetra/temperature``.

``T_ref`` is the mean temperature of the calibration window, fixed in the term: a drift
``c (T - T_ref)`` and the hard iron ``b`` trade a constant, so compensation must use the
``T_ref`` the fit used.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..types import FloatArray
from ..units import NT_PER_T, T_PER_NT
from .base import TEMPERATURE, Channels, Effect, LiveRegressor
from .simulation import EffectSpec, Truth


class _Live(LiveRegressor):
    """The channel values of the sample: no history to keep."""

    def __init__(self, reference_c: float) -> None:
        self.reference_c = reference_c

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        return np.array([values.get(TEMPERATURE, np.nan) - self.reference_c])

    def reset(self) -> None:
        return None


class ThermalDrift(Effect):
    name = 'thermal_drift'
    physics = (
        'Offsets of the fluxgates (and of the hard iron near them) that change with the '
        'temperature of the electronics and the housing: c_i (T - T_ref) with the temperature '
        'from /tetra/temperature, c_i in nT/degC per sensor and axis.'
    )
    file_unit = 'nT/degC'
    file_factor = NT_PER_T
    separated_by = (
        'a temperature change while the attitude and the current stay steady (or a run '
        'whose temperature does not follow its manoeuvres)'
    )
    arbitrary_zero = True

    def inputs(self, available: tuple[str, ...]) -> tuple[str, ...]:
        return (TEMPERATURE,) if TEMPERATURE in available else ()

    def missing(self, available: tuple[str, ...]) -> str:
        return '' if TEMPERATURE in available else 'the temperature (/tetra/temperature)'

    def labels(self, inputs: tuple[str, ...]) -> tuple[str, ...]:
        return ('T-T_ref_degC',)

    def reference(self, channels: Channels, inputs: tuple[str, ...]) -> tuple[float, ...]:
        return (float(np.nanmean(channels.series[TEMPERATURE])),)

    def regressors(
        self, channels: Channels, inputs: tuple[str, ...], reference: tuple[float, ...]
    ) -> FloatArray:
        return (np.asarray(channels.series[TEMPERATURE], float) - reference[0])[:, None]

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        return _Live(reference[0])

    #: (4, 3) T/degC: sensor, axis.
    simulation = EffectSpec((4, 3), 'T/degC', 'nT_per_degC', T_PER_NT)

    def simulated_regressors(self, truth: Truth) -> FloatArray:
        """The true temperature's excess over the drift's zero, (N, 1) degC."""
        temperature = np.asarray(truth.series[TEMPERATURE], float)
        return (temperature - truth.temperature_reference_c)[:, None]
