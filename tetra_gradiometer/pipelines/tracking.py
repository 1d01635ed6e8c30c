"""The calibration tracker (core/tracking.py) over a stream of compensated sets, chunk by
chunk: ``compensate --track-calibration``. (The compensator node's ``track_calibration``
calls :meth:`~tetra_gradiometer.core.tracking.OffsetTracker.one` per message, equal to this
path without the attitude.)

:class:`TrackedStream` takes each chunk's stamps, readings and tensors compensated with the
frozen calibration, and returns the tracked tensors and the state's share of their variance.
It feeds the health monitor (when there is one) with the tracked tensors, block by block,
and the monitor's steps go back to the tracker. The attitude, when known, lets it separate
the body-fixed from the world-fixed gradient; without it only the four combinations the
constraints observe are tracked.

The audit trail (:meth:`TrackedStream.document`, ``tracking.json`` in a report folder) holds
every block's verdict (update, gated, excluded), the offsets' change and its 1-sigma after
it, and every step (when, which sensor, how big, how sure). The CSV's ``db_*`` columns carry
the change removed from each row, nT.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.geometry import TetraGeometry, interp_orientation
from ..core.model import InterferenceParameters
from ..core.odometry import check_odometry
from ..core.tracking import OffsetTracker, TrackerConfig, handed_over
from ..core.types import FloatArray
from ..core.units import NS_PER_S, NT_PER_T, S_PER_NS
from ..errors import InputError
from ..io import conversions as cv
from .health import HealthRecorder

__all__ = [
    'TRACK_BY_DEFAULT',
    'TRACKING_COLUMNS',
    'TrackedStream',
    'learn_after_ns',
    'odometry_orientation',
    'target_spans',
    'track_tensors',
    'tracked_stream',
]

#: Whether ``compensate``, ``survey``, ``locate``, ``batch`` (and the compensator node's
#: ``track_calibration``) track the calibration unless told otherwise (``--freeze-calibration``
#: switches it off). On: drifting hulls go from 7-12x the floor frozen to 1.01-1.03x with
#: ``/odom`` (bench/results/tracker.json); vehicles that do not change stay within 0.5 % of
#: frozen (bench/results/window.json) and survey cells keep their sigma (docs/offline.md).
TRACK_BY_DEFAULT = True

#: Seconds each side of a detected anomaly the tracker does not learn from.
TARGET_MARGIN_S = 5.0

#: The CSV's columns of the pair offsets' change (nT): ``db_<sensor>1<axis>``.
TRACKING_COLUMNS = tuple(f'db_{s}1{axis}' for s in (2, 3, 4) for axis in 'xyz')


@dataclass(frozen=True)
class OrientationSource:
    """``/odom``'s orientations (checked for norms and a frozen pose, core/odometry.py; not
    against the magnetometers), slerped onto set stamps (ns)."""

    stamps_ns: np.ndarray
    quaternions: FloatArray

    def __call__(self, stamps_ns: np.ndarray) -> FloatArray:
        """(n, 4) x, y, z, w at ``stamps_ns`` (n,)."""
        return interp_orientation(self.stamps_ns, self.quaternions, stamps_ns)


def odometry_orientation(bag: Any) -> tuple[OrientationSource | None, str]:
    """The bag's ``/odom`` orientation as a source for the tracker, or None and why not."""
    series = bag.read_series(cv.ODOM_TOPIC)
    if series is None:
        return None, f'no {cv.ODOM_TOPIC}: the tracker follows the 4 constrained combinations only'
    check = check_odometry(series.stamps_ns, series.values)
    if not check.orientation_ok:
        return None, f'{cv.ODOM_TOPIC} unusable ({check.text()}): constrained combinations only'
    return OrientationSource(check.stamps_ns, check.pose[:, cv.POSE_ORIENTATION]), ''


