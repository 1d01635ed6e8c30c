"""Discrepancy workflow as a library call, on simulated missions with hidden effects.

Every case draws its own geometry (non-regular tetrahedron, edge 0.2-1 m, any orientation),
Earth field (25 000-65 000 nT, any direction), manoeuvre, noise (0.02-0.2 nT), base
interference and, in some cases, a distant target; each hidden effect sits in random
sensors with an RMS contribution of 20-80 x the noise there. The workflow is never told
which effect is hidden.
"""

import itertools
import json
import re

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import CANDIDATES, LIBRARY, Settings, analyze
from tetra_gradiometer.core.discrepancy.synthetic import EFFECT_NAMES, make_case
from tetra_gradiometer.reports.discrepancy import write_report

REQUIRED = (
    'eddy_current',
    'sensor_misalignment',
    'reference_interference',
    'time_skew',
    'thermal_drift',
    'vehicle_current',
)

# Each effect's physics, known without the code: the recorded input beyond the magnetometers
# (and /odom for the absolute view) that its terms are made of, and its parameters per sensor.
PHYSICS = {
    'eddy_current': ((), 9),  # E_i dB^b/dt, a general 3x3 E_i
    'sensor_misalignment': ((), 3),  # a rotation vector omega_i
    'reference_interference': (('odom',), 9),  # symmetric K_1 (6) and B_1^h (3)
    'time_skew': ((), 1),  # one delay tau_i, the same on all axes
    'thermal_drift': (('temperature',), 3),  # c_i per axis (+3 offsets at the clean sensor 1)
    'vehicle_current': (('current',), 3),  # v_i per axis
}


def _parameters_at(effect, sensor):
    # Thermal drift is c (T - T_ref) with T_ref unknown: sensor 1 has no hard iron to absorb
    # the constant, so it carries three offsets of its own.
    extra = 3 if (effect == 'thermal_drift' and sensor == 1) else 0
    return PHYSICS[effect][1] + extra


def _evidence_sensors(evidence):
    match = re.match(r'added for sensor\(s\) ([0-9, ]+):', evidence)
    assert match, evidence
    return sorted(int(s) for s in match.group(1).split(','))


def _run(case, *, earth=True, **recording):
    return analyze(
        case.recording(**recording),
        case.scenario.geometry,
        case.scenario.earth_field_enu if earth else None,
        keep_series=False,
    )


def test_every_consumer_reads_the_one_registry():
    # Synthetic cases hide exactly the library entries the simulator produces; the command
    # line offers the whole library.
    import argparse

    from tetra_gradiometer.cli.discrepancy import add_arguments

    assert EFFECT_NAMES == tuple(c.name for c in CANDIDATES if c.simulated is not None)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    help_text = next(a.help for a in parser._actions if a.dest == 'candidates')
    assert help_text is not None and help_text.endswith(','.join(LIBRARY))


def test_library_holds_the_required_named_effects_with_physics():
    assert set(REQUIRED) <= set(LIBRARY)
    assert set(EFFECT_NAMES) <= set(LIBRARY)
    for name, (requires, _) in PHYSICS.items():
        assert LIBRARY[name].requires == requires, name
    # A field fixed in the world frame needs the attitude to be seen in the body frame.
    assert LIBRARY['external_field'].requires == ('odom',)


@pytest.mark.parametrize('effect', REQUIRED)
@pytest.mark.parametrize('seed', [101, pytest.param(202, marks=pytest.mark.slow)])
def test_one_hidden_effect_is_named_first_and_the_gap_shrinks(effect, seed):
    case = make_case(seed + 7 * REQUIRED.index(effect), (effect,), duration_s=150.0)
    report = _run(case, earth=seed % 2 == 1)
    assert report.named_effects[:1] == [effect], (case.hidden, report.rounds[0]['candidates'][:3])
    assert report.named_effects == [effect]
    assert report.gap_initial_nT >= 3.0 * report.gap_final_nT
    assert report.gap_final_nT <= 1.25 * report.noise_floor_nT
    assert report.adequate
    step = report.steps[0]
    truth = case.hidden[effect]
    sigma, sensors = truth['noise_nT'], truth['sensors']
    # The base model can absorb part of the effect, hardly add to it: the held-out gap before
    # is at most the hidden effect (its RMS over the 4 sensors) on top of the noise.
    effect_rms = truth['rms_nT'] * np.sqrt(len(sensors) / 4)
    assert sigma < step.gap_before_nT <= 1.2 * np.hypot(sigma, effect_rms)
    assert step.gap_after_nT < step.gap_before_nT / 3
    # With the one hidden effect named, what is left is the white noise of known sigma.
    assert step.gap_after_nT == pytest.approx(sigma, rel=0.05)
    # Named in exactly the sensors where it was hidden, with its physical parameter count.
    per_sensor = step.parameters['per_sensor']
    assert sorted(per_sensor) == [f'sensor_{s}' for s in sensors]
    for s in sensors:
        assert len(per_sensor[f'sensor_{s}']) == _parameters_at(effect, s)
    assert step.n_parameters == sum(_parameters_at(effect, s) for s in sensors)
    assert _evidence_sensors(step.evidence) == sensors


