"""The unresolved rule: a line at the manoeuvre's frequency, or a step
within a target's pass or at an excluded span's edge, is reported as unresolved with the data
that would separate it, not named; a line elsewhere and a step away from the targets are
still named (test_dipoles_survey.py). Against the simulator's manoeuvre and analytic tracks."""

from dataclasses import replace

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.core.discrepancy.unresolved import (
    named_and_unresolved,
    pass_intervals,
    resolve,
)


@pytest.fixture(scope='module')
def line_at_the_roll_frequency():
    """A 300 s trim with a 10-sigma line on sensor 2 at the trim's roll frequency."""
    case = make_case(12, (), duration_s=300.0, far_target=False)
    run = case.recording()
    roll_hz = 1.0 / case.scenario.segments[0].roll_period_s
    amplitude = np.random.default_rng(5).normal(size=3)
    amplitude *= 10 * case.scenario.noise_t / np.linalg.norm(amplitude)
    fields = run.fields.copy()
    fields[:, 1] += amplitude * np.sin(2 * np.pi * roll_hz * run.t_s[:, None])
    report = analyze(replace(run, fields=fields), case.scenario.geometry, keep_series=False)
    return roll_hz, report


def test_a_line_at_the_manoeuvre_frequency_is_unresolved_not_named(line_at_the_roll_frequency):
    roll_hz, report = line_at_the_roll_frequency
    lines = [f for f in report.findings if f['effect'] == 'periodic_interference']
    (line,) = [f for f in lines if abs(f['frequency_hz'] / roll_hz - 1) < 0.01]
    assert line['status'] == 'unresolved'
    assert any(c.startswith('field_rate') for c in line['recorded_with_line'])
    assert 'heading rate' in line['separated_by']
    assert 'periodic_interference' not in report.named_effects, report.findings
    assert 'periodic_interference' in report.unresolved_effects
    assert report.to_dict()['unresolved_effects'] == report.unresolved_effects


def test_the_pass_is_the_half_width_of_a_straight_line():
    # A straight line at 2 m/s passing 30 m from a target at t = 50 s: the pass is where the
    # along-track distance is within the closest approach, |t - 50| <= 30 / 2 s.
    t = np.arange(0.0, 100.0, 0.1)
    track = np.column_stack([2.0 * (t - 50.0), np.zeros_like(t), np.zeros_like(t)])
    ((start, end),) = pass_intervals(t, track, np.array([0.0, 0.0, -30.0]))
    assert start == pytest.approx(35.0, abs=0.11) and end == pytest.approx(65.0, abs=0.11)


def test_a_step_in_a_pass_or_at_a_span_edge_is_unresolved_and_one_away_is_named():
    step = {'effect': 'hard_iron_step', 'sensors': [3], 'confounded_with': [], 'evidence': ''}
    line = {'effect': 'periodic_interference', 'frequency_hz': 1.7, 'recorded_with_line': []}
    findings = [dict(step, t_s=40.0), dict(step, t_s=113.0), dict(step, t_s=200.0), line]
    span = {'start_s': 100.0, 'end_s': 110.0, 'duration_s': 10.0}
    out = resolve(findings, [[(35.0, 65.0)]], [span])
    assert [f['status'] for f in out] == ['unresolved', 'unresolved', 'named', 'named']
    assert (
        'pass' in out[0]['unresolved_because'] and 'excluded span' in out[1]['unresolved_because']
    )
    assert out[0]['separated_by']
    assert named_and_unresolved(['hard_iron_step', 'periodic_interference'], out) == (
        ['hard_iron_step', 'periodic_interference'],
        [],
    )
    only_edges = resolve(findings[:2], [[(35.0, 65.0)]], [span])
    assert named_and_unresolved(['hard_iron_step'], only_edges) == ([], ['hard_iron_step'])
