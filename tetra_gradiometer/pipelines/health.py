"""The health monitor of :mod:`tetra_gradiometer.core.health` run over a bag's compensated
sets, chunk by chunk, keeping what the offline report (:mod:`tetra_gradiometer.reports.health`)
needs: the alarms and the largest statistics per second.
"""

from __future__ import annotations

import numpy as np

from ..core.geometry import TetraGeometry
from ..core.health import HealthConfig, HealthMonitor, HealthTrace
from ..core.model import InterferenceParameters
from ..core.units import NS_PER_S, NT_PER_T, S_PER_NS

__all__ = ['BIN_S', 'HealthRecorder', 'alarm_cause']

#: Set stamps further than this from the bag's first log time are on another clock.
SAME_CLOCK_NS = 86_400 * NS_PER_S
#: An alarm within this many seconds of the first set says the calibration never held on
#: this recording (a calibration of another vehicle or time alarms at once).
FROM_START_S = 10.0
#: Plot bins, seconds (the largest statistic of each).
BIN_S = 1.0


def alarm_cause(after_first_s: float, data: str) -> str:
    """The likely cause of an alarm ``after_first_s`` seconds after the first set of the
    ``data`` (``recording``, ``run``): from the data's first seconds the calibration never held
    (made for another vehicle or time, or the array changed since); later, the vehicle changed
    during it."""
    if after_first_s <= FROM_START_S:
        return (
            f'it does not hold from the start of the data (alarm {after_first_s:.1f} s after '
            "the first set): this calibration is not this vehicle's as it is now (another "
            "vehicle's, an old one, or the array changed since the trim: a sensor turned or "
            f'moved, the positions or frame edited); calibrate on a trim of this {data}'
        )
    return f'the vehicle changed during the {data}; recalibrate (a new trim)'


class HealthRecorder:
    """Feeds the monitor chunk by chunk and keeps what the report needs (binned statistics).

    Parameters
    ----------
    geometry, parameters, sensor_noise_t, covariance, config
        As for :class:`~tetra_gradiometer.core.health.HealthMonitor`.
    """

    def __init__(
        self,
        geometry: TetraGeometry,
        parameters: InterferenceParameters,
        sensor_noise_t: float,
        covariance: np.ndarray | None,
        config: HealthConfig | None = None,
    ) -> None:
        self.monitor = HealthMonitor(geometry, parameters, sensor_noise_t, covariance, config)
        self._sensor_noise_t = sensor_noise_t
        self._origin_ns: int | None = None
        self.origin = 'bag start'
        self._first_s: float | None = None
        self.bins: dict[int, tuple[float, float]] = {}

    @property
    def origin_ns(self) -> int | None:
        """The stamp the monitor's times count from, ns (None before the first set)."""
        return self._origin_ns

    def add_recording(
        self, stamps_ns: np.ndarray, fields: np.ndarray, tensors: np.ndarray
    ) -> None:
        """A whole recording's sets (times from its first set), those with a compensated
        tensor (a set whose channel was stale has none)."""
        known = np.all(np.isfinite(tensors.reshape(len(tensors), 9)), axis=1)
        if known.any():
            stamps = stamps_ns[known]
            self.add(stamps, fields[known], tensors[known], bag_start_ns=int(stamps[0]))

    def add(
        self, stamps_ns: np.ndarray, fields: np.ndarray, tensors: np.ndarray, *, bag_start_ns: int
    ) -> None:
        """One chunk: stamps (n,) ns, fields (n, 4, 3) T, compensated tensors (n, 3, 3) T/m;
        ``bag_start_ns`` the log time of the bag's first message."""
        if not len(stamps_ns):
            return
        if self._origin_ns is None:
            first = int(stamps_ns[0])
            same_clock = abs(first - int(bag_start_ns)) <= SAME_CLOCK_NS
            self._origin_ns = int(bag_start_ns) if same_clock else first
            self.origin = 'bag start' if same_clock else 'first set'
        t_s = (np.asarray(stamps_ns, dtype=np.int64) - self._origin_ns) * S_PER_NS
        if self._first_s is None:
            self._first_s = float(t_s[0])
        self._keep(self.monitor.update(t_s, tensors, fields[:, 0, :]))

    def _keep(self, trace: HealthTrace) -> None:
        """The largest statistics per plot bin (NaN-free)."""
        if not len(trace.t_s):
            return
        bins = np.floor(trace.t_s / BIN_S).astype(np.int64)
        order = np.argsort(bins, kind='stable')
        keys, starts = np.unique(bins[order], return_index=True)
        largest = [
            np.fmax.reduceat(np.where(np.isfinite(v), v, np.nan)[order], starts)
            for v in (trace.glr, trace.drift)
        ]
        for b, glr_max, drift_max in zip(keys.tolist(), *largest, strict=True):
            old = self.bins.get(b, (np.nan, np.nan))
            self.bins[b] = (float(np.fmax(old[0], glr_max)), float(np.fmax(old[1], drift_max)))

    def document(self) -> dict:
        """The content of ``report.json``."""
        monitor, config = self.monitor, self.monitor.config
        alarms = [alarm.to_dict() for alarm in monitor.alarms]
        if alarms:
            first = alarms[0]
            verdict = (
                f'{len(alarms)} alarm(s): first at {first["t_s"]:.1f} s, {first["kind"]}'
                + (f', sensor(s) {first["sensors"]}' if first['sensors'] else '')
                + ': the calibration no longer holds; '
                + alarm_cause(float(first['t_s']) - (self._first_s or 0.0), 'recording')
            )
        else:
            verdict = 'no change detected'
        finite = float(monitor.threshold) if np.isfinite(monitor.threshold) else None
        return {
            'alarms': alarms,
            'time_origin_ns': self._origin_ns,
            'time_origin': self.origin,
            'monitor': {
                'threshold': finite,
                'false_alarms_per_hour': config.false_alarms_per_hour,
                'sample_rate_hz': (
                    monitor.sample_rate_hz if np.isfinite(monitor.sample_rate_hz) else None
                ),
                'noise_scale': monitor.noise_scale,
                'sensor_noise_nT': self._sensor_noise_t * NT_PER_T,
                'windows_s': list(config.windows_s),
                'drift_time_constant_s': config.drift_time_constant_s,
                'min_source_range_edges': config.min_source_range_edges,
                'samples': monitor.samples,
            },
            'verdict': verdict,
        }
