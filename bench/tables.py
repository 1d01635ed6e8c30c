"""Write the README's benchmark tables from the data in ``bench/results/`` (``make bench``
runs it after the benchmarks).

Each table sits in README.md from its caption line, which ends in ``<!-- bench:NAME -->``,
to ``<!-- /bench:NAME -->``, where NAME is a results file's stem (``bench/results/NAME.json``);
those lines are replaced, nothing else (a new table: the two markers on lines of their own).
Each table names the machine its figures came from: ``bench/results/machines.json`` maps a
results file to that machine, and ``--measured-here FILE ...`` records this machine for the
files a run has just written.

    .venv/bin/python bench/tables.py [--measured-here accuracy.json ...] [--check]

``--check`` rewrites nothing and exits 1 when README.md differs from what the data gives.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / 'bench' / 'results'
MACHINES = RESULTS / 'machines.json'
README = REPO / 'README.md'
SECTION = re.compile(r'^[^\n]*<!-- bench:(\w+) -->\n.*?<!-- /bench:\1 -->', re.S | re.M)

Table = tuple[str, list[str], list[list[str]]]  # caption, header, rows


def num(value: float) -> str:
    """Four significant digits, thousands grouped by a space from 10 000: 0.3021, 5250, 10 936."""
    if abs(value) >= 10_000:
        return f'{value:,.0f}'.replace(',', ' ')
    if abs(value) >= 1000:
        return f'{value:.0f}'
    return f'{value:.4g}'


def ratio(value: float) -> str:
    """A ratio to the noise floor: 1.004x, 3848x."""
    return f'{value:.3f}x' if value < 10 else f'{num(value)}x'


def _load(name: str):
    return json.loads((RESULTS / f'{name}.json').read_text(encoding='utf-8'))


def paper() -> Table:
    data = _load('paper')
    floor = data['scenario']['noise_floor_nT_per_m']
    data_of = {'paper_ga': '30 pass points', 'constraint_lstsq': '30 pass points',
               'pei_yeo_2009': '30 pass points'}
    rows = [[f'`{name}`', data_of.get(name, 'trim'), f'{m["compensated_percent"]:.3f}',
             num(m['rms_residual_nT_per_m']), num(m['improvement_ratio'])]
            for name, m in data['methods'].items()]
    return (f'**The paper reproduced** (`make paper`, Earth-field reading; noise floor '
            f'{floor:.3f} nT/m)', ['method', 'identified on', 'compensated % (eq. 24)',
                                   'RMS residual nT/m', 'improvement'], rows)


def accuracy() -> Table:
    data = _load('accuracy')
    by = {(r['scenario'], r['method']): r for r in data}
    methods = [m for s, m in by if s == 'reference clean' and 'wide' not in m]
    scenarios = list(dict.fromkeys(s for s, _ in by))

    def cell(r: dict) -> str:
        rms, improvement = num(r['rms_nT_per_m']), num(r['improvement_ratio'])
        return f'{rms} ({ratio(r["floor_ratio"])}), {improvement}'
    rows = [[f'`{m}`'] + [cell(by[s, m]) for s in scenarios] for m in methods]
    floor = data[0]['noise_floor_nT_per_m']
    return (f'**Accuracy** (`bench/bench_accuracy.py`: 5 min trim, three passes over a dipole, '
            f'0.05 nT noise, floor {floor:.4f} nT/m; RMS nT/m (x floor), improvement; target '
            f'1.2x the floor)', ['method, calibrated on the trim'] + scenarios, rows)


def window() -> Table:
    rows = [[r['mission'], r['window_s'], f'{r["floor_ratio"]:.3f}x'] for r in _load('window')]
    return ('**Calibration window found in the bag** (`bench/bench_window.py`: `calibrate` '
            'without `--window`, then `compensate`; survey against truth; target 1.2x)',
            ['mission', 'window found (s)', 'survey / floor'], rows)


def scale() -> Table:
    rows = [[r['storage'], f'{r["wall_s"]:.1f} s', num(r['sets_per_s']), f'{r["peak_mb"]:.0f} MB']
            for r in _load('scale') if r['command'] == 'compensate --csv']
    return ('**Scale** (`bench/bench_scale.py`: `compensate --csv` of 1 h at 100 Hz, 360 000 '
            'sets; target < 60 s, < 500 MB)', ['storage', 'wall', 'sets/s', 'peak RSS'], rows)


def effects() -> Table:
    data = _load('effects')
    rows = [[r['vehicle'], ', '.join(r['terms']) or 'none', ratio(r['before_ratio']),
             ratio(r['after_ratio'])] for r in data['table']]
    return ('**Vehicle effects** (`bench/bench_effects.py`: survey residual / noise floor; '
            'before: `calibrate --effects none --force`, after: defaults)',
            ['vehicle', 'terms kept', 'before', 'after'], rows)


def chain() -> Table:
    rows = [[str(r['rate']), str(r['sent']), str(r['received']), f'{r["p50_ms"]:g}',
             f'{r["p99_ms"]:g}', f'{r["cpu_s_per_1000_sets"]:g} s']
            for r in _load('chain')['rows']]
    return ('**Node chain** (`bench/bench_chain.py`: tensor and compensator as processes over '
            'Fast DDS on loopback, default parameters (the calibration tracked); target 1000 '
            'sets/s, no drop, p99 < 10 ms)',
            ['sets/s', 'sent', 'received', 'p50 ms', 'p99 ms', 'CPU per 1000 sets'], rows)


def tracker() -> Table:
    data = _load('tracker')
    missions, blind = data['drifting'], data['without_attitude']['drifting']

    def span(runs: list[dict], key: str, which: str) -> str:
        values = [r[key][which] for r in runs]
        return f'{min(values):.2f}-{max(values):.2f}x'
    limits = {'first_5_min': '1.74x', 'before_step': '1.2x', 'after_step': '1.2x'}
    names = {'first_5_min': 'first 5 min', 'before_step': '5 min before the step',
             'after_step': 'after the step'}
    rows = [[names[k], span(missions, k, 'frozen'), span(missions, k, 'tracked'),
             span(blind, k, 'tracked'), limits[k]] for k in limits]
    recovery = max(r['recovery_s'] for r in missions)
    covered = [r['within_2_sigma'] for r in missions]
    geology = [g['survey']['tracked_over_frozen'] for g in data['geology']]
    moved = max(max(t['position_change_over_sigma'], t['moment_change_over_sigma'])
                for m in data['targets'] for t in m['targets'])
    streamed = max(max(t['position_change_over_sigma'], t['moment_change_over_sigma'])
                   for m in data['targets_streamed'] for t in m['targets'])
    never = sum(r['recovery_s'] is None for r in blind)
    offline = data['offline_cost']['s_per_hour_of_data_at_10_hz']
    return (f'**Calibration tracking** (`bench/bench_tracker.py`: {len(missions)} missions of '
            f'30 min, '
            f'the hull relaxing after the trim and a 2 nT/m step on one sensor; '
            f'residual / floor of the default `compensate`, `--freeze-calibration` beside it): '
            f'back at the floor {recovery:g} s after the step (without /odom: never in {never} '
            f'of {len(blind)}); |error| <= 2 sigma for {min(covered):.1%}-{max(covered):.1%}; '
            f'over geology tracked / frozen {min(geology):.3f}-{max(geology):.3f}; `locate` '
            f'moved at most {moved:.2g} sigma ({streamed:.2g} on a stream, `compensate` and the '
            f'node: no target is known beforehand, the gate alone); {offline:g} s per hour of 10 Hz data offline, '
            f'{data["live_cost"]["with_health_monitor"]["us_per_set"]:.0f} us per set live',
            ['span', 'frozen', 'tracked (with /odom)', 'tracked, no /odom', 'limit'], rows)


def health() -> Table:
    data = _load('health')
    fa = data['false_alarms']
    rows = [[f'{float(size):g}', f'{d["median_delay_s"]:g} s', f'{d["p95_delay_s"]:g} s',
             f'{d["named_first_fraction"]:.0%}'] for size, d in data['delays'].items()]
    return (f'**Health monitor** (`bench/bench_health.py`: {fa["alarms"]} false alarms in '
            f'{fa["hours"]:g} h of survey over targets; target < 1 per 10 h, a 2 nT jump within '
            f'5 s)', ['offset jump nT', 'median delay', '95th percentile', 'sensor named first'],
            rows)


def discrepancy() -> Table:
    data = _load('discrepancy')
    groups: dict[str, list[dict]] = {}
    for r in data['rows']:
        key = ('none (clean)' if not r['hidden'] else f'`{r["hidden"][0]}`'
               if len(r['hidden']) == 1 else 'two at once')
        groups.setdefault(key, []).append(r)
    rows = [[key, f'{sum(r["correct"] for r in rs)}/{len(rs)}',
             f'{statistics.median(r["gap_before_nT"] for r in rs):.3g} -> '
             f'{statistics.median(r["gap_after_nT"] for r in rs):.3g}',
             f'{max(r["gap_after_nT"] / r["noise_floor_nT"] for r in rs):.2f}']
            for key, rs in groups.items()]
    timing = ', '.join(f'{t["end_to_end_s"]:.1f} s ({t["storage"]})' for t in data['timing'])
    return (f'**Discrepancy** (`bench/bench_discrepancy.py`: the hidden effect named; a 10-minute '
            f'10 Hz bag end to end in {timing}; target < 60 s)',
            ['hidden', 'named correctly', 'gap nT, median', 'after / floor, worst'], rows)


def discrepancy_survey() -> Table:
    rows = [[r['vehicle'], ', '.join(r['named']),
             ', '.join(f'{e:.4f}' for e in r['target_error_m']),
             f'{r["gap_nT"] / r["floor_nT"]:.2f}x', f'{r["excluded_fraction"]:.0%}',
             f'{r["cpu_s"]:.1f} s'] for r in _load('discrepancy_survey')['rows']]
    return ('**Discrepancy on a whole survey** (`bench/bench_discrepancy_survey.py`: 1000 s at '
            '10 Hz, two dipoles modelled; target 20 s)',
            ['vehicle', 'named', 'target errors m', 'gap / floor', 'excluded', 'CPU'], rows)


def openworld() -> Table:
    data = _load('openworld')
    labels = {'step': '`hard_iron_step`', 'line': '`periodic_interference`',
              'triple': 'eddy + time skew + thermal', 'target': 'target pass + one effect'}
    rows = []
    for kind, label in labels.items():
        rs = data[kind]['rows']
        rows.append([label, f'{data[kind]["passed"]}/{data[kind]["cases"]}',
                     f'{min(r["gap_initial_nT"] / r["gap_final_nT"] for r in rs):.2g}-'
                     f'{max(r["gap_initial_nT"] / r["gap_final_nT"] for r in rs):.2g}x',
                     f'{max(r["gap_final_nT"] / r["noise_floor_nT"] for r in rs):.3f}'])
    return ('**Discrepancy, open world** (`bench/bench_openworld.py`: seeds the tests never use, '
            'the workflow told nothing)', ['case', 'passed', 'gap shrink', 'after / floor, worst'],
            rows)


def signals() -> Table:
    d = _load('signals')

    def cell(value: float | None) -> str:
        return 'refused' if value is None else ratio(value)

    rows = [[name, f"{'refused' if v['paper_refused'] else 'calibrated'}, forced "
             f"{cell(v['paper_forced'])}", cell(v['default']), cell(v['declared']),
             cell(v['discovered'])]
            for name, v in d.get('vehicles', {}).items()]
    kept = len(d.get('clean_seeds_keeping_a_signal', ()))
    return ('**Recorded signals** (`bench/bench_signals.py`, magpylib vehicles: survey residual '
            'over the noise floor after a 240 s trim; `discrepancy` on a 300 s trim with ten '
            f'recorded signals, six of them fields: {len(d["named_effects"])} named, gap '
            f'{d["gap_over_floor"]:.2f}x the floor, {d["discrepancy_s"]:.1f} s (target < 20 s), '
            f'its declaration {ratio(d["survey_over_floor"])}; on a 30-minute mission '
            f'{d.get("mission_discrepancy_s", float("nan")):.1f} s (target < 60 s); a clean '
            f'vehicle recording moving fins and currents keeps a signal term in {kept} of '
            f'{d.get("clean_seeds", 0)} seeds)',
            ['vehicle', "the paper's k, b alone", 'default (finds the signals)', 'declared',
             "discrepancy's declaration"], rows)


def targets() -> Table:
    d = _load('targets')
    c, r = d['accuracy']['compensated'], d['accuracy']['raw']

    def row(name: str, t: dict) -> list[str]:
        return [name, f'{t["targets"] - t["missed"]}/{t["targets"]}', str(t['extra']),
                f'{t["position_error_m_max"]:.3g} m', f'{t["moment_error_pct_max"]:.3g} %',
                f'{t["z_rms_position"]:.2f} / {t["z_rms_moment"]:.2f}']
    return (f'**Targets** (`bench/bench_targets.py`: {d["accuracy"]["missions"]} missions; '
            f'`locate` on a 1-hour 10 Hz bag in {d["speed"]["compensated_only_s"]:.1f} s; '
            f'{d["false_alarms"]["detections_per_hour"]:.3f} false detections per target-free '
            f'hour at the stated 0.1)', ['tensor', 'found', 'extra', 'position error, max',
                                    'moment error, max', 'RMS error/σ pos. / moment'],
            [row('compensated', c), row('raw', r)])


def survey() -> Table:
    d = _load('survey')
    return ('**Survey products** (`bench/bench_survey.py`: a 1-hour 10 Hz survey, five targets, '
            'every product; target < 60 s, < 1 GB)',
            ['grid cells', 'targets', 'wall', 'CPU', 'peak RSS', 'report.html'],
            [[str(d['grid']['cells_gridded']), str(d['targets']), f'{d["wall_s"]:.1f} s',
              f'{d["cpu_s"]:.1f} s', f'{d["peak_MB"]} MB',
              f'{d["files_bytes"]["report.html"] / 1e6:.1f} MB']])


TABLES: dict[str, Callable[[], Table]] = {f.__name__: f for f in (
    paper, accuracy, window, scale, effects, chain, tracker, health, discrepancy,
    discrepancy_survey, openworld, signals, targets, survey)}


def render(name: str, machines: dict[str, str]) -> str:
    """Table ``name`` with its caption, the caption line ending in its begin marker."""
    caption, header, rows = TABLES[name]()
    lines = [f'{caption}; measured on {machines[f"{name}.json"]}. <!-- bench:{name} -->',
             '| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(row) + ' |' for row in rows]
    return '\n'.join(lines) + f'\n<!-- /bench:{name} -->'


def rewrite(text: str, machines: dict[str, str]) -> str:
    """``text`` with every marked table regenerated."""
    return SECTION.sub(lambda m: render(m.group(1), machines), text)


def this_machine() -> str:
    """A description of the machine running this, for the runs it has just made."""
    model = platform.processor() or platform.machine()
    cpuinfo = Path('/proc/cpuinfo')
    if cpuinfo.exists():
        found = re.search(r'^model name\s*:\s*(.+)$', cpuinfo.read_text(), re.M)
        model = found.group(1).strip() if found else model
    return (f'{model}, {os.cpu_count()} CPUs, Python {platform.python_version()}, '
            f'{datetime.date.today().isoformat()}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--measured-here', nargs='*', default=[], metavar='FILE',
                        help='results files in bench/results this machine has just written')
    parser.add_argument('--check', action='store_true', help='exit 1 if README.md is out of date')
    args = parser.parse_args()
    machines = json.loads(MACHINES.read_text(encoding='utf-8'))
    if args.measured_here:
        machines.update({name: this_machine() for name in args.measured_here})
        document = json.dumps(machines, indent=1, sort_keys=True) + '\n'
        MACHINES.write_text(document, encoding='utf-8')
    text = README.read_text(encoding='utf-8')
    new = rewrite(text, machines)
    if args.check:
        return int(new != text)
    README.write_text(new, encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())
