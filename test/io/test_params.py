"""io/params.py: the params file and the errors that name the problem."""
import pytest

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.io.params import (
    ParamsError,
    earth_field_from_params,
    geometry_from_params,
    load_params,
    params_document,
)

GEOMETRY = TetraGeometry.regular(0.5)


def test_params_file_errors_name_the_problem(tmp_path):
    good = tmp_path / 'p.yaml'
    good.write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    assert geometry_from_params(load_params(good)).condition_number == pytest.approx(2.0)
    bad = tmp_path / 'bad.yaml'
    bad.write_text(params_document({'sensor_positions': [0.0] * 9}))
    with pytest.raises(ParamsError, match='sensor_positions must be 12'):
        geometry_from_params(load_params(bad))
    flat = tmp_path / 'flat.yaml'
    flat.write_text(params_document({'sensor_positions': [0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0]}))
    with pytest.raises(ParamsError, match='condition number'):
        geometry_from_params(load_params(flat))
    with pytest.raises(ParamsError, match='not found'):
        load_params(tmp_path / 'none.yaml')


@pytest.mark.parametrize('content, fragment', [
    (b'\xff\xfe\x00s\x00e\x00n\x00', 'is not UTF-8 text: byte 0xff at offset 0'),
    (b'/**:\n  ros__parameters:\n    sensor_positions: [0.0, \xe9]\n', 'is not UTF-8 text: byte 0xe9'),
    (b'/**: {ros__parameters: [1, 2\n', 'is not valid YAML: '),
    (b'a: b: c\n', 'is not valid YAML: mapping values are not allowed here (line 1, column 5)'),
    (b'a: !!python/object:os.system x\n', 'is not valid YAML: could not determine a constructor'),
    (b'[' * 5000, 'is not valid YAML'),
    (b'', 'is empty'),
    (b'# only a comment\n\n', 'is empty'),
])
def test_unreadable_params_files_are_named(tmp_path, content, fragment):
    """read_yaml's failures are one ParamsError line naming the file and the problem."""
    path = tmp_path / 'params.yaml'
    path.write_bytes(content)
    with pytest.raises(ParamsError) as error:
        load_params(path)
    message = str(error.value)
    assert message.startswith(f'params file {path} ') and fragment in message, message
    assert '\n' not in message


def test_a_directory_as_params_file_is_named(tmp_path):
    with pytest.raises(ParamsError, match=f'params file {tmp_path} is a directory'):
        load_params(tmp_path)


@pytest.mark.parametrize('value', ['abc', [1e-5, [2e-5, 3e-5]], {'e': 1.0}, [0.0, 2e-5, float('nan')],
                                   [0.0, 2e-2, 0.0]])
def test_earth_field_must_be_three_plausible_floats(value):
    with pytest.raises(ParamsError, match='earth_field_enu must be'):
        earth_field_from_params({'earth_field_enu': value}, 'P.yaml')
    assert earth_field_from_params({'earth_field_enu': [0.0, 2e-5, -4e-5]}).tolist() == [0.0, 2e-5, -4e-5]