def learn_after_ns(diagnostics: dict[str, Any]) -> int | None:
    """The stamp (ns) up to which the tracker does not learn: the last set the calibration
    fitted (its ``diagnostics``' ``samples_window_s``, written by ``calibrate`` and the
    calibrator node), or None when the file does not say. Up to there the fit is the truth:
    a stream holding the calibration's own trim (one bag of the whole mission, or its live
    replay) is compensated as fitted until the trim's end, and a trim before it, over a
    target, teaches the offsets nothing. A stream recorded before the calibration is not
    tracked at all. One rule, on stamps, for ``compensate`` and the compensator node."""
    window: Any = diagnostics.get('samples_window_s')
    try:
        return int(round(float(window[1]) * NS_PER_S))
    except (TypeError, ValueError, IndexError):
        return None


def tracked_stream(
    bag_path: Any,
    geometry: TetraGeometry,
    parameters: InterferenceParameters | None,
    sensor_noise_t: float | None,
    health: HealthRecorder | None,
    asked: bool | None = None,
    fitted: int | None = None,
) -> tuple[TrackedStream | None, str]:
    """The tracker of a bag's compensation (``compensate``, ``batch``), with ``/odom`` when
    it is usable, and what it goes without ('' when nothing). ``asked`` True or False
    (``--track-calibration``, ``--freeze-calibration``), None: :data:`TRACK_BY_DEFAULT`, and
    then no tracker, with a note, when the calibration gives no sensor noise. ``fitted``:
    the calibration's last fitted stamp (:func:`learn_after_ns`): the tracker learns only
    from the sets stamped after it.

    Raises
    ------
    InputError
        Tracking asked for without a calibration or a sensor noise.
    """
    from ..io.bag import MagneticBag

    if not (TRACK_BY_DEFAULT if asked is None else asked):
        return None, ''
    if parameters is None or sensor_noise_t is None:
        if asked:
            raise InputError('--track-calibration needs a calibration and a sensor noise')
        return None, (
            'the calibration is not tracked: no calibration or no sensor noise estimate '
            '(give --sensor-noise-nt)' * (parameters is not None)
        )
    with MagneticBag(bag_path) as bag:
        orientation, note = odometry_orientation(bag)
    tracking = TrackedStream(geometry, parameters, sensor_noise_t, orientation, health)
    tracking.learn_after_ns = fitted
    return tracking, note


def target_spans(
    t_s: FloatArray, tensors: FloatArray, positions: FloatArray, rotations: FloatArray
) -> np.ndarray:
    """The samples (N,) bool the tracker must not learn from: the anomalies detected on the
    frozen calibration's ``tensors`` (N, 3, 3) T/m along the track (``t_s`` (N,) s,
    ``positions`` (N, 3) m, ``rotations`` (N, 3, 3) body -> world), widened by
    :data:`TARGET_MARGIN_S` each side. (Learning from a target's pass moved its located
    position and moment by up to 1.7 sigma; excluded, by under 0.1.)"""
    from ..core.targets.detection import DetectorSettings, detect

    exclude = np.zeros(len(t_s), dtype=bool)
    known = np.flatnonzero(np.all(np.isfinite(tensors.reshape(len(tensors), 9)), axis=1))
    try:
        found = detect(
            t_s[known], tensors[known], positions[known], rotations[known], DetectorSettings()
        )
    except InputError:  # no straight leg to search: nothing to exclude
        return exclude
    for detection in found.detections:
        first = t_s[known[detection.start]] - TARGET_MARGIN_S
        last = t_s[known[detection.stop - 1]] + TARGET_MARGIN_S
        exclude |= (t_s >= first) & (t_s <= last)
    return exclude


