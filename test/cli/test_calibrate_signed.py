"""``calibrate --key-file``: an offline calibration signed as the calibrator node signs, so a
compensator configured with the key loads it. The signature is recomputed here
with ``hmac``/``hashlib`` from the file's own content, independently of the signer."""
from __future__ import annotations

import hashlib
import hmac
import json
import os
from pathlib import Path

import pytest
import yaml
from cli_helpers import run_cli

from tetra_gradiometer.io.calibration import load_calibration
from tetra_gradiometer.nodes.authentication import verify

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / 'bags' / 'trim'
KEY = b'0123456789abcdef0123456789abcdef-offline'


@pytest.fixture(scope='module')
def params(tmp_path_factory) -> Path:
    """The sample bag's params, as bags/README.md says to get them (the scenario's own)."""
    root = tmp_path_factory.mktemp('params')
    from tetra_gradiometer.__main__ import main

    assert main(['simulate', '--scenario', str(REPO / 'bags' / 'trim.yaml'), '--out',
                 str(root / 'trim_sim'), '--mag-only', '--no-progress']) == 0
    return root / 'trim_sim.params.yaml'


def _key_file(tmp_path: Path, mode: int = 0o600) -> Path:
    path = tmp_path / 'calibration.key'
    path.write_bytes(KEY + b'\n')
    os.chmod(path, mode)
    return path


def test_a_calibration_signed_offline_verifies_with_the_key_and_loads(tmp_path, capsys, params):
    out = tmp_path / 'calibration.yaml'
    code, _, err = run_cli(capsys, 'calibrate', BAG, '--params', params, '--out', out,
                           '--key-file', _key_file(tmp_path))
    assert code == 0, err
    text = out.read_text(encoding='utf-8')
    document = yaml.safe_load(text)
    signature = document.pop('signature')
    expected = hmac.new(KEY, json.dumps(document, sort_keys=True, separators=(',', ':')).encode(),
                        hashlib.sha256).hexdigest()
    assert signature['algorithm'] == 'HMAC-SHA256' and signature['value'] == expected
    verify(text, KEY, str(out))  # what a compensator with the key does at start
    assert load_calibration(out).parameters.k_soft.shape[0] == 3  # still a calibration file


def test_a_key_file_others_can_read_is_refused_before_any_work(tmp_path, capsys, params):
    out = tmp_path / 'calibration.yaml'
    code, _, err = run_cli(capsys, 'calibrate', BAG, '--params', params, '--out', out,
                           '--key-file', _key_file(tmp_path, 0o644))
    assert code == 1
    assert err.startswith('error: calibration_key_file') and 'chmod 600' in err, err
    assert not out.exists()
