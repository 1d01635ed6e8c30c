"""Recorded-style test missions with hidden effects of a chosen size (tests and bench).

``make_case`` draws a random geometry (non-regular tetrahedron), Earth field, manoeuvre,
noise and base interference, hides the named effects in random sensors, and scales each so
that its RMS contribution over the sensors it affects is ``factor x noise``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ...errors import InputError
from ..geometry import TetraGeometry
from ..simulator import (
    CurrentProfile,
    Dipole,
    Effects,
    MissionData,
    Scenario,
    SensorInterference,
    SurveyLine,
    TemperatureProfile,
    TrimManoeuvre,
    random_interference,
    simulate,
)
from ..units import NS_PER_S, NT_PER_T, S_PER_NS
from .candidate import Hidden
from .effects import CANDIDATES, LIBRARY
from .prepare import RecordedRun

Array = NDArray[np.float64]

#: The effects synthetic missions can hide: every library entry the simulator produces.
EFFECT_NAMES = tuple(c.name for c in CANDIDATES if c.simulated is not None)


@dataclass(frozen=True)
class Case:
    """A simulated mission with its truth."""

    scenario: Scenario
    mission: MissionData
    hidden: dict[str, dict[str, Any]]  # effect -> {'sensors': [...], 'rms_nT': float}

    def recording(
        self, *, odom: bool = True, temperature: bool = True, battery: bool = True
    ) -> RecordedRun:
        """The mission as a recorded run (what ``io.recording.read_recording`` would give,
        on integer-nanosecond stamps), with the optional topics left out on request."""
        m = self.mission
        missing = {}
        if not odom:
            missing['/odom'] = 'not recorded'
        if not temperature:
            missing['/tetra/temperature'] = 'not recorded'
        if not battery:
            missing['/battery_state'] = 'not recorded'
        stamps_ns = np.round(m.t * NS_PER_S).astype(np.int64)
        return RecordedRun(
            (stamps_ns - stamps_ns[0]) * S_PER_NS,
            m.fields_measured,
            m.orientation_xyzw if odom else None,
            m.temperature_c if temperature else None,
            m.current_a if battery else None,
            missing,
            dict(zip(m.current_topics[1:], m.currents_a[:, 1:].T, strict=True)) if battery else {},
            m.position_enu if odom else None,
        )


def random_geometry(rng: np.random.Generator) -> TetraGeometry:
    """A non-regular tetrahedron: edge 0.2-1 m, vertices moved up to 20 % of the edge, any
    orientation."""
    edge = rng.uniform(0.2, 1.0)
    base = TetraGeometry.regular(edge).positions
    base = base + rng.uniform(-0.2, 0.2, (4, 3)) * edge
    base = Rotation.random(random_state=rng.integers(2**31)).apply(base - base[0])
    return TetraGeometry(base + rng.uniform(-1.0, 1.0, 3))


def random_earth_field(rng: np.random.Generator) -> np.ndarray:
    """25 000-65 000 nT, inclination -75..75 deg, any declination; tesla, ENU."""
    magnitude = rng.uniform(25e-6, 65e-6)
    inc, dec = np.radians(rng.uniform(-75, 75)), rng.uniform(0, 2 * np.pi)
    return magnitude * np.array(
        [np.cos(inc) * np.sin(dec), np.cos(inc) * np.cos(dec), -np.sin(inc)]
    )


def random_trim(
    rng: np.random.Generator,
    duration_s: float,
    center: tuple[float, float, float] = TrimManoeuvre.center,
) -> TrimManoeuvre:
    """A trim manoeuvre of ``duration_s`` with random rates, amplitudes, periods and heading."""
    return TrimManoeuvre(
        duration_s=duration_s,
        center=center,
        heading_rate_deg_s=rng.choice([-1, 1]) * rng.uniform(2.0, 10.0),
        roll_amplitude_deg=rng.uniform(8, 30),
        roll_period_s=rng.uniform(7, 16),
        pitch_amplitude_deg=rng.uniform(6, 25),
        pitch_period_s=rng.uniform(10, 25),
        initial_heading_deg=rng.uniform(0, 360),
        speed_m_s=rng.uniform(0.5, 2.0),
    )


def random_segments(rng: np.random.Generator, duration_s: float) -> tuple:
    """A trim manoeuvre (random rates, amplitudes, periods), sometimes followed by a survey
    line."""
    trim_s = duration_s if rng.random() < 0.5 else duration_s * rng.uniform(0.6, 0.8)
    trim = random_trim(rng, trim_s)
    segments: tuple = (trim,)
    rest = duration_s - trim_s
    if rest > 1.0:
        speed = rng.uniform(1.0, 2.5)
        heading = rng.uniform(0, 2 * np.pi)
        start = np.array([0.0, 0.0, -50.0])
        end = start + speed * rest * np.array([np.cos(heading), np.sin(heading), 0.0])
        segments += (
            SurveyLine(
                tuple(start),
                tuple(end),
                speed_m_s=speed,
                roll_amplitude_deg=rng.uniform(0, 5),
                pitch_amplitude_deg=rng.uniform(0, 4),
            ),
        )
    return segments


def _unit_effect(name: str, rng: np.random.Generator, sensors: list[int]) -> Hidden:
    """Random terms of unit size of the library effect ``name`` in ``sensors`` (0-based)."""
    candidate = LIBRARY.get(name)
    if candidate is None or candidate.simulated is None:
        raise InputError(f'unknown effect {name!r}; synthetic cases know {list(EFFECT_NAMES)}')
    mask = np.zeros(4)
    mask[sensors] = 1.0
    return candidate.simulated.draw(rng, mask)


def _scaled(hidden: Hidden, factor: float) -> Hidden:
    inter = hidden.interference
    return Hidden(
        {name: value * factor for name, value in hidden.effects.items()},
        None
        if inter is None
        else SensorInterference(inter.k_soft * factor, inter.b_hard * factor),
    )


def _combine(a: dict[str, Array], b: dict[str, Array]) -> dict[str, Array]:
    out = dict(a)
    for name, value in b.items():
        out[name] = value if name not in out else out[name] + value
    return out


def _with_interference(
    interference: SensorInterference, extra: SensorInterference | None
) -> SensorInterference:
    if extra is None:
        return interference
    return SensorInterference(
        interference.k_soft + extra.k_soft, interference.b_hard + extra.b_hard
    )


def _fixed_sensors(name: str) -> tuple[int, ...] | None:
    simulated = LIBRARY[name].simulated if name in LIBRARY else None
    return simulated.sensors if simulated is not None else None


def make_case(
    seed: int,
    effects: tuple[str, ...] = (),
    *,
    duration_s: float = 180.0,
    factor: tuple[float, float] = (20.0, 80.0),
    noise_nT: tuple[float, float] = (0.02, 0.2),
    rate_hz: float = 10.0,
    far_target: bool | None = None,
    sensors: dict[str, list[int]] | None = None,
    near_target: bool = False,
    target_depth_m: tuple[float, float] = (20.0, 50.0),
    target_moment_am2: tuple[float, float] = (1e4, 1e5),
) -> Case:
    """A mission with ``effects`` hidden, each ``factor`` (drawn uniformly) x noise RMS over
    the sensors it affects. Sensor choice (unless ``sensors`` names them, 1-based),
    magnitudes, geometry, Earth field, manoeuvre and noise come from ``seed``.

    ``near_target``: the run is a trim manoeuvre (55-70 % of it) followed by a survey line
    that passes ``target_depth_m`` over a dipole of ``target_moment_am2`` A m^2 (any
    direction), its closest approach in the middle half of the line; drawn from a stream of
    its own, so the rest of the case is the same as without it."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(*noise_nT) * 1e-9
    interference = random_interference(
        rng, k_scale=rng.uniform(1e-3, 1e-2), b_scale_t=rng.uniform(20e-9, 300e-9)
    )
    dipoles: tuple = ()
    if far_target if far_target is not None else rng.random() < 0.3:
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2])
        position = np.array([0.0, 0.0, -50.0]) + rng.uniform(
            800.0, 2000.0
        ) * direction / np.linalg.norm(direction)
        dipoles = (Dipole(position, rng.normal(0, 2e6, 3)),)
    base = Scenario(
        geometry=random_geometry(rng),
        earth_field_enu=random_earth_field(rng),
        segments=random_segments(rng, duration_s),
        sample_rate_hz=rate_hz,
        dipoles=dipoles,
        interference=interference,
        noise_t=0.0,
        temperature=_random_temperature(rng),
        current=_random_current(rng),
    )
    if near_target:
        base = replace(
            base,
            **_target_pass(
                np.random.default_rng([seed, 4242]),
                duration_s,
                target_depth_m,
                target_moment_am2,
                dipoles,
            ),
        )
    scenario, hidden = _hide(base, seed, rng, effects, factor, noise, sensors)
    mission = simulate(scenario, np.random.default_rng(seed + 1))
    for info in hidden.values():
        info['noise_nT'] = noise * NT_PER_T
    return Case(scenario, mission, hidden)


