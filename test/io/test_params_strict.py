"""io/params.py reads strictly: numbers are numbers, unknown names in the
package's sections are refused with the closest known one, repeated keys are refused."""
from pathlib import Path

import pytest
import yaml

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.io.params import (
    KNOWN_PARAMETERS,
    ParamsError,
    earth_field_from_params,
    geometry_from_params,
    load_params,
    params_document,
)

REPO = Path(__file__).resolve().parents[2]
FLAT = TetraGeometry.regular(0.5).to_flat()


def _write(tmp_path, text: str) -> Path:
    path = tmp_path / 'params.yaml'
    path.write_text(text, encoding='utf-8')
    return path


@pytest.mark.parametrize('values, shown', [
    ([True, False] * 6, 'True (bool)'),
    ([str(v) for v in FLAT], "(str)"),
    ([*FLAT[:11], '0.4'], "'0.4' (str)"),
])
def test_sensor_positions_must_be_numbers(tmp_path, values, shown):
    path = _write(tmp_path, params_document({'sensor_positions': values}))
    with pytest.raises(ParamsError) as error:
        geometry_from_params(load_params(path), source=str(path))
    message = str(error.value)
    assert message.startswith(f'{path}: sensor_positions must be 12 numbers (metres), got ')
    assert shown in message


@pytest.mark.parametrize('values', [[False, True, False], ['0.0', '2e-5', '-4.5e-5'], 5e-5])
def test_earth_field_must_be_numbers(tmp_path, values):
    path = _write(tmp_path, params_document({'sensor_positions': FLAT, 'earth_field_enu': values}))
    with pytest.raises(ParamsError, match='earth_field_enu must be 3'):
        earth_field_from_params(load_params(path), str(path))


def test_integers_are_numbers(tmp_path):
    """A YAML int is a number (0 rather than 0.0): still read."""
    ints = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    path = _write(tmp_path, params_document({'sensor_positions': ints,
                                             'earth_field_enu': [0, 0, 0]}))
    geometry = geometry_from_params(load_params(path))
    assert geometry.positions[1].tolist() == [1.0, 0.0, 0.0]
    assert earth_field_from_params(load_params(path)).tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize('section, key, closest', [
    ('/**', 'earth_field_enu_typo', 'earth_field_enu'),
    ('/**', 'sensor_position', 'sensor_positions'),
    ('/tetra/calibrator', 'max_sample', 'max_samples'),
    ('compensator', 'sensor_noise', 'sensor_noise_t'),
])
def test_unknown_names_are_refused_with_the_closest(tmp_path, section, key, closest):
    document = {'/**': {'ros__parameters': {'sensor_positions': FLAT}}}
    document.setdefault(section, {'ros__parameters': {}})['ros__parameters'][key] = 1.0
    path = _write(tmp_path, yaml.safe_dump(document))
    with pytest.raises(ParamsError) as error:
        load_params(path)
    assert str(error.value) == (
        f'params file {path}: unknown parameter {key!r} in "{section}"; did you mean '
        f'{closest!r}? (docs/ros.md lists the parameters)'
    )


def test_other_packages_sections_are_not_checked(tmp_path):
    document = {'/**': {'ros__parameters': {'sensor_positions': FLAT, 'use_sim_time': True}},
                '/robot_state_publisher': {'ros__parameters': {'robot_description': 'x'}}}
    path = _write(tmp_path, yaml.safe_dump(document))
    assert load_params(path)['sensor_positions'] == FLAT


def test_repeated_keys_are_refused(tmp_path):
    path = _write(tmp_path, '/**:\n  ros__parameters:\n    sensor_positions: [0.0]\n'
                            '    sensor_positions: [1.0]\n')
    with pytest.raises(ParamsError) as error:
        load_params(path)
    assert str(error.value) == (
        f"params file {path} is not valid YAML: duplicate key 'sensor_positions' "
        '(line 4, column 5)'
    )


def test_known_names_are_the_config_files():
    """KNOWN_PARAMETERS is the shipped config's names (which test/ros keeps equal to the
    nodes' declarations) plus use_sim_time: a node parameter added there must be added here."""
    config = yaml.safe_load((REPO / 'config' / 'tetra_gradiometer.yaml').read_text())
    names = {key for section in config.values() for key in section['ros__parameters']}
    assert KNOWN_PARAMETERS - {'use_sim_time'} == names


@pytest.mark.parametrize('path', ['config/tetra_gradiometer.yaml'])
def test_shipped_params_still_load(path):
    params = load_params(REPO / path)
    assert geometry_from_params(params).condition_number == pytest.approx(2.0)
    assert earth_field_from_params(params).tolist() == [0.0, 2.0e-5, -4.5e-5]
