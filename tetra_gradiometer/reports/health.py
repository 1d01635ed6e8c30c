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

from ..io.outputs import HEALTH_REPORT, atomic_output
from ..pipelines.health import BIN_S, HealthRecorder

__all__ = ['write_health_report']


def write_health_report(
    recorder: HealthRecorder,
    out_dir: str | os.PathLike,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    extra: dict[str, dict] | None = None,
) -> Path:
    """``report.json`` and ``health.png`` into the folder ``out_dir``, atomically, with the
    JSON documents of ``extra`` (file name -> content: the tracker's ``tracking.json``)."""
    document = recorder.document()
    with atomic_output(
        out_dir, HEALTH_REPORT, force=force, inputs=inputs, command='compensate'
    ) as out:
        out.mkdir()
        (out / 'report.json').write_text(
            json.dumps(document, indent=2, allow_nan=False) + '\n', encoding='utf-8'
        )
        for name, content in (extra or {}).items():
            (out / name).write_text(json.dumps(content, allow_nan=False) + '\n', encoding='utf-8')
        _plot(recorder, out / 'health.png')
    return Path(out_dir)


def _plot(recorder: HealthRecorder, path: Path) -> None:
    from matplotlib.figure import Figure

    keys = sorted(recorder.bins)
    t = np.array(keys, dtype=float) * BIN_S
    values = np.array([recorder.bins[k] for k in keys]).reshape(-1, 2)
    threshold = recorder.monitor.threshold
    fig = Figure(figsize=(9, 5))
    axes = fig.subplots(2, 1, sharex=True)
    labels = ('windowed GLR (level and jump tests)', 'drift tracker')
    for ax, column, label in zip(axes, values.T, labels, strict=True):
        ax.semilogy(t, np.maximum(column, 1e-3), lw=0.7, label=label)
        if np.isfinite(threshold):
            ax.axhline(threshold, color='red', lw=0.8, label=f'threshold {threshold:.1f}')
        for alarm in recorder.monitor.alarms:
            ax.axvline(alarm.t_s, color='black', ls='--', lw=0.8)
        ax.set_ylabel('chi2(4) statistic')
        ax.legend(loc='upper left', fontsize=8)
    names = ', '.join(
        f'{a.t_s:.1f} s {a.kind} {list(a.sensors)}' for a in recorder.monitor.alarms[:3]
    )
    axes[0].set_title('Health of the calibration' + (f': alarms {names}' if names else ''))
    axes[1].set_xlabel(f's since the {recorder.origin}')
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)