def track_tensors(
    bag_path: Any,
    geometry: TetraGeometry,
    parameters: InterferenceParameters | None,
    sensor_noise_t: float | None,
    recording: Any,
    tensors: FloatArray,
    track: tuple[FloatArray, FloatArray, FloatArray],
    asked: bool | None = None,
    fitted: int | None = None,
) -> tuple[FloatArray, FloatArray, str]:
    """A whole recording's compensated ``tensors`` (N, 3, 3) T/m tracked as ``compensate``
    tracks them (``survey``, ``locate``), never learning from the anomalies
    detected along ``track`` (``t_s``, ``positions``, ``rotations``: :func:`target_spans`):
    the tracked tensors (NaN rows stay NaN), the state's variance (N, 3, 3) (T/m)^2 and the
    tracker's summary line (or why there is none). ``recording``: its ``stamps_ns`` (N,)
    and ``fields`` (N, 4, 3) T; ``asked``, ``fitted``: as :func:`tracked_stream`'s."""
    tracking, note = tracked_stream(
        bag_path, geometry, parameters, sensor_noise_t, None, asked, fitted
    )
    variance = np.zeros_like(tensors)
    if tracking is None:
        return tensors, variance, note
    exclude = target_spans(track[0], tensors, track[1], track[2])
    known = np.all(np.isfinite(tensors.reshape(len(tensors), 9)), axis=1)
    tracked = tensors.copy()
    if known.any():
        stamps = recording.stamps_ns
        g, var, _ = tracking(
            stamps[known],
            recording.fields[known],
            tensors[known],
            int(stamps[0]),
            exclude[known],
        )
        tracked[known], variance[known] = g, var.reshape(-1, 3, 3)
    return tracked, variance, '; '.join(part for part in (note, tracking.text()) if part)


