"""Mission simulator: a UUV carrying the tetrahedron through trim manoeuvres and survey
lines over dipole targets in the Earth's field, with vehicle interference and noise.

Frames: world ENU (x east, y north, z up); body REP 103 (x forward, y left, z up);
attitude ``R`` rotates body vectors into the world (yaw about z from east, then pitch about
y, then roll about x: ``Rotation.from_euler('ZYX', [yaw, pitch, roll])``).

The background that magnetises the vehicle, ``B^b``, is the true (clean) field at sensor 1,
in the body frame. With a clean sensor 1 the paper's assumption ``B^b = B_1'`` is then
exact up to noise, and every modelling error comes from an effect switched on here.

The world field is ``B(x) = B_earth + G_w x`` plus the dipoles, with ``G_w`` the regional
(geological) gradient, uniform, and ``x`` the ENU position from the world origin.

Truth: ``g_true`` is eq. 7 applied to the clean, noise-free fields (what a perfect
instrument of this geometry reads: the compensation target); ``g_analytic`` is the exact
gradient at the array centroid, ``R^T (G_w + dipole gradients) R`` (it differs from
``g_true`` by the differencing truncation of the dipoles; a linear field is exact).

Sensor clocks (:mod:`.clocks`): without them the four sensors sample together at ``t``.
With them each sensor samples on its own instants; the mission's arrays are then taken at
sensor 1's instants and each sensor's own messages are in ``MissionData.streams``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ._validate import frozen_array, require_positive
from .clocks import SensorClocks, SensorStream, kept_messages, sample_instants, select_streams
from .effects import EFFECTS, TEMPERATURE, current_channel
from .effects.simulation import EffectSpec, Truth
from .fields import dipole_field, dipole_gradient, uniform_field
from .geometry import TetraGeometry, difference_tensor, to_body
from .model import SensorInterference
from .simulated_effects import ADDITIVE, EFFECT_SPECS, Effects, sensor_matrices
from .types import ArrayLike, FloatArray
from .vehicle_signals import (
    BATTERY_TOPIC,
    CurrentProfile,
    Currents,
    TemperatureProfile,
    Thruster,
    draw_currents,
)

__all__ = [
    'BATTERY_TOPIC',
    'EFFECT_SPECS',
    'CurrentProfile',
    'Dipole',
    'EffectSpec',
    'Effects',
    'MissionData',
    'Scenario',
    'SurveyLine',
    'TemperatureProfile',
    'Thruster',
    'TrimManoeuvre',
    'check_gradient_tensor',
    'random_interference',
    'simulate',
]

_DERIVATIVE_STEP_S = 1.0e-3
#: Relative tolerance (of the tensor's norm) of the regional gradient's symmetry and trace.
GRADIENT_TOLERANCE = 1e-9


def check_gradient_tensor(value: ArrayLike, name: str = 'regional_gradient_enu') -> FloatArray:
    """``value`` as a read-only (3, 3) array once checked to be the uniform gradient
    ``G[i, j] = dB_i / dx_j`` of a source-free field (symmetric, traceless).

    Parameters
    ----------
    value : array_like, shape (3, 3)
        Any unit (T/m in the core); the checks are relative to its Frobenius norm.
    name : str
        What to call it in an error message.

    Raises
    ------
    InputError
        Naming ``name``: not (3, 3) or not finite; not symmetric (a curl) or not traceless
        (a divergence) beyond :data:`GRADIENT_TOLERANCE` of its norm.
    """
    tensor = frozen_array(value, name, (3, 3))
    tolerance = GRADIENT_TOLERANCE * float(np.linalg.norm(tensor))
    curl = float(np.linalg.norm(tensor - tensor.T)) / 2
    if curl > tolerance:
        raise InputError(
            f'{name} must be symmetric: |G - G^T|/2 = {curl:.3g} > {GRADIENT_TOLERANCE:g} |G|'
        )
    trace = float(np.trace(tensor))
    if abs(trace) > tolerance:
        raise InputError(
            f'{name} must be traceless: trace = {trace:.3g}, |trace| > {GRADIENT_TOLERANCE:g} |G|'
        )
    return tensor


@dataclass(frozen=True)
class Dipole:
    """A point dipole target: ``position`` (3,) m ENU, ``moment`` (3,) A m^2 ENU."""

    position: np.ndarray
    moment: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, 'position', frozen_array(self.position, 'dipole position', (3,)))
        object.__setattr__(self, 'moment', frozen_array(self.moment, 'dipole moment', (3,)))


@dataclass(frozen=True)
class TrimManoeuvre:
    """Heading turns with roll and pitch oscillations, flown on a circle around ``center``.

    Parameters (units in the names): ``heading_rate_deg_s`` (0: straight), sinusoidal roll
    and pitch of the given amplitude and period, ``speed_m_s`` along the track.
    """

    duration_s: float
    center: tuple[float, float, float] = (0.0, 0.0, -50.0)
    heading_rate_deg_s: float = 6.0
    roll_amplitude_deg: float = 25.0
    roll_period_s: float = 11.0
    pitch_amplitude_deg: float = 20.0
    pitch_period_s: float = 17.0
    initial_heading_deg: float = 0.0
    speed_m_s: float = 1.0

    def __post_init__(self) -> None:
        require_positive(
            'TrimManoeuvre',
            duration_s=self.duration_s,
            roll_period_s=self.roll_period_s,
            pitch_period_s=self.pitch_period_s,
            speed_m_s=self.speed_m_s,
        )

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (N, 3) m and (yaw, pitch, roll) (N, 3) rad at segment-local times (s)."""
        rate = np.radians(self.heading_rate_deg_s)
        yaw = np.radians(self.initial_heading_deg) + rate * t
        center = np.asarray(self.center, dtype=float)
        if rate == 0.0:
            offset = self.speed_m_s * t[:, None] * np.array([np.cos(yaw[0]), np.sin(yaw[0]), 0.0])
        else:
            radius = self.speed_m_s / abs(rate)
            offset = radius * np.sign(rate) * np.column_stack([np.sin(yaw), -np.cos(yaw), 0 * t])
        roll = np.radians(self.roll_amplitude_deg) * np.sin(2 * np.pi * t / self.roll_period_s)
        pitch = np.radians(self.pitch_amplitude_deg) * np.sin(2 * np.pi * t / self.pitch_period_s)
        return center + offset, np.column_stack([yaw, pitch, roll])


