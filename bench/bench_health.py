"""Health monitor (core/health.py, issue 12): false alarms and detection delay.

Missions of a 5 min trim (the calibration, ``known_gradient_lstsq_general``) then a
lawnmower of survey lines at 2 m/s over three magnetized targets (5e4 A m^2, 25-40 m below
the lines) at 10 Hz, each with its own seed (interference, noise 0.05 nT, targets):

* **false alarms**: the monitor runs over change-free surveys; the alarms counted per hour;
* **detection delay vs step size**: an offset jump of ``size`` nT in a random direction on
  a random sensor at a random time on the lines; the delay from the jump to the alarm, and
  how often the jumped sensor is named (anywhere in the list, and first).

    .venv/bin/python bench/bench_health.py [--hours 20] [--steps 40] [--figure PNG] [--json FILE]

Target (issue 12): below one false alarm per 10 hours; a 2 nT jump alarmed within 5 s.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tetra_gradiometer.core import (  # noqa: E402
    Dipole,
    Scenario,
    SurveyLine,
    TetraGeometry,
    TrimManoeuvre,
    compensate,
    difference_tensor,
    known_gradient_lstsq,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.health import HealthMonitor  # noqa: E402

GEOMETRY = TetraGeometry.regular(0.5)
EARTH = np.array([0.0, 21000e-9, -45376.2e-9])
SIZES_NT = (0.25, 0.5, 1.0, 2.0, 4.0)


def mission(seed: int, n_lines: int):
    """Trim + ``n_lines`` 600 m lines (300 s each) 10 m apart over three random targets."""
    rng = np.random.default_rng(seed)
    lines = tuple(
        SurveyLine((-300.0 * d, 10.0 * i - 5.0 * n_lines, -50.0),
                   (300.0 * d, 10.0 * i - 5.0 * n_lines, -50.0),
                   roll_amplitude_deg=2.0, pitch_amplitude_deg=1.0)
        for i, d in enumerate(np.resize([1, -1], n_lines))
    )
    targets = tuple(
        Dipole(position=[rng.uniform(-250, 250), rng.uniform(-5 * n_lines, 5 * n_lines),
                         -50.0 - rng.uniform(25, 40)],
               moment=rng.normal(size=3) / np.sqrt(3) * 5e4)
        for _ in range(3)
    )
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH,
                        segments=(TrimManoeuvre(300.0, center=(3000.0, 3000.0, -50.0)), *lines),
                        sample_rate_hz=10.0, dipoles=targets,
                        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9),
                        noise_t=0.05e-9)
    data = simulate(scenario, rng)
    trim = data.segment == 0
    g = difference_tensor(data.fields_measured, GEOMETRY)
    calibration = known_gradient_lstsq(g[trim], data.fields_measured[trim, 0], GEOMETRY,
                                       symmetric_k=False)
    return data, calibration


def monitor_survey(data, calibration, fields) -> HealthMonitor:
    survey = data.segment > 0
    t, fields = data.t[survey], fields[survey]
    g = compensate(difference_tensor(fields, GEOMETRY), fields[:, 0], calibration.parameters,
                   GEOMETRY)
    monitor = HealthMonitor(GEOMETRY, calibration.parameters,
                            calibration.details['sensor_noise_nT'] * 1e-9, calibration.covariance)
    for i in range(0, len(t), 3000):
        monitor.update(t[i:i + 3000], g[i:i + 3000], fields[i:i + 3000, 0])
    return monitor


def false_alarms(hours: float) -> dict:
    n_lines = 12  # 1 h of lines per mission
    missions = max(1, int(round(hours)))
    alarms, surveyed_s, started = 0, 0.0, time.perf_counter()
    for seed in range(missions):
        data, calibration = mission(1000 + seed, n_lines)
        monitor = monitor_survey(data, calibration, data.fields_measured)
        alarms += len(monitor.alarms)
        surveyed_s += float(np.sum(data.segment > 0)) / 10.0
        print(f'  mission {seed}: {len(monitor.alarms)} alarms, threshold {monitor.threshold:.1f}',
              flush=True)
    return {'hours': surveyed_s / 3600, 'alarms': alarms,
            'per_10_hours': 10 * alarms / (surveyed_s / 3600),
            'seconds': time.perf_counter() - started}


def delays(steps: int) -> dict:
    results: dict = {}
    for size in SIZES_NT:
        delay, named, first, missed = [], 0, 0, 0
        for k in range(steps):
            rng = np.random.default_rng([int(size * 100), k])
            data, calibration = mission(5000 + k, 2)
            sensor = int(rng.integers(4))
            t_change = float(rng.uniform(320.0, 880.0))
            direction = rng.normal(size=3)
            fields = data.fields_measured.copy()
            fields[data.t >= t_change, sensor] += size * 1e-9 * direction / np.linalg.norm(direction)
            alarms = monitor_survey(data, calibration, fields).alarms
            if not alarms or alarms[0].t_s < t_change:
                missed += 1
                continue
            delay.append(alarms[0].t_s - t_change)
            named += (sensor + 1) in alarms[0].sensors
            first += bool(alarms[0].sensors) and alarms[0].sensors[0] == sensor + 1
        n = len(delay)
        results[size] = {'steps': steps, 'missed_or_early': missed,
                         'median_delay_s': float(np.median(delay)) if n else None,
                         'p95_delay_s': float(np.percentile(delay, 95)) if n else None,
                         'named_fraction': named / max(n, 1), 'named_first_fraction': first / max(n, 1)}
        print(f'  {size} nT: {results[size]}', flush=True)
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--hours', type=float, default=20.0, help='hours of change-free survey')
    parser.add_argument('--steps', type=int, default=40, help='jumps per step size')
    parser.add_argument('--figure', default=None, help='PNG of delay vs step size')
    parser.add_argument('--json', default=None, help='write the results here')
    args = parser.parse_args()
    print('false alarms:', flush=True)
    fa = false_alarms(args.hours)
    print(f'  {fa}')
    print('detection delay vs step size:', flush=True)
    dl = delays(args.steps)
    if args.figure:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
        sizes = [s for s in SIZES_NT if dl[s]['median_delay_s'] is not None]
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.plot(sizes, [dl[s]['median_delay_s'] for s in sizes], 'o-', label='median')
        ax.plot(sizes, [dl[s]['p95_delay_s'] for s in sizes], 's--', label='95th percentile')
        ax.axhline(5.0, color='grey', lw=0.8, label='target for 2 nT: 5 s')
        ax.set(xscale='log', yscale='log', xlabel='offset jump on one sensor (nT)',
               ylabel='alarm delay (s)', title='Health monitor: detection delay (10 Hz, 0.05 nT noise)')
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.figure, dpi=120)
    if args.json:
        Path(args.json).write_text(json.dumps({'false_alarms': fa, 'delays': dl}, indent=2))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
