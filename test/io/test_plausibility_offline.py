"""Fault table, plausibility offline: the bag tools drop and count what the nodes drop, and
refuse calibrations and geometries outside physical bounds (core/plausibility.py).

Each row asserts against independent truth: the interference the readings were built with,
the stamps written, the bytes of the files involved, the exit status and the one ``error:``
line without traceback.
"""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from cli_helpers import assert_refused, run_cli, snapshot
from interference_helpers import make_interference, trim_data

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.io.bag import BagWriter
from tetra_gradiometer.io.calibration import CalibrationFile, load_calibration
from tetra_gradiometer.io.params import params_document

GEOMETRY = TetraGeometry.regular(0.5)
START_NS = 1_767_225_600 * 10**9
N_TRIM = 1200
BAD_SETS = np.arange(50, 1150, 110)  # ten sets, spread over the trim


@pytest.fixture(scope='module')
def trim_bag(tmp_path_factory):
    """1200 trim sets (uniform field, random attitudes, 0.01 nT noise) of a known interference,
    ten of them with one 1 T reading; the params file of the array."""
    root = tmp_path_factory.mktemp('trim')
    rng = np.random.default_rng(11)
    interference = make_interference(rng)
    fields = trim_data(rng, interference, n=N_TRIM, noise=0.01e-9)
    fields[BAD_SETS, 2, 0] = 1.0  # a saturated or corrupt sensor 3
    stamps = START_NS + np.arange(N_TRIM, dtype=np.int64) * 100_000_000
    with BagWriter(root / 'bag') as writer:
        writer.write_fields(stamps, fields)
    (root / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    return root, interference.effective_parameters(), stamps


def test_readings_of_one_tesla_are_dropped_and_counted_never_fitted(trim_bag, capsys, tmp_path):
    root, exact, _ = trim_bag
    code, out, err = run_cli(capsys, 'calibrate', root / 'bag', '--params', root / 'params.yaml',
                             '--out', tmp_path / 'calib.yaml')
    assert code == 0, err
    assert '10 with |B| > 0.001 T' in out
    saved = load_calibration(tmp_path / 'calib.yaml')
    assert saved.diagnostics['sets_dropped_field_magnitude'] == 10
    assert saved.diagnostics['sets_in_window'] == N_TRIM - 10
    # Fitted on the 1190 good sets: k within 1e-5 of the truth (with the ten 1 T sets in the
    # fit, K_21 came out near 209).
    assert np.abs(saved.parameters.k_soft - exact.k_soft).max() < 1e-5
    assert np.abs(saved.parameters.b_hard - exact.b_hard).max() < 0.05e-9


def test_compensate_drops_the_same_sets(trim_bag, capsys, tmp_path):
    root, _, stamps = trim_bag
    code, out, err = run_cli(capsys, 'compensate', root / 'bag', '--params', root / 'params.yaml',
                             '--raw', '--csv', tmp_path / 'g.csv')
    assert code == 0, err
    assert f'{N_TRIM - 10} sets' in out and '10 with |B| > 0.001 T' in out
    rows = (tmp_path / 'g.csv').read_text().splitlines()[1:]
    written = [int(row.split(',')[0].replace('.', '')) for row in rows]
    assert written == np.delete(stamps, BAD_SETS).tolist()
    # A uniform field differenced leaves the interference (|K| 5e-3 of 5e4 nT, |B^h| 150 nT:
    # under 2000 nT/m over 0.5 m); one 1 T reading would give ~2e9 nT/m.
    assert np.abs(np.loadtxt(rows, delimiter=',', usecols=range(1, 10))).max() < 2000


@pytest.mark.parametrize('scale,fragment', [(1e-300, 'apart'), (1e300, 'from the body origin'),
                                            (0.004, '0.004 m apart'), (40.0, '40 m apart')])
def test_params_outside_the_physical_scale_are_refused(trim_bag, capsys, tmp_path, scale, fragment):
    root, _, _ = trim_bag
    positions = (np.array(TetraGeometry.regular(1.0).to_flat()) * scale).tolist()
    (tmp_path / 'p.yaml').write_text(params_document({'sensor_positions': positions}))
    assert_refused(run_cli(capsys, 'compensate', root / 'bag', '--params', tmp_path / 'p.yaml', '--raw',
                           '--csv', tmp_path / 'g.csv'), fragment)
    assert not (tmp_path / 'g.csv').exists()


def _calibration_text(**changes) -> str:
    record = CalibrationFile.from_yaml(yaml.safe_dump({
        'tetra_gradiometer_calibration': 1, 'method': 'known_gradient_lstsq_general', 'symmetric_k': False,
        'sensor_positions': GEOMETRY.to_flat(), 'k_soft': np.zeros((3, 3, 3)).tolist(),
        'b_hard_T': np.zeros((3, 3)).tolist()}))
    document = yaml.safe_load(record.to_yaml())
    document.update(changes)
    return yaml.safe_dump(document)


@pytest.mark.parametrize('changes,fragment', [
    ({'k_soft': np.full((3, 3, 3), 1e308).tolist()}, 'k_soft[0, 0, 0] = 1e+308 is implausible'),
    ({'b_hard_T': [[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], [0.0, 0.0, 0.0]]}, 'b_hard[1, 2] = 0.01 T is implausible'),
    ({'sensor_positions': [float('nan')] + GEOMETRY.to_flat()[1:]}, 'sensor_positions[0] = nan is not finite'),
])
def test_implausible_calibrations_are_refused_and_left_untouched(trim_bag, capsys, tmp_path, changes, fragment):
    root, _, _ = trim_bag
    calibration = tmp_path / 'calib.yaml'
    calibration.write_text(_calibration_text(**changes))
    before = snapshot(calibration)
    assert_refused(run_cli(capsys, 'compensate', root / 'bag', '--params', root / 'params.yaml',
                           '--calibration', calibration, '--csv', tmp_path / 'g.csv'), fragment)
    assert snapshot(calibration) == before and not (tmp_path / 'g.csv').exists()


def test_negative_and_pre_1970_stamps_are_written_exactly(capsys, tmp_path):
    stamps = np.array([-1_503_142_200_000, -1, 0, 999_999_999, 1_000_000_000], dtype=np.int64)
    fields = np.repeat(trim_data(np.random.default_rng(2), make_interference(np.random.default_rng(3)), n=1),
                       len(stamps), axis=0)
    with BagWriter(tmp_path / 'bag') as writer:
        writer.write_fields(stamps, fields)
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    code, _, err = run_cli(capsys, 'compensate', tmp_path / 'bag', '--params', tmp_path / 'params.yaml', '--raw',
                           '--csv', tmp_path / 'g.csv')
    assert code == 0, err
    column = [row.split(',')[0] for row in (tmp_path / 'g.csv').read_text().splitlines()[1:]]
    assert column == ['-1503.142200000', '-0.000000001', '0.000000000', '0.999999999', '1.000000000']
