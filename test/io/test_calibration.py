"""io/calibration.py: calibration files round trip (from parameters and from a fit), refuse
corruption, and are never left truncated by a writer killed mid-write."""
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tetra_gradiometer.core import (InterferenceParameters, Scenario, SensorInterference, TetraGeometry,
                                    TrimManoeuvre, difference_tensor, known_gradient_lstsq, random_interference, simulate)
from tetra_gradiometer.io.calibration import (CalibrationFile, CalibrationFileError, load_calibration,
                                              save_calibration)

REPO = Path(__file__).resolve().parents[2]
GEOMETRY = TetraGeometry.regular(0.5)


def test_calibration_file_round_trip_and_corruption(tmp_path):
    rng = np.random.default_rng(0)
    parameters = InterferenceParameters(rng.normal(0, 1e-2, (3, 3, 3)), rng.normal(0, 1e-7, (3, 3)))
    original = CalibrationFile(parameters, 'known_gradient_lstsq_general', False, GEOMETRY.to_flat(),
                               {'rank': 36, 'condition_number': 12.5})
    path = save_calibration(tmp_path / 'c.yaml', original)
    loaded = load_calibration(path)
    np.testing.assert_array_equal(loaded.parameters.k_soft, parameters.k_soft)
    np.testing.assert_array_equal(loaded.parameters.b_hard, parameters.b_hard)
    assert loaded.method == original.method and loaded.diagnostics['rank'] == 36
    path.write_text(path.read_text()[:200])  # truncated
    with pytest.raises(CalibrationFileError):
        load_calibration(path)
    with pytest.raises(CalibrationFileError, match='cannot read'):
        load_calibration(tmp_path / 'absent.yaml')


def test_calibration_file_from_a_fit(tmp_path):
    rng = np.random.default_rng(1)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5],
                                segments=[TrimManoeuvre(60.0)], interference=random_interference(rng)), rng)
    fit = known_gradient_lstsq(difference_tensor(mission.fields_measured, GEOMETRY),
                               mission.fields_measured[:, 0], GEOMETRY, symmetric_k=False)
    loaded = load_calibration(save_calibration(tmp_path / 'c.yaml', CalibrationFile.from_calibration(fit, GEOMETRY)))
    assert loaded.symmetric_k is False and loaded.diagnostics['rank'] == 36
    np.testing.assert_array_equal(loaded.parameters.k_soft, fit.parameters.k_soft)
    # The uncertainty travels with the file: the covariance exactly, the noise estimate near
    # the simulated 0.1 nT.
    np.testing.assert_array_equal(loaded.covariance, fit.covariance)
    assert loaded.covariance.shape == (36, 36)
    assert abs(loaded.sensor_noise_t - 0.1e-9) < 0.01e-9
    document = yaml.safe_load((tmp_path / 'c.yaml').read_text())
    for key, value, fragment in (('covariance', [[1.0, 2.0]], 'covariance must be 36 x 36'),
                                 ('sensor_noise_T', -1.0, 'outside [0, 1e-6] T')):
        with pytest.raises(CalibrationFileError, match=re.escape(fragment)):
            CalibrationFile.from_yaml(yaml.safe_dump({**document, key: value}))


def test_a_fit_outside_the_physical_bounds_is_never_written(tmp_path):
    # Sensor 3 with a soft iron of 1.5 (its induced field 1.5x the Earth's): the fit finds it
    # exactly, and the file refuses it (a window that was not a trim gives such numbers).
    rng = np.random.default_rng(2)
    interference = random_interference(rng)
    k_soft = np.array(interference.k_soft)
    k_soft[2] += 1.5 * np.eye(3)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5], segments=[TrimManoeuvre(60.0)],
                                interference=SensorInterference(k_soft, interference.b_hard)), rng)
    fit = known_gradient_lstsq(difference_tensor(mission.fields_measured, GEOMETRY),
                               mission.fields_measured[:, 0], GEOMETRY, symmetric_k=False)
    assert abs(fit.parameters.k_soft[1, 0, 0] - 1.5) < 1e-2  # the fit itself is right
    with pytest.raises(CalibrationFileError, match=r'k_soft\[1, 0, 0\] = 1\.\d+ is implausible.*not written'):
        CalibrationFile.from_calibration(fit, GEOMETRY)