@dataclass(frozen=True)
class SurveyLine:
    """Straight line from ``start`` to ``end`` (m, ENU) at ``speed_m_s``, heading along it,
    with optional small roll/pitch sway (sea state)."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    speed_m_s: float = 2.0
    roll_amplitude_deg: float = 0.0
    pitch_amplitude_deg: float = 0.0
    sway_period_s: float = 9.0

    def __post_init__(self) -> None:
        require_positive(
            'SurveyLine',
            speed_m_s=self.speed_m_s,
            sway_period_s=self.sway_period_s,
            length_m=float(np.linalg.norm(np.subtract(self.end, self.start))),
        )

    @property
    def duration_s(self) -> float:
        return float(np.linalg.norm(np.subtract(self.end, self.start)) / self.speed_m_s)

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        start, end = np.asarray(self.start, float), np.asarray(self.end, float)
        direction = (end - start) / np.linalg.norm(end - start)
        position = start + self.speed_m_s * t[:, None] * direction
        yaw = np.full_like(t, np.arctan2(direction[1], direction[0]))
        phase = 2 * np.pi * t / self.sway_period_s
        roll = np.radians(self.roll_amplitude_deg) * np.sin(phase)
        pitch = np.radians(self.pitch_amplitude_deg) * np.sin(0.61 * phase)
        return position, np.column_stack([yaw, pitch, roll])


Segment = TrimManoeuvre | SurveyLine


@dataclass(frozen=True)
class Scenario:
    """Everything a simulated mission needs; SI units throughout.

    Parameters
    ----------
    geometry : TetraGeometry
    earth_field_enu : (3,) tesla
    segments : sequence of TrimManoeuvre | SurveyLine, flown in order
    sample_rate_hz : float
    dipoles : sequence of Dipole
    interference : SensorInterference
        Per-sensor soft and hard iron (sensor 1 clean or not).
    noise_t : float
        White noise per sensor axis, tesla RMS.
    effects : Effects
    temperature : TemperatureProfile
    current : CurrentProfile
        The hotel load and the thrusters' channels (:mod:`.vehicle_signals`).
    regional_gradient_enu : (3, 3) T/m
        Uniform world-frame gradient ``G_w`` (symmetric, traceless): the world field gains
        ``G_w x`` at ENU position ``x`` (m from the world origin). Default zero.
    clocks : SensorClocks or None
        Each sensor's own sampling instants and message loss; None (default): the four
        sensors sample together at ``k / sample_rate_hz``.

    Raises
    ------
    InputError
        No segment, a non-positive rate, negative noise, a regional gradient that is not
        symmetric and traceless (:func:`check_gradient_tensor`), or a ``vehicle_current``
        whose channels are not the current profile's.
    """

    geometry: TetraGeometry
    earth_field_enu: np.ndarray
    segments: tuple[Segment, ...]
    sample_rate_hz: float = 10.0
    dipoles: tuple[Dipole, ...] = ()
    interference: SensorInterference = field(default_factory=SensorInterference.zero)
    noise_t: float = 0.1e-9
    effects: Effects = field(default_factory=Effects)
    temperature: TemperatureProfile = field(default_factory=TemperatureProfile)
    current: CurrentProfile = field(default_factory=CurrentProfile)
    regional_gradient_enu: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    clocks: SensorClocks | None = None

    def __post_init__(self) -> None:
        object.__setattr__(
            self, 'earth_field_enu', frozen_array(self.earth_field_enu, 'earth_field_enu', (3,))
        )
        object.__setattr__(
            self, 'regional_gradient_enu', check_gradient_tensor(self.regional_gradient_enu)
        )
        object.__setattr__(self, 'segments', tuple(self.segments))
        object.__setattr__(self, 'dipoles', tuple(self.dipoles))
        if not self.segments:
            raise InputError('a scenario needs at least one segment')
        if not self.sample_rate_hz > 0:
            raise InputError(f'sample_rate_hz must be positive, got {self.sample_rate_hz}')
        if not self.noise_t >= 0:
            raise InputError(f'noise_t must be >= 0, got {self.noise_t}')
        per_amp = self.effects.vehicle_current
        topics = self.current.topics
        if per_amp is not None and per_amp.reshape(4, 3, -1).shape[2] != len(topics):
            raise InputError(
                f'vehicle_current has {per_amp.reshape(4, 3, -1).shape[2]} column(s) per sensor '
                f'and axis for {len(topics)} current channel(s) ({", ".join(topics)})'
            )

    @property
    def duration_s(self) -> float:
        return float(sum(s.duration_s for s in self.segments))


@dataclass(frozen=True)
class MissionData:
    """A simulated mission, sampled at ``t``; body-frame vectors unless named ``_enu``.

    With sensor clocks (``Scenario.clocks``), ``t`` are sensor 1's true instants (all of
    them, also those whose message is lost) and every array is taken there: ground truth lines
    up with sensor 1's stamps. ``fields_measured[:, s]`` for the other sensors is what sensor
    ``s`` would read at sensor 1's instants (noise included), not what it logged: that is
    in ``streams``.

    Attributes
    ----------
    t : (N,) s from the start
    segment : (N,) index into ``Scenario.segments``
    position_enu : (N, 3) m, body origin in the world
    orientation_xyzw : (N, 4) quaternion rotating body vectors into ENU
    b_background : (N, 3) T, true field at sensor 1 (``B^b``)
    fields_true : (N, 4, 3) T, clean noise-free readings
    fields_measured : (N, 4, 3) T, with interference, effects and noise
    g_true : (N, 3, 3) T/m, eq. 7 on ``fields_true``
    g_analytic : (N, 3, 3) T/m, exact gradient at the centroid
    temperature_c : (N,) degC
    current_a : (N,) A, the battery's (``/battery_state``)
    currents_a : (N, m) A, every current channel: the battery's (``current_a``) first, then
        each thruster's, in the order of ``current_topics``
    streams : tuple of four SensorStream, or None
        Without clocks None. With clocks, each sensor's messages as logged on its own
        instants, after message loss: ``t`` (n_s,) s and ``fields`` (n_s, 3) T measured
        (interference, effects, noise). Sensor 1's stream is ``fields_measured[:, 0]`` at the
        instants of ``t`` whose message arrived.
    current_topics : (m,) the BatteryState topic of each current channel
    """

    t: np.ndarray
    segment: np.ndarray
    position_enu: np.ndarray
    orientation_xyzw: np.ndarray
    b_background: np.ndarray
    fields_true: np.ndarray
    fields_measured: np.ndarray
    g_true: np.ndarray
    g_analytic: np.ndarray
    temperature_c: np.ndarray
    current_a: np.ndarray
    currents_a: np.ndarray
    streams: tuple[SensorStream, ...] | None = None
    current_topics: tuple[str, ...] = (BATTERY_TOPIC,)

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: npt.NDArray[np.bool_] | npt.NDArray[np.intp] | slice) -> MissionData:
        """The samples that ``mask`` (bool (N,), indices or a slice) selects.

        Streams keep their messages within the time span of the selected ``t``, widened by
        half a period of sensor 1 (:func:`~.clocks.select_streams`): for a contiguous
        selection (a segment, a window) that is every message of that stretch of the mission;
        a scattered one keeps every message between its first and last instant.
        """
        fixed = ('streams', 'current_topics')
        names = [name for name in self.__dataclass_fields__ if name not in fixed]
        arrays = {name: getattr(self, name)[mask] for name in names}
        streams = self.streams
        if streams is not None:
            streams = select_streams(streams, self.t, arrays['t'])
        return MissionData(**arrays, streams=streams, current_topics=self.current_topics)


def _segment_index(scenario: Scenario, t: np.ndarray) -> np.ndarray:
    """Index of the segment flown at absolute times ``t`` (s)."""
    starts = np.cumsum([0.0] + [s.duration_s for s in scenario.segments])
    return np.clip(np.searchsorted(starts, t, side='right') - 1, 0, len(scenario.segments) - 1)


def _pose(
    scenario: Scenario, t: np.ndarray, index: np.ndarray | None = None
) -> tuple[np.ndarray, Rotation, np.ndarray]:
    """Position (N, 3), attitude, and segment index at absolute times ``t`` (s).

    ``index`` forces the segment of each time (a segment's pose is smooth past its ends),
    so that derivatives taken across a segment boundary stay within one segment.
    """
    starts = np.cumsum([0.0] + [s.duration_s for s in scenario.segments])
    if index is None:
        index = _segment_index(scenario, t)
    position, euler = np.empty((len(t), 3)), np.empty((len(t), 3))
    for i, segment in enumerate(scenario.segments):
        here = index == i
        if np.any(here):
            position[here], euler[here] = segment.pose(t[here] - starts[i])
    return position, Rotation.from_euler('ZYX', euler), index


def _world_field(scenario: Scenario, points: np.ndarray) -> np.ndarray:
    """World field (N, 3) T at ENU points (N, 3) m: Earth, regional gradient, dipoles."""
    total = uniform_field(len(points), scenario.earth_field_enu)
    if np.any(scenario.regional_gradient_enu):
        total += points @ scenario.regional_gradient_enu.T
    for dipole in scenario.dipoles:
        total += dipole_field(points, dipole.moment, dipole.position)
    return total


def _clean_fields(
    scenario: Scenario, t: np.ndarray, index: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, Rotation, np.ndarray]:
    """Clean body-frame readings (N, 4, 3) T at times ``t``, plus position, attitude, segment."""
    position, attitude, index = _pose(scenario, t, index)
    n = len(t)
    rotation = attitude.as_matrix()
    points = position[:, None, :] + np.einsum('nij,sj->nsi', rotation, scenario.geometry.positions)
    world = _world_field(scenario, points.reshape(-1, 3)).reshape(n, 4, 3)
    body = np.einsum('nji,nsj->nsi', rotation, world)  # R^T B
    return body, position, attitude, index


def _kinematics(
    scenario: Scenario, t: np.ndarray, index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Speed (N,) m/s and (yaw, pitch, roll) rates (N, 3) deg/s at times ``t`` (s) flown on
    segments ``index`` (each rate within its own segment, as the eddy term's)."""
    starts = np.cumsum([0.0] + [s.duration_s for s in scenario.segments])
    speed = np.array([s.speed_m_s for s in scenario.segments])[index]
    rates = np.zeros((len(t), 3))
    step = _DERIVATIVE_STEP_S
    for i, segment in enumerate(scenario.segments):
        here = index == i
        if np.any(here):
            local = t[here] - starts[i]
            ahead, behind = segment.pose(local + step)[1], segment.pose(local - step)[1]
            rates[here] = (ahead - behind) / (2 * step)
    return speed, np.degrees(rates)


def _currents_at(
    scenario: Scenario, currents: Currents, t: np.ndarray, index: np.ndarray
) -> np.ndarray:
    """Every current channel (N, m) A at times ``t`` (s) flown on segments ``index``."""
    return currents(t, lambda: _kinematics(scenario, t, index))


def _truth(scenario: Scenario, t: np.ndarray, index: np.ndarray, currents: Currents) -> Truth:
    """What the registry's effects read at times ``t`` (s) on segments ``index``: the
    temperature, every current channel and the exact rate of the background field."""
    series = {TEMPERATURE: scenario.temperature(t, scenario.duration_s)}
    values = _currents_at(scenario, currents, t, index)
    for j, topic in enumerate(scenario.current.topics):
        series[current_channel(topic)] = values[:, j]

    def rate() -> np.ndarray:
        # Within the segment of each sample: segments join with a jump in pose, and a
        # difference across the join would read it as a huge dB/dt.
        step = _DERIVATIVE_STEP_S
        ahead = _clean_fields(scenario, t + step, index)[0][:, 0]
        return (ahead - _clean_fields(scenario, t - step, index)[0][:, 0]) / (2 * step)

    return Truth(t, series, rate, scenario.temperature.mean_c)


def _readings(
    scenario: Scenario,
    t: np.ndarray,
    currents: Currents,
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Noise-free measured readings (N, 4, 3) T at times ``t`` (on segments ``index``, default
    the segments flown at ``t``): interference, the registry's effects (each its own
    physics, :meth:`~.effects.Effect.simulate`, in :data:`EFFECT_SPECS`' order), then each
    sensor's response (:func:`~.simulated_effects.sensor_matrices`)."""
    if index is None:
        index = _segment_index(scenario, t)
    fields, _, _, _ = _clean_fields(scenario, t, index)
    background = fields[:, 0, :]
    readings = scenario.interference.apply(fields, background)
    effects = scenario.effects
    active = [name for name in ADDITIVE if getattr(effects, name) is not None]
    if active:
        truth = _truth(scenario, t, index, currents)
        for name in active:
            readings += EFFECTS[name].simulate(getattr(effects, name), truth)
    matrices = sensor_matrices(effects)
    if matrices is not None:
        readings = np.einsum('sij,nsj->nsi', matrices, readings)
    return readings


def _measured(
    scenario: Scenario,
    t: np.ndarray,
    index: np.ndarray,
    currents: Currents,
    rng: np.random.Generator,
) -> np.ndarray:
    """Measured readings (N, 4, 3) T of the four sensors at the instants ``t`` (s, flown on
    segments ``index``): interference, effects, time skew and noise."""
    measured = _readings(scenario, t, currents)
    skew = scenario.effects.time_skew
    if skew is not None:
        for sensor in np.flatnonzero(skew):
            # The skewed sensor reads the same segment's trajectory, earlier (not the pose
            # of the previous segment across a join, which is a jump).
            measured[:, sensor] = _readings(scenario, t - skew[sensor], currents, index)[:, sensor]
    measured += rng.normal(0.0, scenario.noise_t, measured.shape) if scenario.noise_t > 0 else 0.0
    return measured


def _streams(
    scenario: Scenario,
    clocks: SensorClocks,
    instants: tuple[np.ndarray, ...],
    first: np.ndarray,
    currents: Currents,
    rng: np.random.Generator,
) -> tuple[SensorStream, ...]:
    """Each sensor's logged messages: its measured readings at its own ``instants`` (s), with
    fresh noise (sensor 1's are ``first`` (n_1, 3) T, already measured), after message loss."""
    fields = [first]
    skew = scenario.effects.time_skew
    for sensor in range(1, 4):
        t = instants[sensor]
        delay = 0.0 if skew is None else float(skew[sensor])
        # As in _measured: a skewed sensor reads its own segment's trajectory, earlier.
        readings = _readings(scenario, t - delay, currents, _segment_index(scenario, t))[:, sensor]
        if scenario.noise_t > 0:
            readings += rng.normal(0.0, scenario.noise_t, readings.shape)
        fields.append(readings)
    kept = kept_messages(clocks, tuple(len(t) for t in instants), rng)
    return tuple(SensorStream(t[k], f[k]) for t, f, k in zip(instants, fields, kept, strict=True))


def simulate(scenario: Scenario, rng: np.random.Generator) -> MissionData:
    """Fly ``scenario`` and return every sample.

    Parameters
    ----------
    scenario : Scenario
    rng : numpy.random.Generator
        Source of the current profile (the hotel load's levels, then each thruster's
        steps), the clocks' jitter, the noise and the message loss (drawn in that order;
        without clocks only the current profile and the noise).

    Raises
    ------
    InputError
        If sensor 1 takes no sample within the scenario.
    """
    currents = draw_currents(scenario.current, scenario.duration_s, rng)
    clocks = scenario.clocks
    if clocks is None:
        n = int(np.floor(scenario.duration_s * scenario.sample_rate_hz + 1e-9))  # 4.35 s x 100 Hz
        t = np.arange(n) / scenario.sample_rate_hz
    else:
        instants = sample_instants(clocks, scenario.sample_rate_hz, scenario.duration_s, rng)
        t = instants[0]
    if len(t) < 1:
        raise InputError('the scenario is shorter than one sample period (of sensor 1)')
    fields_true, position, attitude, index = _clean_fields(scenario, t)
    measured = _measured(scenario, t, index, currents, rng)
    streams = None
    if clocks is not None:
        streams = _streams(scenario, clocks, instants, measured[:, 0], currents, rng)
    centroid_world = position + attitude.apply(scenario.geometry.centroid)
    g_world = np.zeros((len(t), 3, 3))
    if np.any(scenario.regional_gradient_enu):
        g_world += scenario.regional_gradient_enu
    for dipole in scenario.dipoles:
        g_world += dipole_gradient(centroid_world, dipole.moment, dipole.position)
    rot = attitude.as_matrix()
    currents_a = _currents_at(scenario, currents, t, index)
    return MissionData(
        t=t,
        segment=index,
        position_enu=position,
        orientation_xyzw=attitude.as_quat(),
        b_background=fields_true[:, 0, :].copy(),
        fields_true=fields_true,
        fields_measured=measured,
        g_true=difference_tensor(fields_true, scenario.geometry),
        g_analytic=to_body(g_world, rot),
        temperature_c=scenario.temperature(t, scenario.duration_s),
        current_a=currents_a[:, 0].copy(),
        currents_a=currents_a,
        streams=streams,
        current_topics=scenario.current.topics,
    )


def random_interference(
    rng: np.random.Generator,
    *,
    k_scale: float = 5e-3,
    b_scale_t: float = 150e-9,
    reference_clean: bool = True,
) -> SensorInterference:
    """Symmetric soft iron with entries uniform in ``±k_scale`` and hard iron uniform in
    ``±b_scale_t`` (tesla) per sensor; sensor 1 zero when ``reference_clean``."""
    k = rng.uniform(-k_scale, k_scale, (4, 3, 3))
    k = 0.5 * (k + np.swapaxes(k, 1, 2))
    b = rng.uniform(-b_scale_t, b_scale_t, (4, 3))
    if reference_clean:
        k[0], b[0] = 0.0, 0.0
    return SensorInterference(k, b)
