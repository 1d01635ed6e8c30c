"""Vehicle effects in calibration and compensation (issue 28).

    .venv/bin/python bench/bench_effects.py [--selection N] [--table] [--scale] [--json FILE]

* ``--selection N`` (default 100): N clean vehicles (random iron, sensor 1 clean or not), a
  5-minute trim at 10 Hz each, with a battery current and a temperature recorded: how many
  get a term (target: at most 1 in 100); and 20 vehicles per effect: how often it is found.
  Core-level (simulate, ``select_terms``): no bags.
* ``--table``: the issue's vehicles (none, battery current 3-27 A at 0.5-2.4 nT/A, eddy
  currents, thermal drift 0.08-0.28 nT/degC over ~13 -> 18 degC, all three, and all three
  with each fluxgate's scale error (+-3000 ppm), non-orthogonality and misalignment
  (+-0.3 and +-0.5 deg)) on one mission
  (5 min trim 3.5 km from anything, then three 400 m lines past two dipoles, 10 Hz): default
  ``calibrate`` on the trim and ``compensate`` of the survey through the commands; the
  survey residual against the truth over the noise floor (the compensated tensor's 1-sigma
  from the sensor noise), and the same with ``--effects none --force`` (before).
* ``--scale``: ``config/scenarios/long_survey_100hz_effects.yaml`` (1 hour, 100 Hz, the three
  effects, /battery_state and /tetra/temperature at 100 Hz): calibrate on the trim and
  compensate the whole bag in subprocesses, wall time and peak memory (target: compensate
  < 60 s and < 500 MB).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'bench'))

from bench_scale import run  # noqa: E402

from tetra_gradiometer.core import (  # noqa: E402
    Effects,
    Scenario,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.effects import TEMPERATURE, Channels, current_channel  # noqa: E402
from tetra_gradiometer.core.identification.terms import candidates_for, select_terms  # noqa: E402

EDGE = 0.5
NAMES = ('vehicle_current', 'eddy_current', 'thermal_drift')


def _draw_effect(rng: np.random.Generator, name: str) -> dict:
    """One effect at the issue's magnitudes, SI, per sensor (sensor 1 included)."""
    sign = rng.choice([-1.0, 1.0], (4, 3))
    if name == 'vehicle_current':
        return {name: rng.uniform(0.5e-9, 2.4e-9, (4, 3)) * sign}
    if name == 'thermal_drift':
        return {name: rng.uniform(0.08e-9, 0.28e-9, (4, 3)) * sign}
    return {name: rng.normal(0.0, 3e-4, (4, 3, 3))}


def _trim_selection(seed: int, effects: dict, geometry: TetraGeometry) -> list[str]:
    rng = np.random.default_rng(seed)
    scenario = Scenario(
        geometry,
        np.array([0.0, 21000e-9, -45376.2e-9]),
        (TrimManoeuvre(300.0, center=(3500.0, 0.0, -50.0)),),
        sample_rate_hz=10.0,
        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9,
                                          reference_clean=bool(rng.integers(2))),
        noise_t=0.05e-9,
        effects=Effects(**effects),
    )
    mission = simulate(scenario, rng)
    b1 = mission.fields_measured[:, 0]
    channels = Channels(mission.t, b1, {current_channel('/battery_state'): mission.current_a,
                                        TEMPERATURE: mission.temperature_c})
    candidates, _ = candidates_for(channels)
    pairs = difference_tensor(mission.fields_measured, geometry) @ geometry.a
    return [c.name for c in select_terms(pairs, b1, candidates).chosen]


