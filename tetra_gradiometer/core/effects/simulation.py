"""What the simulator needs from an effect: how a scenario gives its per-sensor
coefficients (:class:`EffectSpec`) and what the simulator knows exactly when it adds the
effect's field (:class:`Truth`).

An effect's physics in the simulator is :meth:`~.base.Effect.simulate`: per-sensor
coefficients ``W_s`` (3, m) times the effect's *true* regressors ``x(t)`` (m,), the exact
values of what calibration and compensation estimate from recorded channels (the true
current of each channel, the profile's temperature, the exact rate of the clean background
field at sensor 1). The simulator's own effects that are not operational terms (time skew,
a sensor's misalignment, scale factor and non-orthogonality) use :class:`EffectSpec` too, so
that :data:`tetra_gradiometer.core.simulator.EFFECT_SPECS` is one table.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from .._validate import frozen_array
from ..types import ArrayLike, FloatArray


@dataclass(frozen=True)
class EffectSpec:
    """How the simulator and a scenario file give one effect's magnitude.

    Attributes
    ----------
    shape : the value's shape in the simulator (SI); ``None`` for a size that follows the
        scenario (``vehicle_current``: one column per current channel)
    unit : the SI unit of the value
    scenario_key : the key under ``effects: {name: {key: ...}}`` of a scenario file
    scenario_factor : the factor from the file's unit (in the key's name) to SI
    also : further shapes accepted (``vehicle_current`` (4, 3): the battery's channel alone,
        as scenario files had it before there were several current channels)
    """

    shape: tuple[int | None, ...]
    unit: str
    scenario_key: str
    scenario_factor: float = 1.0
    also: tuple[tuple[int | None, ...], ...] = ()

    def check(self, value: ArrayLike, name: str) -> FloatArray:
        """``value`` as a read-only array of one of the accepted shapes, finite.

        Raises
        ------
        InputError
            Naming ``name``, the shape(s) it must have, or a non-finite entry.
        """
        array = np.asarray(value, dtype=float)
        for shape in self.also:
            fits = array.ndim == len(shape) and all(
                want is None or want == got for want, got in zip(shape, array.shape, strict=True)
            )
            if fits:
                return frozen_array(array, name, shape)
        try:
            return frozen_array(array, name, self.shape)
        except InputError as error:
            if not self.also or 'shape' not in str(error):
                raise
        wanted = ' or '.join(_text(s) for s in (self.shape, *self.also))
        raise InputError(f'{name} must have shape {wanted}, got {array.shape}')


def _text(shape: tuple[int | None, ...]) -> str:
    """``(4, 3, m)``: a shape for a message, ``m`` for a size that follows the scenario."""
    return '(' + ', '.join('m' if s is None else str(s) for s in shape) + ')'


@dataclass(frozen=True)
class Truth:
    """What the simulator knows exactly at its sample instants, SI.

    Attributes
    ----------
    t_s : (N,) s
    series : channel name -> (N,) true values: ``temperature`` degC and one
        ``current:<topic>`` A per current channel, in the scenario's order (the battery's
        first)
    reference_rate : returns the exact rate (N, 3) T/s of the clean background field at
        sensor 1, body frame (computed when an effect asks for it: it costs two more
        evaluations of the field)
    temperature_reference_c : the temperature at which the thermal drift is zero, degC
    """

    t_s: np.ndarray
    series: Mapping[str, np.ndarray]
    reference_rate: Callable[[], np.ndarray]
    temperature_reference_c: float = float('nan')


def linear_field(coefficients: ArrayLike, regressors: np.ndarray) -> FloatArray:
    """``sum_j W[s, a, j] x[n, j]``: the field (N, 4, 3) of per-sensor coefficients
    ``coefficients`` (4, 3, m) (or (4, 3) for m = 1) on regressors (N, m).

    Raises
    ------
    InputError
        The coefficients' m is not the regressors'.
    """
    w = np.asarray(coefficients, dtype=float)
    w = w.reshape(4, 3, -1)
    if w.shape[2] != regressors.shape[1]:
        raise InputError(
            f'{w.shape[2]} coefficients per sensor and axis for {regressors.shape[1]} regressors'
        )
    return np.einsum('saj,nj->nsa', w, regressors)
