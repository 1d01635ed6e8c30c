"""Benchmark: the vehicle's own recorded signals, found and calibrated (issue 40's figures).

A 300 s trim and a 120 s survey of the magpylib vehicle of ``test/pipelines/
test_recorded_signals.py`` (four fin servo magnets on ``/joint_states``, a switched sonar
and a thruster harness on ``std_msgs/Float64`` power-board topics), with four more recorded
signals that do nothing to the field (a pump's current, a CTD's pressure, two payload
voltages): ten signals beyond the contract. Measured: ``discrepancy`` on the trim (what it
names, its gap over its floor, its time; target < 20 s), then ``calibrate --effects-from``
its report and ``compensate`` the survey (residual over the noise floor; target <= 1.2x).

    .venv/bin/python bench/bench_signals.py [--json bench/results/signals.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / 'test' / 'io'), str(REPO / 'test' / 'pipelines')]

from stream_faults import GEOMETRY, short_mission  # noqa: E402
from test_recorded_signals import _currents, _fin_angles, _fin_field, _wire_field, _write  # noqa: E402

from tetra_gradiometer.__main__ import main as cli  # noqa: E402
from tetra_gradiometer.core.metrics import noise_floor  # noqa: E402
from tetra_gradiometer.io.bag import BagWriter  # noqa: E402

DISTRACTORS = ('/power/pump', '/ctd/pressure', '/payload/v1', '/payload/v2')


def _add_distractors(bag: Path, t: np.ndarray, start_ns: int) -> None:
    """Four signals that move but make no field, into a copy of the bag."""
    from tetra_gradiometer.io.bag import MagneticBag

    rng = np.random.default_rng(9)
    walks = np.cumsum(rng.normal(0, 0.05, (len(t), len(DISTRACTORS))), axis=0)
    source = bag.with_name('clean_bag')
    bag.rename(source)
    with MagneticBag(source) as reader, BagWriter(bag) as writer:
        for connection, log_ns, raw in reader.reader.messages():
            writer.write_raw(connection.topic, connection.msgtype, raw, log_ns)
        Float64 = writer.types['std_msgs/msg/Float64']
        for i, t_s in enumerate(t):
            for k, topic in enumerate(DISTRACTORS):
                writer.write(topic, Float64(data=float(walks[i, k])), start_ns + int(t_s * 1e9))


def run(out: Path) -> dict:
    from stream_faults import START_NS

    mission = short_mission(trim_s=300.0, survey_s=120.0, seed=11)
    angles, currents = _fin_angles(mission.t, 3), _currents(mission.t, 4)
    fields = mission.fields_measured + _fin_field(angles) + _wire_field(currents, 5)
    _write(out, mission, angles, currents, fields)
    _add_distractors(out / 'bag', mission.t, START_NS)
    started = time.perf_counter()
    assert cli(['discrepancy', str(out / 'bag'), '--params', str(out / 'plain.yaml'), '--window', '0:299.9',
                '--out', str(out / 'report'), '--no-plots']) == 0
    discrepancy_s = time.perf_counter() - started
    report = json.loads((out / 'report' / 'report.json').read_text())
    started = time.perf_counter()
    assert cli(['calibrate', str(out / 'bag'), '--params', str(out / 'plain.yaml'), '--window', '0:299.9',
                '--effects-from', str(out / 'report' / 'report.json'), '--out', str(out / 'c.yaml')]) == 0
    calibrate_s = time.perf_counter() - started
    assert cli(['compensate', str(out / 'bag'), '--params', str(out / 'plain.yaml'), '--calibration',
                str(out / 'c.yaml'), '--csv', str(out / 'survey.csv')]) == 0
    g = np.loadtxt(out / 'survey.csv', delimiter=',', skiprows=1, usecols=range(1, 10)).reshape(-1, 3, 3) * 1e-9
    survey = mission.segment > 0
    residual = float(np.sqrt(np.mean((g[survey] - mission.g_true[survey]) ** 2)))
    return {
        'signals_read': report['data']['signals_read'],
        'named_effects': report['named_effects'],
        'gap_over_floor': report['gap_final_nT'] / report['noise_floor_nT'],
        'discrepancy_s': discrepancy_s,
        'calibrate_s': calibrate_s,
        'survey_over_floor': residual / noise_floor(1e-10, GEOMETRY),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--json', default=None, help='write the result here')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix='tg_signals_') as tmp:
        result = run(Path(tmp))
    print(json.dumps(result, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + '\n')
    met = result['discrepancy_s'] < 20 and result['survey_over_floor'] <= 1.2
    print('targets met' if met else 'TARGET MISSED')
    return 0 if met else 1


if __name__ == '__main__':
    sys.exit(main())