def _hide(
    base: Scenario,
    seed: int,
    rng: np.random.Generator,
    effects: tuple[str, ...],
    factor: tuple[float, float],
    noise: float,
    sensors: dict[str, list[int]] | None,
) -> tuple[Scenario, dict[str, dict[str, Any]]]:
    """``base`` with ``effects`` hidden, each scaled to ``factor`` x ``noise`` RMS over the
    sensors it affects, and the truth per effect."""
    interference = base.interference
    clean = simulate(base, np.random.default_rng(seed + 1)).fields_measured
    total_effects: dict[str, Array] = {}
    total_inter = interference
    hidden: dict[str, dict[str, Any]] = {}
    fixed = {name: _fixed_sensors(name) for name in effects}
    free = [s for s in range(4) if not any(s in (f or ()) for f in fixed.values())]
    for name in effects:
        # Effects in different sensors (eddy_current and time_skew in one sensor are one
        # general eddy term: no data can tell them apart).
        sensors_fixed = fixed[name]
        if sensors_fixed is not None:
            chosen = list(sensors_fixed)
        elif sensors and name in sensors:
            chosen = [s - 1 for s in sensors[name]]
        else:
            size = int(rng.integers(1, 3)) if len(effects) == 1 else 1
            chosen = sorted(rng.choice(free, size=size, replace=False).tolist())
        free = [s for s in free if s not in chosen]
        unit = _unit_effect(name, rng, chosen)
        probe = replace(
            base,
            effects=Effects(**unit.effects),
            interference=_with_interference(interference, unit.interference),
        )
        delta = simulate(probe, np.random.default_rng(seed + 1)).fields_measured - clean
        unit_rms = float(np.sqrt(np.mean(delta[:, chosen] ** 2)))
        target = rng.uniform(*factor) * noise
        scaled = _scaled(unit, target / unit_rms)
        total_effects = _combine(total_effects, scaled.effects)
        total_inter = _with_interference(total_inter, scaled.interference)
        hidden[name] = {'sensors': [s + 1 for s in chosen], 'rms_nT': target * NT_PER_T}
    scenario = replace(
        base, effects=Effects(**total_effects), interference=total_inter, noise_t=noise
    )
    return scenario, hidden


