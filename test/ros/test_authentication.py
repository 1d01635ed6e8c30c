"""nodes/authentication.py without a graph: the signature is HMAC-SHA256 of the canonical
calibration (checked with hmac/hashlib written out here), any change of the content, another
key or no signature is refused, a signed file still loads as a calibration, and key files
that others may read are refused."""
from __future__ import annotations

import hashlib
import hmac
import json

import numpy as np
import pytest
import yaml

from tetra_gradiometer import core
from tetra_gradiometer.errors import ParamsError
from tetra_gradiometer.io.calibration import CalibrationFile
from tetra_gradiometer.nodes.authentication import AuthenticationError, load_key, sign, verify

KEY = b'k' * 16 + bytes(range(16, 48))
GEOMETRY = core.TetraGeometry.regular(0.5)


def _calibration() -> CalibrationFile:
    rng = np.random.default_rng(1)
    parameters = core.InterferenceParameters(rng.uniform(-1e-3, 1e-3, (3, 3, 3)), rng.uniform(-1e-7, 1e-7, (3, 3)))
    return CalibrationFile(parameters=parameters, method='known_gradient_lstsq_general', symmetric_k=False,
                           sensor_positions=GEOMETRY.to_flat(), created_utc='2026-11-26T09:00:00Z',
                           sensor_noise_t=1e-10)


def test_the_signature_is_hmac_sha256_of_the_canonical_document_and_the_file_still_loads():
    text = _calibration().to_yaml()
    signed = sign(text, KEY)
    assert signed.startswith(text)  # appended: the calibration's own bytes unchanged
    document = yaml.safe_load(signed)
    signature = document.pop('signature')
    expected = hmac.new(KEY, json.dumps(document, sort_keys=True, separators=(',', ':')).encode(),
                        hashlib.sha256).hexdigest()
    assert signature == {'algorithm': 'HMAC-SHA256', 'key_id': hashlib.sha256(KEY).hexdigest()[:16],
                         'value': expected}
    verify(signed, KEY, 'test')
    loaded, plain = CalibrationFile.from_yaml(signed), CalibrationFile.from_yaml(text)
    np.testing.assert_array_equal(loaded.parameters.k_soft, plain.parameters.k_soft)
    np.testing.assert_array_equal(loaded.parameters.b_hard, plain.parameters.b_hard)
    # The layout does not matter, the content does: re-dumped YAML verifies too.
    verify(yaml.safe_dump(yaml.safe_load(signed), sort_keys=True), KEY, 'test')


@pytest.mark.parametrize('change', ['k', 'b', 'noise', 'created', 'positions'])
def test_any_change_of_the_content_is_refused(change):
    document = yaml.safe_load(sign(_calibration().to_yaml(), KEY))
    if change == 'k':
        document['k_soft'][1][2][0] *= 1.5  # the issue's +50 % on one k
    elif change == 'b':
        document['b_hard_T'][0][0] += 20e-9  # +20 nT on one offset
    elif change == 'noise':
        document['sensor_noise_T'] = 1e-6
    elif change == 'created':
        document['created_utc'] = '2027-01-01T00:00:00Z'
    else:
        document['sensor_positions'][3] += 0.01
    with pytest.raises(AuthenticationError, match='does not match'):
        verify(yaml.safe_dump(document, sort_keys=False), KEY, 'the forgery')


def test_no_signature_another_key_or_algorithm_is_refused():
    text = _calibration().to_yaml()
    with pytest.raises(AuthenticationError, match='not signed'):
        verify(text, KEY, 'test')
    with pytest.raises(AuthenticationError, match='another key'):
        verify(sign(text, b'x' * 32), KEY, 'test')
    document = yaml.safe_load(sign(text, KEY))
    document['signature']['algorithm'] = 'none'
    with pytest.raises(AuthenticationError, match="'none', not HMAC-SHA256"):
        verify(yaml.safe_dump(document), KEY, 'test')


def test_a_key_file_others_may_read_a_short_one_or_none_is_refused(tmp_path):
    path = tmp_path / 'calibration.key'
    path.write_bytes(KEY + b'\n')
    path.chmod(0o600)
    assert load_key(path) == KEY
    for mode in (0o640, 0o604, 0o620, 0o644):
        path.chmod(mode)
        with pytest.raises(ParamsError, match=f'mode {mode:04o}.*chmod 600'):
            load_key(path)
    path.chmod(0o600)
    path.write_bytes(b'short')
    with pytest.raises(ParamsError, match='5 bytes: at least 32'):
        load_key(path)
    with pytest.raises(ParamsError, match='No such file'):
        load_key(tmp_path / 'missing.key')