class TrackedStream:
    """Tracks the calibration over consecutive chunks of sets.

    Parameters
    ----------
    geometry : TetraGeometry
    parameters : InterferenceParameters
        The frozen calibration the chunks were compensated with.
    sensor_noise_t : float
        Per-axis sensor noise, tesla.
    orientation : OrientationSource or None
        The attitude on set stamps; None: the constrained combinations only.
    health : HealthRecorder, optional
        Fed the tracked tensors (its steps handed to the tracker); otherwise the tracker's
        own gate finds steps.
    config : TrackerConfig, optional
    """

    def __init__(
        self,
        geometry: TetraGeometry,
        parameters: InterferenceParameters,
        sensor_noise_t: float,
        orientation: OrientationSource | None = None,
        health: HealthRecorder | None = None,
        config: TrackerConfig | None = None,
    ) -> None:
        self.tracker = OffsetTracker(
            geometry,
            parameters,
            sensor_noise_t,
            config,
            with_world=orientation is not None,
            monitored=health is not None,
        )
        self.orientation = orientation
        self.health = health
        #: The stamp (ns) up to which the sets stay as compensated (:func:`learn_after_ns`).
        self.learn_after_ns: int | None = None
        self._origin_ns: int | None = None

    def __call__(
        self,
        stamps_ns: np.ndarray,
        fields: FloatArray,
        tensors: FloatArray,
        bag_start_ns: int,
        exclude: np.ndarray | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """One chunk: ``stamps_ns`` (n,), ``fields`` (n, 4, 3) T, ``tensors`` (n, 3, 3) T/m
        compensated with the frozen calibration, ``exclude`` (n,) bool samples not learnt
        from (targets). Returns the tracked tensors (n, 3, 3) T/m,
        the state's variance per component (n, 9) (T/m)^2 and the change removed (n, 9) T.
        Sets stamped up to :attr:`learn_after_ns` are the frozen ones: the tracker starts
        after them."""
        if self._origin_ns is None and len(stamps_ns):
            self._origin_ns = int(stamps_ns[0])
        elapsed = np.asarray(stamps_ns, dtype=np.int64) - (self._origin_ns or 0)
        t_s = elapsed.astype(np.float64) * S_PER_NS
        n = len(t_s)
        held = (
            0
            if self.learn_after_ns is None
            else int(np.searchsorted(stamps_ns, self.learn_after_ns, side='right'))
        )
        g, variance, offsets = tensors.copy(), np.zeros((n, 9)), np.zeros((n, 9))
        health = self.health
        if held and health is not None:
            health.add(stamps_ns[:held], fields[:held], tensors[:held], bag_start_ns=bag_start_ns)
        if held == n:
            return g, variance, offsets
        rows = slice(held, n)
        quaternions = None if self.orientation is None else self.orientation(stamps_ns[rows])
        feed = None
        if health is not None:

            def feed(
                start: int, stop: int, tracked: FloatArray
            ) -> list[tuple[float, tuple[int, ...]]]:
                before = len(health.monitor.alarms)
                part = slice(held + start, held + stop)
                health.add(stamps_ns[part], fields[part], tracked, bag_start_ns=bag_start_ns)
                steps = handed_over(health.monitor.alarms[before:])
                # The monitor's times are from the bag's start, the tracker's from the first set.
                shift = ((health.origin_ns or 0) - (self._origin_ns or 0)) * S_PER_NS
                return [(t + shift, sensors) for t, sensors in steps]

        chunk = self.tracker.update(
            t_s[rows],
            tensors[rows],
            quaternions,
            None if exclude is None else exclude[rows],
            health=feed,
        )
        g[rows], variance[rows], offsets[rows] = chunk.g, chunk.variance, chunk.offsets
        return g, variance, offsets

    #: The CSV header's further columns.
    csv_columns = ',' + ','.join(TRACKING_COLUMNS)

    def apply(
        self,
        stamps_ns: np.ndarray,
        fields: FloatArray,
        tensors: FloatArray,
        sigmas: FloatArray | None,
        bag_start_ns: int,
    ) -> tuple[FloatArray, FloatArray | None, FloatArray]:
        """:meth:`__call__`, with the 1-sigma ``sigmas`` (n, 3, 3) T/m (or None) widened in
        quadrature by the state's share."""
        tracked, variance, offsets = self(stamps_ns, fields, tensors, bag_start_ns)
        if sigmas is not None:
            sigmas = np.sqrt(sigmas**2 + variance.reshape(-1, 3, 3))
        return tracked, sigmas, offsets

    def document(self) -> dict[str, Any]:
        """``tracking.json``: the settings, the steps and every block's verdict (columnar:
        ``t_s`` from the first set, ``kind``, ``offsets_nT`` and ``sigma_nT`` (9 each), the
        innovation chi-square)."""
        events = self.tracker.events
        blocks = [e for e in events if e.kind != 'step']
        steps = [e.to_dict() for e in events if e.kind == 'step']
        kinds = ('update', 'gated', 'excluded', 'transient')
        counts = {kind: sum(e.kind == kind for e in blocks) for kind in kinds}
        return {
            'time_origin_ns': self._origin_ns,
            'attitude': self.orientation is not None,
            'config': {
                k: getattr(self.tracker.config, k) for k in TrackerConfig.__dataclass_fields__
            },
            'columns': list(TRACKING_COLUMNS),
            'steps': steps,
            'counts': counts,
            'final_offsets_nT': (self.tracker.offsets_t * NT_PER_T).reshape(9).tolist(),
            'final_sigma_nT': (self.tracker.offsets_sigma_t * NT_PER_T).reshape(9).tolist(),
            'blocks': {
                't_s': [round(e.t_s, 3) for e in blocks],
                'kind': [e.kind for e in blocks],
                'offsets_nT': [
                    (e.offsets_t * NT_PER_T).reshape(9).round(5).tolist() for e in blocks
                ],
                'sigma_nT': [(e.sigma_t * NT_PER_T).reshape(9).round(5).tolist() for e in blocks],
                'statistic': [
                    None if np.isnan(e.statistic) else round(e.statistic, 2) for e in blocks
                ],
            },
        }

    def text(self) -> str:
        """One line for the command's summary."""
        doc = self.document()
        steps = ', '.join(
            f'sensor {s["sensors"][0]} at {s["t_s"]:.1f} s by {np.linalg.norm(s["step_nT"]):.3g} '
            f'nT (1-sigma {max(s["step_sigma_nT"]):.2g} nT per axis)'
            for s in doc['steps']
            if s['sensors'] and 'step_nT' in s
        )
        final = np.abs(np.asarray(doc['final_offsets_nT'])).max()
        return (
            f'calibration tracked ({"with" if doc["attitude"] else "without"} the attitude): '
            f'{doc["counts"]["update"]} updates, {doc["counts"]["gated"]} gated, '
            f'steps: {steps or "none"}; largest offset change at the end {final:.3f} nT'
        )
