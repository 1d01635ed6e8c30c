"""Regression: a step a revision renames or creates reports the held-out gap of the model just
before its family entered, as the round records show (it reported the gap of the round its
replaced unit was named in: the initial gap). Snippet for test/core/discrepancy/."""

import numpy as np

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.effects import LIBRARY
from tetra_gradiometer.core.discrepancy.fit import Family
from tetra_gradiometer.core.discrepancy.result import Step
from tetra_gradiometer.core.discrepancy.search import _revise
from tetra_gradiometer.core.discrepancy.synthetic import make_case


def _entered(rounds: list[dict], effect: str) -> int:
    """The round from which on every recorded model holds ``effect``."""
    families = [{unit.split('@')[0] for unit in r['model']} for r in rounds]
    r = len(families) - 1
    assert effect in families[r]
    while r > 0 and effect in families[r - 1]:
        r -= 1
    return r


def test_a_revised_step_reports_the_gap_of_the_round_before_its_family_entered():
    # A large delay in sensor 4 and a thermal drift in sensor 1: eddy terms are named first;
    # after the second round the one in sensor 4 is replaced by time_skew, which names that
    # step time_skew two rounds after its eddy term was named.
    case = make_case(620, ('time_skew', 'thermal_drift'), duration_s=150.0, factor=(300.0, 400.0))
    report = analyze(
        case.recording(), case.scenario.geometry, case.scenario.earth_field_enu, keep_series=False
    )
    assert sorted(report.named_effects) == ['thermal_drift', 'time_skew']
    assert any('replaced by the more parsimonious time_skew' in n for n in report.notes)
    entered = {s.effect: _entered(report.rounds, s.effect) for s in report.steps}
    assert entered['time_skew'] >= 2  # the revision came after a later round
    for step in report.steps:
        assert entered[step.effect] > 0
        assert step.gap_before_nT == report.rounds[entered[step.effect] - 1]['gap_nT']
    # Listed in the order the families entered the model.
    assert [entered[s.effect] for s in report.steps] == sorted(entered.values())
    assert report.steps[0].gap_before_nT == report.gap_initial_nT
    assert report.steps[-1].gap_before_nT < report.gap_initial_nT / 2


def _unit(name: str, sensor: int, p: int) -> Family:
    return Family(LIBRARY[name], np.zeros((5, 4, 3, p)), None, [(sensor, name)] * p)


def _step(name: str, before: float, after: float) -> Step:
    return Step(name, before, after, {}, f'added for sensor(s) ...: {name}', 9, -1.0, 1.0, 0.0)


def test_revise_gives_an_entering_family_the_last_recorded_gap():
    # Rounds recorded: base 40 nT, then 20 nT (eddy_current named), then thermal_drift named;
    # the revision replaces the eddy term by a delay: the delay enters after the 20 nT round.
    steps = [_step('eddy_current', 40.0, 20.0), _step('thermal_drift', 20.0, 0.2)]
    active = (_unit('eddy_current', 3, 9), _unit('thermal_drift', 0, 3))
    delay = _unit('time_skew', 3, 1)
    out, members, units = _revise(
        steps, [[0], [1]], active, 0, delay, 'eddy -> delay', gap_after=0.19, gap_before=20.0
    )
    assert [s.effect for s in out] == ['thermal_drift', 'time_skew']
    assert members == [[1], [0]] and units[0] is delay
    assert (out[1].gap_before_nT, out[1].gap_after_nT) == (20.0, 0.19)
    assert out[1].evidence.endswith('revised later: eddy -> delay')  # the step's history kept
    assert (out[0].gap_before_nT, out[0].gap_after_nT) == (20.0, 0.2)

    # One of two eddy units replaced: the delay gets a step of its own, the eddy step stays.
    steps = [_step('eddy_current', 40.0, 0.2)]
    active = (_unit('eddy_current', 1, 9), _unit('eddy_current', 3, 9))
    out, members, _ = _revise(
        steps, [[0, 1]], active, 1, delay, 'eddy -> delay', gap_after=0.19, gap_before=40.0
    )
    assert [s.effect for s in out] == ['eddy_current', 'time_skew'] and members == [[0], [1]]
    assert (out[1].gap_before_nT, out[1].gap_after_nT) == (40.0, 0.19)
    assert out[0].gap_before_nT == 40.0