@pytest.mark.parametrize('seed', [11, 12, 13])
def test_clean_data_names_nothing_and_the_model_is_adequate(seed):
    case = make_case(seed, (), duration_s=150.0, far_target=seed == 12)
    report = _run(case, earth=seed != 13)
    assert report.named_effects == []
    assert report.steps == []
    assert report.adequate is True
    # Nothing hidden: the base model's held-out gap, the final gap and the noise floor are all
    # the white noise of known sigma (~18 000 values: the RMS is good to well below 5 %).
    noise = case.scenario.noise_t * 1e9
    assert report.gap_initial_nT == pytest.approx(noise, rel=0.05)
    assert report.noise_floor_nT == pytest.approx(noise, rel=0.05)
    assert report.gap_final_nT == pytest.approx(noise, rel=0.05)


#: Every effect in one pair `make test` runs (the others are slow: `make test-slow`).
FIRST_PAIRS = tuple(zip(REQUIRED[0::2], REQUIRED[1::2], strict=True))


@pytest.mark.parametrize('pair', [pair if pair in FIRST_PAIRS else pytest.param(pair, marks=pytest.mark.slow)
                                  for pair in itertools.combinations(REQUIRED, 2)])
def test_two_hidden_effects_are_both_named(pair):
    seed = 300 + 13 * REQUIRED.index(pair[0]) + REQUIRED.index(pair[1])
    case = make_case(seed, pair, duration_s=150.0)
    report = _run(case)
    assert sorted(report.named_effects) == sorted(pair), (case.hidden, report.named_effects)
    assert report.gap_final_nT <= 1.25 * report.noise_floor_nT
    assert report.adequate


@pytest.mark.parametrize('effect', [e for e in REQUIRED if e != 'reference_interference'])
def test_without_odom_the_pair_view_still_names_the_effect(effect):
    case = make_case(400 + REQUIRED.index(effect), (effect,), duration_s=150.0)
    report = _run(case, earth=False, odom=False)
    assert report.view == 'pair'
    assert 'reference_interference' in report.untestable
    assert report.named_effects == [effect]
    assert report.gap_initial_nT >= 3.0 * report.gap_final_nT
    assert any('B^b = B_1' in note for note in report.notes)


def test_missing_temperature_and_current_make_their_candidates_untestable():
    case = make_case(501, ('sensor_misalignment',), duration_s=120.0)
    report = _run(case, temperature=False, battery=False)
    assert set(report.untestable) == {'thermal_drift', 'vehicle_current'}
    assert 'temperature' in report.untestable['thermal_drift']
    assert 'battery_state' in report.untestable['vehicle_current']
    assert report.named_effects == ['sensor_misalignment']


def test_parsimony_time_skew_is_not_called_eddy_current():
    # A large delay: the nine-parameter eddy term would explain the same first-order signal.
    case = make_case(612, ('time_skew',), duration_s=150.0, factor=(300.0, 400.0))
    report = _run(case)
    assert report.named_effects == ['time_skew']
    taus = [v['tau_s'] for v in report.steps[0].parameters['per_sensor'].values()]
    sensors = case.hidden['time_skew']['sensors']
    truth = case.scenario.effects.time_skew
    assert truth is not None
    for s in sensors:
        est = report.steps[0].parameters['per_sensor'][f'sensor_{s}']['tau_s']
        assert est == pytest.approx(truth[s - 1], rel=0.05)
    assert len(taus) == len(sensors)


