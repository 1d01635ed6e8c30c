"""Diagnostics: where measurement and simulation disagree, as the residual's RMS per sensor,
its largest correlation with each driver (time, attitude, field rate, temperature, current),
its strongest spectral line per sensor, its RMS along the run, and its RMS on the gradient
tensor: the characterization of what no candidate explains."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..geometry import TetraGeometry, difference_tensor
from ..units import NT_PER_T
from .openworld import false_alarm, line_power, periodogram
from .prepare import Prepared

Array = NDArray[np.float64]


def drivers(prep: Prepared) -> dict[str, Array]:
    """The series a residual is compared with, by name (unit in the name)."""
    out: dict[str, Array] = {
        'time_s': prep.t,
        'field_rate_nT_s': np.linalg.norm(prep.b_rate, axis=1),
    }
    if prep.attitude is not None:
        out.update(
            {
                'heading_deg': prep.attitude[:, 0],
                'pitch_deg': prep.attitude[:, 1],
                'roll_deg': prep.attitude[:, 2],
            }
        )
    if prep.temperature_c is not None:
        out['temperature_c'] = prep.temperature_c
    if prep.current_a is not None:
        out['current_a'] = prep.current_a
    for topic, values in prep.extra_currents:
        out[f'current_a[{topic}]'] = values
    return out


def _strongest_correlation(d: Array, residual: Array, sensors: tuple[int, ...]) -> dict[str, Any]:
    """The sensor and axis whose residual correlates most with ``d``, and the coefficient."""
    dc = d - d.mean()
    best = (0.0, '')
    for s in sensors:
        for a in range(3):
            r = residual[:, s, a] - residual[:, s, a].mean()
            den = np.sqrt((dc @ dc) * (r @ r))
            corr = float(dc @ r / den) if den > 0 else 0.0
            if abs(corr) > abs(best[0]):
                best = (corr, f'sensor {s + 1} {"xyz"[a]}')
    return {'r': best[0], 'where': best[1]}


def diagnostics(prep: Prepared, residual: Array) -> dict[str, Any]:
    """RMS per sensor and axis of ``residual`` (N, 4, 3) nT, and its largest correlation
    with each driver."""
    series = drivers(prep)
    out: dict[str, Any] = {'rms_nT': {}, 'correlation': {}}
    for s in prep.sensors:
        out['rms_nT'][f'sensor_{s + 1}'] = [
            float(v) for v in np.sqrt(np.mean(residual[:, s] ** 2, axis=0))
        ]
    for name, d in series.items():
        if np.ptp(d) == 0:
            continue
        if name == 'heading_deg':
            d = np.cos(np.radians(d))
        out['correlation'][name] = _strongest_correlation(d, residual, prep.sensors)
    out['drivers'] = list(series)
    out['spectrum'] = _strongest_lines(prep, residual)
    tenths = np.array_split(np.arange(len(prep.t)), 10)
    out['time_profile'] = [
        {
            'start_s': float(prep.t[idx[0]]),
            'end_s': float(prep.t[idx[-1]]),
            'rms_nT': float(np.sqrt(np.mean(residual[idx][:, list(prep.sensors)] ** 2))),
        }
        for idx in tenths
        if len(idx)
    ]
    return out


def _strongest_lines(prep: Prepared, residual: Array) -> dict[str, Any]:
    """Per sensor, the periodogram bin with the most power over the local noise level of
    ``residual`` (N, 4, 3) nT: its frequency (Hz), that ratio and its false-alarm
    probability (a line too weak to name still shows where to look)."""
    if len(prep.t) < 64:
        return {}
    frequencies, power = periodogram(
        prep.t, residual[:, list(prep.sensors)].reshape(len(prep.t), -1)
    )
    usable = frequencies > 10.0 / max(float(prep.t[-1] - prep.t[0]), 1e-9)
    z = line_power(power)[usable].reshape(int(usable.sum()), -1, 3).max(axis=2)
    out = {}
    for k, s in enumerate(prep.sensors):
        i = int(np.argmax(z[:, k]))
        out[f'sensor_{s + 1}'] = {
            'frequency_hz': float(frequencies[usable][i]),
            'power_over_noise': float(z[i, k]),
            'false_alarm': float(false_alarm(z[i : i + 1, k], 3 * len(prep.t) // 2)[0]),
        }
    return out


def tensor_rms(prep: Prepared, residual: Array, geometry: TetraGeometry) -> float:
    """RMS of ``residual`` (N, 4, 3) nT on the gradient tensor, nT/m (pair view: sensor 1's
    residual is zero by construction)."""
    if prep.absolute:
        g = difference_tensor(residual / NT_PER_T, geometry) * NT_PER_T
    else:
        n = len(residual)
        fields = np.concatenate([np.zeros((n, 1, 3)), residual[:, 1:]], axis=1)
        g = difference_tensor(fields / NT_PER_T, geometry) * NT_PER_T
    return float(np.sqrt(np.mean(g**2)))
