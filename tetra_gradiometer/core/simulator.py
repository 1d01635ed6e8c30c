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

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ._validate import frozen_array, require_positive
from .clocks import SensorClocks, SensorStream, kept_messages, sample_instants, select_streams
from .fields import dipole_field, dipole_gradient, uniform_field
from .geometry import TetraGeometry, difference_tensor, to_body
from .model import SensorInterference
from .types import ArrayLike, FloatArray
from .units import T_PER_NT

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
class CurrentProfile:
    """Battery current, A (negative while discharging): a base load plus thruster steps,
    random levels every ``step_s`` seconds linearly joined (seeded by the scenario)."""

    base_a: float = -8.0
    step_amplitude_a: float = 6.0
    step_s: float = 15.0


@dataclass(frozen=True)
class EffectSpec:
    """One simulated physical effect: its parameter shape and SI unit, and how a scenario
    file gives it (key and the factor from the file's unit to SI)."""

    shape: tuple[int, ...]
    unit: str
    scenario_key: str
    scenario_factor: float = 1.0


#: The simulator's effects, each spelled once: :class:`Effects`, its validation and
#: ``active()``, and the scenario format (``io/scenario.py``) all read this table.
EFFECT_SPECS: dict[str, EffectSpec] = {
    'eddy_current': EffectSpec((4, 3, 3), 's', 'coefficients_s'),
    'sensor_misalignment': EffectSpec((4, 3), 'rad', 'rotation_deg', float(np.pi / 180.0)),
    'time_skew': EffectSpec((4,), 's', 'delay_s'),
    'thermal_drift': EffectSpec((4, 3), 'T/degC', 'nT_per_degC', T_PER_NT),
    'vehicle_current': EffectSpec((4, 3), 'T/A', 'nT_per_A', T_PER_NT),
}


@dataclass(frozen=True)
class Effects:
    """Physical effects beyond the paper's model, each off (None) or with its magnitude
    (shapes and units in :data:`EFFECT_SPECS`).

    Attributes
    ----------
    eddy_current : (4, 3, 3) seconds
        ``B_i += E_i dB^b/dt`` (body-frame rate of the background field).
    sensor_misalignment : (4, 3) rad
        Rotation vector of each sensor's axes against the array frame.
    time_skew : (4,) s
        Each sensor's constant delay: its reading stamped ``t`` is the field at ``t - skew``.
    thermal_drift : (4, 3) T/degC
        Offset per degree away from the profile's mean temperature.
    vehicle_current : (4, 3) T/A
        Field per ampere of battery current.
    """

    eddy_current: FloatArray | None = None
    sensor_misalignment: FloatArray | None = None
    time_skew: FloatArray | None = None
    thermal_drift: FloatArray | None = None
    vehicle_current: FloatArray | None = None

    def __post_init__(self) -> None:
        for name, spec in EFFECT_SPECS.items():
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, frozen_array(value, name, spec.shape))

    def active(self) -> list[str]:
        """Names of the effects that are switched on."""
        return [name for name in EFFECT_SPECS if getattr(self, name) is not None]


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
    regional_gradient_enu : (3, 3) T/m
        Uniform world-frame gradient ``G_w`` (symmetric, traceless): the world field gains
        ``G_w x`` at ENU position ``x`` (m from the world origin). Default zero.
    clocks : SensorClocks or None
        Each sensor's own sampling instants and message loss; None (default): the four
        sensors sample together at ``k / sample_rate_hz``.

    Raises
    ------
    InputError
        No segment, a non-positive rate, negative noise, or a regional gradient that is not
        symmetric and traceless (:func:`check_gradient_tensor`).
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
    current_a : (N,) A
    streams : tuple of four SensorStream, or None
        Without clocks None. With clocks, each sensor's messages as logged on its own
        instants, after message loss: ``t`` (n_s,) s and ``fields`` (n_s, 3) T measured
        (interference, effects, noise). Sensor 1's stream is ``fields_measured[:, 0]`` at the
        instants of ``t`` whose message arrived.
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
    streams: tuple[SensorStream, ...] | None = None

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: npt.NDArray[np.bool_] | npt.NDArray[np.intp] | slice) -> MissionData:
        """The samples that ``mask`` (bool (N,), indices or a slice) selects.

        Streams keep their messages within the time span of the selected ``t``, widened by
        half a period of sensor 1 (:func:`~.clocks.select_streams`): for a contiguous
        selection (a segment, a window) that is every message of that stretch of the mission;
        a scattered one keeps every message between its first and last instant.
        """
        names = [name for name in self.__dataclass_fields__ if name != 'streams']
        arrays = {name: getattr(self, name)[mask] for name in names}
        streams = self.streams
        if streams is not None:
            streams = select_streams(streams, self.t, arrays['t'])
        return MissionData(**arrays, streams=streams)


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


