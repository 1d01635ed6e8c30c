"""``compensate --report DIR``: the health monitor over a bag, end to end through
``__main__.main``. A simulated bag (trim, then survey passes over a dipole) is calibrated on
its trim; a 2 nT offset jump is injected into sensor 2's readings at a known time before
the bag is written, so the alarm's time and sensor are checked against what was done."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cli_helpers import assert_refused, run_cli
from tetra_gradiometer.core import (Dipole, Scenario, SurveyLine, TetraGeometry, TrimManoeuvre, random_interference,
                                    simulate)
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)
T_JUMP = 250.0  # s from the first sample (= the bag's first message)


def _mission(seed: int):
    rng = np.random.default_rng(seed)
    scenario = Scenario(
        geometry=GEOMETRY, earth_field_enu=np.array([0.0, 21000e-9, -45376.2e-9]), sample_rate_hz=10.0,
        segments=(TrimManoeuvre(120.0, center=(3000.0, 3000.0, -50.0)),
                  SurveyLine((-200.0, 0.0, -50.0), (200.0, 0.0, -50.0)),
                  SurveyLine((200.0, 10.0, -50.0), (-200.0, 10.0, -50.0))),
        dipoles=(Dipole((0.0, 0.0, -80.0), (3.0e4, 2.0e4, -3.3e4)),),
        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9), noise_t=0.05e-9)
    return simulate(scenario, rng)


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('health')
    mission = _mission(31)
    write_mission_bag(root / 'clean', mission, odom=False, temperature=False, battery=False, command='test')
    jumped = mission.fields_measured.copy()
    jumped[mission.t >= T_JUMP, 1] += [1.2e-9, 0.0, -1.6e-9]  # 2 nT on sensor 2
    write_mission_bag(root / 'jump', replace(mission, fields_measured=jumped), odom=False, temperature=False,
                      battery=False, command='test')
    (root / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    return root


def _calibrate(capsys, root):
    if not (root / 'calib.yaml').exists():
        code, _, err = run_cli(capsys, 'calibrate', root / 'clean', '--params', root / 'params.yaml', '--window',
                               '0:119.95', '--out', root / 'calib.yaml', '--no-progress')
        assert code == 0, err


def test_a_2nt_jump_is_alarmed_within_5s_with_its_sensor(capsys, bags):
    _calibrate(capsys, bags)
    code, out, err = run_cli(capsys, 'compensate', bags / 'jump', '--params', bags / 'params.yaml', '--calibration',
                             bags / 'calib.yaml', '--report', bags / 'report_jump', '--no-progress')
    assert code == 0, err
    assert 'warning: health: 1 alarm(s)' in err and 'the vehicle changed during the recording' in err
    document = json.loads((bags / 'report_jump' / 'report.json').read_text())
    alarm = document['alarms'][0]
    assert set(alarm) >= {'t_s', 'kind', 'sensors', 'statistic', 'threshold'}
    assert T_JUMP <= alarm['t_s'] <= T_JUMP + 5.0
    assert 2 in alarm['sensors'] and alarm['statistic'] > alarm['threshold']
    assert document['time_origin'] == 'bag start'
    assert (bags / 'report_jump' / 'health.png').stat().st_size > 10_000


def test_no_alarm_without_a_change_and_the_report_is_ours_to_replace(capsys, bags):
    _calibrate(capsys, bags)
    base = ('compensate', bags / 'clean', '--params', bags / 'params.yaml', '--calibration', bags / 'calib.yaml',
            '--report', bags / 'report_clean', '--no-progress')
    code, out, err = run_cli(capsys, *base)
    assert code == 0, err
    document = json.loads((bags / 'report_clean' / 'report.json').read_text())
    assert document['alarms'] == [] and document['verdict'] == 'no change detected'
    assert document['monitor']['samples'] > 3000
    assert_refused(run_cli(capsys, *base), 'report_clean', '--force')  # a previous report needs --force
    code, _, err = run_cli(capsys, *base, '--force')
    assert code == 0, err


def test_report_refuses_the_raw_tensor(capsys, bags):
    assert_refused(run_cli(capsys, 'compensate', bags / 'clean', '--params', bags / 'params.yaml', '--raw',
                           '--report', bags / 'report_raw', '--no-progress'), '--report monitors a calibration')
