"""Survey products of a bag: the compensated tensor along the track in the world frame,
placed on the Earth (:mod:`~tetra_gradiometer.io.geo`), gridded
(:mod:`.survey_grid`), with the targets, the health alarms, the lost and refused spans and
the per-leg residual against the noise floor (:func:`survey_bag`).

Along the track, per set: the tensor compensated as by ``compensate`` (eq. 19 with the
calibration's ``k``, ``b`` and terms; :func:`~.compensation.load_compensation` gives the
1-sigma model), rotated into the odom frame with the ``/odom`` attitude (``R G R^T``,
:func:`~tetra_gradiometer.core.geometry.to_world`) and then into the geodetic ENU frame
(the georeference's yaw). Its 1-sigma is split into the sensor-noise part (the same model
without the parameters' covariance) and the calibration part (the rest), which grid
differently (:mod:`.survey_grid`).

Spans along the track: *lost* where consecutive sets are more than 3 median periods apart
(messages lost or sets dropped as implausible); *refused* where a set has no compensated
tensor (a channel a calibration term reads was unknown).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..core import TetraGeometry, compensate, difference_tensor
from ..core.geometry import to_world
from ..core.targets import LocatorSettings, Survey, Target, legs, locate
from ..core.targets.detection import DetectorSettings
from ..core.timebase import DEFAULT_TIMEBASE, TimeBase
from ..core.types import FloatArray
from ..core.uncertainty import SigmaModel
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import BagError, InputError
from ..io import conversions as cv
from ..io.bag import MagneticBag
from ..io.geo import Fixes, Georeference, fit_fixes, read_fixes
from ..io.recording import Recording, read_recording
from .compensation import Compensation
from .health import HealthRecorder
from .survey_grid import GridSettings, SurveyGrids, grid_track
from .terms import StreamRegressors
from .tracking import track_tensors

__all__ = [
    'LegResidual',
    'Span',
    'SurveyResult',
    'SurveyTrack',
    'georeference_of',
    'gridded_samples',
    'track_spans',
    'survey_bag',
]

#: A gap between sets of more than this many median periods is a lost span.
LOST_PERIODS = 3.0


@dataclass(frozen=True)
class Span:
    """A stretch of the track, seconds from the first set: ``kind`` 'lost' or 'refused'."""

    kind: str
    start_s: float
    stop_s: float


@dataclass(frozen=True)
class LegResidual:
    """One straight leg's check: the RMS of the compensated tensor's non-field part (its
    trace / sqrt(3) and the antisymmetric (g_ij - g_ji) / sqrt(2), nT/m) against the RMS of
    their 1-sigma (the noise floor, nT/m)."""

    start_s: float
    stop_s: float
    residual_nT_per_m: float
    floor_nT_per_m: float


@dataclass(frozen=True)
class SurveyTrack:
    """The track, world frame.

    t_s (N,) s from the first set; stamps_ns (N,); odom_m (N, 3) the tensor's point (body
    origin; the array is 0.5 m); xy_m (N, 2) in the CRS; lonlat (N, 3); tensors (N, 3, 3)
    T/m in geodetic ENU (NaN where refused); sigma_noise, sigma_calibration (N, 3, 3) T/m;
    legs: (start, stop) index pairs.
    """

    t_s: FloatArray
    stamps_ns: np.ndarray
    odom_m: FloatArray
    xy_m: FloatArray
    lonlat: FloatArray
    tensors: FloatArray
    sigma_noise: FloatArray
    sigma_calibration: FloatArray
    legs: list[tuple[int, int]]


@dataclass(frozen=True)
class SurveyResult:
    """:func:`survey_bag`'s products (the folder's content, :mod:`..reports.survey`)."""

    track: SurveyTrack
    grids: SurveyGrids
    georeference: Georeference
    crs: str
    targets: list[Target]
    detections: int
    false_alarms_per_hour: float
    t0_stamp_s: float
    health: dict[str, Any]
    spans: list[Span]
    leg_residuals: list[LegResidual]
    input_counts: dict[str, int]
    timings_s: dict[str, float]


def _stage(on_stage: Callable[[str], None] | None, text: str) -> None:
    if on_stage is not None:
        on_stage(text)


def survey_bag(
    bag: str | os.PathLike[str],
    geometry: TetraGeometry,
    compensation: Compensation,
    *,
    origin: tuple[float, float, float] | None = None,
    navsat_topic: str | None = None,
    crs: str | None = None,
    grid: GridSettings | None = None,
    detector: DetectorSettings | None = None,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    progress: bool | None = None,
    on_stage: Callable[[str], None] | None = None,
    earth_field_enu: np.ndarray | None = None,
    tracked: bool | None = None,
) -> SurveyResult:
    """The survey products of ``bag`` (module docstring), placed by ``origin`` (lat, lon, h)
    or fitted to the fixes of ``navsat_topic`` (one of them); the odometry's world frame
    tested against ``earth_field_enu`` (3,) T (the params file's, or IGRF at origin); the
    calibration ``tracked`` (None: as ``compensate`` by default).

    Raises ``BagError`` (no usable ``/odom``, the cause named; the NavSatFix topic absent or
    empty; the data contract), ``InputError`` (both or neither placement, too few fixes,
    nothing to grid)."""
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    _stage(on_stage, 'reading the bag')
    recording = read_recording(
        bag, timebase=timebase, progress=progress, uses='survey', earth_field_enu=earth_field_enu
    )
    if recording.position_m is None or recording.orientation_xyzw is None:
        raise BagError(f'{bag}: {recording.missing[cv.ODOM_TOPIC]}')
    timings['read'] = time.perf_counter() - clock
    clock = time.perf_counter()
    _stage(on_stage, 'compensating and placing the track')
    georeference = georeference_of(bag, recording, origin, navsat_topic)
    crs = crs or georeference.default_crs()
    rotations = Rotation.from_quat(recording.orientation_xyzw).as_matrix()
    compensated = _compensated(bag, recording, geometry, compensation, (rotations, tracked))
    body = compensated[0]
    track = _track(recording, rotations, georeference, crs, compensated)
    track = replace(
        track, legs=legs(track.t_s, track.odom_m, rotations, detector or DetectorSettings())
    )
    health = _health(recording, geometry, compensation, body)
    timings['compensate'] = time.perf_counter() - clock
    clock = time.perf_counter()
    _stage(on_stage, 'gridding')
    index, leg_index = gridded_samples(track.legs, len(track.t_s), (grid or GridSettings()))
    grids = grid_track(
        track.xy_m[index],
        track.tensors[index],
        track.sigma_noise[index],
        track.sigma_calibration[index],
        legs=leg_index,
        array_size_m=_array_size(geometry),
        settings=grid,
    )
    timings['grid'] = time.perf_counter() - clock
    clock = time.perf_counter()
    _stage(on_stage, 'locating targets')
    known = np.all(np.isfinite(body.reshape(len(body), 9)), axis=1)
    survey = Survey(track.t_s[known], recording.position_m[known], rotations[known], body[known])
    targets, detected = locate(survey, geometry, LocatorSettings(detector or DetectorSettings()))
    timings['locate'] = time.perf_counter() - clock
    return SurveyResult(
        track,
        grids,
        georeference,
        crs,
        targets,
        len(detected.detections),
        detected.settings.false_alarms_per_hour,
        float(recording.stamps_ns[0] * S_PER_NS),
        health,
        track_spans(track.t_s, known),
        _leg_residuals(track),
        recording.input_counts(),
        timings,
    )


def gridded_samples(
    track_legs: list[tuple[int, int]], n: int, settings: GridSettings
) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The samples that are gridded (indices) and the legs as ranges of them: the straight
    legs' samples (turns, the trim and transits are not survey data), or every sample with
    ``settings.all_samples`` or when the track has no straight leg."""
    if settings.all_samples or not track_legs:
        return np.arange(n), list(track_legs)
    index = np.concatenate([np.arange(a, b) for a, b in track_legs])
    ends = np.cumsum([b - a for a, b in track_legs])
    return index, [(int(e - (b - a)), int(e)) for e, (a, b) in zip(ends, track_legs, strict=True)]


def _track(
    recording: Recording,
    rotations: FloatArray,
    georeference: Georeference,
    crs: str,
    compensated: tuple[FloatArray, FloatArray, FloatArray],
) -> SurveyTrack:
    """The track in the world frame (no legs yet)."""
    assert recording.position_m is not None
    body, sigma_noise, sigma_cal = compensated
    world_rotations = georeference.rotation[None] @ rotations
    return SurveyTrack(
        recording.t_s,
        recording.stamps_ns,
        recording.position_m,
        georeference.to_crs(recording.position_m, crs),
        georeference.to_lonlat(recording.position_m),
        to_world(body, world_rotations),
        _abs_world(sigma_noise, world_rotations),
        _abs_world(sigma_cal, world_rotations),
        [],
    )


def _array_size(geometry: TetraGeometry) -> float:
    """The largest sensor-to-sensor distance, m."""
    p = geometry.positions
    return float(np.max(np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)))


