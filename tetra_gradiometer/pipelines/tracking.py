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
from ..core.units import NT_PER_T, S_PER_NS
from ..io import conversions as cv
from .health import HealthRecorder

__all__ = [
    'TRACK_BY_DEFAULT',
    'TRACKING_COLUMNS',
    'TrackedStream',
    'odometry_orientation',
    'tracked_stream',
]

#: Whether ``compensate`` tracks the calibration unless told to freeze it. Off while
#: ``locate``'s targets are not measured with it, and because without ``/odom`` (the
#: compensator node's case) the drift is followed only in part (docs/offline.md,
#: bench/results/tracker.json).
TRACK_BY_DEFAULT = False

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


def tracked_stream(
    bag_path: Any,
    geometry: TetraGeometry,
    parameters: InterferenceParameters,
    sensor_noise_t: float,
    health: HealthRecorder | None,
) -> tuple[TrackedStream, str]:
    """The tracker of a bag's compensation (``compensate``), with ``/odom`` when it is
    usable; and what it goes without ('' when nothing)."""
    from ..io.bag import MagneticBag

    with MagneticBag(bag_path) as bag:
        orientation, note = odometry_orientation(bag)
    return TrackedStream(geometry, parameters, sensor_noise_t, orientation, health), note


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
            geometry, parameters, sensor_noise_t, config, with_world=orientation is not None
        )
        self.orientation = orientation
        self.health = health
        self._origin_ns: int | None = None

    def __call__(
        self, stamps_ns: np.ndarray, fields: FloatArray, tensors: FloatArray, bag_start_ns: int
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """One chunk: ``stamps_ns`` (n,), ``fields`` (n, 4, 3) T, ``tensors`` (n, 3, 3) T/m
        compensated with the frozen calibration. Returns the tracked tensors (n, 3, 3) T/m,
        the state's variance per component (n, 9) (T/m)^2 and the change removed (n, 9) T."""
        if self._origin_ns is None and len(stamps_ns):
            self._origin_ns = int(stamps_ns[0])
        elapsed = np.asarray(stamps_ns, dtype=np.int64) - (self._origin_ns or 0)
        t_s = elapsed.astype(np.float64) * S_PER_NS
        quaternions = None if self.orientation is None else self.orientation(stamps_ns)
        feed = None
        health = self.health
        if health is not None:

            def feed(start: int, stop: int, g: FloatArray) -> list[tuple[float, tuple[int, ...]]]:
                before = len(health.monitor.alarms)
                rows = slice(start, stop)
                health.add(stamps_ns[rows], fields[rows], g, bag_start_ns=bag_start_ns)
                steps = handed_over(health.monitor.alarms[before:])
                # The monitor's times are from the bag's start, the tracker's from the first set.
                shift = ((health.origin_ns or 0) - (self._origin_ns or 0)) * S_PER_NS
                return [(t + shift, sensors) for t, sensors in steps]

        chunk = self.tracker.update(t_s, tensors, quaternions, health=feed)
        return chunk.g, chunk.variance, chunk.offsets

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
