"""``compensate --csv`` with its nine sigma columns, end to end in-process through
``__main__.main``: a simulated bag (trim, then a pass over a dipole), ``calibrate`` on the
trim, ``compensate`` of the whole bag; the columns against the simulator's ``g_true``
(92-98 % of the survey's components within 2 sigma), the noise option, and the refusals."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_helpers import assert_refused, run_cli
from tetra_gradiometer.core import (Dipole, Scenario, SensorInterference, SurveyLine, TetraGeometry, TrimManoeuvre,
                                    random_interference, simulate)
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)
NOISE_NT = 0.05
HEADER = 'stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz'
SIGMA_HEADER = HEADER + ',' + ','.join(f'sigma_{c}' for c in HEADER.split(',')[1:])
#: With the calibration tracked (the default): the pair offsets' change removed, nT.
TRACKED_HEADER = SIGMA_HEADER + ',db_21x,db_21y,db_21z,db_31x,db_31y,db_31z,db_41x,db_41y,db_41z'


def _mission(rng, interference):
    scenario = Scenario(
        geometry=GEOMETRY, earth_field_enu=np.array([0.0, 21000e-9, -45376.2e-9]), sample_rate_hz=10.0,
        segments=(TrimManoeuvre(60.0, center=(3000.0, 3000.0, -50.0), heading_rate_deg_s=12.0, roll_period_s=7.0,
                                pitch_period_s=9.0),
                  SurveyLine((-60.0, 0.0, -50.0), (60.0, 0.0, -50.0), speed_m_s=2.0)),
        dipoles=(Dipole((0.0, 0.0, -75.0), (3.0e4, 2.0e4, -3.3e4)),), interference=interference,
        noise_t=NOISE_NT * 1e-9)
    return simulate(scenario, rng)


@pytest.fixture(scope='module')
def survey(tmp_path_factory):
    """``(root, mission)``: the bag of a vehicle with sensor 1 not clean, its params, and the
    calibration ``calibrate`` makes on its trim."""
    root = tmp_path_factory.mktemp('sigma')
    rng = np.random.default_rng(21)
    mission = _mission(rng, random_interference(rng, k_scale=0.01, b_scale_t=300e-9, reference_clean=False))
    write_mission_bag(root / 'bag', mission, odom=False, temperature=False, battery=False, command='test')
    (root / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    return root, mission


def _read(path: Path) -> tuple[str, np.ndarray, np.ndarray | None]:
    """(header, tensors (N, 3, 3) nT/m, sigmas (N, 3, 3) nT/m or None)."""
    header = path.read_text().split('\n', 1)[0]
    values = np.loadtxt(path, delimiter=',', skiprows=1, ndmin=2)
    sigmas = values[:, 10:19].reshape(-1, 3, 3) if values.shape[1] >= 19 else None
    return header, values[:, 1:10].reshape(-1, 3, 3), sigmas


def _within_two_sigma(g_nt, sigma_nt, truth_t, rows):
    return float(np.mean(np.abs(g_nt[rows] - truth_t[rows] * 1e9) <= 2 * sigma_nt[rows]))


def test_two_sigma_covers_92_to_98_percent_of_the_survey_against_simulator_truth(capsys, survey):
    root, mission = survey
    code, out, err = run_cli(capsys, 'calibrate', root / 'bag', '--params', root / 'params.yaml', '--window',
                             '0:59.95', '--out', root / 'calib.yaml', '--no-progress')
    assert code == 0, err
    calibration = yaml.safe_load((root / 'calib.yaml').read_text())
    assert calibration['sensor_noise_T'] == pytest.approx(NOISE_NT * 1e-9, rel=0.1)
    code, out, err = run_cli(capsys, 'compensate', root / 'bag', '--params', root / 'params.yaml', '--calibration',
                             root / 'calib.yaml', '--csv', root / 'comp.csv', '--no-progress')
    assert code == 0, err
    assert 'sigma from sensor noise and calibration covariance' in out
    header, g, sigma = _read(root / 'comp.csv')
    assert header == TRACKED_HEADER and len(g) == len(mission)
    survey_rows = mission.segment == 1
    fraction = _within_two_sigma(g, sigma, mission.g_true, survey_rows)
    with capsys.disabled():
        print(f'compensate --csv: {100 * fraction:.2f} % of the survey components within 2 sigma')
    assert 0.92 <= fraction <= 0.98, fraction
    assert np.abs(mission.g_true[survey_rows]).max() * 1e9 > 100 * sigma.max()  # a real target
    # nT/m, 6 decimals: about the noise floor's share per component (1.42 sigma / d over 3).
    assert 0.05 < sigma.min() and sigma.max() < 0.2

    # --sensor-noise-nt overrides the estimate: twice the true noise covers (nearly) everything.
    code, out, err = run_cli(capsys, 'compensate', root / 'bag', '--params', root / 'params.yaml', '--calibration',
                             root / 'calib.yaml', '--csv', root / 'comp.csv', '--force', '--no-progress',
                             '--sensor-noise-nt', 2 * NOISE_NT)
    assert code == 0 and 'noise 0.1 nT from --sensor-noise-nt' in out, (out, err)
    _, g_again, sigma_wide = _read(root / 'comp.csv')
    # The tracker weighs the data by the noise figure too: the tensors move, far below the
    # floor (0.14 nT/m).
    assert np.abs(g_again - g).max() < 0.014 and np.sqrt(np.mean((g_again - g) ** 2)) < 0.0014
    assert _within_two_sigma(g, sigma_wide, mission.g_true, survey_rows) > 0.999


def test_raw_sigma_needs_the_noise_option_and_covers_a_clean_vehicle(capsys, tmp_path):
    """No interference: the raw tensor minus ``g_true`` is the noise alone."""
    rng = np.random.default_rng(5)
    mission = _mission(rng, SensorInterference.zero())
    write_mission_bag(tmp_path / 'bag', mission, odom=False, temperature=False, battery=False, command='test')
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    base = ('compensate', tmp_path / 'bag', '--params', tmp_path / 'params.yaml', '--raw', '--no-progress')
    code, out, err = run_cli(capsys, *base, '--csv', tmp_path / 'plain.csv')
    assert code == 0 and 'no sigma columns' in out, (out, err)
    assert _read(tmp_path / 'plain.csv')[0] == HEADER  # the ten columns as before
    code, out, err = run_cli(capsys, *base, '--csv', tmp_path / 'raw.csv', '--sensor-noise-nt', NOISE_NT)
    assert code == 0 and 'sigma from sensor noise only' in out, (out, err)
    header, g, sigma = _read(tmp_path / 'raw.csv')
    assert header == SIGMA_HEADER
    fraction = _within_two_sigma(g, sigma, mission.g_true, slice(None))
    with capsys.disabled():
        print(f'compensate --raw --csv: {100 * fraction:.2f} % within 2 sigma')
    assert 0.92 <= fraction <= 0.98, fraction
    # A previous CSV of either layout is ours to replace with --force.
    for target in ('plain.csv', 'raw.csv'):
        code, _, err = run_cli(capsys, *base, '--csv', tmp_path / target, '--force',
                               *(['--sensor-noise-nt', 0.1] if target == 'plain.csv' else []))
        assert code == 0, err


def test_a_calibration_without_a_noise_estimate_needs_the_option(capsys, survey, tmp_path):
    root, _ = survey
    code, _, err = run_cli(capsys, 'calibrate', root / 'bag', '--params', root / 'params.yaml', '--window',
                           '0:59.95', '--out', tmp_path / 'calib.yaml', '--no-progress')
    assert code == 0, err
    document = yaml.safe_load((tmp_path / 'calib.yaml').read_text())
    del document['sensor_noise_T'], document['covariance']  # as an older file, or paper_ga's
    (tmp_path / 'old.yaml').write_text(yaml.safe_dump(document, sort_keys=False))
    command = ('compensate', root / 'bag', '--params', root / 'params.yaml', '--calibration', tmp_path / 'old.yaml',
               '--no-progress', '--csv', tmp_path / 'out.csv')
    assert_refused(run_cli(capsys, *command), 'old.yaml', 'has no sensor noise estimate', '--sensor-noise-nt')
    assert not (tmp_path / 'out.csv').exists()
    code, out, err = run_cli(capsys, *command, '--sensor-noise-nt', NOISE_NT)
    assert code == 0 and 'sensor noise only: the calibration has no covariance' in out, (out, err)
    assert _read(tmp_path / 'out.csv')[0] == TRACKED_HEADER



def test_held_out_sample_bags_two_sigma_covers_92_to_98_percent(capsys, tmp_path):
    """Calibrate on bags/trim, compensate bags/survey (recorded over ROS with its own noise
    seed): the survey's own recorded ``/tetra/gradient/truth`` is the truth."""
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io.bag import MagneticBag

    bags = Path(__file__).resolve().parents[2] / 'bags'
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    code, _, err = run_cli(capsys, 'calibrate', bags / 'trim', '--params', tmp_path / 'params.yaml', '--out',
                           tmp_path / 'calib.yaml', '--no-progress')
    assert code == 0, err
    code, _, err = run_cli(capsys, 'compensate', bags / 'survey', '--params', tmp_path / 'params.yaml',
                           '--calibration', tmp_path / 'calib.yaml', '--csv', tmp_path / 'survey.csv', '--no-progress')
    assert code == 0, err
    stamps = [int(row.split(',', 1)[0].replace('.', '')) for row in
              (tmp_path / 'survey.csv').read_text().splitlines()[1:]]
    _, g, sigma = _read(tmp_path / 'survey.csv')
    with MagneticBag(bags / 'survey') as bag:
        truth = {cv.stamp_to_ns(m.header.stamp): cv.tensor_from_msg(m) for m in (
            bag.reader.deserialize(raw, c.msgtype) for c, _, raw in bag.reader.messages()
            if c.topic == '/tetra/gradient/truth')}
    rows = [i for i, s in enumerate(stamps) if s in truth]
    assert len(rows) > 1400
    true_t = np.array([truth[stamps[i]] for i in rows])
    fraction = _within_two_sigma(g[rows], sigma[rows], true_t, slice(None))
    with capsys.disabled():
        print(f'held-out bags/survey: {100 * fraction:.2f} % within 2 sigma')
    assert 0.92 <= fraction <= 0.98, fraction