def _target_pass(
    rng: np.random.Generator,
    duration_s: float,
    depth_m: tuple[float, float],
    moment_am2: tuple[float, float],
    dipoles: tuple,
) -> dict[str, Any]:
    """Segments (trim, then a survey line over a target) and the dipoles with the target added."""
    trim_s = duration_s * rng.uniform(0.55, 0.7)
    trim = random_trim(rng, trim_s, center=(2000.0, 2000.0, -40.0))
    rest = duration_s - trim_s
    speed = rng.uniform(1.0, 2.5)
    heading = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(heading), np.sin(heading), 0.0])
    start = np.array([0.0, 0.0, -40.0])
    end = start + speed * rest * direction
    line = SurveyLine(
        tuple(start),
        tuple(end),
        speed_m_s=speed,
        roll_amplitude_deg=rng.uniform(0, 3),
        pitch_amplitude_deg=rng.uniform(0, 2),
    )
    closest = start + rng.uniform(0.3, 0.7) * speed * rest * direction
    offset = rng.uniform(0.0, 0.5)  # lateral share of the distance
    distance = rng.uniform(*depth_m)
    lateral = np.array([-direction[1], direction[0], 0.0]) * rng.choice([-1, 1])
    position = closest + distance * (
        offset * lateral + np.sqrt(1 - offset**2) * np.array([0.0, 0.0, -1.0])
    )
    moment = rng.normal(size=3)
    moment *= rng.uniform(*moment_am2) / np.linalg.norm(moment)
    return {'segments': (trim, line), 'dipoles': tuple(dipoles) + (Dipole(position, moment),)}


def _random_temperature(rng: np.random.Generator) -> TemperatureProfile:
    return TemperatureProfile(
        mean_c=rng.uniform(2, 25),
        ramp_c=rng.uniform(-6, 6),
        amplitude_c=rng.uniform(0.3, 2),
        period_s=rng.uniform(60, 500),
    )


def _random_current(rng: np.random.Generator) -> CurrentProfile:
    return CurrentProfile(
        base_a=rng.uniform(-15, -3), step_amplitude_a=rng.uniform(2, 8), step_s=rng.uniform(8, 30)
    )
