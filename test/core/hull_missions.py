"""Missions whose vehicle changes after the trim, built from magpylib (an independent forward
model) around the core simulator's kinematics, for the calibration tracker's tests and bench.

The hull is a handful of magnetised cuboids fixed in the body frame, 0.8-2.5 m from the
array; after the trim each one's remanence relaxes by its own fraction (0.3-0.7 %) with a
600 s time constant, scaled so that full relaxation moves the tensor by 1.2 nT/m RMS. One
sensor's offset steps by 1 nT (about 2 nT/m in the tensor) two thirds into the survey.
Geology, when asked for, is deep magpylib dipoles (50-450 m below the track: anomalies of
those scales) scaled to 1 nT/m RMS along the survey. The survey is five 660 m lines at 2 m/s
joined by 30 s U-turns (the first reversal after 330 s), about 30 minutes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import magpylib
import numpy as np
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (
    Scenario,
    SensorInterference,
    SurveyLine,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    known_gradient_lstsq,
    simulate,
)

GEOMETRY = TetraGeometry.regular(0.5)
EARTH_ENU = np.array([0.0, 21000e-9, -45376.2e-9])
NOISE_T = 0.05e-9
RATE_HZ = 10.0
TRIM_S = 300.0
RELAXATION_S = 600.0
DRIFT_RMS_T_PER_M = 1.2e-9
GEOLOGY_RMS_T_PER_M = 1.0e-9
STEP_T = 1.0e-9
LINE_M, SPEED_M_S, TURN_DEG_S, N_LINES = 660.0, 2.0, 6.0, 5
DEPTH_M = -50.0


@dataclass(frozen=True)
class HullMission:
    """A flown mission: ``t_s`` (N,) s, ``fields`` (N, 4, 3) T measured, ``g_true`` (N, 3, 3)
    T/m (eq. 7 on the clean fields, geology included), ``orientation_xyzw`` (N, 4),
    ``survey`` (N,) bool, the frozen calibration (a ``TensorCalibration`` of the trim),
    ``t_step_s`` and ``step_sensor`` (0-based; None: no step); ``data`` the simulator's
    ``MissionData`` with these readings (to write a bag)."""

    t_s: np.ndarray
    fields: np.ndarray
    g_true: np.ndarray
    orientation_xyzw: np.ndarray
    position_enu: np.ndarray
    survey: np.ndarray
    calibration: object
    t_survey_s: float
    t_step_s: float | None
    step_sensor: int | None
    data: object = None

    @property
    def floor_t_per_m(self) -> float:
        """The noise floor (RMS over components of the tensor noise), T/m, from the
        simulated noise (metrics.noise_floor's formula, written out)."""
        a_inv = GEOMETRY.a_inv
        variance = (a_inv**2).sum(axis=0) + a_inv.sum(axis=0) ** 2
        return float(NOISE_T * np.sqrt(variance.mean()))


def _segments() -> tuple:
    """Trim, then lines joined by U-turns (left at the east end, right at the west end)."""
    radius = SPEED_M_S / np.radians(TURN_DEG_S)
    turn_s = 180.0 / TURN_DEG_S
    segments: list = [TrimManoeuvre(TRIM_S, center=(-200.0, -100.0, DEPTH_M))]
    for i in range(N_LINES):
        y = 2 * radius * i
        east = i % 2 == 0
        start, end = (0.0, LINE_M) if east else (LINE_M, 0.0)
        segments.append(SurveyLine((start, y, DEPTH_M), (end, y, DEPTH_M), speed_m_s=SPEED_M_S,
                                   roll_amplitude_deg=1.0, pitch_amplitude_deg=0.5))
        if i < N_LINES - 1:
            rate = TURN_DEG_S if east else -TURN_DEG_S
            segments.append(TrimManoeuvre(turn_s, center=(end, y + radius, DEPTH_M),
                                          heading_rate_deg_s=rate, roll_amplitude_deg=0.0,
                                          pitch_amplitude_deg=0.0,
                                          initial_heading_deg=0.0 if east else 180.0,
                                          speed_m_s=SPEED_M_S))
    return tuple(segments)


def _hull_bodies(rng: np.random.Generator) -> list:
    """Five magnetised cuboids (body frame, 0.8-2.5 m from the centroid)."""
    centroid = GEOMETRY.positions.mean(axis=0)
    bodies = []
    for _ in range(5):
        direction = rng.normal(size=3)
        position = centroid + rng.uniform(0.8, 2.5) * direction / np.linalg.norm(direction)
        polarization = rng.normal(size=3) * 5e-3
        bodies.append(magpylib.magnet.Cuboid(polarization=polarization,
                                             dimension=rng.uniform(0.05, 0.15, 3),
                                             position=position))
    return bodies


def _hull_fields(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Each body's field at the four sensors (B, 4, 3) T, and each body's relaxation fraction
    (B,), scaled so that full relaxation moves the tensor by DRIFT_RMS_T_PER_M."""
    bodies = _hull_bodies(rng)
    fields = np.stack([np.asarray(b.getB(GEOMETRY.positions)) for b in bodies])
    fractions = rng.uniform(0.003, 0.007, len(bodies))
    change = -np.einsum('b,bsi->si', fractions, fields)
    rms = np.sqrt(np.mean(difference_tensor(change[None], GEOMETRY) ** 2))
    return fields * (DRIFT_RMS_T_PER_M / rms), fractions


def _geology(rng: np.random.Generator, points_enu: np.ndarray, n_sources: int = 40):
    """Deep dipoles under the survey area; the field (M, 3) T at ``points_enu`` (M, 3) m,
    before scaling."""
    depth = rng.uniform(50.0, 450.0, n_sources)
    xy = np.column_stack([rng.uniform(-300, LINE_M + 300, n_sources),
                          rng.uniform(-300, 460, n_sources)])
    positions = np.column_stack([xy, DEPTH_M - depth])
    moments = rng.normal(size=(n_sources, 3)) * (depth**3)[:, None]
    sources = [magpylib.misc.Dipole(moment=m, position=p) for m, p in zip(moments, positions)]
    return np.asarray(magpylib.getB(sources, points_enu, sumup=True))


#: Seabed targets (magpylib dipoles, ENU m and A m^2) 22-30 m below three of the lines.
TARGETS = (((200.0, 0.0, -75.0), (800.0, -500.0, 1200.0)),
           ((450.0, 76.4, -80.0), (-600.0, 900.0, -1500.0)),
           ((330.0, 152.8, -72.0), (400.0, 300.0, 900.0)))


def build_mission(seed: int, *, drift: bool = True, step: bool = True,
                  geology: bool = False, targets: bool = False) -> HullMission:
    """Fly the mission of the module docstring (``seed`` draws the hull, soft iron, step
    direction and sensor, geology and noise), over :data:`TARGETS` with ``targets``;
    calibrate on its trim."""
    rng = np.random.default_rng(seed)
    k = rng.uniform(-5e-3, 5e-3, (4, 3, 3))
    k = 0.5 * (k + np.swapaxes(k, 1, 2))
    k[0] = 0.0
    soft = SensorInterference(k, np.zeros((4, 3)))
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH_ENU, segments=_segments(),
                        sample_rate_hz=RATE_HZ, interference=soft, noise_t=NOISE_T)
    data = simulate(scenario, rng)
    t = data.t
    rotation = Rotation.from_quat(data.orientation_xyzw).as_matrix()
    fields_true = data.fields_true.copy()
    measured = data.fields_measured.copy()
    survey = data.segment > 0
    points = data.position_enu[:, None, :] + np.einsum('nij,sj->nsi', rotation,
                                                       GEOMETRY.positions)
    if geology:
        world = _geology(rng, points.reshape(-1, 3)).reshape(len(t), 4, 3)
        body = np.einsum('nji,nsj->nsi', rotation, world)
        scale = GEOLOGY_RMS_T_PER_M / np.sqrt(np.mean(difference_tensor(body[survey],
                                                                        GEOMETRY) ** 2))
        body *= scale
        fields_true += body
        measured += soft.apply(body, body[:, 0])  # the geology magnetises the hull too
    if targets:
        sources = [magpylib.misc.Dipole(moment=m, position=p) for p, m in TARGETS]
        world = np.asarray(magpylib.getB(sources, points.reshape(-1, 3), sumup=True))
        body = np.einsum('nji,nsj->nsi', rotation, world.reshape(len(t), 4, 3))
        fields_true += body
        measured += soft.apply(body, body[:, 0])
    hull, fractions = _hull_fields(rng)
    relaxed = np.clip(t - TRIM_S, 0.0, None)
    scale = 1.0 - np.outer(1.0 - np.exp(-relaxed / RELAXATION_S), fractions if drift else 0 * fractions)
    measured += np.einsum('nb,bsi->nsi', scale, hull)
    t_step = sensor = None
    if step:
        t_step = TRIM_S + (t[-1] - TRIM_S) * 2.0 / 3.0
        sensor = int(rng.integers(4))
        direction = rng.normal(size=3)
        measured[t >= t_step, sensor] += STEP_T * direction / np.linalg.norm(direction)
    trim = ~survey
    calibration = known_gradient_lstsq(difference_tensor(measured[trim], GEOMETRY),
                                       measured[trim, 0], GEOMETRY, symmetric_k=False,
                                       orientation_xyzw=data.orientation_xyzw[trim] if geology else None)
    g_true = difference_tensor(fields_true, GEOMETRY)
    flown = replace(data, fields_measured=measured, fields_true=fields_true, g_true=g_true)
    return HullMission(t, measured, g_true, data.orientation_xyzw, data.position_enu, survey,
                       calibration, TRIM_S, t_step, sensor, flown)


def spans(mission: HullMission) -> dict[str, np.ndarray]:
    """The spans compared, as masks (N,): the first 5 min of the survey, the 5 min before the
    step, and after it (to the end)."""
    t = mission.t_s
    start = mission.t_survey_s
    out = {'first_5_min': (t >= start) & (t < start + 300.0)}
    if mission.t_step_s is not None:
        out['before_step'] = (t >= mission.t_step_s - 300.0) & (t < mission.t_step_s)
        out['after_step'] = t >= mission.t_step_s
    else:
        out['survey'] = mission.survey
    return out
