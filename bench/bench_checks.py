"""What the self-checks cost ``compensate`` on the 1-hour 100 Hz bag (bench_scale's).

Every compensation runs the health monitor and the tensor's convention test, and reads the
terms' channels against the calibration window. This runs ``compensate --csv`` in-process
under cProfile and takes the CPU of the checks (``HealthRecorder.add``, ``document``,
``TensorSample.add``, ``conventions_text``, ``WindowRanges.add``) against the whole run.

    .venv/bin/python bench/bench_checks.py [--bag DIR] [--json FILE]

``--bag`` defaults to bench_scale's cached sqlite3 bag (generated when missing: a few
minutes). Target: the checks < 10 % of compensate's CPU.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'bench'))

from bench_scale import cached_bag, run  # noqa: E402

from tetra_gradiometer.__main__ import main as cli  # noqa: E402

CHECKS = (
    ('pipelines/health.py', 'add'),
    ('pipelines/health.py', 'document'),
    ('core/conventions.py', 'add'),
    ('core/conventions.py', 'conventions_text'),
    ('pipelines/terms.py', 'add'),
)
TARGET_SHARE = 0.10


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', default=None)
    parser.add_argument('--json', default=None)
    args = parser.parse_args()
    bag = Path(args.bag) if args.bag else cached_bag(Path('/tmp/tetra_bench_scale'), 'sqlite3')
    params = Path(f'{bag}.params.yaml')
    with tempfile.TemporaryDirectory() as tmp:
        calibration = Path(tmp) / 'calib.yaml'
        run('calibrate', bag, '--params', params, '--window', '0:299.99', '--out', calibration,
            '--no-progress', '--force')
        profile = cProfile.Profile()
        profile.enable()
        code = cli(['compensate', str(bag), '--params', str(params), '--calibration', str(calibration),
                    '--csv', str(Path(tmp) / 'out.csv'), '--no-progress'])
        profile.disable()
    if code != 0:
        raise SystemExit(f'compensate failed ({code})')
    stats = pstats.Stats(profile).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    total = sum(tt for _, _, tt, _, _ in stats.values())
    parts = {}
    for (path, _, name), (_, _, _, cumulative, _) in stats.items():
        for suffix, function in CHECKS:
            if path.endswith(suffix) and name == function:
                parts[f'{suffix}:{function}'] = parts.get(f'{suffix}:{function}', 0.0) + cumulative
    checks = sum(parts.values())
    result = {'bag': str(bag), 'compensate_cpu_s': total, 'checks_cpu_s': checks,
              'share': checks / total, 'parts_cpu_s': parts, 'target_share': TARGET_SHARE}
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + '\n')
    met = result['share'] < TARGET_SHARE
    print(('target met' if met else 'TARGET MISSED') + f': the checks are {result["share"]:.1%} of compensate')
    return 0 if met else 1


if __name__ == '__main__':
    sys.exit(main())
