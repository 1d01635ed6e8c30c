"""``calibrate --report DIR`` (cli/calibrate.py, reports/calibration.py, pipelines/calibration.
assess_window) through the CLI in-process: the printed trim assessment and the report folder,
against the simulator's truth (the vehicle's exact parameters, the trim's attitudes), and the
refusals that keep foreign files safe."""
from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import assert_refused, run_cli, snapshot

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.core.guidance import heading_roll_pitch
from tetra_gradiometer.core.simulator import Scenario, TrimManoeuvre, random_interference, simulate
from tetra_gradiometer.io.outputs import MARKER
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)
EARTH_T = [0.0, 2.0e-5, -4.5e-5]
PNG = b'\x89PNG\r\n\x1a\n'


@pytest.fixture(scope='module')
def data(tmp_path_factory):
    """A short trim that lacks roll (pitching while turning through 30° of heading): the fit
    accepts it, the guidance does not. With /odom (``bag``) and without (``bare``)."""
    root = tmp_path_factory.mktemp('report')
    rng = np.random.default_rng(21)
    vehicle = random_interference(rng, reference_clean=False)
    trim = TrimManoeuvre(30.0, roll_amplitude_deg=0.0, heading_rate_deg_s=1.0, initial_heading_deg=45.0)
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=np.array(EARTH_T), segments=(trim,),
                        interference=vehicle, noise_t=0.1e-9, sample_rate_hz=10.0)
    mission = simulate(scenario, rng)
    write_mission_bag(root / 'bag', mission, command='test', temperature=False, battery=False)
    write_mission_bag(root / 'bare', mission, command='test', odom=False, temperature=False, battery=False)
    (root / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat(),
                                                      'earth_field_enu': EARTH_T}))
    (root / 'positions.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    return root, mission, vehicle.effective_parameters()


def calibrate(capsys, root, bag, params, *extra, out):
    return run_cli(capsys, 'calibrate', root / bag, '--params', root / params, '--out', out, '--no-progress', *extra)


def test_report_holds_the_assessment_the_plots_and_parameters_consistent_with_the_truth(capsys, data, tmp_path):
    root, mission, exact = data
    report = tmp_path / 'report'
    code, out, err = calibrate(capsys, root, 'bag', 'params.yaml', '--report', report, out=tmp_path / 'c.yaml')
    assert code == 0, err
    assert 'trim assessment: not enough' in out and 'next manoeuvre: ' in out, out
    assert 'Earth field from the params file' in out
    document = json.loads((report / 'report.json').read_text())
    assessment = document['assessment']
    assert assessment['enough'] is False and assessment['advice']['text'] in out
    assert assessment['ratio'] > 1.1
    # Coverage from /odom: exactly the trim's attitudes, binned independently here.
    angles = heading_roll_pitch(mission.orientation_xyzw)
    counts = np.array(assessment['coverage']['counts'])
    assert assessment['coverage']['source'] == 'attitude' and counts.sum() == len(mission)
    expected = np.histogram(angles[:, 0], bins=np.arange(0, 361, 30))[0]
    np.testing.assert_array_equal(counts.sum(axis=(1, 2)), expected)
    assert not counts[:, [0, 4], :].any()  # no roll beyond ±5°: the trim lacks roll
    # Parameters with sigma: the fit's values lie within 5 sigma of the vehicle's exact ones.
    parameters = document['parameters']
    assert parameters['sigma_source'] == 'fit'
    k_error = np.abs(np.array(parameters['k_soft']) - exact.k_soft) / np.array(parameters['k_soft_sigma'])
    b_error = np.abs(np.array(parameters['b_hard_nT']) - exact.b_hard * 1e9) / np.array(parameters['b_hard_sigma_nT'])
    assert k_error.max() < 5 and b_error.max() < 5, (k_error.max(), b_error.max())
    # The residual over the window is noise: near the assessment's floor.
    assert document['residual']['rms_nT_per_m'] == pytest.approx(assessment['noise_floor_nT_per_m'], rel=0.15)
    assert set(document['figures']) == {'residual', 'parameters', 'coverage', 'survey'}
    for name in document['figures'].values():
        assert (report / name).read_bytes().startswith(PNG)
    assert json.loads((report / MARKER).read_text())['kind'] == 'calibration report folder'
    assert assessment['text'] in (report / 'report.md').read_text()


def test_without_odom_or_earth_field_the_report_says_why_and_keeps_the_rest(capsys, data, tmp_path):
    root, _, _ = data
    code, out, err = calibrate(capsys, root, 'bare', 'positions.yaml', '--report', tmp_path / 'r1',
                               out=tmp_path / 'c1.yaml')
    assert code == 0, err
    assert 'no trim assessment' in out and '\n  trim assessment:' not in out
    document = json.loads((tmp_path / 'r1' / 'report.json').read_text())
    assert document['assessment'] is None and set(document['figures']) == {'residual', 'parameters'}
    # No /odom but an Earth field: the coverage is of the field direction, and says so.
    code, out, err = calibrate(capsys, root, 'bare', 'params.yaml', '--report', tmp_path / 'r2',
                               out=tmp_path / 'c2.yaml')
    assert code == 0, err
    assert 'no /odom' in out and '\n  trim assessment: ' in out
    coverage = json.loads((tmp_path / 'r2' / 'report.json').read_text())['assessment']['coverage']
    assert coverage['source'] == 'field direction' and np.array(coverage['counts']).shape == (12, 6)


def test_the_report_never_replaces_a_foreign_folder_nor_the_calibration(capsys, data, tmp_path):
    root, _, _ = data
    foreign = tmp_path / 'mine'
    foreign.mkdir()
    (foreign / 'notes.txt').write_text('keep me')
    before = snapshot(foreign)
    out = tmp_path / 'c.yaml'
    assert_refused(calibrate(capsys, root, 'bag', 'params.yaml', '--report', foreign, out=out),
                   'not a calibration report folder', 'nothing was written')
    assert snapshot(foreign) == before and not out.exists()
    assert_refused(calibrate(capsys, root, 'bag', 'params.yaml', '--report', out, out=out), 'is the input')
    # A previous report is replaced only with --force (checked before any work).
    report = tmp_path / 'report'
    assert calibrate(capsys, root, 'bag', 'params.yaml', '--report', report, out=tmp_path / 'a.yaml')[0] == 0
    before = snapshot(report)
    assert_refused(calibrate(capsys, root, 'bag', 'params.yaml', '--report', report, out=tmp_path / 'b.yaml'),
                   'a previous calibration report folder', '--force')
    assert snapshot(report) == before and not (tmp_path / 'b.yaml').exists()
