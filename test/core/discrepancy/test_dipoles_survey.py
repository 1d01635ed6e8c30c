"""Targets modelled as dipoles beside real open-world effects and with tails over the whole
line: a magnetization step and a rotating magnet's line are still found at
their time and frequency with a target on the line, and a target whose field is above the
noise everywhere on a short line is modelled, not excluded, and nothing else is named. All
against the simulator's truth (the dipole) and the injected step and line."""

from dataclasses import replace

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.synthetic import make_case
from tetra_gradiometer.core.fields import dipole_field

STEP_SENSOR = 3  # 1-based
LINE_SENSOR = 1
LINE_HZ = 1.7


def _closest_approach(case):
    """Time (s from the start) and distance (m) of the track's closest approach to the target."""
    distance = np.linalg.norm(
        case.mission.position_enu - case.scenario.dipoles[-1].position, axis=1
    )
    i = int(np.argmin(distance))
    return case.mission.t[i] - case.mission.t[0], float(distance[i])


# Seed 44: before the detector looked at the located run with the dipoles' moments fixed,
# the step left the pass out of its robust fit, the free moments blew up (4.6e4 nT) and the
# whole line (38 %) was excluded, target and step with it. Seed 48: before the targets were
# placed with their field in B^b and the detector after them fitted every sample, 31.6 % was
# excluded, no target listed, the step lost; seed 47: a spurious 0.041 Hz line (the target
# 0.09 m off until placed again with the named step). After those fixes 10 of 10 fresh seeds
# (100-109) passed; the test keeps the seeds that failed.
@pytest.fixture(scope='module', params=[pytest.param(44, marks=pytest.mark.slow), 47, pytest.param(48, marks=pytest.mark.slow)])
def stepped_and_lined(request):
    """A trim and a line over a target, with a 30-sigma step on sensor 3 on the line as far
    from the target's pass as it can be (15 s or more from the line's ends: the change-point
    scan keeps 10 s, MIN_SEGMENT_S, either side of a step) and a 10-sigma 1.7 Hz line on
    sensor 1 throughout."""
    case = make_case(request.param, (), duration_s=240.0, near_target=True, far_target=False)
    run = case.recording()
    t_pass, _ = _closest_approach(case)
    line_start = case.scenario.segments[0].duration_s
    on_line = run.t_s[(run.t_s > line_start + 15.0) & (run.t_s < run.t_s[-1] - 15.0)]
    t_step = float(on_line[np.argmax(np.abs(on_line - t_pass))])
    noise = case.scenario.noise_t
    rng = np.random.default_rng(request.param)
    jump = rng.normal(size=3)
    jump *= 30 * noise / np.linalg.norm(jump)
    amplitude = rng.normal(size=3)
    amplitude *= 10 * noise / np.linalg.norm(amplitude)
    phase = rng.uniform(0, 2 * np.pi, 3)
    fields = run.fields.copy()
    fields[run.t_s >= t_step, STEP_SENSOR - 1] += jump
    fields[:, LINE_SENSOR - 1] += amplitude * np.sin(
        2 * np.pi * LINE_HZ * run.t_s[:, None] + phase
    )
    report = analyze(
        replace(run, fields=fields),
        case.scenario.geometry,
        case.scenario.earth_field_enu,
        keep_series=False,
    )
    return case, t_pass, t_step, report


def test_the_step_is_on_the_line_and_away_from_the_pass(stepped_and_lined):
    # The setup itself: otherwise the next test would not test what it says.
    case, t_pass, t_step, _ = stepped_and_lined
    _, distance = _closest_approach(case)
    speed = case.scenario.segments[1].speed_m_s
    assert t_step > case.scenario.segments[0].duration_s
    assert abs(t_step - t_pass) > distance / speed  # beyond the pass's half-width


def test_a_step_and_a_line_beside_a_target_are_found_and_nothing_else(stepped_and_lined):
    case, _, t_step, report = stepped_and_lined
    assert sorted(report.named_effects) == ['hard_iron_step', 'periodic_interference'], (
        report.named_effects,
        report.notes,
    )
    assert len(report.findings) == 2, report.findings
    (step,) = [f for f in report.findings if f['effect'] == 'hard_iron_step']
    assert step['sensors'] == [STEP_SENSOR] and step['status'] == 'named'
    assert abs(step['t_s'] - t_step) <= 1.0
    (line,) = [f for f in report.findings if f['effect'] == 'periodic_interference']
    assert line['sensors'] == [LINE_SENSOR] and line['status'] == 'named'
    assert report.unresolved_effects == []
    assert line['frequency_hz'] == pytest.approx(LINE_HZ, rel=1e-3)
    truth = case.scenario.dipoles[-1].position
    errors = [np.linalg.norm(np.array(t['position_m']) - truth) for t in report.targets]
    assert errors and min(errors) < 0.5, report.targets
    assert report.excluded_fraction == 0.0 and report.excluded_spans == []
    assert report.gap_final_nT <= 1.2 * report.noise_floor_nT


# Seeds 41 and 42 (gap 1.24 and 1.32 x the floor) and 48 (31.5 % excluded, no target)
# failed until the targets were placed with their field in B^b (the soft iron's K_i B_target,
# ~6 nT at 25 m, had moved the fitted position by 0.09 m, 60 sigma). After the fix 10 of 10
# fresh seeds (100-109) passed; the test keeps the seeds that failed.
@pytest.fixture(scope='module', params=[41, pytest.param(42, marks=pytest.mark.slow), pytest.param(48, marks=pytest.mark.slow)])
def long_tails(request):
    """A 5e4 A m^2 dipole 25 m from a short line (about 40-100 m long): its field is far above
    the noise at every sample of the line."""
    case = make_case(
        request.param,
        (),
        duration_s=120.0,
        near_target=True,
        far_target=False,
        target_depth_m=(25.0, 25.0),
        target_moment_am2=(5e4, 5e4),
    )
    report = analyze(
        case.recording(), case.scenario.geometry, case.scenario.earth_field_enu, keep_series=False
    )
    return case, report


def test_the_target_field_is_above_the_noise_on_the_whole_line(long_tails):
    # The setup, from the simulator's truth: the weakest target field on the line (nT).
    case, _ = long_tails
    target = case.scenario.dipoles[-1]
    on_line = case.mission.t - case.mission.t[0] >= case.scenario.segments[0].duration_s
    field = dipole_field(case.mission.position_enu[on_line], target.moment, target.position)
    weakest_nT = np.linalg.norm(field, axis=1).min() * 1e9
    assert weakest_nT > 20 * case.scenario.noise_t * 1e9


def test_tails_over_the_whole_line_are_a_target_not_steps_or_lines(long_tails):
    case, report = long_tails
    assert report.named_effects == [], (report.findings, report.notes)
    truth = case.scenario.dipoles[-1].position
    errors = [np.linalg.norm(np.array(t['position_m']) - truth) for t in report.targets]
    assert errors and min(errors) < 0.5, report.targets
    assert report.excluded_fraction == 0.0 and report.excluded_spans == []
    assert report.gap_final_nT <= 1.2 * report.noise_floor_nT
    assert report.adequate
