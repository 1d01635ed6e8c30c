"""Every compensation checks itself: the health monitor runs without ``--report`` and a
calibration that never holds on the recording (another vehicle's) is named as such.

Truth: two simulated vehicles with independently drawn interference; each one's own trim
calibration holds on its own survey, the other's does not.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'io'))
from cli_helpers import run_cli  # noqa: E402
from stream_faults import GEOMETRY, write_bag, write_params  # noqa: E402

from tetra_gradiometer.core import Scenario, SurveyLine, TrimManoeuvre, simulate  # noqa: E402
from tetra_gradiometer.core.simulator import random_interference  # noqa: E402

EARTH = [0.0, 2.0e-5, -4.5e-5]


def _vehicle(seed: int):
    rng = np.random.default_rng(seed)
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, noise_t=1e-10, sample_rate_hz=10.0,
                        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9),
                        segments=[TrimManoeuvre(60.0), SurveyLine((0, 0, -50), (120, 0, -50))])
    return simulate(scenario, rng)


@pytest.fixture(scope='module')
def vehicles(tmp_path_factory):
    root = tmp_path_factory.mktemp('vehicles')
    params = write_params(root / 'params.yaml')
    out = {}
    for name, seed in (('a', 1), ('b', 2)):
        bag = write_bag(root / name, _vehicle(seed))
        calibration = root / f'{name}.yaml'
        from tetra_gradiometer.__main__ import main
        assert main(['calibrate', str(bag), '--params', str(params), '--window', '0:59',
                     '--out', str(calibration)]) == 0
        out[name] = bag, calibration
    return params, out


def test_its_own_calibration_passes_the_default_health_check(vehicles, tmp_path, capsys):
    params, out = vehicles
    bag, calibration = out['a']
    code, stdout, err = run_cli(capsys, 'compensate', bag, '--params', params, '--calibration', calibration,
                                '--csv', tmp_path / 'a.csv')
    assert code == 0 and 'warning' not in err, err
    assert 'health: no change detected' in stdout


def test_another_vehicles_calibration_is_named_without_being_asked(vehicles, tmp_path, capsys):
    params, out = vehicles
    code, stdout, err = run_cli(capsys, 'compensate', out['b'][0], '--params', params,
                                '--calibration', out['a'][1], '--csv', tmp_path / 'b.csv')
    assert code == 0
    assert 'warning: health:' in err and 'does not hold from the start of the data' in err, err
    assert "this calibration is not this vehicle's as it is now" in err


@pytest.mark.parametrize('command', ['locate', pytest.param('survey', marks=pytest.mark.slow)])
def test_locate_and_survey_check_their_compensated_tensor_too(vehicles, tmp_path, capsys, command):
    """The same check in the commands that hand products to a client: the foreign
    calibration is named, the own one passes."""
    params, out = vehicles
    extra = ('--origin', '43.2,5.3') if command == 'survey' else ()
    for bag_of, calibration_of, foreign in (('b', 'a', True), ('a', 'a', False)):
        code, stdout, err = run_cli(capsys, command, out[bag_of][0], '--params', params, '--calibration',
                                    out[calibration_of][1], '--out', tmp_path / f'{command}_{bag_of}', *extra)
        text = stdout + err
        if foreign:
            assert "this calibration is not this vehicle's as it is now" in text, text
        else:
            assert "not this vehicle's" not in text, text
