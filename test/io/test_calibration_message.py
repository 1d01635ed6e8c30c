"""io/calibration_message.py: a calibration file, as the calibrator writes it (signed, with a
vehicle effect's term) and as `calibrate` writes it, becomes a tetra_gradiometer_msgs/
Calibration whose summary fields say what the file says (k, b and the term's coefficients by
name, the covariance, the fit's figures, the provenance, the signature), goes through CDR
(rclpy writes, rosbags reads: a bag's message) and comes back as the file loaded; a message
whose fields disagree with its document is refused naming the field."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tetra_gradiometer import core
from tetra_gradiometer.core.effects import Term
from tetra_gradiometer.errors import CalibrationFileError
from tetra_gradiometer.io.calibration import CalibrationFile, load_calibration, save_calibration
from tetra_gradiometer.io.calibration_message import calibration_fields, calibration_from_message
from tetra_gradiometer.nodes.authentication import sign

REPO = Path(__file__).resolve().parents[2]
GEOMETRY = core.TetraGeometry.regular(0.5)
KEY = bytes(range(32, 80))
NT = 1e-9


def _with_a_term(tmp_path) -> Path:
    """A signed calibration of k, b and vehicle_current (one regressor), as the calibrator
    writes it: its node name and sample window in the diagnostics."""
    rng = np.random.default_rng(21)
    coefficients = rng.normal(size=(3, 3, 1)) * NT
    term = Term('vehicle_current', ('current:/battery_state',), coefficients, channel_noise=(0.01,))
    parameters = core.InterferenceParameters(rng.normal(size=(3, 3, 3)) * 1e-3, rng.normal(size=(3, 3)) * 100 * NT,
                                             (term,))
    covariance = np.diag(np.arange(1.0, 46.0)) * 1e-12
    calibration = CalibrationFile(
        parameters=parameters, method='known_gradient_lstsq_general', symmetric_k=False,
        sensor_positions=GEOMETRY.to_flat(), created_utc='2026-11-28T10:00:00Z', sensor_noise_t=0.1 * NT,
        covariance=covariance,
        diagnostics={'rank': 45, 'residual_rms_nT_per_m': 0.28, 'source': '/tetra/calibrator',
                     'samples_window_s': [1700000010.0, 1700000069.9]})
    return save_calibration(tmp_path / 'calibration.yaml', calibration, sign=lambda text: sign(text, KEY))


def _through_cdr(fields: dict):
    """The message rclpy serializes from ``fields``, as rosbags reads it from a bag."""
    from rclpy.serialization import serialize_message
    from tetra_gradiometer_msgs.msg import Calibration

    from tetra_gradiometer.io.bag import typestore

    data = serialize_message(Calibration(**fields))
    return typestore().deserialize_cdr(bytes(data), 'tetra_gradiometer_msgs/msg/Calibration')


def test_a_signed_calibration_with_a_term_round_trips_and_its_fields_name_each_value(tmp_path):
    path = _with_a_term(tmp_path)
    text = path.read_text()
    written = yaml.safe_load(text)  # the file, read here independently
    k = np.array(written['k_soft'])
    b = np.array(written['b_hard_T'])
    w = np.array(written['terms'][0]['coefficients']) * NT  # the file's unit: nT/A

    message = _through_cdr(calibration_fields(text))
    assert message.document == text
    assert yaml.safe_load(message.signature) == written['signature']
    assert (message.method, message.symmetric_k, list(message.terms)) == (
        'known_gradient_lstsq_general', False, ['vehicle_current'])
    np.testing.assert_array_equal(message.sensor_positions, written['sensor_positions'])
    names = list(message.parameter_names)
    assert len(names) == len(message.parameters) == 45 and len(set(names)) == 45
    values = dict(zip(names, message.parameters, strict=True))
    assert values['K_31[yz]'] == k[1, 1, 2] and values['K_41[zx]'] == k[2, 2, 0]
    assert values['B_21[x]'] == b[0, 0] and values['B_41[z]'] == b[2, 2]
    label = 'vehicle_current[31][y][I[/battery_state]_A]'
    assert values[label] == pytest.approx(w[1, 1, 0], rel=1e-15)
    np.testing.assert_array_equal(np.reshape(message.covariance, (45, 45)), written['covariance'])
    assert message.sensor_noise_t == written['sensor_noise_T']
    assert message.residual_t_per_m == pytest.approx(0.28 * NT, rel=1e-15) and message.rank == 45
    assert (message.created_utc, message.source) == ('2026-11-28T10:00:00Z', '/tetra/calibrator')
    np.testing.assert_array_equal(message.window_s, [1700000010.0, 1700000069.9])

    loaded = calibration_from_message(message, 'the message')
    expected = load_calibration(path)
    np.testing.assert_array_equal(loaded.parameters.full_vector(), expected.parameters.full_vector())
    np.testing.assert_array_equal(loaded.covariance, expected.covariance)
    assert [(t.effect, t.inputs, t.channel_noise) for t in loaded.parameters.terms] == [
        ('vehicle_current', ('current:/battery_state',), (0.01,))]
    assert (loaded.created_utc, loaded.sensor_noise_t) == (expected.created_utc, expected.sensor_noise_t)


def test_the_file_calibrate_writes_round_trips_with_its_bag_and_window_as_provenance(tmp_path):
    out = tmp_path / 'trim.yaml'
    subprocess.run([sys.executable, '-m', 'tetra_gradiometer', 'calibrate', str(REPO / 'bags' / 'trim'),
                    '--params', str(REPO / 'config' / 'tetra_gradiometer.yaml'), '--out', str(out)],
                   check=True, capture_output=True, cwd=REPO)
    text = out.read_text()
    written = yaml.safe_load(text)
    message = _through_cdr(calibration_fields(text))
    assert message.source == str(REPO / 'bags' / 'trim') and message.signature == ''
    # The window as the fitted sets' stamps (s): the found window's span, in bag time.
    np.testing.assert_array_equal(message.window_s, written['diagnostics']['samples_window_s'])
    start, end = written['diagnostics']['window_found']['window_s']
    assert abs((message.window_s[1] - message.window_s[0]) - (end - start)) < 1e-3, message.window_s
    assert message.sensor_noise_t == written['sensor_noise_T']
    assert message.rank == written['diagnostics']['rank'] == 36
    np.testing.assert_array_equal(message.parameters[:27], np.ravel(written['k_soft']))
    np.testing.assert_array_equal(message.parameters[27:], np.ravel(written['b_hard_T']))
    loaded = calibration_from_message(message, 'the message')
    np.testing.assert_array_equal(loaded.parameters.k_soft, written['k_soft'])
    np.testing.assert_array_equal(loaded.covariance, written['covariance'])


@pytest.mark.parametrize('field, value', [
    ('method', 'paper_ga'), ('symmetric_k', True), ('terms', []), ('rank', 44), ('source', '/tetra/elsewhere'),
    ('created_utc', '2026-11-29T10:00:00Z'), ('residual_t_per_m', 1e-12), ('sensor_noise_t', float('nan')),
    ('window_s', [0.0, 0.0]), ('signature', ''), ('parameter_names', None), ('parameters', None),
    ('covariance', []),
])
def test_a_field_that_disagrees_with_the_document_is_refused_naming_it(tmp_path, field, value):
    fields = calibration_fields(_with_a_term(tmp_path).read_text())
    if field == 'parameter_names':
        value = list(reversed(fields[field]))
    if field == 'parameters':
        value = list(fields[field])
        value[40] += 1e-15  # one coefficient of the term, by a little
    fields[field] = value
    with pytest.raises(CalibrationFileError, match=f'the message: the field {field} disagrees with the document'):
        calibration_from_message(_through_cdr(fields), 'the message')


def test_a_document_that_is_not_a_calibration_is_refused_with_the_files_reason(tmp_path):
    fields = calibration_fields(_with_a_term(tmp_path).read_text())
    fields['document'] = 'tetra_gradiometer_calibration: 1\nk_soft: [[[0.1, '
    with pytest.raises(CalibrationFileError, match='the message is not valid YAML'):
        calibration_from_message(_through_cdr(fields), 'the message')
