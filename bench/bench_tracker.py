"""Calibration tracker (core/tracking.py): frozen vs tracked on magpylib hull missions, the
recovery after a step, the tracker's cost per set and per hour of data.

Missions (test/core/hull_missions.py): a 5 min trim, then ~30 min of lines with U-turns at
10 Hz, noise 0.05 nT; a hull of magnetised cuboids whose remanence relaxes by 0.3-0.7 %
(600 s) after the trim (1.2 nT/m RMS at full relaxation) and a 1 nT step on one sensor two
thirds into the survey; the same survey over geology (deep dipoles, 1 nT/m RMS), and over
three seabed targets (hull_missions.TARGETS, 22-30 m below three lines), with a vehicle
that does not change. Calibration: ``known_gradient_lstsq_general`` on the trim. The
tracker runs with the health monitor handing it steps, with the attitude and without it
(a bag without ``/odom``); over targets it never learns from the anomalies detected on the
frozen tensor (pipelines.tracking.target_spans, as ``locate`` and ``survey`` do), and,
streamed as ``compensate`` and the compensator node track, with the gate alone.

    .venv/bin/python bench/bench_tracker.py [--seeds 1,2,3,4,5,6,7,8] [--json FILE]

Figures per mission: the residual (compensated minus the clean fields' tensor) over the
noise floor in three spans (the first 5 min of the survey, the 5 min before the step, after
it), frozen and tracked; the recovery (the first second after the step from which every 2 s
window stays within 1.5x the floor); the share of components within 2 sigma; over geology
the tracked residual over the frozen one; over targets how far ``locate``'s positions and
moments moved, over their 1-sigma. ``--table FILE`` prints them as markdown.
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
sys.path.insert(0, str(REPO / 'test' / 'core'))

from hull_missions import GEOMETRY, TARGETS, build_mission, spans  # noqa: E402

from tetra_gradiometer.core import (  # noqa: E402
    InterferenceParameters,
    Scenario,
    TrimManoeuvre,
    compensate,
    difference_tensor,
    simulate,
)
from tetra_gradiometer.core.health import HealthMonitor  # noqa: E402
from tetra_gradiometer.core.tracking import OffsetTracker, monitor_feed  # noqa: E402
from tetra_gradiometer.core.uncertainty import SigmaModel  # noqa: E402
from tetra_gradiometer.pipelines.tracking import target_spans  # noqa: E402

LIMITS = {'first_5_min': 1.74, 'before_step': 1.2, 'after_step': 1.2}


def track(mission, chunk: int = 600, attitude: bool = True, exclude=None):
    """Frozen and tracked tensors over the survey (chunks of ``chunk`` sets), the state's
    variance, the tracker and the seconds it took; ``attitude`` False: the tracker without
    the orientation (a bag without ``/odom``), the constrained combinations only."""
    s = mission.survey
    t, fields = mission.t_s[s], mission.fields[s]
    calibration = mission.calibration
    frozen = compensate(
        difference_tensor(fields, GEOMETRY), fields[:, 0], calibration.parameters, GEOMETRY
    )
    noise = calibration.details['sensor_noise_nT'] * 1e-9
    tracker = OffsetTracker(
        GEOMETRY, calibration.parameters, noise, with_world=attitude, monitored=True
    )
    monitor = HealthMonitor(GEOMETRY, calibration.parameters, noise, calibration.covariance)
    q = mission.orientation_xyzw[s]
    parts, started = [], time.perf_counter()
    for i in range(0, len(t), chunk):
        rows = slice(i, i + chunk)
        parts.append(
            tracker.update(
                t[rows],
                frozen[rows],
                q[rows] if attitude else None,
                None if exclude is None else exclude[rows],
                health=monitor_feed(monitor, t[rows], fields[rows, 0]),
            )
        )
    seconds = time.perf_counter() - started
    tracked = np.concatenate([p.g for p in parts])
    variance = np.concatenate([p.variance for p in parts])
    sigma = SigmaModel.build(GEOMETRY, noise, calibration.parameters, calibration.covariance)(
        fields[:, 0]
    ).reshape(-1, 9)
    return frozen, tracked, np.sqrt(sigma**2 + variance), tracker, seconds


def ratio(mission, g, mask) -> float:
    error = g[mask] - mission.g_true[mission.survey][mask]
    return float(np.sqrt(np.mean(error**2)) / mission.floor_t_per_m)


def recovery_s(mission, tracked) -> float | None:
    """Seconds from the step to the first 2 s window from which every later one stays
    within 1.5x the floor (None: never)."""
    t = mission.t_s[mission.survey]
    after = t >= mission.t_step_s
    error = (tracked - mission.g_true[mission.survey])[after].reshape(-1, 9)
    per_sample = np.mean(error**2, axis=1)
    n = len(per_sample) // 5 * 5
    windows = per_sample[:n].reshape(-1, 5).mean(axis=1)  # 0.5 s
    rms = np.sqrt(np.convolve(windows, np.ones(4) / 4, mode='valid')) / mission.floor_t_per_m
    bad = np.flatnonzero(rms > 1.5)
    if not len(bad):
        return 0.0
    if bad[-1] + 1 >= len(rms):
        return None
    return float((bad[-1] + 1) * 0.5)


def drifting(seed: int, attitude: bool = True) -> dict:
    mission = build_mission(seed)
    frozen, tracked, sigma, tracker, seconds = track(mission, attitude=attitude)
    out: dict = {'seed': seed, 'step_sensor': mission.step_sensor + 1}
    for name, mask in spans(mission).items():
        mask = mask[mission.survey]
        out[name] = {
            'frozen': round(ratio(mission, frozen, mask), 3),
            'tracked': round(ratio(mission, tracked, mask), 3),
        }
    out['recovery_s'] = recovery_s(mission, tracked)
    error = (tracked - mission.g_true[mission.survey]).reshape(-1, 9)
    out['within_2_sigma'] = round(float(np.mean(np.abs(error) <= 2 * sigma)), 4)
    out['steps'] = [e.to_dict() for e in tracker.events if e.kind == 'step']
    for step in out['steps']:
        step['after_step_s'] = round(step.pop('t_s') - mission.t_step_s, 2)
        step.pop('offsets_nT'), step.pop('sigma_nT')
    out['tracker_s'] = round(seconds, 2)
    out['survey_s'] = float(mission.t_s[mission.survey][-1] - mission.t_survey_s)
    out['passes'] = bool(
        all(out[k]['tracked'] <= v for k, v in LIMITS.items())
        and out['recovery_s'] is not None
        and out['recovery_s'] <= 3.0
        and 0.92 <= out['within_2_sigma'] <= 0.98
    )
    return out


def geology(seed: int, attitude: bool = True) -> dict:
    mission = build_mission(seed, drift=False, step=False, geology=True)
    frozen, tracked, _, _, seconds = track(mission, attitude=attitude)
    out: dict = {'seed': seed}
    for name, mask in spans(mission).items():
        mask = mask[mission.survey]
        f, g = ratio(mission, frozen, mask), ratio(mission, tracked, mask)
        out[name] = {
            'frozen': round(f, 3),
            'tracked': round(g, 3),
            'tracked_over_frozen': round(g / f, 3),
        }
    out['passes'] = out['survey']['tracked_over_frozen'] <= 1.05
    out['tracker_s'] = round(seconds, 2)
    return out


def targets(seed: int, attitude: bool = True, streamed: bool = False) -> dict:
    """``locate`` on the frozen and on the tracked tensor of a vehicle that does not change,
    over the seabed targets of hull_missions.TARGETS: each target's position and moment
    change between the two, over their 1-sigma. ``streamed``: tracked as ``compensate`` and
    the compensator node track a stream, with no target found beforehand (the gate alone)."""
    from scipy.spatial.transform import Rotation

    from tetra_gradiometer.core.targets import Survey, locate

    mission = build_mission(seed, drift=False, step=False, targets=True)
    s = mission.survey
    rotations = Rotation.from_quat(mission.orientation_xyzw[s]).as_matrix()
    frozen, _, _, _, _ = track(mission, attitude=attitude)
    # What locate and survey do: no learning from the anomalies found on the frozen tensor.
    exclude = target_spans(mission.t_s[s], frozen, mission.position_enu[s], rotations)
    if streamed:
        exclude = np.zeros_like(exclude)
    _, tracked, _, _, _ = track(mission, attitude=attitude, exclude=exclude)
    found = {}
    for name, g in (('frozen', frozen), ('tracked', tracked)):
        survey = Survey(mission.t_s[s], mission.position_enu[s], rotations, g)
        found[name] = [t.fit for t in locate(survey, GEOMETRY)[0]]
    rows = []
    for truth_position, _ in TARGETS:
        a, b = (min(fits, key=lambda f: np.linalg.norm(f.position - truth_position))
                for fits in (found['frozen'], found['tracked']))
        rows.append({
            'truth_m': list(truth_position),
            'frozen_m': a.position.round(2).tolist(),
            'position_change_over_sigma': round(float(np.max(
                np.abs(b.position - a.position) / a.position_sigma)), 3),
            'moment_change_over_sigma': round(float(np.max(
                np.abs(b.moment - a.moment) / a.moment_sigma)), 3),
        })
    worst = max(max(r['position_change_over_sigma'], r['moment_change_over_sigma']) for r in rows)
    return {'seed': seed, 'attitude': attitude, 'streamed': streamed, 'targets': rows,
            'excluded_fraction': round(float(exclude.mean()), 4),
            'found': {k: len(v) for k, v in found.items()}, 'passes': worst <= 1.0}


def live_cost(rate_hz: float = 1000.0, seconds: float = 60.0, batch: int = 100) -> dict:
    """Per-set cost of the tracker fed batches of ``batch`` sets at ``rate_hz`` (the
    compensator's 0.1 s batches at 1000 sets/s), with the health monitor handing steps."""
    geometry = GEOMETRY
    scenario = Scenario(
        geometry=geometry,
        earth_field_enu=np.array([0.0, 2.1e-5, -4.5e-5]),
        segments=(TrimManoeuvre(seconds),),
        sample_rate_hz=rate_hz,
        noise_t=0.05e-9,
    )
    data = simulate(scenario, np.random.default_rng(0))
    g = difference_tensor(data.fields_measured, geometry)
    parameters = InterferenceParameters.zero()
    result = {}
    for with_health in (False, True):
        tracker = OffsetTracker(geometry, parameters, 0.05e-9)
        monitor = HealthMonitor(geometry, parameters, 0.05e-9)
        times = []
        for i in range(0, len(g), batch):
            rows = slice(i, i + batch)
            feed = (
                monitor_feed(monitor, data.t[rows], data.fields_measured[rows, 0])
                if with_health
                else None
            )
            started = time.perf_counter()
            tracker.update(data.t[rows], g[rows], data.orientation_xyzw[rows], health=feed)
            times.append(time.perf_counter() - started)
        times_ms = np.asarray(times) * 1e3
        key = 'with_health_monitor' if with_health else 'tracker_alone'
        result[key] = {
            'us_per_set': round(float(times_ms.sum() * 1e3 / len(g)), 2),
            'batch_p99_ms': round(float(np.percentile(times_ms, 99)), 3),
            'batch_sets': batch,
            'rate_hz': rate_hz,
        }
    return result


def table(results: dict) -> str:
    """The table of a results file: each span's residual over the floor, frozen and
    tracked with and without the attitude (the range over the missions), the recovery,
    the 2-sigma share, geology and targets."""
    blind = results.get('without_attitude', {})

    def cell(rows, fmt, scale=1.0):
        values = [scale * v for v in rows]
        return f'{fmt.format(min(values))}-{fmt.format(max(values))}' if values else '-'

    def column(kind, pick, fmt, scale=1.0, source=None):
        rows = (results if source is None else source).get(kind, [])
        return cell([pick(row) for row in rows if pick(row) is not None], fmt, scale)

    lines = ['| span | frozen | tracked | tracked without /odom |', '|---|---|---|---|']
    for key, name in (
        ('first_5_min', 'first 5 min of the survey'),
        ('before_step', '5 min before the step'),
        ('after_step', 'after the step'),
    ):
        cells = [column('drifting', lambda r, w=which: r[key][w], '{:.2f}') + 'x'
                 for which in ('frozen', 'tracked')]
        cells.append(column('drifting', lambda r: r[key]['tracked'], '{:.2f}', source=blind) + 'x')
        lines.append(f'| {name} | ' + ' | '.join(cells) + ' |')
    rows = (
        ('back within 1.5x the floor after the step', 'drifting',
         lambda r: r['recovery_s'], '{:.1f}', 1.0, ' s'),
        ('within 2 sigma (drifting)', 'drifting', lambda r: r['within_2_sigma'], '{:.1f}',
         100.0, ' %'),
        ('over geology, tracked / frozen residual', 'geology',
         lambda r: r['survey']['tracked_over_frozen'], '{:.3f}', 1.0, ''),
        ('over targets, located position or moment moved', 'targets',
         lambda r: max(max(t['position_change_over_sigma'], t['moment_change_over_sigma'])
                       for t in r['targets']), '{:.2f}', 1.0, ' sigma'),
    )
    for name, kind, pick, fmt, scale, unit in rows:
        lines.append(f'| {name} | - | {column(kind, pick, fmt, scale)}{unit} | '
                     f'{column(kind, pick, fmt, scale, blind)}{unit} |')
    moved = rows[-1][2]
    lines.append(f'| over targets streamed (the gate alone), moved | - | '
                 f'{column("targets_streamed", moved, "{:.2f}")} sigma | - |')
    never = sum(r['recovery_s'] is None for r in blind.get('drifting', []))
    note = f' Without /odom {never} of them never came back within 1.5x.' if never else ''
    return '\n'.join(lines) + f'\n\n{len(results["drifting"])} missions of each kind.{note}'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', default='1,2,3,4,5', help='missions (comma separated)')
    parser.add_argument('--json', default=None, help='write the results here')
    parser.add_argument(
        '--table',
        default=None,
        metavar='JSON',
        help='print the markdown table of a results file and stop',
    )
    args = parser.parse_args()
    if args.table:
        print(table(json.loads(Path(args.table).read_text())))
        return 0
    seeds = [int(s) for s in args.seeds.split(',')]
    results: dict = {'drifting': [], 'geology': [], 'targets': [], 'targets_streamed': [],
                     'without_attitude': {'drifting': [], 'geology': [], 'targets': []}}
    for seed in seeds:
        for attitude, into in ((True, results), (False, results['without_attitude'])):
            for kind, run in (('drifting', drifting), ('geology', geology), ('targets', targets)):
                into[kind].append(run(seed, attitude))
                print(json.dumps(into[kind][-1]), flush=True)
        results['targets_streamed'].append(targets(seed, streamed=True))
        print(json.dumps(results['targets_streamed'][-1]), flush=True)
    survey_s = results['drifting'][0]['survey_s']
    offline = np.mean([d['tracker_s'] for d in results['drifting']])
    results['offline_cost'] = {
        's_per_hour_of_data_at_10_hz': round(float(offline * 3600 / survey_s), 2),
        'note': 'tracker and health monitor, chunks of 600 sets',
    }
    results['live_cost'] = live_cost()
    print(json.dumps({k: results[k] for k in ('offline_cost', 'live_cost')}), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
