"""The simulated vehicle's own recorded signals: its temperature and its currents per
channel (the battery's ``/battery_state`` and one BatteryState per thruster).

Currents are in the sign of ``sensor_msgs/BatteryState.current``: negative while the
battery discharges. Each thruster draws

    ``I_k(t) = idle + speed v^2 + activity . |w| + turn w_yaw + steps_k(t)``, at most 0,

with ``v`` the speed through the water (m/s), ``w`` the (yaw, pitch, roll) rates (deg/s):
propulsion power rises with the square of the speed, and the control of a turn, a roll or a
pitch oscillation costs current in proportion to its rate (``turn``: the signed part of a
turn, differential thrust, opposite on the port and starboard thrusters); the steps are
random levels held for ``step_s`` and changed over ``ramp_s`` (commanded changes). An ESC
does not charge the battery: the current is never positive. The battery carries the sum of
the thrusters plus the hotel load (payload, electronics): :class:`CurrentProfile`'s
random levels every ``step_s`` seconds, linearly joined, which without thrusters is the
whole battery current (as scenarios had it before there were thrusters).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._validate import require_positive
from .types import FloatArray

#: The battery's BatteryState topic (``io.conversions.BATTERY_TOPIC``).
BATTERY_TOPIC = '/battery_state'


@dataclass(frozen=True)
class TemperatureProfile:
    """``T(t) = mean + ramp * t / duration + amplitude * sin(2 pi t / period)``, degC."""

    mean_c: float = 10.0
    ramp_c: float = 4.0
    amplitude_c: float = 1.0
    period_s: float = 437.0

    def __call__(self, t: np.ndarray, duration_s: float) -> np.ndarray:
        return (
            self.mean_c
            + self.ramp_c * t / max(duration_s, 1e-9)
            + self.amplitude_c * np.sin(2 * np.pi * t / self.period_s)
        )


@dataclass(frozen=True)
class Thruster:
    """One thruster's current channel (see the module for the model), A and the units in
    the names; ``topic`` is its BatteryState topic. ``activity_a_per_deg_s`` weighs the
    (yaw, pitch, roll) rates' magnitudes, ``turn_a_per_deg_s`` the signed yaw rate."""

    topic: str
    idle_a: float = -0.5
    speed_a_per_m2_s2: float = -2.0
    activity_a_per_deg_s: tuple[float, float, float] = (-0.08, -0.05, -0.05)
    turn_a_per_deg_s: float = 0.0
    step_amplitude_a: float = 1.0
    step_s: float = 20.0
    ramp_s: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.topic, str) or not self.topic.startswith('/'):
            raise InputError(
                f'a thruster topic must be a name starting with /, got {self.topic!r}'
            )
        require_positive(f'Thruster {self.topic}', step_s=self.step_s, ramp_s=self.ramp_s)
        activity = tuple(float(v) for v in self.activity_a_per_deg_s)
        if len(activity) != 3:
            raise InputError(
                f'Thruster {self.topic}: activity_a_per_deg_s needs 3 values (yaw, pitch, '
                f'roll), got {self.activity_a_per_deg_s!r}'
            )
        object.__setattr__(self, 'activity_a_per_deg_s', activity)
        values = (self.idle_a, self.speed_a_per_m2_s2, self.turn_a_per_deg_s, *activity)
        if not np.all(np.isfinite(values)) or not self.step_amplitude_a >= 0:
            raise InputError(f'Thruster {self.topic}: values must be finite, amplitude >= 0')
        if self.ramp_s >= self.step_s:
            raise InputError(f'Thruster {self.topic}: ramp_s must be shorter than step_s')


@dataclass(frozen=True)
class CurrentProfile:
    """The vehicle's currents, A (negative while discharging): the hotel load, a base
    plus random levels every ``step_s`` seconds linearly joined (seeded by the scenario),
    and the ``thrusters``' channels. Without thrusters the hotel load is the battery
    current; with them the battery carries their sum too."""

    base_a: float = -8.0
    step_amplitude_a: float = 6.0
    step_s: float = 15.0
    thrusters: tuple[Thruster, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, 'thrusters', tuple(self.thrusters))
        topics = self.topics
        if len(set(topics)) != len(topics):
            raise InputError(f'current channels must have distinct topics, got {list(topics)}')

    @property
    def topics(self) -> tuple[str, ...]:
        """The BatteryState topics of the current channels: the battery's first."""
        return (BATTERY_TOPIC, *(thruster.topic for thruster in self.thrusters))


#: The kinematics a thruster's current follows at given instants: ``(speed (N,) m/s,
#: (yaw, pitch, roll) rates (N, 3) deg/s)``.
Kinematics = Callable[[], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Currents:
    """A mission's current channels, drawn once (:func:`draw_currents`) and evaluated at
    any instants."""

    profile: CurrentProfile
    hotel: tuple[np.ndarray, np.ndarray]
    steps: tuple[tuple[np.ndarray, np.ndarray], ...]

    def __call__(self, t: np.ndarray, kinematics: Kinematics) -> FloatArray:
        """Currents (N, m) A at instants ``t`` (s): the battery's first, then each
        thruster's; ``kinematics`` is asked only when there are thrusters."""
        hotel = np.interp(t, *self.hotel)
        if not self.profile.thrusters:
            return hotel[:, None]
        speed, rates = kinematics()
        columns = []
        for thruster, steps in zip(self.profile.thrusters, self.steps, strict=True):
            current = (
                thruster.idle_a
                + thruster.speed_a_per_m2_s2 * speed**2
                + np.abs(rates) @ np.asarray(thruster.activity_a_per_deg_s)
                + thruster.turn_a_per_deg_s * rates[:, 0]
                + np.interp(t, *steps)
            )
            columns.append(np.minimum(current, 0.0))
        thrusters = np.column_stack(columns)
        return np.column_stack([hotel + thrusters.sum(axis=1), thrusters])


def draw_currents(
    profile: CurrentProfile, duration_s: float, rng: np.random.Generator
) -> Currents:
    """The random parts of the currents: the hotel load's levels (drawn first, as a
    scenario without thrusters always drew them), then each thruster's steps."""
    knots = np.arange(0.0, duration_s + 2 * profile.step_s, profile.step_s) - profile.step_s
    levels = profile.base_a + profile.step_amplitude_a * rng.uniform(-1.0, 1.0, len(knots))
    steps = []
    for thruster in profile.thrusters:
        starts = np.arange(0.0, duration_s + 2 * thruster.step_s, thruster.step_s)
        starts -= thruster.step_s
        held = thruster.step_amplitude_a * rng.uniform(-1.0, 1.0, len(starts))
        # Level k from starts[k] + ramp to starts[k + 1], ramped from level k - 1 before.
        times = np.column_stack([starts, starts + thruster.ramp_s]).ravel()[1:]
        values = np.column_stack([np.roll(held, 1), held]).ravel()[1:]
        steps.append((times, values))
    return Currents(profile, (knots, levels), tuple(steps))
