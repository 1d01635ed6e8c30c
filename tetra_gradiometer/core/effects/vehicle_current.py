"""Vehicle currents: the field of the currents drawn from the battery (thrusters, payload)
along the vehicle's wiring. By Biot-Savart it is proportional to each current: sensor ``s``
reads ``V_s I(t)`` more, ``V_s`` (3, m) T/A for the ``m`` current channels (the battery's
``/battery_state``, and one BatteryState per thruster ESC where the vehicle reports them:
each circuit runs its own path, so each has its own ``V``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..types import FloatArray
from ..units import NT_PER_T, T_PER_NT
from .base import CURRENT_PREFIX, Channels, Effect, LiveRegressor
from .simulation import EffectSpec, Truth


class _Live(LiveRegressor):
    """The channel values of the sample: no history to keep."""

    def __init__(self, inputs: tuple[str, ...]) -> None:
        self.inputs = inputs

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        return np.array([values.get(name, np.nan) for name in self.inputs], dtype=float)

    def reset(self) -> None:
        return None


class VehicleCurrent(Effect):
    name = 'vehicle_current'
    physics = (
        'The field of the currents drawn from the battery (thrusters, payload) along the '
        "vehicle's wiring: by Biot-Savart proportional to each current, V_i I(t) per sensor "
        'with I from each recorded sensor_msgs/BatteryState (the battery and, where reported, '
        'each thruster), V_i in nT/A per sensor, axis and current.'
    )
    file_unit = 'nT/A'
    file_factor = NT_PER_T
    separated_by = (
        'current changes at steady attitude and temperature (thruster steps during a straight leg)'
    )

    def inputs(self, available: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(sorted(name for name in available if name.startswith(CURRENT_PREFIX)))

    def missing(self, available: tuple[str, ...]) -> str:
        if self.inputs(available):
            return ''
        return 'a current (sensor_msgs/BatteryState: /battery_state, or --current-topics)'

    def labels(self, inputs: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(f'I[{name.removeprefix(CURRENT_PREFIX)}]_A' for name in inputs)

    def regressors(
        self, channels: Channels, inputs: tuple[str, ...], reference: tuple[float, ...]
    ) -> FloatArray:
        return np.column_stack([np.asarray(channels.series[name], float) for name in inputs])

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        return _Live(inputs)

    #: (4, 3, m) T/A: sensor, axis, current channel (the battery's first, then the
    #: scenario's thrusters); (4, 3) is the battery's alone.
    simulation = EffectSpec((4, 3, None), 'T/A', 'nT_per_A', T_PER_NT, also=((4, 3),))

    def simulated_regressors(self, truth: Truth) -> FloatArray:
        """The true current of every channel (N, m) A, in the scenario's order."""
        names = [name for name in truth.series if name.startswith(CURRENT_PREFIX)]
        return np.column_stack([np.asarray(truth.series[name], float) for name in names])
