"""The offline health report of ``compensate --report DIR``: the monitor of
:mod:`tetra_gradiometer.core.health` run over a bag's compensated sets.

``DIR/report.json``::

    {"alarms": [{"t_s", "onset_s", "kind", "sensors" (1-based, best first), "statistic",
                 "threshold", "shift_nT_per_m", "settled"}],
     "time_origin_ns": ..., "time_origin": "bag start" | "first set",
     "monitor": {"threshold", "false_alarms_per_hour", "sample_rate_hz", "noise_scale",
                 "sensor_noise_nT", "windows_s", "drift_time_constant_s",
                 "min_source_range_edges", "samples"},
     "verdict": "no change detected" | "N alarm(s): ..."}

``t_s`` is seconds since the bag's first message (its log time), unless the set stamps are
on another clock than the log times (more than a day apart: a replay stamped from zero),
then since the first set; ``time_origin`` says which. ``DIR/health.png`` plots the two
statistics over time (the largest per second) against the threshold, alarms marked.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ..core.geometry import TetraGeometry
from ..core.health import HealthConfig, HealthMonitor, HealthTrace
from ..core.model import InterferenceParameters
from ..core.units import NS_PER_S, NT_PER_T, S_PER_NS
from .outputs import HEALTH_REPORT, atomic_output

__all__ = ['HealthRecorder']

#: Set stamps further than this from the bag's first log time are on another clock.
SAME_CLOCK_NS = 86_400 * NS_PER_S
#: Plot bins, seconds (the largest statistic of each).
BIN_S = 1.0


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
        self._origin = 'bag start'
        self._bins: dict[int, tuple[float, float]] = {}

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
            self._origin = 'bag start' if same_clock else 'first set'
        t_s = (np.asarray(stamps_ns, dtype=np.int64) - self._origin_ns) * S_PER_NS
        self._keep(self.monitor.update(t_s, tensors, fields[:, 0, :]))

    def _keep(self, trace: HealthTrace) -> None:
        """The largest statistics per plot bin (NaN-free)."""
        bins = np.floor(trace.t_s / BIN_S).astype(np.int64)
        for b in np.unique(bins):
            inside = bins == b
            glr = trace.glr[inside]
            drift = trace.drift[inside]
            glr_max = float(np.nanmax(glr)) if np.any(np.isfinite(glr)) else np.nan
            drift_max = float(np.nanmax(drift)) if np.any(np.isfinite(drift)) else np.nan
            old = self._bins.get(int(b), (np.nan, np.nan))
            self._bins[int(b)] = (
                float(np.fmax(old[0], glr_max)),
                float(np.fmax(old[1], drift_max)),
            )

    def document(self) -> dict:
        """The content of ``report.json``."""
        monitor, config = self.monitor, self.monitor.config
        alarms = [alarm.to_dict() for alarm in monitor.alarms]
        if alarms:
            first = alarms[0]
            verdict = (
                f'{len(alarms)} alarm(s): first at {first["t_s"]:.1f} s, {first["kind"]}'
                + (f', sensor(s) {first["sensors"]}' if first['sensors'] else '')
                + ': the calibration no longer holds; recalibrate'
            )
        else:
            verdict = 'no change detected'
        finite = float(monitor.threshold) if np.isfinite(monitor.threshold) else None
        return {
            'alarms': alarms,
            'time_origin_ns': self._origin_ns,
            'time_origin': self._origin,
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

    def write(
        self,
        out_dir: str | os.PathLike,
        *,
        force: bool = False,
        inputs: Iterable[str | os.PathLike] = (),
    ) -> Path:
        """``report.json`` and ``health.png`` into the folder ``out_dir``, atomically."""
        document = self.document()
        with atomic_output(
            out_dir, HEALTH_REPORT, force=force, inputs=inputs, command='compensate'
        ) as out:
            out.mkdir()
            (out / 'report.json').write_text(
                json.dumps(document, indent=2, allow_nan=False) + '\n', encoding='utf-8'
            )
            self._plot(out / 'health.png')
        return Path(out_dir)

    def _plot(self, path: Path) -> None:
        from matplotlib.figure import Figure

        keys = sorted(self._bins)
        t = np.array(keys, dtype=float) * BIN_S
        values = np.array([self._bins[k] for k in keys]).reshape(-1, 2)
        threshold = self.monitor.threshold
        fig = Figure(figsize=(9, 5))
        axes = fig.subplots(2, 1, sharex=True)
        labels = ('windowed GLR (level and jump tests)', 'drift tracker')
        for ax, column, label in zip(axes, values.T, labels, strict=True):
            ax.semilogy(t, np.maximum(column, 1e-3), lw=0.7, label=label)
            if np.isfinite(threshold):
                ax.axhline(threshold, color='red', lw=0.8, label=f'threshold {threshold:.1f}')
            for alarm in self.monitor.alarms:
                ax.axvline(alarm.t_s, color='black', ls='--', lw=0.8)
            ax.set_ylabel('chi2(4) statistic')
            ax.legend(loc='upper left', fontsize=8)
        names = ', '.join(
            f'{a.t_s:.1f} s {a.kind} {list(a.sensors)}' for a in self.monitor.alarms[:3]
        )
        axes[0].set_title('Health of the calibration' + (f': alarms {names}' if names else ''))
        axes[1].set_xlabel(f's since the {self._origin}')
        fig.tight_layout()
        fig.savefig(path, format='png', dpi=90)
