"""Scale of the offline chain: compensate a 1-hour, 100 Hz bag (issue 4).

The bag (config/scenarios/long_survey_100hz.yaml: 360 000 sets, 1.44 M MagneticField
messages plus /odom, /tetra/temperature, /battery_state at 100 Hz) is generated once per
storage and cached under ``--cache`` (default /tmp/tetra_bench_scale); generating it takes
a few minutes. Each command then runs in its own subprocess, timed by the wall clock, its
peak memory read from ``ru_maxrss`` (os.wait4).

    .venv/bin/python bench/bench_scale.py [--storage sqlite3 mcap] [--cache DIR] [--out-bag] [--generic]

Target: compensate (CSV) in < 60 s with < 500 MB peak memory.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / 'config/scenarios/long_survey_100hz.yaml'
TARGET_S = 60.0
TARGET_MB = 500.0


def run(*args: object) -> tuple[float, float, str]:
    """Run ``python -m tetra_gradiometer ARGS``; return (wall s, peak RSS MB, stdout)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with tempfile.TemporaryFile('w+') as errors:
        started = time.perf_counter()
        process = subprocess.Popen([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)],
                                   stdout=subprocess.PIPE, stderr=errors, env=env, cwd=REPO, text=True)
        stdout = process.stdout.read()
        _, status, usage = os.wait4(process.pid, 0)  # this child's own rusage (ru_maxrss in KiB)
        elapsed = time.perf_counter() - started
        process.returncode = os.waitstatus_to_exitcode(status)
        process.stdout.close()
        if process.returncode != 0:
            errors.seek(0)
            raise SystemExit(f'failed ({process.returncode}): {" ".join(map(str, args))}\n{errors.read()}')
    return elapsed, usage.ru_maxrss / 1024.0, stdout


def cached_bag(cache: Path, storage: str) -> Path:
    key = hashlib.sha256(SCENARIO.read_bytes()).hexdigest()[:12]
    bag = cache / f'{storage}_{key}' / 'long'
    if not (bag / 'metadata.yaml').exists():
        print(f'generating {bag} (cached for later runs) ...', flush=True)
        elapsed, peak, _ = run('simulate', '--scenario', SCENARIO, '--out', bag, '--storage', storage)
        print(f'  simulate: {elapsed:.0f} s, peak {peak:.0f} MB', flush=True)
    return bag


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--storage', nargs='+', default=['sqlite3', 'mcap'], choices=['sqlite3', 'mcap'])
    parser.add_argument('--cache', default='/tmp/tetra_bench_scale')
    parser.add_argument('--out-bag', action='store_true', help='also time compensate --out-bag')
    parser.add_argument('--generic', action='store_true',
                        help='also time compensate --generic-reader (rosbags deserializer, StampMatcher)')
    parser.add_argument('--json', default=None)
    args = parser.parse_args()
    cache = Path(args.cache)
    rows = []
    for storage in args.storage:
        bag = cached_bag(cache, storage)
        params = Path(f'{bag}.params.yaml')
        size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 1e6
        work = bag.parent
        elapsed, peak, _ = run('calibrate', bag, '--params', params, '--window', '0:299.99',
                               '--out', work / 'calib.yaml', '--no-progress', '--force')
        rows.append({'storage': storage, 'command': 'calibrate (window 0:300 s, 30 000 sets)', 'wall_s': elapsed,
                     'peak_mb': peak, 'bag_mb': size_mb})
        commands = [('compensate --csv', ['--csv', work / 'out.csv'])]
        if args.out_bag:
            commands.append(('compensate --csv --out-bag', ['--csv', work / 'out.csv', '--out-bag', work / 'out_bag']))
        if args.generic:
            commands.append(('compensate --csv --generic-reader', ['--csv', work / 'out.csv', '--generic-reader']))
        for label, extra in commands:
            elapsed, peak, stdout = run('compensate', bag, '--params', params, '--calibration', work / 'calib.yaml',
                                        '--no-progress', '--force', *extra)
            n_sets = int(stdout.split()[1])
            rows.append({'storage': storage, 'command': label, 'wall_s': elapsed, 'peak_mb': peak,
                         'sets': n_sets, 'sets_per_s': n_sets / elapsed, 'bag_mb': size_mb})
        print(json.dumps(rows[-len(commands) - 1:], indent=1), flush=True)
    print()
    print('| storage | command | wall, s | sets/s | peak RSS, MB | bag size, MB |')
    print('|---|---|---|---|---|---|')
    for r in rows:
        sets_per_s = f'{r["sets_per_s"]:.0f}' if 'sets_per_s' in r else '-'
        print(f'| {r["storage"]} | {r["command"]} | {r["wall_s"]:.1f} | {sets_per_s} | {r["peak_mb"]:.0f} | '
              f'{r["bag_mb"]:.0f} |')
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    missed = [r for r in rows if r['command'] == 'compensate --csv'
              and not (r['wall_s'] < TARGET_S and r['peak_mb'] < TARGET_MB)]
    for r in missed:
        print(f'TARGET MISSED ({r["storage"]}): {r["wall_s"]:.1f} s, {r["peak_mb"]:.0f} MB')
    if not missed:
        print(f'target met: compensate --csv < {TARGET_S:g} s and < {TARGET_MB:g} MB on every storage')
    return 1 if missed else 0


if __name__ == '__main__':
    sys.exit(main())
