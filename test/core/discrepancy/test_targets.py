"""Discrepancy workflow on runs with a target passed close to the track.

Each mission is a trim manoeuvre followed by a survey line that passes 20-50 m over a
dipole of 1e4-1e5 A m^2 (``make_case(..., near_target=True)``): its field differs between
the sensors and no candidate represents it. The workflow must find the passage on its own,
leave it out (saying so), and still name exactly the hidden effect with the gap at the
noise floor. Genuine effects (in turns, slow, large) must not be taken for a target.
"""

import json

import numpy as np
import pytest

from tetra_gradiometer.__main__ import main
from tetra_gradiometer.core.discrepancy import Settings, analyze
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag
from tetra_gradiometer.reports.discrepancy import write_report

#: The exclusion path (what the workflow does without the track): targets not modelled.
EXCLUDE = Settings(model_targets=False)

EFFECTS = (
    'eddy_current',
    'sensor_misalignment',
    'reference_interference',
    'time_skew',
    'thermal_drift',
    'vehicle_current',
)


def _closest_approach(case):
    m = case.mission
    target = case.scenario.dipoles[-1]
    distance = np.linalg.norm(m.position_enu - target.position, axis=1)
    return float(m.t[np.argmin(distance)]), float(distance.min())


def _trim_s(case):
    return float(case.scenario.segments[0].duration_s)


def _check_spans(case, report):
    """The passage is excluded (its closest approach inside a span), the trim is not."""
    assert report.excluded_spans, report.notes
    t_closest, _ = _closest_approach(case)
    assert any(s['start_s'] <= t_closest <= s['end_s'] for s in report.excluded_spans)
    for span in report.excluded_spans:
        assert span['start_s'] >= _trim_s(case) - 0.5  # the manoeuvre (where effects show) is kept
        assert 'target' in span['reason'] and span['peak_over_noise'] > 4
    assert report.data['excluded_s'] > 0


@pytest.mark.parametrize('hidden', ('clean',) + EFFECTS)
def test_target_pass_is_excluded_and_the_hidden_effect_named(hidden):
    effects = () if hidden == 'clean' else (hidden,)
    seed = 40 + (EFFECTS.index(hidden) + 1 if effects else 0)
    case = make_case(seed, effects, duration_s=150.0, near_target=True)
    _, distance = _closest_approach(case)
    assert 20.0 <= distance <= 50.5
    report = analyze(
        case.recording(),
        case.scenario.geometry,
        case.scenario.earth_field_enu if seed % 2 else None,
        keep_series=False,
        settings=EXCLUDE,
    )
    assert report.named_effects == list(effects), (report.named_effects, report.excluded_spans)
    # The passage is a third of the run: never "adequate" on what is left.
    assert report.excluded_fraction > 0.1 and not report.adequate
    assert any('cannot be called adequate' in note for note in report.notes)
    assert report.gap_final_nT <= 1.1 * report.noise_floor_nT
    noise = case.scenario.noise_t * 1e9
    assert report.noise_floor_nT == pytest.approx(noise, rel=0.15)
    if effects:
        assert report.gap_initial_nT >= 2.0 * report.gap_final_nT
    _check_spans(case, report)


def test_without_the_exclusion_the_target_leaves_the_model_inadequate():
    # The limit the exclusion removes: the same run analysed with the passage in.
    # (The base model only: a full search over a run that no candidate can fit costs a minute.)
    case = make_case(44, ('time_skew',), duration_s=150.0, near_target=True)
    kept = analyze(
        case.recording(),
        case.scenario.geometry,
        case.scenario.earth_field_enu,
        keep_series=False,
        settings=Settings(exclude_targets=False, max_effects=0, model_targets=False),
    )
    assert not kept.adequate and kept.excluded_spans == []
    report = analyze(
        case.recording(),
        case.scenario.geometry,
        case.scenario.earth_field_enu,
        keep_series=False,
        settings=Settings(max_effects=0, model_targets=False),
    )
    assert report.excluded_spans
    # Most of the base model's gap is the target: without it the gap is the hidden delay's.
    assert kept.gap_initial_nT > 5 * report.gap_initial_nT


@pytest.mark.parametrize('effect', ['eddy_current', 'vehicle_current'])
def test_without_odom_the_pair_view_excludes_the_target_gradient(effect):
    case = make_case(60 + EFFECTS.index(effect), (effect,), duration_s=150.0, near_target=True)
    report = analyze(case.recording(odom=False), case.scenario.geometry, None, keep_series=False)
    assert report.view == 'pair'
    assert report.named_effects == [effect]
    assert report.gap_final_nT <= 1.25 * report.noise_floor_nT
    _check_spans(case, report)
    assert all(s['peak_common_rms_nT'] is None for s in report.excluded_spans)


