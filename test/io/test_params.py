"""io/params.py: the params file and the errors that name the problem."""
import pytest

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.io.params import ParamsError, geometry_from_params, load_params, params_document

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
