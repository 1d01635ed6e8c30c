"""Benchmark of the discrepancy workflow on a whole survey with targets (issue 31).

A 1,000 s, 10 Hz mission: a 5-minute trim far from the targets, then three 400 m lines
passing two dipoles (2.0e4 and 4.6e4 A m^2) at 30-35 m closest approach; sensor 1 not
clean. Two vehicles: clean, and with battery current (``vehicle_current``). Each is
simulated into a bag (``simulate``) and analysed end to end through the command line
(``discrepancy BAG --params FILE --out DIR``); reported: what is named, the targets against
the truth, the gap against the noise floor, the excluded share, wall and CPU time (CPU summed over
threads: the analysis runs on one BLAS thread, see pipelines/discrepancy.py) and the 1-minute
load average before and after each run.

    nice -n 10 .venv/bin/python bench/bench_discrepancy_survey.py
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tetra_gradiometer.__main__ import main as cli_main  # noqa: E402

DIPOLES = [
    ((-70.0, 18.0, -68.0), (15000.0, -8000.0, -11000.0)),
    ((85.0, 45.0, -72.0), (-30000.0, 20000.0, 28000.0)),
]
SCENARIO = """description: whole survey, two targets (bench_discrepancy_survey)
seed: {seed}
sample_rate_hz: 10
noise_nT: 0.05
geometry: {{regular_edge_m: 0.5}}
earth_field: {{enu_nT: [1200.0, 17500.0, -47000.0]}}
dipoles:
{dipoles}
interference:
  random: {{k_scale: 0.005, b_scale_nT: 150, reference_clean: false}}
segments:
  - trim: {{duration_s: 300, center_m: [3000.0, 3000.0, -40.0]}}
  - line: {{start_m: [-200.0, 0.0, -40.0], end_m: [200.0, 0.0, -40.0], speed_m_s: 1.72}}
  - line: {{start_m: [200.0, 30.0, -40.0], end_m: [-200.0, 30.0, -40.0], speed_m_s: 1.72}}
  - line: {{start_m: [-200.0, 60.0, -40.0], end_m: [200.0, 60.0, -40.0], speed_m_s: 1.72}}
effects: {effects}
"""
VEHICLES = {
    'clean': ('{}', []),
    'battery current': (
        '{vehicle_current: {nT_per_A: [[0, 0, 0], [0.5, -0.2, 0.1], [-0.3, 0.4, 0.2], '
        '[0.1, 0.1, -0.6]]}}',
        ['vehicle_current'],
    ),
}


def run(name: str, effects: str, seed: int, tmp: Path) -> dict:
    dipoles = '\n'.join(
        f'  - {{position_m: {list(p)}, moment_Am2: {list(m)}}}' for p, m in DIPOLES
    )
    scenario = tmp / f'{seed}.yaml'
    scenario.write_text(SCENARIO.format(seed=seed, dipoles=dipoles, effects=effects))
    bag = tmp / f'bag{seed}'
    cli_main(['simulate', '--scenario', str(scenario), '--out', str(bag), '--no-progress'])
    out = tmp / f'out{seed}'
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    code = cli_main(
        ['discrepancy', str(bag), '--params', f'{bag}.params.yaml', '--out', str(out),
         '--no-plots']
    )  # fmt: skip
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    report = json.loads((out / 'report.json').read_text())
    errors = [
        min(np.linalg.norm(np.array(t['position_m']) - np.array(p)) for t in report['targets'])
        if report['targets']
        else float('inf')
        for p, _ in DIPOLES
    ]
    return {
        'vehicle': name,
        'exit_code': code,
        'named': report['named_effects'],
        'targets': len(report['targets']),
        'target_error_m': errors,
        'gap_nT': report['gap_final_nT'],
        'floor_nT': report['noise_floor_nT'],
        'excluded_fraction': report['excluded_fraction'],
        'adequate': report['adequate'],
        'wall_s': wall,
        'cpu_s': cpu,
        'load_1min': [load, os.getloadavg()[0]],  # before and after: the machine is shared
    }


def main() -> int:
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        for seed, (name, (effects, hidden)) in enumerate(VEHICLES.items(), start=11):
            row = run(name, effects, seed, Path(tmp_name))
            row['hidden'] = hidden
            rows.append(row)
            print(json.dumps(row, default=float), flush=True)
    print(
        '| vehicle | hidden | named | targets (error, m) | gap / floor, nT | excluded | '
        'adequate | wall, s | CPU, s | load |'
    )
    print('|---|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        err = ', '.join(f'{e:.2f}' for e in r['target_error_m'])
        print(
            f'| {r["vehicle"]} | {", ".join(r["hidden"]) or "-"} | {", ".join(r["named"])} | '
            f'{r["targets"]} ({err}) | {r["gap_nT"]:.3g} / {r["floor_nT"]:.3g} | '
            f'{100 * r["excluded_fraction"]:.0f} % | {r["adequate"]} | {r["wall_s"]:.1f} | '
            f'{r["cpu_s"]:.1f} | {r["load_1min"][0]:.1f}-{r["load_1min"][1]:.1f} |'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