def _current_function(
    scenario: Scenario, rng: np.random.Generator
) -> Callable[[np.ndarray], np.ndarray]:
    profile = scenario.current
    knots = (
        np.arange(0.0, scenario.duration_s + 2 * profile.step_s, profile.step_s) - profile.step_s
    )
    levels = profile.base_a + profile.step_amplitude_a * rng.uniform(-1.0, 1.0, len(knots))
    return lambda t: np.interp(t, knots, levels)


def _readings(
    scenario: Scenario,
    t: np.ndarray,
    current: Callable[[np.ndarray], np.ndarray],
    index: np.ndarray | None = None,
) -> np.ndarray:
    """Noise-free measured readings (N, 4, 3) T at times ``t`` (on segments ``index``, default
    the segments flown at ``t``): interference and effects."""
    if index is None:
        index = _segment_index(scenario, t)
    fields, _, _, _ = _clean_fields(scenario, t, index)
    background = fields[:, 0, :]
    readings = scenario.interference.apply(fields, background)
    effects = scenario.effects
    if effects.eddy_current is not None:
        step = _DERIVATIVE_STEP_S
        # Within the segment of each sample: segments join with a jump in pose, and a
        # difference across the join would read it as a huge dB/dt.
        rate = (
            _clean_fields(scenario, t + step, index)[0][:, 0]
            - _clean_fields(scenario, t - step, index)[0][:, 0]
        ) / (2 * step)
        readings += np.einsum('sij,nj->nsi', effects.eddy_current, rate)
    if effects.thermal_drift is not None:
        excess = scenario.temperature(t, scenario.duration_s) - scenario.temperature.mean_c
        readings += excess[:, None, None] * effects.thermal_drift[None]
    if effects.vehicle_current is not None:
        readings += current(t)[:, None, None] * effects.vehicle_current[None]
    if effects.sensor_misalignment is not None:
        # A writable copy: scipy's Cython Rotation refuses read-only buffers.
        rotations = Rotation.from_rotvec(np.array(effects.sensor_misalignment)).as_matrix()
        readings = np.einsum('sij,nsj->nsi', rotations, readings)
    return readings


def _measured(
    scenario: Scenario,
    t: np.ndarray,
    index: np.ndarray,
    current: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
) -> np.ndarray:
    """Measured readings (N, 4, 3) T of the four sensors at the instants ``t`` (s, flown on
    segments ``index``): interference, effects, time skew and noise."""
    measured = _readings(scenario, t, current)
    skew = scenario.effects.time_skew
    if skew is not None:
        for sensor in np.flatnonzero(skew):
            # The skewed sensor reads the same segment's trajectory, earlier (not the pose
            # of the previous segment across a join, which is a jump).
            measured[:, sensor] = _readings(scenario, t - skew[sensor], current, index)[:, sensor]
    measured += rng.normal(0.0, scenario.noise_t, measured.shape) if scenario.noise_t > 0 else 0.0
    return measured


def _streams(
    scenario: Scenario,
    clocks: SensorClocks,
    instants: tuple[np.ndarray, ...],
    first: np.ndarray,
    current: Callable[[np.ndarray], np.ndarray],
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
        readings = _readings(scenario, t - delay, current, _segment_index(scenario, t))[:, sensor]
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
        Source of the current profile, the clocks' jitter, the noise and the message loss
        (drawn in that order; without clocks only the current profile and the noise).

    Raises
    ------
    InputError
        If sensor 1 takes no sample within the scenario.
    """
    current = _current_function(scenario, rng)
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
    measured = _measured(scenario, t, index, current, rng)
    streams = None
    if clocks is not None:
        streams = _streams(scenario, clocks, instants, measured[:, 0], current, rng)
    centroid_world = position + attitude.apply(scenario.geometry.centroid)
    g_world = np.zeros((len(t), 3, 3))
    if np.any(scenario.regional_gradient_enu):
        g_world += scenario.regional_gradient_enu
    for dipole in scenario.dipoles:
        g_world += dipole_gradient(centroid_world, dipole.moment, dipole.position)
    rot = attitude.as_matrix()
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
        current_a=current(t),
        streams=streams,
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