KILL_WRITER = '''
import sys
import numpy as np
from tetra_gradiometer.core import InterferenceParameters, TetraGeometry
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration
geometry = TetraGeometry.regular(0.5)
big = {f"entry_{i}": float(i) for i in range(20000)}  # a large file: each write takes a while
i = 0
while True:
    i += 1
    params = InterferenceParameters(np.full((3, 3, 3), 1e-6 * i), np.full((3, 3), 1e-12 * i))
    save_calibration(sys.argv[1], CalibrationFile(params, "test", False, geometry.to_flat(), big), force=True)
    print(i, flush=True)
'''


@pytest.mark.slow
def test_a_writer_killed_mid_write_never_leaves_a_truncated_calibration_file(tmp_path):
    target = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(11)
    for _ in range(5):
        process = subprocess.Popen([sys.executable, '-c', KILL_WRITER, str(target)], cwd=REPO,
                                   env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE, text=True)
        try:
            process.stdout.readline()                  # at least one complete write
            time.sleep(rng.uniform(0.0, 0.3))
            process.send_signal(signal.SIGKILL)        # mid-write, most likely
            process.wait(timeout=10)
        finally:
            if process.poll() is None:
                process.kill()
        loaded = load_calibration(target)                # complete, parseable ...
        i = round(loaded.parameters.k_soft[0, 0, 0] / 1e-6)
        np.testing.assert_allclose(loaded.parameters.b_hard, 1e-12 * i)  # ... and self-consistent
        assert len(loaded.diagnostics) == 20000


def test_a_misspelt_or_unknown_key_is_refused_naming_it(tmp_path):
    parameters = InterferenceParameters(np.zeros((3, 3, 3)), np.zeros((3, 3)))
    original = CalibrationFile(parameters, 'known_gradient_lstsq_general', False, GEOMETRY.to_flat(), {},
                               sensor_noise_t=1e-10)
    path = save_calibration(tmp_path / 'c.yaml', original)
    text = path.read_text()
    assert 'sensor_noise_T:' in text
    path.write_text(text.replace('sensor_noise_T:', 'sensor_noise_t:') + 'colour: blue\n')
    with pytest.raises(CalibrationFileError, match=r"unknown keys 'sensor_noise_t' \(did you mean "
                                                   r"'sensor_noise_T'\?\), 'colour'"):
        load_calibration(path)


def test_a_file_too_large_or_binary_is_refused_before_it_is_parsed(tmp_path):
    import resource

    big = tmp_path / 'big.yaml'
    with big.open('wb') as handle:  # 120 MB of YAML-looking text
        handle.write(b'k_soft: [' + b'0.0, ' * (24 * 2**20) + b']\n')
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    with pytest.raises(CalibrationFileError, match='too large to be a calibration'):
        load_calibration(big)
    assert time.perf_counter() - start < 5.0
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 500
    binary = tmp_path / 'bag.db3'
    binary.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(CalibrationFileError, match='not UTF-8 text'):
        load_calibration(binary)


@pytest.mark.slow
def test_a_calibration_nested_too_deeply_is_refused_not_a_crash(tmp_path):
    """libyaml's parser recurses in C: 100 000 nested brackets (200 kB) would end the process,
    in a file or in a calibration's text on the topic, before its signature is checked;
    brackets inside a quoted string are text, however many."""
    from tetra_gradiometer.nodes.authentication import verify

    deep = 'k_soft: ' + '[' * 100_000 + ']' * 100_000 + '\n'
    path = tmp_path / 'deep.yaml'
    path.write_text(deep)
    refused = 'is not valid YAML: brackets nested deeper than the parser can follow'
    with pytest.raises(CalibrationFileError, match=refused):
        load_calibration(path)
    with pytest.raises(CalibrationFileError, match=f'the topic {refused}'):
        verify(deep, b'k' * 32, 'the topic')
    written = save_calibration(tmp_path / 'brackets.yaml', CalibrationFile(
        InterferenceParameters.zero(), 'known_gradient_lstsq', False, GEOMETRY.to_flat(),
        {'note': '[' * 150 + '{' * 150}))
    assert load_calibration(written).diagnostics['note'] == '[' * 150 + '{' * 150
    shallow = CalibrationFile.from_yaml(save_calibration(tmp_path / 'c.yaml', CalibrationFile(
        InterferenceParameters.zero(), 'known_gradient_lstsq', False, GEOMETRY.to_flat())).read_text())
    assert shallow.method == 'known_gradient_lstsq'
