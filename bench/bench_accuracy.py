"""Accuracy of the offline chain at the sensor-noise floor (issue 4).

For each realistic-mission scenario (config/scenarios/realistic_mission*.yaml): simulate a
bag, calibrate on the 5 min trim manoeuvre (window 0:299.95 s, true gradient zero) with
every method of ``calibrate``, compensate the whole bag with each calibration, and compare
the CSV on the survey passes with the simulator's truth ``g_true`` (the clean difference
tensor). Pei & Yeo 2009 has no calibration-file form (it maps each sensor onto sensor 1),
so it is fitted and applied in memory on the same sets, read from the same bag.

Everything goes through the command line in subprocesses, as a user runs it.

    .venv/bin/python bench/bench_accuracy.py [--out DIR] [--figure PNG] [--json FILE]

Targets: ``known_gradient_lstsq_general`` RMS <= 1.2 x noise floor (metrics.noise_floor,
about 1.42 sigma / d) and improvement ratio >= 1000, with and without a clean sensor 1.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tetra_gradiometer.core import noise_floor, summarize  # noqa: E402
from tetra_gradiometer.core.identification import pei_yeo_2009  # noqa: E402
from tetra_gradiometer.io.bag import MagneticBag  # noqa: E402
from tetra_gradiometer.io.params import geometry_from_params, load_params  # noqa: E402

SCENARIOS = {'reference clean': 'config/scenarios/realistic_mission.yaml',
             'sensor 1 with soft + hard iron': 'config/scenarios/realistic_mission_dirty_reference.yaml'}
WINDOW = '0:299.95'
METHODS = [  # (label, calibrate arguments)
    ('known_gradient_lstsq_general', ['--method', 'known_gradient_lstsq_general']),
    ('known_gradient_lstsq', ['--method', 'known_gradient_lstsq']),
    ('constraint_lstsq', ['--method', 'constraint_lstsq']),
    ('paper_ga', ['--method', 'paper_ga', '--seed', '1']),
    ('paper_ga (wide bounds)', ['--method', 'paper_ga', '--seed', '1', '--wide-bounds']),
]
TARGET_FLOOR_RATIO = 1.2
TARGET_IMPROVEMENT = 1000.0


def cli(*args: object) -> str:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    result = subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)], capture_output=True,
                            text=True, env=env, cwd=REPO)
    if result.returncode != 0:
        raise SystemExit(f'failed: {" ".join(map(str, args))}\n{result.stderr}')
    return result.stdout


def read_csv(path: Path) -> np.ndarray:
    return np.loadtxt(path, delimiter=',', skiprows=1, usecols=range(1, 10)).reshape(-1, 3, 3) * 1e-9


def evaluate(label: str, scenario: str, out: Path) -> list[dict]:
    slug = label.split()[0] + ('_dirty' if 'soft' in label else '')
    bag = out / f'mission_{slug}'
    t0 = time.perf_counter()
    cli('simulate', '--scenario', scenario, '--out', bag, '--force')
    print(f'[{label}] simulated in {time.perf_counter() - t0:.1f} s', flush=True)
    params = Path(f'{bag}.params.yaml')
    truth = np.load(f'{bag}.truth.npz')
    geometry = geometry_from_params(load_params(params))
    survey = truth['segment'] > 0
    g_true = truth['g_true'][survey]
    cli('compensate', bag, '--params', params, '--raw', '--csv', out / f'{slug}_raw.csv', '--force')
    g_raw = read_csv(out / f'{slug}_raw.csv')[survey]
    floor = noise_floor(float(truth['noise_t']), geometry)
    rows = []
    for method, options in METHODS:
        name = method.replace(' ', '_').replace('(', '').replace(')', '')
        calib = out / f'{slug}_{name}.yaml'
        t0 = time.perf_counter()
        cli('calibrate', bag, '--params', params, '--window', WINDOW, '--out', calib, '--force', *options)
        t_cal = time.perf_counter() - t0
        # constraint_lstsq and paper_ga estimate no sensor noise: give the simulated one for the
        # sigma columns (compensate refuses a calibration without any noise figure).
        noise = ('--sensor-noise-nt', float(truth['noise_t']) * 1e9)
        cli('compensate', bag, '--params', params, '--calibration', calib, '--csv', out / f'{slug}_{name}.csv',
            '--force', *noise)
        g_after = read_csv(out / f'{slug}_{name}.csv')[survey]
        import yaml
        diagnostics = yaml.safe_load(calib.read_text())['diagnostics']
        rows.append(_row(label, method, g_raw, g_after, g_true, floor, t_cal, diagnostics['n_parameters'],
                         diagnostics['rank']))
        print(f'[{label}] {method}: {rows[-1]["rms_nT_per_m"]:.4g} nT/m', flush=True)
    # Pei & Yeo 2009, in memory, on the same sets.
    with MagneticBag(bag) as reader:
        stamps, fields = reader.read_sets()
    t_s = (stamps - stamps[0]) * 1e-9
    window = t_s <= float(WINDOW.split(':')[1])
    t0 = time.perf_counter()
    calibration = pei_yeo_2009(fields[window])
    t_cal = time.perf_counter() - t0
    g_after = calibration.compensate_fields(fields[survey], geometry)
    rows.append(_row(label, 'pei_yeo_2009', g_raw, g_after, g_true, floor, t_cal, calibration.n_parameters,
                     calibration.rank))
    return rows


def _row(label, method, g_raw, g_after, g_true, floor, t_cal, n_par, rank) -> dict:
    metrics = summarize(g_raw, g_after, g_true)
    return {'scenario': label, 'method': method, 'parameters': int(n_par), 'rank': int(rank),
            'rms_before_nT_per_m': float(np.sqrt(np.mean((g_raw - g_true) ** 2)) * 1e9),
            'rms_nT_per_m': metrics['rms_residual_nT_per_m'], 'noise_floor_nT_per_m': floor * 1e9,
            'floor_ratio': metrics['rms_residual_nT_per_m'] / (floor * 1e9),
            'improvement_ratio': metrics['improvement_ratio'],
            'compensated_percent': metrics['compensated_percent'], 'calibration_s': t_cal}


def table(rows: list[dict]) -> str:
    lines = ['| scenario | method | parameters (rank) | RMS before, nT/m | RMS after, nT/m | after / floor '
             '| improvement | ε compensated |',
             '|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f'| {r["scenario"]} | {r["method"]} | {r["parameters"]} ({r["rank"]}) | '
                     f'{r["rms_before_nT_per_m"]:.1f} | {r["rms_nT_per_m"]:.4g} | {r["floor_ratio"]:.3f} | '
                     f'{r["improvement_ratio"]:.4g} | {r["compensated_percent"]:.3f} % |')
    return '\n'.join(lines)


def figure(rows: list[dict], out: Path, path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    labels = list(dict.fromkeys(r['method'] for r in rows))
    scenarios = list(dict.fromkeys(r['scenario'] for r in rows))
    width = 0.8 / len(scenarios)
    for k, scenario in enumerate(scenarios):
        values = [next(r['rms_nT_per_m'] for r in rows if r['scenario'] == scenario and r['method'] == m)
                  for m in labels]
        axes[0].bar(np.arange(len(labels)) + k * width, values, width, label=scenario)
    floor = rows[0]['noise_floor_nT_per_m']
    axes[0].axhline(floor, color='k', ls='--', lw=1, label=f'noise floor {floor:.3f} nT/m')
    axes[0].set_yscale('log')
    axes[0].set_xticks(np.arange(len(labels)) + width * (len(scenarios) - 1) / 2)
    axes[0].set_xticklabels(labels, rotation=25, ha='right', fontsize=8)
    axes[0].set_ylabel('RMS residual on the survey, nT/m')
    axes[0].legend(fontsize=8)
    axes[0].set_title('compensated tensor vs truth (survey passes)')
    # Time series: G_xz on the first pass, sensor 1 not clean.
    slug = 'sensor_dirty'
    truth = np.load(out / f'mission_{slug}.truth.npz')
    t = truth['t_s']
    first = truth['segment'] == 1
    raw = read_csv(out / f'{slug}_raw.csv')
    good = read_csv(out / f'{slug}_known_gradient_lstsq_general.csv')
    raw_error = np.sqrt(np.mean((raw[first, 0, 2] - truth['g_true'][first, 0, 2]) ** 2)) * 1e9
    axes[1].plot(t[first], good[first, 0, 2] * 1e9, lw=0.8, label='compensated (36, general)')
    axes[1].plot(t[first], truth['g_true'][first, 0, 2] * 1e9, 'k--', lw=0.8, label='truth g_true')
    axes[1].set_xlabel('time from first stamp, s')
    axes[1].set_ylabel('G_xz, nT/m')
    axes[1].set_title(f'first pass, sensor 1 not clean (raw is off by {raw_error:.0f} nT/m RMS)', fontsize=9)
    axes[1].legend(fontsize=8)
    residual = (good[first] - truth['g_true'][first]).reshape(-1, 9) * 1e9
    axes[2].plot(t[first], residual[:, 2], lw=0.6, label='G_xz compensated - truth')
    axes[2].axhspan(-floor, floor, color='0.85', label=f'+-1 noise floor ({floor:.3f} nT/m)')
    axes[2].set_xlabel('time from first stamp, s')
    axes[2].set_ylabel('nT/m')
    axes[2].set_title('residual on the first pass')
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--out', default='/tmp/tetra_bench_accuracy', help='work folder (bags, CSVs)')
    parser.add_argument('--figure', default=str(REPO / 'docs/figures/offline_accuracy.png'))
    parser.add_argument('--json', default=None, help='also write the rows as JSON here')
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for label, scenario in SCENARIOS.items():
        rows.extend(evaluate(label, scenario, out))
    print()
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    figure(rows, out, Path(args.figure))
    print(f'\nfigure: {args.figure}')
    failed = [r for r in rows if r['method'] == 'known_gradient_lstsq_general'
              and not (r['floor_ratio'] <= TARGET_FLOOR_RATIO and r['improvement_ratio'] >= TARGET_IMPROVEMENT)]
    for r in failed:
        print(f'TARGET MISSED: {r["scenario"]}: {r["rms_nT_per_m"]:.4g} nT/m = {r["floor_ratio"]:.3f} x floor, '
              f'improvement {r["improvement_ratio"]:.4g}')
    if not failed:
        print(f'targets met: known_gradient_lstsq_general <= {TARGET_FLOOR_RATIO} x floor and improvement >= '
              f'{TARGET_IMPROVEMENT:g} in every scenario')
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