@pytest.mark.parametrize(
    'effect',
    ['eddy_current', 'time_skew', 'sensor_misalignment', 'thermal_drift', 'vehicle_current'],
)
def test_large_genuine_effects_are_not_taken_for_a_target(effect):
    # 300-1000 x the noise, in turns (eddy, delay, misalignment) or slow (temperature, current):
    # the full candidate model explains them everywhere, so nothing is localized.
    case = make_case(
        70 + EFFECTS.index(effect), (effect,), duration_s=120.0, factor=(300.0, 1000.0)
    )
    report = analyze(
        case.recording(), case.scenario.geometry, case.scenario.earth_field_enu, keep_series=False
    )
    assert report.excluded_spans == [], report.excluded_spans
    assert report.named_effects == [effect]
    assert report.data['target_detector']['peak_over_level'] < Settings().target_high


def test_window_restricts_the_analysis_to_the_trim():
    case = make_case(45, ('thermal_drift',), duration_s=150.0, near_target=True)
    trim = _trim_s(case)
    report = analyze(
        case.recording(),
        case.scenario.geometry,
        case.scenario.earth_field_enu,
        keep_series=False,
        window_s=(0.0, trim - 1.0),
    )
    assert report.data['window_s'] == [0.0, trim - 1.0]
    assert report.data['duration_s'] <= trim - 1.0
    assert report.excluded_spans == []
    assert report.named_effects == ['thermal_drift'] and report.adequate
    assert any('window' in note for note in report.notes)
    with pytest.raises(ValueError, match='window'):
        analyze(case.recording(), window_s=(500.0, 600.0))
    with pytest.raises(ValueError, match='window'):
        analyze(case.recording(), window_s=(10.0, 5.0))


def test_report_and_cli_list_the_modelled_target(tmp_path, capsys):
    case = make_case(46, ('vehicle_current',), duration_s=120.0, near_target=True)
    bag = write_mission_bag(tmp_path / 'bag', case.mission)
    params = tmp_path / 'params.yaml'
    params.write_text(
        params_document(
            {
                'sensor_positions': case.scenario.geometry.to_flat(),
                'earth_field_enu': [float(v) for v in case.scenario.earth_field_enu],
            }
        )
    )
    out = tmp_path / 'out'
    assert (
        main(['discrepancy', str(bag), '--params', str(params), '--out', str(out), '--no-plots'])
        == 0
    )
    data = json.loads((out / 'report.json').read_text())
    # The bag has the track (/odom position): the target is modelled, nothing excluded.
    assert data['named_effects'] == ['vehicle_current'] and data['adequate'] is True
    assert data['excluded_fraction'] == 0.0 and data['excluded_spans'] == []
    truth = case.scenario.dipoles[-1].position
    assert min(np.linalg.norm(np.array(t['position_m']) - truth) for t in data['targets']) < 0.5
    text = (out / 'report.md').read_text()
    assert '## Targets (modelled as dipoles)' in text
    # --window: only the trim, nothing to exclude.
    out2 = tmp_path / 'out2'
    trim = _trim_s(case)
    assert (
        main(
            [
                'discrepancy',
                str(bag),
                '--params',
                str(params),
                '--out',
                str(out2),
                '--no-plots',
                '--window',
                f':{trim - 1.0:.1f}',
            ]
        )
        == 0
    )
    data = json.loads((out2 / 'report.json').read_text())
    assert data['excluded_spans'] == [] and data['named_effects'] == ['vehicle_current']
    assert data['data']['window_s'] == [0.0, pytest.approx(trim - 1.0, abs=0.05)]
    capsys.readouterr()
    # A malformed window is a usage error (exit 2, one line naming the option).
    with pytest.raises(SystemExit) as stop:
        main(['discrepancy', str(bag), '--params', str(params), '--out', str(tmp_path / 'o3'),
              '--window', 'nonsense'])
    assert stop.value.code == 2
    assert 'argument --window: must be T0:T1' in capsys.readouterr().err
    assert not (tmp_path / 'o3').exists()


def test_plots_mark_the_excluded_spans(tmp_path):
    case = make_case(47, (), duration_s=100.0, near_target=True)
    report = analyze(
        case.recording(), case.scenario.geometry, case.scenario.earth_field_enu, settings=EXCLUDE
    )
    out = write_report(report, tmp_path / 'out')
    assert (out / 'residual_base.png').exists()
    assert report.named_effects == [] and report.excluded_spans
    assert report.adequate == (report.excluded_fraction <= 0.1)
