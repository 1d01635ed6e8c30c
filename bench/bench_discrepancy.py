"""Benchmark of the discrepancy workflow.

1. Timing: a 10-minute, 10 Hz recorded-style bag (one hidden effect) analysed end to end
   through the command line (read the bag, analyse, write report.json, report.md, plots).
2. Detection table: for each library effect (and clean data, and pairs of effects), several
   random seeds (geometry, Earth field, manoeuvre, noise 0.02-0.2 nT, magnitude 20-80 x noise);
   named correctly?, named first?, held-out gap before/after against the noise floor.

    .venv/bin/python bench/bench_discrepancy.py [--seeds 4] [--duration 180] [--pairs 1]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tetra_gradiometer.__main__ import main as cli_main  # noqa: E402
from tetra_gradiometer.core.discrepancy import analyze  # noqa: E402
from tetra_gradiometer.core.discrepancy.synthetic import EFFECT_NAMES, make_case  # noqa: E402
from tetra_gradiometer.io.params import params_document  # noqa: E402
from tetra_gradiometer.io.recording import write_mission_bag  # noqa: E402


def timing(storage: str, duration_s: float = 600.0) -> dict:
    case = make_case(2024, ('time_skew',), duration_s=duration_s)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        bag = write_mission_bag(tmp / 'bag', case.mission, storage=storage)
        (tmp / 'params.yaml').write_text(
            params_document(
                {
                    'sensor_positions': case.scenario.geometry.to_flat(),
                    'earth_field_enu': [float(v) for v in case.scenario.earth_field_enu],
                }
            )
        )
        started = time.perf_counter()
        code = cli_main(
            [
                'discrepancy',
                str(bag),
                '--params',
                str(tmp / 'params.yaml'),
                '--out',
                str(tmp / 'out'),
            ]
        )
        elapsed = time.perf_counter() - started
        report = json.loads((tmp / 'out' / 'report.json').read_text())
    return {
        'storage': storage,
        'samples': len(case.mission),
        'exit_code': code,
        'end_to_end_s': elapsed,
        'analysis_s': report['runtime_s'],
        'named': report['named_effects'],
        'hidden': list(case.hidden),
    }


def detection(seeds: int, duration_s: float, pairs: int) -> list[dict]:
    sets: list[tuple[str, ...]] = [()] + [(e,) for e in EFFECT_NAMES]
    if pairs:
        sets += list(itertools.combinations(EFFECT_NAMES, 2))
    rows: list[dict] = []
    for effects in sets:
        n = seeds if len(effects) < 2 else pairs
        for seed in range(n):
            case = make_case(90_000 + 1000 * seed + 37 * len(rows), effects, duration_s=duration_s)
            earth = case.scenario.earth_field_enu if seed % 2 == 0 else None
            report = analyze(case.recording(), case.scenario.geometry, earth, keep_series=False)
            rows.append(
                {
                    'hidden': list(effects),
                    'seed': seed,
                    'named': report.named_effects,
                    'correct': sorted(report.named_effects) == sorted(effects),
                    'first': (report.named_effects[:1] == list(effects[:1]))
                    if len(effects) == 1
                    else None,
                    'gap_before_nT': report.gap_initial_nT,
                    'gap_after_nT': report.gap_final_nT,
                    'noise_floor_nT': report.noise_floor_nT,
                    'true_noise_nT': case.scenario.noise_t * 1e9,
                    'adequate': report.adequate,
                    'runtime_s': report.runtime_s,
                }
            )
            print(
                f'{"+".join(effects) or "clean":45s} seed {seed}: named {report.named_effects} '
                f'gap {report.gap_initial_nT:.3g} -> {report.gap_final_nT:.3g} nT '
                f'(floor {report.noise_floor_nT:.3g}) {report.runtime_s:.2f} s',
                flush=True,
            )
    return rows


def table(rows: list[dict]) -> str:
    lines = [
        '| hidden | runs | named correctly | named first | gap before, nT (median) '
        '| gap after, nT (median) | noise floor, nT (median) | after / floor (max) | adequate |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    groups: dict[str, list[dict]] = {}
    for r in rows:
        key = ' + '.join(r['hidden']) if r['hidden'] else 'clean'
        key = key if len(r['hidden']) < 2 else 'pairs (all 15)'
        groups.setdefault(key, []).append(r)
    for key, rs in groups.items():
        first = [r['first'] for r in rs if r['first'] is not None]
        lines.append(
            f'| {key} | {len(rs)} | {sum(r["correct"] for r in rs)}/{len(rs)} | '
            f'{(str(sum(first)) + "/" + str(len(first))) if first else "-"} | '
            f'{np.median([r["gap_before_nT"] for r in rs]):.3g} | '
            f'{np.median([r["gap_after_nT"] for r in rs]):.3g} | '
            f'{np.median([r["noise_floor_nT"] for r in rs]):.3g} | '
            f'{max(r["gap_after_nT"] / r["noise_floor_nT"] for r in rs):.3g} | '
            f'{sum(r["adequate"] for r in rs)}/{len(rs)} |'
        )
    return '\n'.join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, default=4, help='seeds per single effect and clean')
    parser.add_argument('--pairs', type=int, default=1, help='seeds per pair of effects (0: none)')
    parser.add_argument(
        '--duration', type=float, default=180.0, help='mission length for the table, s'
    )
    parser.add_argument('--no-timing', action='store_true')
    parser.add_argument('--json', default=None, help='write all rows here')
    args = parser.parse_args()
    results: dict = {}
    if not args.no_timing:
        results['timing'] = [timing('sqlite3'), timing('mcap')]
        for t in results['timing']:
            print(
                f'10 min at 10 Hz ({t["samples"]} samples, {t["storage"]}): '
                f'end to end {t["end_to_end_s"]:.1f} s '
                f'(analysis {t["analysis_s"]:.1f} s); hidden {t["hidden"]}, named {t["named"]}',
                flush=True,
            )
    rows = detection(args.seeds, args.duration, args.pairs)
    results['rows'] = rows
    print()
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == '__main__':
    sys.exit(main())