def georeference_of(
    bag: str | os.PathLike[str],
    recording: Recording,
    origin: tuple[float, float, float] | None,
    navsat_topic: str | None,
) -> Georeference:
    """The placement of the recording's odom frame: at ``origin``, or fitted to the fixes
    of ``navsat_topic`` that fall within the recording (odom interpolated at their stamps)."""
    if (origin is None) == (navsat_topic is None):
        raise InputError(
            'place the survey with --origin LAT,LON[,ALT] or --navsat-topic TOPIC (one of them)'
        )
    if origin is not None:
        return Georeference(origin)
    assert navsat_topic is not None and recording.position_m is not None
    fixes = read_fixes(bag, navsat_topic)
    stamps = recording.stamps_ns
    inside = (fixes.stamps_ns >= stamps[0]) & (fixes.stamps_ns <= stamps[-1])
    odom = np.column_stack(
        [np.interp(fixes.stamps_ns[inside], stamps, c) for c in recording.position_m.T]
    )
    used = Fixes(
        fixes.stamps_ns[inside],
        fixes.lat_deg[inside],
        fixes.lon_deg[inside],
        fixes.alt_m[inside],
        fixes.unlocked,
    )
    return fit_fixes(used, odom, navsat_topic)


def _compensated(
    bag: str | os.PathLike[str],
    recording: Recording,
    geometry: TetraGeometry,
    compensation: Compensation,
    tracking: tuple[FloatArray, bool | None],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Body-frame compensated tensors (N, 3, 3) T/m (NaN where a term's channel is
    unknown; the calibration tracked, pipelines/tracking.py, off the anomalies found along
    the track: ``tracking`` the rotations (N, 3, 3) body -> odom and whether to track, None:
    as ``compensate`` by default), the noise and the calibration parts of
    their 1-sigma (N, 3, 3) T/m."""
    parameters, sigma = compensation.parameters, compensation.sigma
    if parameters is None or sigma is None or compensation.sensor_noise_t is None:
        raise BagError('the survey needs a calibration with a sensor noise figure')
    fields = recording.fields
    x = None
    if parameters.terms:
        with MagneticBag(bag) as reader:
            x = StreamRegressors(parameters.terms, reader, bag)(recording.stamps_ns, fields)
    known = np.ones(len(fields), bool) if x is None else np.all(np.isfinite(x), axis=1)
    raw = difference_tensor(fields, geometry)
    body = np.full_like(raw, np.nan)
    noise_model = SigmaModel.build(geometry, compensation.sensor_noise_t, parameters)
    total = np.full_like(raw, np.nan)
    noise = np.full_like(raw, np.nan)
    xk = None if x is None else x[known]
    body[known] = compensate(raw[known], fields[known, 0, :], parameters, geometry, xk)
    # Tracked when asked (or by default): the tracker's state is part of the calibration sigma.
    assert recording.position_m is not None  # survey_bag refuses a bag without /odom
    track = (recording.t_s, recording.position_m, tracking[0])
    body, variance, _ = track_tensors(
        bag,
        geometry,
        parameters,
        compensation.sensor_noise_t,
        recording,
        body,
        track,
        tracking[1],
        compensation.fitted,
    )
    total[known] = sigma(fields[known, 0, :], xk)
    noise[known] = noise_model(fields[known, 0, :], xk)
    calibration = np.sqrt(np.maximum(total**2 - noise**2, 0.0) + variance)
    return body, noise, calibration


def _abs_world(sigma: FloatArray, rotations: FloatArray) -> FloatArray:
    """Per-component 1-sigma of ``R G R^T`` for independent body components:
    ``sqrt(sum_kl R_ik^2 R_jl^2 s_kl^2)``."""
    squared = np.square(rotations)
    return np.sqrt(np.einsum('nik,nkl,njl->nij', squared, np.square(sigma), squared))


def _health(
    recording: Recording, geometry: TetraGeometry, compensation: Compensation, body: FloatArray
) -> dict[str, Any]:
    """The health monitor's ``report.json`` document over the compensated sets (times from
    the first set)."""
    assert compensation.parameters is not None and compensation.sensor_noise_t is not None
    recorder = HealthRecorder(
        geometry, compensation.parameters, compensation.sensor_noise_t, compensation.covariance
    )
    recorder.add_recording(recording.stamps_ns, recording.fields, body)
    return recorder.document()


def track_spans(t_s: FloatArray, known: np.ndarray) -> list[Span]:
    """Lost spans (gaps over :data:`LOST_PERIODS` median periods) and refused ones (runs of
    sets without a compensated tensor)."""
    out = []
    if len(t_s) > 1:
        period = float(np.median(np.diff(t_s)))
        for i in np.flatnonzero(np.diff(t_s) > LOST_PERIODS * period):
            out.append(Span('lost', float(t_s[i]), float(t_s[i + 1])))
    edges = np.diff(np.concatenate([[0], (~known).astype(np.int8), [0]]))
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        out.append(Span('refused', float(t_s[start]), float(t_s[stop - 1])))
    return sorted(out, key=lambda span: span.start_s)


def _leg_residuals(track: SurveyTrack) -> list[LegResidual]:
    """Per leg: the non-field part of the world-frame tensor against its noise floor
    (:class:`LegResidual`; the trace and the antisymmetric part's norm are frame-free)."""
    sigma = np.sqrt(track.sigma_noise**2 + track.sigma_calibration**2)
    out = []
    for start, stop in track.legs:
        g, s = track.tensors[start:stop], sigma[start:stop]
        finite = np.all(np.isfinite(g.reshape(len(g), 9)), axis=1)
        if not finite.any():
            continue
        g, s = g[finite], s[finite]
        parts = [np.trace(g, axis1=1, axis2=2) / np.sqrt(3.0)]
        floors = [np.sqrt(np.sum(np.square(np.diagonal(s, axis1=1, axis2=2)), axis=1) / 3.0)]
        for i, j in ((0, 1), (0, 2), (1, 2)):
            parts.append((g[:, i, j] - g[:, j, i]) / np.sqrt(2.0))
            floors.append(np.sqrt((s[:, i, j] ** 2 + s[:, j, i] ** 2) / 2.0))
        residual = float(np.sqrt(np.mean(np.square(parts))))
        floor = float(np.sqrt(np.mean(np.square(floors))))
        out.append(
            LegResidual(
                float(track.t_s[start]),
                float(track.t_s[stop - 1]),
                residual * NT_PER_T,
                floor * NT_PER_T,
            )
        )
    return out
