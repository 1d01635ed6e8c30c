"""Open-world sweep of the discrepancy workflow (issue 11) on held-out-like runs.

Each case is a recorded-style run (``make_case``: random geometry, Earth field, manoeuvre,
noise 0.02-0.2 nT, vehicle interference) with physics the library does not hold added to
the fields; the workflow is told nothing. Seeds differ from the test suite's.

* **step**: one sensor's hard iron jumps (sensor 1-4, at 60-540 s of 600 s, 10-50 x the
  noise) -> ``hard_iron_step`` on that sensor within 3 s, <= 5 % excluded, gap >= 3 x
  smaller (or at the floor, when it started below 3 x the floor) and <= 1.5 x the floor;
* **line**: a rotating magnet (0.2-5 Hz, log-uniform; one or two sensors, 5-20 x the
  noise) -> ``periodic_interference`` at the frequency +- 1 %, on those sensors only, gap
  >= 3 x smaller (or at the floor); named, or unresolved when a recorded channel has a line
  there too (issue 31's rule);
* **triple**: eddy current + time skew + thermal drift -> eddy and thermal named, the skew
  named or under the eddy term's ``confounded_with``, gap <= 1.5 x the floor;
* **target**: a survey line passing 20-50 m over a 1e4-1e5 A m^2 dipole after the trim,
  one random library effect hidden -> the target listed within 0.5 m (modelled as a
  dipole, issue 31), nothing excluded, the effect named and nothing else, gap <= 1.5 x the
  floor.

    .venv/bin/python bench/bench_openworld.py [--cases 6] [--first-seed 900] [--kinds step,line,triple,target] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tetra_gradiometer.core.discrepancy import analyze  # noqa: E402
from tetra_gradiometer.core.discrepancy.synthetic import make_case  # noqa: E402

LIBRARY_EFFECTS = ('eddy_current', 'sensor_misalignment', 'reference_interference',
                   'time_skew', 'thermal_drift', 'vehicle_current')  # fmt: skip


def step_case(seed: int) -> dict:
    rng = np.random.default_rng([11, seed])
    sensor, t_step, size = int(rng.integers(1, 5)), rng.uniform(60, 540), rng.uniform(10, 50)
    case = make_case(seed, (), duration_s=600.0, far_target=False)
    run = case.recording()
    jump = rng.normal(size=3)
    jump *= size * case.scenario.noise_t / np.linalg.norm(jump)
    fields = run.fields.copy()
    fields[run.t_s >= t_step, sensor - 1] += jump
    report = analyze(replace(run, fields=fields), case.scenario.geometry)
    steps = [f for f in report.findings if f['effect'] == 'hard_iron_step']
    hit = len(steps) == 1 and steps[0]['sensors'] == [sensor] and abs(steps[0]['t_s'] - t_step) <= 3
    ok = (report.named_effects == ['hard_iron_step'] and hit and report.excluded_fraction <= 0.05
          and gaps_ok(report, shrink=3.0, floor=1.5))  # fmt: skip
    return {'truth': {'sensor': sensor, 't_s': t_step, 'size_noise': size},
            'found': [{'sensors': f['sensors'], 't_s': f['t_s']} for f in steps], **common(report, ok)}  # fmt: skip


def line_case(seed: int) -> dict:
    rng = np.random.default_rng([12, seed])
    frequency = float(np.exp(rng.uniform(np.log(0.2), np.log(5.0))))
    sensors = sorted(rng.choice(4, size=int(rng.integers(1, 3)), replace=False) + 1)
    size = rng.uniform(5, 20)
    case = make_case(seed, (), duration_s=600.0, far_target=False)
    run = case.recording()
    fields = run.fields.copy()
    for s in sensors:
        amplitude = rng.normal(size=3)
        amplitude *= size * case.scenario.noise_t / np.linalg.norm(amplitude)
        fields[:, s - 1] += amplitude * np.sin(2 * np.pi * frequency * run.t_s[:, None] + rng.uniform(0, 6, 3))
    report = analyze(replace(run, fields=fields), case.scenario.geometry)
    lines = [f for f in report.findings if f['effect'] == 'periodic_interference']
    hit = (len(lines) == 1 and abs(lines[0]['frequency_hz'] / frequency - 1) <= 0.01
           and lines[0]['sensors'] == [int(s) for s in sensors])  # fmt: skip
    # Issue 31's rule: a line that a recorded channel (the manoeuvre's field rate, ...) has
    # too is reported unresolved, not named; that is the right answer there.
    unresolved = (report.named_effects == [] and report.unresolved_effects == ['periodic_interference']
                  and all(f['recorded_with_line'] for f in lines))  # fmt: skip
    named_ok = report.named_effects == ['periodic_interference'] or unresolved
    ok = named_ok and hit and gaps_ok(report, shrink=3.0)
    return {'truth': {'frequency_hz': frequency, 'sensors': [int(s) for s in sensors], 'size_noise': size},
            'found': [{'frequency_hz': f['frequency_hz'], 'sensors': f['sensors'], 'status': f['status'],
                       'recorded_with_line': f['recorded_with_line']} for f in lines],
            **common(report, ok)}  # fmt: skip


def triple_case(seed: int) -> dict:
    case = make_case(seed, ('eddy_current', 'time_skew', 'thermal_drift'), duration_s=300.0)
    report = analyze(case.recording(), case.scenario.geometry)
    named = set(report.named_effects)
    eddy = [f for f in report.findings if f['effect'] == 'eddy_current']
    skew = 'time_skew' in named or any('time_skew' in f['confounded_with'] for f in eddy)
    ok = {'eddy_current', 'thermal_drift'} <= named and skew and gaps_ok(report, floor=1.5)
    return {'truth': case.hidden, 'confounded': {f['effect']: f['confounded_with'] for f in report.findings},
            **common(report, ok)}  # fmt: skip


def target_case(seed: int) -> dict:
    effect = LIBRARY_EFFECTS[seed % len(LIBRARY_EFFECTS)]
    case = make_case(seed, (effect,), duration_s=300.0, near_target=True)
    report = analyze(case.recording(), case.scenario.geometry)
    m, target = case.mission, case.scenario.dipoles[-1]
    distance = np.linalg.norm(m.position_enu - target.position, axis=1)
    t_closest = float(m.t[np.argmin(distance)])
    spans = report.excluded_spans
    # Issue 31: the target is modelled as a dipole (listed within 0.5 m), not excluded.
    errors = [float(np.linalg.norm(np.array(t['position_m']) - target.position))
              for t in report.targets]
    listed = bool(errors) and min(errors) < 0.5
    # A distant dipole of make_case (1e6-scale A m^2, 0.8-2 km) is a field from outside the
    # vehicle on the track: external_field is then there too.
    far = len(case.scenario.dipoles) > 1
    named_ok = report.named_effects in ([effect], [effect, 'external_field'] if far else None)
    ok = named_ok and listed and not spans and gaps_ok(report, floor=1.5)
    return {'truth': {'effect': effect, 'distance_m': float(distance.min()), 't_closest_s': t_closest,
                      'far_dipole': far},
            'target_errors_m': errors,
            'spans': [{k: s[k] for k in ('start_s', 'end_s', 'reason')} for s in spans],
            **common(report, ok)}  # fmt: skip


def gaps_ok(report, shrink: float | None = None, floor: float | None = None) -> bool:
    """``shrink``: the gap ``shrink`` x smaller, or at the noise floor (within 5 %) when the
    initial gap is less than ``shrink`` x the floor (a small effect: nothing more to take)."""
    ok = True
    if shrink is not None:
        at_floor = report.gap_final_nT <= 1.05 * report.noise_floor_nT
        ok &= report.gap_final_nT <= report.gap_initial_nT / shrink or at_floor
    if floor is not None:
        ok &= report.gap_final_nT <= floor * report.noise_floor_nT
    return bool(ok)


def common(report, ok: bool) -> dict:
    return {'ok': ok, 'named': report.named_effects, 'adequate': report.adequate,
            'excluded_fraction': report.excluded_fraction, 'gap_initial_nT': report.gap_initial_nT,
            'gap_final_nT': report.gap_final_nT, 'noise_floor_nT': report.noise_floor_nT}  # fmt: skip


KINDS = {'step': step_case, 'line': line_case, 'triple': triple_case, 'target': target_case}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cases', type=int, default=6)
    parser.add_argument('--first-seed', type=int, default=900)
    parser.add_argument('--kinds', default=','.join(KINDS))
    parser.add_argument('--json', type=Path)
    args = parser.parse_args()
    results: dict = {}
    for kind in args.kinds.split(','):
        rows = []
        for i in range(args.cases):
            started = time.perf_counter()
            row = KINDS[kind](args.first_seed + i)
            row['seconds'] = time.perf_counter() - started
            rows.append(row)
            print(f'{kind} {args.first_seed + i}: {"ok" if row["ok"] else "FAIL"} named={row["named"]} '
                  f'gap {row["gap_initial_nT"]:.3g}->{row["gap_final_nT"]:.3g} (floor '
                  f'{row["noise_floor_nT"]:.3g}) excl {row["excluded_fraction"]:.3f} '
                  f'{row["seconds"]:.0f} s; truth {row["truth"]} found {row.get("found", row.get("spans", row.get("confounded")))}',
                  flush=True)  # fmt: skip
        results[kind] = {'passed': sum(r['ok'] for r in rows), 'cases': len(rows), 'rows': rows}
    print(json.dumps({k: f'{v["passed"]}/{v["cases"]}' for k, v in results.items()}))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=float) + '\n')


if __name__ == '__main__':
    main()