def selection(n: int) -> dict:
    geometry = TetraGeometry.regular(EDGE)
    started = time.perf_counter()
    clean = [_trim_selection(1000 + seed, {}, geometry) for seed in range(n)]
    false = sum(1 for chosen in clean if chosen)
    found = {}
    for name in NAMES:
        hits = 0
        for seed in range(20):
            rng = np.random.default_rng(5000 + seed)
            chosen = _trim_selection(2000 + seed, _draw_effect(rng, name), geometry)
            hits += chosen == [name]
        found[name] = hits
    out = {'clean_seeds': n, 'clean_with_a_term': false,
           'clean_terms': sorted({t for c in clean for t in c}),
           'found_exactly_of_20': found, 'wall_s': time.perf_counter() - started}
    print(json.dumps(out, indent=1), flush=True)
    return out


MISSION = {
    'description': 'issue 28 table: 5 min trim 3.5 km from anything, three 400 m lines past two dipoles',
    'seed': 2028,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': EDGE},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'dipoles': [{'position_m': [-60.0, 5.0, -85.0], 'moment_Am2': [20000.0, -8000.0, -15000.0]},
                {'position_m': [80.0, -10.0, -75.0], 'moment_Am2': [-30000.0, 25000.0, -20000.0]}],
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': False}},
    'current': {'base_a': -15.0, 'step_amplitude_a': 12.0, 'step_s': 15.0},
    'temperature': {'mean_c': 12.6, 'ramp_c': 5.3, 'amplitude_c': 0.3, 'period_s': 437.0},
    'segments': [
        {'trim': {'duration_s': 300, 'center_m': [3500.0, 0.0, -50.0]}},
        {'line': {'start_m': [-200.0, 0.0, -45.0], 'end_m': [200.0, 0.0, -45.0], 'speed_m_s': 2.0,
                  'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}},
        {'line': {'start_m': [200.0, 20.0, -45.0], 'end_m': [-200.0, 20.0, -45.0], 'speed_m_s': 2.0,
                  'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}},
        {'line': {'start_m': [-200.0, -20.0, -50.0], 'end_m': [200.0, -20.0, -50.0], 'speed_m_s': 2.0,
                  'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}},
    ],
}


def _vehicles() -> dict[str, dict]:
    rng = np.random.default_rng(28)
    sign = lambda shape: rng.choice([-1.0, 1.0], shape)  # noqa: E731
    current = {'vehicle_current': {'nT_per_A': (rng.uniform(0.5, 2.4, (4, 3)) * sign((4, 3))).tolist()}}
    eddy = {'eddy_current': {'coefficients_s': rng.normal(0, 3e-4, (4, 3, 3)).tolist()}}
    thermal = {'thermal_drift': {'nT_per_degC': (rng.uniform(0.08, 0.28, (4, 3)) * sign((4, 3))).tolist()}}
    sensors = {
        'scale_factor': {'error_ppm': rng.uniform(-3000, 3000, (4, 3)).tolist()},
        'non_orthogonality': {'angles_deg': rng.uniform(-0.3, 0.3, (4, 3)).tolist()},
        'sensor_misalignment': {'rotation_deg': rng.uniform(-0.5, 0.5, (4, 3)).tolist()},
    }
    return {'none': {}, 'battery current': current, 'eddy currents': eddy,
            'thermal drift': thermal, 'all three': {**current, **eddy, **thermal},
            'all three + fluxgate scale, non-orthogonality, misalignment':
                {**current, **eddy, **thermal, **sensors}}


def _noise_floor() -> float:
    """The noise floor, T/m: RMS over the components of the tensor's 1-sigma from the
    mission's sensor noise alone (eq. 7 on white noise; a calibration's own estimate would
    grow with what it failed to fit)."""
    from tetra_gradiometer.core.uncertainty import noise_sigma

    sigma = noise_sigma(TetraGeometry.regular(EDGE), MISSION['noise_nT'] * 1e-9)
    return float(np.sqrt(np.mean(sigma**2)))


def _survey_ratio(csv: Path, truth: dict) -> float:
    rows = np.loadtxt(csv, delimiter=',', skiprows=1)
    lines = csv.read_text().splitlines()[1:]
    stamps = np.array([int(line.split(',', 1)[0].replace('.', '')) for line in lines])
    index = np.searchsorted(truth['stamps_ns'], stamps)
    survey = truth['t_s'][index] > 300.5
    residual = rows[survey, 1:10] - truth['g_true'][index[survey]].reshape(-1, 9) * 1e9
    return float(np.sqrt(np.mean(residual**2)) / (_noise_floor() * 1e9))


def table() -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as work_dir:
        work = Path(work_dir)
        for name, effects in _vehicles().items():
            scenario = work / 'scenario.yaml'
            scenario.write_text(yaml.safe_dump({**MISSION, 'effects': effects}))
            bag = work / name.replace(' ', '_')
            run('simulate', '--scenario', scenario, '--out', bag, '--no-progress')
            params, truth = f'{bag}.params.yaml', dict(np.load(f'{bag}.truth.npz'))
            row = {'vehicle': name}
            for label, extra in (('before', ['--effects', 'none', '--force']), ('after', [])):
                calib = work / f'{bag.name}_{label}.yaml'
                wall, _, out = run('calibrate', bag, '--params', params, '--window', '0:299.9',
                                   '--out', calib, '--no-progress', *extra)
                csv = work / f'{bag.name}_{label}.csv'
                run('compensate', bag, '--params', params, '--calibration', calib, '--csv', csv,
                    '--no-progress')
                row[f'{label}_ratio'] = _survey_ratio(csv, truth)
                if label == 'after':
                    with open(calib) as stream:
                        document = yaml.safe_load(stream)
                    row['terms'] = [t['effect'] for t in document.get('terms', [])]
                    row['calibrate_s'] = wall
            print(json.dumps(row), flush=True)
            rows.append(row)
    print('\n| vehicle | terms selected | survey residual / noise floor, before (--effects none --force) | after (default) |')
    print('|---|---|---|---|')
    for r in rows:
        print(f'| {r["vehicle"]} | {", ".join(r["terms"]) or "none"} | {r["before_ratio"]:.2f}x | '
              f'{r["after_ratio"]:.3f}x |')
    return rows


def scale(cache: Path) -> list[dict]:
    scenario = REPO / 'config/scenarios/long_survey_100hz_effects.yaml'
    key = hashlib.sha256(scenario.read_bytes()).hexdigest()[:12]
    bag = cache / f'effects_{key}' / 'long'
    if not (bag / 'metadata.yaml').exists():
        print(f'generating {bag} (cached) ...', flush=True)
        run('simulate', '--scenario', scenario, '--out', bag, '--no-progress')
    params = Path(f'{bag}.params.yaml')
    rows = []
    wall, peak, _ = run('calibrate', bag, '--params', params, '--window', '0:299.99',
                        '--out', bag.parent / 'calib.yaml', '--no-progress', '--force')
    rows.append({'command': 'calibrate (trim 0:300 s, 30 000 sets, effects auto)', 'wall_s': wall, 'peak_mb': peak})
    wall, peak, out = run('compensate', bag, '--params', params, '--calibration', bag.parent / 'calib.yaml',
                          '--csv', bag.parent / 'out.csv', '--no-progress', '--force')
    rows.append({'command': 'compensate --csv (360 000 sets, 3 terms)', 'wall_s': wall, 'peak_mb': peak,
                 'sets': int(out.split()[1])})
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--selection', type=int, default=None)
    parser.add_argument('--table', action='store_true')
    parser.add_argument('--scale', action='store_true')
    parser.add_argument('--cache', default='/tmp/tetra_bench_scale')
    parser.add_argument('--json', default=None)
    args = parser.parse_args()
    if args.selection is None and not args.table and not args.scale:
        args.selection, args.table, args.scale = 100, True, True
    results: dict = {}
    if args.selection:
        results['selection'] = selection(args.selection)
    if args.table:
        results['table'] = table()
    if args.scale:
        results['scale'] = scale(Path(args.cache))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
