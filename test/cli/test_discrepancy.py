"""``python -m tetra_gradiometer discrepancy BAG --params FILE --out DIR`` through real bags:
sqlite3 and mcap, and a bag with the optional topics missing."""

import json

import pytest

from tetra_gradiometer.__main__ import main
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.core.geometry import TetraGeometry
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag


def _bag(tmp_path, seed, effects, *, storage='sqlite3', earth=True, **topics):
    case = make_case(seed, effects, duration_s=100.0)
    bag = write_mission_bag(tmp_path / 'bag', case.mission, storage=storage, **topics)
    params = {'sensor_positions': case.scenario.geometry.to_flat()}
    if earth:
        params['earth_field_enu'] = [float(v) for v in case.scenario.earth_field_enu]
    (tmp_path / 'params.yaml').write_text(params_document(params))
    return case, bag, tmp_path / 'params.yaml'


@pytest.mark.parametrize(
    'storage, effects',
    [('sqlite3', ('time_skew',)), ('mcap', ('eddy_current', 'vehicle_current'))],
)
def test_cli_names_the_hidden_effects(tmp_path, capsys, storage, effects):
    case, bag, params = _bag(
        tmp_path,
        21 if storage == 'sqlite3' else 22,
        effects,
        storage=storage,
        earth=storage == 'sqlite3',
    )
    out = tmp_path / 'out'
    assert main(['discrepancy', str(bag), '--params', str(params), '--out', str(out)]) == 0
    report = json.loads((out / 'report.json').read_text())
    assert sorted(report['named_effects']) == sorted(effects)
    assert report['gap_initial_nT'] >= 3 * report['gap_final_nT']
    assert report['adequate'] is True
    assert (out / 'report.md').exists() and (out / 'gap.png').exists()
    assert 'named effects:' in capsys.readouterr().out


def test_cli_with_topics_missing_says_which_candidates_were_untestable(tmp_path, capsys):
    case, bag, params = _bag(
        tmp_path,
        23,
        ('sensor_misalignment',),
        earth=False,
        odom=False,
        temperature=False,
        battery=False,
    )
    out = tmp_path / 'out'
    assert (
        main(['discrepancy', str(bag), '--params', str(params), '--out', str(out), '--no-plots'])
        == 0
    )
    report = json.loads((out / 'report.json').read_text())
    assert set(report['untestable']) == {
        'reference_interference',
        'thermal_drift',
        'vehicle_current',
        'external_field',
    }
    assert report['view'] == 'pair'
    assert report['named_effects'] == ['sensor_misalignment']
    text = (out / 'report.md').read_text()
    assert 'could not be tested' in text and '/odom' in text
    assert 'untestable:' in capsys.readouterr().err


@pytest.mark.parametrize(
    'positions, expected',
    [
        # Four sensors at one point are coplanar: the geometry is refused before the bag is read.
        ([0.0] * 12, 'sensor positions are degenerate'),
        # A regular tetrahedron (edge 0.5 m) is fine; the bag folder does not exist.
        (TetraGeometry.regular(0.5).to_flat(), 'bag not found'),
    ],
)
def test_cli_errors_are_one_line(tmp_path, capsys, positions, expected):
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': positions}))
    code = main(
        [
            'discrepancy',
            str(tmp_path / 'nope'),
            '--params',
            str(tmp_path / 'params.yaml'),
            '--out',
            str(tmp_path / 'out'),
        ]
    )
    assert code == 1
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: ') and expected in lines[0], lines
    assert captured.out == ''
    assert not (tmp_path / 'out').exists()