def test_misalignment_estimate_matches_the_truth():
    case = make_case(713, ('sensor_misalignment',), duration_s=150.0, factor=(200.0, 300.0))
    report = _run(case)
    assert report.named_effects == ['sensor_misalignment']
    per_sensor = report.steps[0].parameters['per_sensor']
    rotations = case.scenario.effects.sensor_misalignment
    assert rotations is not None
    for s in case.hidden['sensor_misalignment']['sensors']:
        est = np.array([per_sensor[f'sensor_{s}'][f'omega_{a}_rad'] for a in 'xyz'])
        truth = rotations[s - 1]
        assert np.linalg.norm(est - truth) < 0.05 * np.linalg.norm(truth)


@pytest.mark.slow
def test_report_files_and_schema(tmp_path):
    case = make_case(808, ('vehicle_current', 'thermal_drift'), duration_s=120.0)
    report = analyze(case.recording(), case.scenario.geometry, case.scenario.earth_field_enu)
    out = write_report(report, tmp_path / 'out')
    data = json.loads((out / 'report.json').read_text())
    noise = case.scenario.noise_t * 1e9
    hidden = case.hidden
    # The file holds the truth of the case: both hidden effects, each in its own sensors,
    # and a final gap (and the last step's) at the white noise of known sigma.
    assert sorted(data['named_effects']) == sorted(hidden)
    assert sorted(s['effect'] for s in data['steps']) == sorted(hidden)
    for step in data['steps']:
        sensors = hidden[step['effect']]['sensors']
        assert sorted(step['parameters']['per_sensor']) == [f'sensor_{s}' for s in sensors]
    assert data['steps'][-1]['gap_after_nT'] == pytest.approx(noise, rel=0.05)
    assert data['gap_final_nT'] == pytest.approx(noise, rel=0.05)
    assert data['noise_floor_nT'] == pytest.approx(noise, rel=0.05)
    effects_rms = np.sqrt(sum(h['rms_nT'] ** 2 * len(h['sensors']) / 4 for h in hidden.values()))
    assert 3 * noise < data['gap_initial_nT'] <= 1.2 * np.hypot(noise, effects_rms)
    assert data['untestable'] == {}  # every topic recorded
    assert data['view'] == 'absolute'  # /odom recorded
    assert data['adequate'] is True
    assert "B_i' = B_i + K_i B^b + B_i^h" in data['base_model']  # Yu et al. 2014 eq. 10
    text = (out / 'report.md').read_text()
    headings = [line for line in text.splitlines() if line.startswith('### ')]
    assert sorted(h.split('. ', 1)[1] for h in headings) == sorted(hidden)
    for name in hidden:
        assert LIBRARY[name].physics[:40] in text
    pngs = sorted(p.name for p in out.glob('*.png'))
    assert 'gap.png' in pngs and 'diagnostics.png' in pngs
    assert any(p.startswith('residual_step1_') for p in pngs)
    assert any(p.startswith('effect_') for p in pngs)
    assert [p.name for p in out.glob('.*')] == [
        '.tetra_gradiometer_output'
    ]  # the marker, no temporary
    assert not list(out.parent.glob('.*partial'))


def test_settings_reject_unknown_candidates():
    case = make_case(909, (), duration_s=60.0)
    with pytest.raises(ValueError, match='unknown candidate'):
        analyze(case.recording(), settings=Settings(candidates=('poltergeist',)))


@pytest.mark.parametrize('effect', ['time_skew', 'eddy_current'])
def test_without_odom_an_effect_of_sensor_1_is_named_and_taken_out_of_the_background(effect):
    # Sensor 1 is the pair view's reference: its term enters every pair, and B^b = B_1'
    # carries it; a large one (200-400 x the noise) must still leave the noise floor.
    case = make_case(
        515, (effect,), duration_s=120.0, factor=(200.0, 400.0), sensors={effect: [1]}
    )
    report = _run(case, earth=False, odom=False)
    assert report.named_effects == [effect]
    assert report.gap_final_nT <= 1.1 * report.noise_floor_nT
    if effect == 'time_skew':
        delays = case.scenario.effects.time_skew
        assert delays is not None
        tau = delays[0]
        values = {s: v['tau_s'] for s, v in report.steps[0].parameters['per_sensor'].items()}
        # Only relative delays are observable: tau_i - tau_1 = -tau_1 for the clean sensors.
        for s in ('sensor_2', 'sensor_3', 'sensor_4'):
            assert values.get(s, 0.0) - values.get('sensor_1', 0.0) == pytest.approx(
                -tau, rel=0.02
            )
