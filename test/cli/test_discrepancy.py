"""``python -m tetra_gradiometer discrepancy BAG --params FILE --out DIR`` through real bags:
sqlite3 and mcap, and a bag with the optional topics missing."""

import json

import numpy as np
import pytest
import yaml

from tetra_gradiometer.__main__ import main
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.core.geometry import TetraGeometry
from tetra_gradiometer.io.bag import BagWriter
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
    [('sqlite3', ('time_skew',)), pytest.param('mcap', ('eddy_current', 'vehicle_current'), marks=pytest.mark.slow)],
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
    # Each row of a round's table names its sensor: a candidate tried per sensor is told apart.
    rounds = (out / 'report.md').read_text().split('## Candidates per round')[1]
    first_round = rounds.split('\nRound 2')[0].split('Round 1')[1]
    tried = [line.split(' | ')[1] for line in first_round.splitlines() if line.startswith(f'| {effects[0]} | ')]
    assert len(tried) >= 3 and len(set(tried)) == len(tried), first_round


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
        # Four sensors at one point: the geometry is refused (edges of 0 m) before the bag is read.
        ([0.0] * 12, 'sensors 1 and 2 are 0 m apart'),
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


def _bag_topics(bag):
    metadata = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    return sorted(t['topic_metadata']['name'] for t in metadata['topics_with_message_count'])


MAG_ONLY_NOTES = [
    "no /odom (attitude): reference_interference, external_field not tested; residuals are pair "
    "differences against sensor 1 (B_i' - B_1')",
    'no /tetra/temperature (sensor temperature): thermal_drift not tested',
    'no /battery_state (vehicle current): vehicle_current not tested',
]


def _check_mag_only_report(out, stdout):
    """The report folder is complete and says, per missing channel, what was not tested."""
    report = json.loads((out / 'report.json').read_text())
    channels = report['channels']
    assert [channels[t]['note'] for t in ('/odom', '/tetra/temperature', '/battery_state')] == MAG_ONLY_NOTES
    assert not any(c['recorded'] for c in channels.values())
    assert channels['/odom']['untested'] == ['reference_interference', 'external_field']
    for note in MAG_ONLY_NOTES:
        assert f'not tested: {note}\n' in stdout
        assert f'- {note}\n' in (out / 'report.md').read_text()
    assert 'named effects:' in stdout.splitlines()[-1]
    assert {'report.json', 'report.md', 'gap.png', 'diagnostics.png'} <= {p.name for p in out.iterdir()}
    return report


def test_magnetometers_only_bag_with_plots_says_which_channels_are_missing(tmp_path, capsys):
    """A bag with only /tetra/mag1..4 (no /odom, temperature, battery): the analysis runs on
    what there is (pair view), writes the whole report with its plots and names, per missing
    channel, the effects it could not test."""
    case, bag, params = _bag(tmp_path, 24, ('eddy_current',), earth=False, odom=False,
                             temperature=False, battery=False)
    assert _bag_topics(bag) == ['/tetra/mag1', '/tetra/mag2', '/tetra/mag3', '/tetra/mag4']
    out = tmp_path / 'out'
    assert main(['discrepancy', str(bag), '--params', str(params), '--out', str(out)]) == 0
    report = _check_mag_only_report(out, capsys.readouterr().out)
    assert report['named_effects'] == ['eddy_current'] and report['view'] == 'pair'


def test_noise_free_magnetometers_only_bag_still_gets_its_report(tmp_path, capsys):
    """Four identical, noise-free readings (noise floor 0): the report (text and plots) is
    written; the markdown says the gap/floor ratio is undefined instead of dividing by 0."""
    geometry = TetraGeometry.regular(0.5)
    stamps = 1_767_225_600 * 10**9 + np.arange(600, dtype=np.int64) * 100_000_000
    fields = np.tile(np.array([2e-5, 0.0, -4e-5]), (len(stamps), 4, 1))
    fields[100, 2] = [1.0, 0.0, 0.0]  # implausible: dropped and counted, never analysed
    fields[200, 1, 0] = np.nan
    with BagWriter(tmp_path / 'bag') as writer:
        writer.write_fields(stamps, fields)
    (tmp_path / 'params.yaml').write_text(params_document({'sensor_positions': geometry.to_flat()}))
    out = tmp_path / 'out'
    code = main(['discrepancy', str(tmp_path / 'bag'), '--params', str(tmp_path / 'params.yaml'),
                 '--out', str(out)])
    assert code == 0
    stdout = capsys.readouterr().out
    report = _check_mag_only_report(out, stdout)
    assert 'input: implausible sets dropped: 1 non-finite, 1 with |B| > 0.001 T' in stdout
    assert report['data']['sets_dropped_field_magnitude'] == 1
    assert report['data']['sets_dropped_non_finite'] == 1
    assert report['noise_floor_nT'] == 0.0
    assert 'ratio undefined: zero noise floor' in (out / 'report.md').read_text()


def test_a_figure_that_raises_does_not_cost_the_report(tmp_path, capsys, monkeypatch):
    """Drawing one figure raises (a plotting bug): report.json and report.md are written,
    report.md names the figure, stderr has the warning and the traceback, exit status 0."""

    def broken(report, path):
        raise RuntimeError('plotting bug')

    monkeypatch.setattr('tetra_gradiometer.reports.discrepancy._plot_diagnostics', broken)
    case, bag, params = _bag(tmp_path, 21, ('time_skew',))
    out = tmp_path / 'out'
    assert main(['discrepancy', str(bag), '--params', str(params), '--out', str(out)]) == 0
    report = json.loads((out / 'report.json').read_text())
    assert report['named_effects'] == ['time_skew']
    text = (out / 'report.md').read_text()
    assert '## Figures not drawn' in text
    assert '`diagnostics.png` (residual against the drivers): RuntimeError: plotting bug' in text
    assert (out / 'gap.png').exists() and not (out / 'diagnostics.png').exists()
    captured = capsys.readouterr()
    assert (
        'warning: figure diagnostics.png (residual against the drivers) not drawn: '
        'RuntimeError: plotting bug\n' in captured.err
    )
    assert 'Traceback (most recent call last)' in captured.err
    assert 'named effects: time_skew;' in captured.out
