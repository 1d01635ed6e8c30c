"""Targets of a recorded survey: the bag's tensor (compensated with a calibration, and raw
for comparison) searched and located by :func:`tetra_gradiometer.core.targets.locate`.

The track is ``/odom``'s pose (position and attitude, interpolated onto the sets' stamps):
a bag without it cannot place anything and is refused.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..core import InterferenceParameters, TetraGeometry, compensate, difference_tensor
from ..core.targets import DetectionResult, LocatorSettings, Survey, Target, locate
from ..core.timebase import DEFAULT_TIMEBASE, TimeBase
from ..core.units import S_PER_NS
from ..errors import BagError
from ..io import conversions as cv
from ..io.bag import MagneticBag
from ..io.recording import Recording, read_recording
from .health import HealthRecorder
from .terms import StreamRegressors
from .tracking import track_tensors


@dataclass(frozen=True)
class Search:
    """One tensor's search: what was searched (``tensor``: 'compensated' or 'raw'), the
    survey, the targets and the first detection pass."""

    tensor: str
    survey: Survey
    targets: list[Target]
    detected: DetectionResult


@dataclass(frozen=True)
class BagTargets:
    """:func:`locate_bag`'s result: the compensated search (``main``; the raw one when no
    calibration was given), the raw comparison (None when not asked for or when ``main``
    is raw), the absolute stamp of the first sample ``t0_stamp_s`` (Unix s), and the
    recording's input counts (sets dropped, messages skipped); ``held_summary``: what was
    done for a channel absent from the bag (``allow_missing_channels``; '' when none)."""

    main: Search
    comparison: Search | None
    t0_stamp_s: float
    input_counts: dict[str, int]
    held_summary: str = ''


def survey_of(recording: Recording, tensors: np.ndarray, where: str) -> Survey:
    """The :class:`Survey` of a recording's samples with ``tensors`` (N, 3, 3) T/m."""
    if recording.position_m is None or recording.orientation_xyzw is None:
        reason = recording.missing.get(cv.ODOM_TOPIC, f'no {cv.ODOM_TOPIC} in the bag')
        raise BagError(
            f'{where}: {reason}: targets are located on the track, which needs the pose '
            '(record the navigation odometry with the magnetometers)'
        )
    rotations = Rotation.from_quat(recording.orientation_xyzw).as_matrix()
    return Survey(recording.t_s, recording.position_m, rotations, tensors)


def _term_regressors(
    bag: str | os.PathLike[str],
    parameters: InterferenceParameters,
    recording: Recording,
    geometry: TetraGeometry | None,
) -> tuple[np.ndarray | None, str]:
    """The calibration's terms' regressors on the recording's sets (None without terms),
    NaN where a channel is unknown; with ``geometry``, an absent channel's terms held
    (:class:`~.terms.HeldTerms`) and what was done ('' otherwise)."""
    if not parameters.terms:
        return None, ''
    with MagneticBag(bag) as reader:
        stream = StreamRegressors(parameters.terms, reader, bag, geometry)
        x = stream(recording.stamps_ns, recording.fields)
    return x, '' if stream.held is None else stream.held.text()


def locate_bag(
    bag: str | os.PathLike[str],
    geometry: TetraGeometry,
    parameters: InterferenceParameters | None,
    *,
    settings: LocatorSettings | None = None,
    comparison: bool = False,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    progress: bool | None = None,
    on_stage: Callable[[str], None] | None = None,
    allow_missing_channels: bool = False,
    earth_field_enu: np.ndarray | None = None,
    health: HealthRecorder | None = None,
    tracking: tuple[float | None, bool | None, int | None] = (None, False, None),
) -> BagTargets:
    """Search the bag's compensated tensor (eq. 19 with ``parameters``; the raw tensor, eq.
    7, when None) and, with ``comparison``, the raw one too. ``allow_missing_channels``: a
    channel the terms read that the bag lacks holds its terms at their calibration-window
    mean instead of refusing (``compensate --allow-missing-channels``). ``earth_field_enu``
    (3,) T, the params file's: the odometry's world frame is tested against it. ``health``
    (pipelines/health) is fed the compensated sets: the output checks itself.
    ``tracking``: the calibration's sensor noise (T), whether to track it
    (pipelines/tracking.py; None: as ``compensate`` by default) and its last fitted stamp, ns
    (:func:`~.tracking.learn_after_ns`).

    Raises
    ------
    BagError
        The bag breaks the data contract or has no ``/odom``.
    InputError
        No straight leg to search (:func:`~tetra_gradiometer.core.targets.detect`).
    """
    recording = read_recording(
        bag, timebase=timebase, progress=progress, uses='locate', earth_field_enu=earth_field_enu
    )
    raw = difference_tensor(recording.fields, geometry)
    track = survey_of(recording, raw, str(bag))  # the pose once; each search its tensor
    searches: list[Search] = []
    kinds: list[tuple[str, np.ndarray]] = []
    held = ''
    if parameters is not None:
        x, held = _term_regressors(
            bag, parameters, recording, geometry if allow_missing_channels else None
        )
        b1 = recording.fields[:, 0, :]
        g = compensate(raw, b1, parameters, geometry, x)
        g, _, _ = track_tensors(
            bag,
            geometry,
            parameters,
            tracking[0],
            recording,
            g,
            (track.t_s, track.positions, track.rotations),
            asked=tracking[1],
            fitted=tracking[2],
        )
        kinds.append(('compensated', g))
        if health is not None:
            health.add_recording(recording.stamps_ns, recording.fields, kinds[-1][1])
    if parameters is None or comparison:
        kinds.append(('raw', raw))
    for tensor, tensors in kinds:
        if on_stage is not None:
            on_stage(f'locating on the {tensor} tensor')
        # Sets where a channel the terms read is unknown have no compensated tensor.
        known = np.all(np.isfinite(tensors.reshape(len(tensors), 9)), axis=1)
        survey = Survey(
            track.t_s[known], track.positions[known], track.rotations[known], tensors[known]
        )
        targets, detected = locate(survey, geometry, settings)
        searches.append(Search(tensor, survey, targets, detected))
    return BagTargets(
        searches[0],
        searches[1] if len(searches) > 1 else None,
        float(recording.stamps_ns[0] * S_PER_NS),
        recording.input_counts(),
        held,
    )
