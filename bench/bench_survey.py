"""Survey products (issue 32): ``survey`` on a 1-hour, 10 Hz survey, all products.

The bag is ``bench_targets.py --speed``'s mission (a 5 min trim 3 km away, then twelve
600 m lines 16 m apart at 2 m/s, 25 m deep, over five dipoles; 0.05 nT noise, vehicle
interference; 39 000 sets), calibrated on the trim; generated once and cached under
``--cache`` (default /tmp/tetra_bench_survey). ``python -m tetra_gradiometer survey`` then
runs in its own subprocess, timed by the wall clock and its CPU time (user + system: what
the wall time is on an idle machine; a shared one stretches the wall), its peak memory from
``ru_maxrss`` (os.wait4); the stage timings come from ``survey.json``.

    .venv/bin/python bench/bench_survey.py [--cache DIR] [--json FILE]

Target: all products (survey.nc, GeoTIFFs, GeoJSON, CSV, report.html) in < 60 s with
< 1 GB peak memory on the 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'bench'))

from bench_targets import DEPTH_M, lines, random_targets  # noqa: E402

TARGET_S = 60.0
TARGET_MB = 1024.0


def run(*args: object) -> tuple[float, float, str, float]:
    """``python -m tetra_gradiometer ARGS``: (wall s, peak RSS MB, stdout, CPU s: user +
    system, the wall time an idle machine would take for this single-process run)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with tempfile.TemporaryFile('w+') as errors:
        started = time.perf_counter()
        process = subprocess.Popen([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)],
                                   stdout=subprocess.PIPE, stderr=errors, env=env, cwd=REPO, text=True)
        stdout = process.stdout.read()
        _, status, usage = os.wait4(process.pid, 0)
        elapsed = time.perf_counter() - started
        process.stdout.close()
        if os.waitstatus_to_exitcode(status) != 0:
            errors.seek(0)
            raise SystemExit(f'failed: {" ".join(map(str, args))}\n{errors.read()}')
    return elapsed, usage.ru_maxrss / 1024.0, stdout, usage.ru_utime + usage.ru_stime


def scenario() -> dict:
    rng = np.random.default_rng(77)
    half = 300.0
    return {
        'seed': 77, 'sample_rate_hz': 10, 'noise_nT': 0.05, 'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'interference': {'random': {'k_scale': 0.005, 'b_scale_nT': 150, 'reference_clean': False}},
        'dipoles': [{'position_m': [float(v) for v in d.position], 'moment_Am2': [float(m) for m in d.moment]}
                    for d in random_targets(rng, 5, half, 90.0)],
        'segments': [{'trim': {'duration_s': 300, 'center_m': [3000.0, 3000.0, DEPTH_M]}}]
        + [{'line': {'start_m': [float(v) for v in line.start], 'end_m': [float(v) for v in line.end],
                     'speed_m_s': 2.0}}
           for line in lines(12, 16.0, half)],
    }  # fmt: skip


def prepared(cache: Path) -> tuple[Path, Path, Path]:
    """The cached bag, its params and its calibration (made once)."""
    bag, params, calibration = cache / 'bag', cache / 'bag.params.yaml', cache / 'cal.yaml'
    if not calibration.exists():
        cache.mkdir(parents=True, exist_ok=True)
        (cache / 'survey.yaml').write_text(yaml.safe_dump(scenario()))
        print(f'generating {bag} (cached for later runs) ...', flush=True)
        run('simulate', '--scenario', cache / 'survey.yaml', '--out', bag, '--force')
        run('calibrate', bag, '--params', params, '--window', '0:299.95', '--out', calibration,
            '--force')
    return bag, params, calibration


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cache', type=Path, default=Path('/tmp/tetra_bench_survey'))
    parser.add_argument('--json', type=Path, default=None)
    args = parser.parse_args()
    bag, params, calibration = prepared(args.cache)
    out = args.cache / 'survey'
    elapsed, peak, stdout, cpu = run('survey', bag, '--params', params, '--calibration', calibration,
                                '--out', out, '--origin', '43.2,5.3', '--force', '--no-progress')
    summary = json.loads((out / 'survey.json').read_text())
    sizes = {p.name: p.stat().st_size for p in out.iterdir() if p.is_file()}
    result = {
        'wall_s': round(elapsed, 1), 'cpu_s': round(cpu, 1), 'peak_MB': round(peak),
        'load_average_1min': os.getloadavg()[0], 'stages_s': summary['timings_s'],
        'grid': summary['grid'], 'targets': summary['targets'], 'files_bytes': sizes,
        'pass': elapsed < TARGET_S and peak < TARGET_MB,
    }
    print(stdout.strip().splitlines()[1])
    print(json.dumps(result, indent=1))
    print(f'survey: {elapsed:.1f} s wall, {cpu:.1f} s CPU (target < {TARGET_S:.0f}), '
          f'peak {peak:.0f} MB (target < {TARGET_MB:.0f})')
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1) + '\n')
    return 0 if result['pass'] else 1


if __name__ == '__main__':
    sys.exit(main())
