"""pipelines/window_check.py directly, in process (fast enough to run per mutant: `make
mutation`): the attitude from /odom against scipy's rotations (a vehicle yawing at a constant
rate: slerp between messages is then exact), gaps in /odom and the live history; and the
checked solve on simulated sets (no bag): a clean trim passes with the simulator's truth, a
window over a target is refused naming a field and the trim that passes, forced it keeps the
warning, a regional gradient is fitted jointly within 3 sigma of the simulator's.
Calibration through bags and the CLI: test/io/test_realworld.py, test/cli/test_calibrate_window.py."""
from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tetra_gradiometer import core
from tetra_gradiometer.core.identification import Options
from tetra_gradiometer.errors import AssumptionError
from tetra_gradiometer.pipelines.window_check import (
    MAX_ODOM_GAP_S,
    AttitudeHistory,
    excited_spans,
    forced,
    identify_checked,
    joint_attitude,
    orientation_at,
)

NS = 10**9
T0 = 1_800_000_000 * NS
RATE_DEG_S = 10.0


def yaw(t_ns):
    return Rotation.from_euler('z', (RATE_DEG_S * (np.asarray(t_ns) - T0) / NS)[:, None], degrees=True)


def odom(period_s=0.05, duration_s=10.0):
    stamps = T0 + np.round(np.arange(0.0, duration_s, period_s) * NS).astype(np.int64)
    return stamps, yaw(stamps).as_quat()


def angle_deg(q, truth):
    return np.degrees((Rotation.from_quat(q) * truth.inv()).magnitude())


def test_orientation_between_messages_is_the_true_attitude():
    stamps, quats = odom()
    samples = T0 + np.round(np.linspace(0.1, 9.8, 500) * NS).astype(np.int64) + 7_000_000
    assert angle_deg(orientation_at(stamps, quats, samples), yaw(samples)).max() < 1e-9


def test_gaps_and_ends_beyond_the_limit_are_unknown():
    stamps, quats = odom()
    keep = (stamps < T0 + 4 * NS) | (stamps > T0 + 6 * NS)  # a 2 s hole in /odom
    edge = int(MAX_ODOM_GAP_S * NS)
    samples = np.array([T0 + 5 * NS, T0 + 4 * NS + edge // 2, stamps[-1] + edge + 1, T0 - edge // 2])
    got = orientation_at(stamps[keep], quats[keep], samples)
    assert np.all(np.isnan(got[[0, 2]]))
    assert np.all(np.isfinite(got[[1, 3]]))  # within the limit: held or slerped across
    assert np.all(np.isnan(orientation_at(stamps[:0], quats[:0], samples)))


def test_the_live_history_gives_the_nearest_message_and_all_samples_at_the_end():
    stamps, quats = odom()
    history = AttitudeHistory()
    for stamp, quat in zip(stamps, quats, strict=True):
        history.add(int(stamp), quat)
    sample = int(stamps[40]) + 20_000_000  # 20 ms after a message, 30 ms before the next
    np.testing.assert_allclose(history.at(sample), quats[40], rtol=0, atol=1e-15)  # normalized: 1 ulp
    samples = stamps[5:-5] + 13_000_000
    np.testing.assert_allclose(history.over(samples), orientation_at(stamps, quats, samples))
    # A short span reads only the messages around it: the same attitudes as from all of them,
    # at its edges, on a message, alone, and beyond the ends (held, then NaN).
    for span in (stamps[50:60] + 7_000_000, stamps[70:71], stamps[:3] - 30_000_000,
                 stamps[-2:] + np.array([0, NS // 2]), np.array([int(stamps[-1]) + 2 * NS]),
                 np.array([int(stamps[0]) - 2 * NS])):
        np.testing.assert_allclose(history.over(span), orientation_at(stamps, quats, span),
                                   rtol=0, atol=1e-12)
    assert history.over(stamps[:0]).shape == (0, 4)
    assert np.all(np.isnan(history.at(int(stamps[-1]) + 2 * NS)))
    history.add(int(stamps[0]), quats[0])  # time went back (a replay restarted): the rest is stale
    assert np.all(np.isnan(history.at(int(stamps[100]))))


def test_the_live_history_drops_zero_norm_and_normalizes_unnormalized_quaternions():
    """Issue 30 item 2, live: an unfilled orientation (all zeros), a NaN one and one scaled by 3
    among the messages. The first two are dropped and counted (the samples around them take the
    neighbouring messages, as if they had not come), the third normalized: the attitudes equal
    the true yaw's, never an error (was `ValueError: Found zero norm quaternions` at ~/calibrate)."""
    stamps, quats = odom()
    fed = quats.copy()
    fed[40] = 0.0
    fed[41, 2] = np.nan
    fed[60] *= 3.0
    history = AttitudeHistory()
    for stamp, quat in zip(stamps, fed, strict=True):
        history.add(int(stamp), quat)
    samples = stamps[5:-5] + 13_000_000
    assert angle_deg(history.over(samples), yaw(samples)).max() < 1e-9
    assert angle_deg(history.at(int(stamps[40]))[None], yaw(stamps[40:41])).max() < 0.6  # a neighbour, 50 ms away
    np.testing.assert_allclose(history.at(int(stamps[60])), quats[60], atol=1e-12)
    assert (history.check.dropped, history.check.normalized) == (2, 1)
    report = history.check.report()
    assert '2 odometry messages with a zero-norm or non-finite orientation dropped' in report, report
    assert '1 odometry orientation not of unit norm (norm 3) normalized' in report, report
    assert history.check.report() == ''  # nothing new since


# ------------------------------------------------------------------ the checked solve

NT = 1e-9
GEOMETRY = core.TetraGeometry.regular(0.5)
TRIM_S = 120.0
#: A target 15 m below the line's middle (passed 25 s into it, 145 s into the mission): its
#: gradient is above the noise for ~30 s of the line (0.9 nT/m RMS over the mission).
TARGET = core.Dipole([0.0, 0.0, -65.0], [1e3, 3e2, -6e2])


def _mission(seed: int, gradient=None, dipoles=(TARGET,)):
    """A 120 s trim far from the target, then a 100 m line over it, at 10 Hz."""
    rng = np.random.default_rng(seed)
    scenario = core.Scenario(
        geometry=GEOMETRY, earth_field_enu=np.array([0.0, 20000.0, -45000.0]) * NT,
        segments=(core.TrimManoeuvre(TRIM_S, center=(3000.0, 3000.0, -50.0)),
                  core.SurveyLine((-50.0, 0.0, -50.0), (50.0, 0.0, -50.0), 2.0,
                                  roll_amplitude_deg=2.0, pitch_amplitude_deg=1.0)),
        sample_rate_hz=10.0, dipoles=dipoles, noise_t=0.1 * NT,
        interference=core.random_interference(rng, reference_clean=True),
        regional_gradient_enu=np.zeros((3, 3)) if gradient is None else gradient)
    return core.simulate(scenario, rng)


@pytest.fixture(scope='module')
def mission():
    return _mission(11)


def _checked(mission, keep, method='known_gradient_lstsq', options=None, **kwargs):
    stamps = np.round(mission.t * 1e9).astype(np.int64)
    fields = mission.fields_measured
    return identify_checked(
        method, stamps[keep], core.difference_tensor(fields[keep], GEOMETRY), fields[keep, 0],
        GEOMETRY, options or Options(), window='the window', first_ns=0, **kwargs)


def test_a_clean_trim_passes_and_compensates_to_the_noise_floor(mission):
    trim = mission.segment == 0
    checked = _checked(mission, trim)
    check = checked.check
    assert check.passed and check.passing_window is None and checked.notes == ()
    assert 0.8 < check.consistency.ratio <= check.consistency.threshold_ratio
    line = check.text()
    assert line.startswith('fit residual ') and 'x the noise' in line
    assert 'fails in' not in line and 'would pass' not in line
    assert checked.diagnostics()['window_check']['passed'] is True
    assert checked.diagnostics()['window_check']['passing_window_s'] is None
    assert checked.regional_text() == ''  # none fitted without attitudes
    survey = mission.segment == 1
    g = core.compensate(core.difference_tensor(mission.fields_measured[survey], GEOMETRY),
                        mission.fields_measured[survey, 0], checked.calibration.parameters, GEOMETRY)
    floor = core.noise_floor(0.1 * NT, GEOMETRY)
    assert core.rms_residual(g, mission.g_true[survey]) < 1.3 * floor


def test_a_window_over_a_target_is_refused_naming_a_field_and_the_trim_that_passes(mission):
    with pytest.raises(AssumptionError) as refused:
        _checked(mission, slice(None))
    text = str(refused.value)
    assert text.startswith('the window (the window) does not fit the model (a target or a '
                           'spatially varying field: '), text
    assert '--force writes it anyway' in text
    # The target is passed 145 s in (the line's 25th second): the failing part holds it, and
    # not the trim (a 1000 A m2 target 3 km away).
    spans = [tuple(map(float, m)) for m in re.findall(r'(\d+)-(\d+) s', text.split('fails in')[1])]
    assert any(a <= 145.0 <= b for a, b in spans) and min(a for a, _ in spans) > 100.0, text
    # The sub-window named lies outside the failing part (its ends printed to 1 s), is 30 s
    # or more, and passes alone.
    t0, t1 = map(float, re.search(r'--window ([\d.]+):([\d.]+) would pass', text).groups())
    assert t1 - t0 >= 30.0 and not any(t0 < b - 1.0 and a + 1.0 < t1 for a, b in spans), text
    assert _checked(mission, (mission.t >= t0) & (mission.t <= t1)).check.passed


def test_forced_the_failing_window_is_kept_with_its_warning(mission):
    checked = _checked(mission, slice(None), force=True, force_name='force:=true',
                       sub_window='window {0:g}-{1:g} s', notes=('a note',))
    assert not checked.check.passed and checked.check.consistency.ratio > 2
    assert checked.notes[0] == 'a note' and len(checked.notes) == 2
    warning = checked.notes[1]
    assert warning.startswith('WARNING (force:=true): the window (the window) does not fit')
    assert 'force:=true writes it anyway' in warning and re.search(r'window [\d.]+-[\d.]+ s would pass', warning)
    assert checked.diagnostics()['window_check']['passed'] is False
    assert checked.diagnostics()['notes'] == list(checked.notes)


def test_without_a_target_trim_and_line_pass_together():
    """No false refusal: the same mission without the target passes on all of it."""
    clean = _mission(11, dipoles=())
    checked = _checked(clean, slice(None))
    assert checked.check.passed and checked.notes == ()


def test_a_regional_gradient_is_fitted_jointly_with_the_attitudes_within_3_sigma():
    g_world = np.array([[2.5, 1.0, -0.8], [1.0, -1.5, 1.4], [-0.8, 1.4, -1.0]])
    g_world *= 4.0 * NT / np.linalg.norm(g_world)
    mission = _mission(12, gradient=g_world, dipoles=())
    trim = mission.segment == 0
    orientation, note = joint_attitude(mission.orientation_xyzw[trim])
    assert orientation is not None and 'estimated jointly' in note
    checked = _checked(mission, trim, options=Options(orientation_xyzw=orientation))
    assert checked.check.passed
    fitted = checked.calibration.regional_gradient_enu
    sigma = checked.calibration.regional_gradient_sigma
    assert np.all(np.abs(fitted - g_world) <= 3 * sigma), (fitted - g_world) / sigma
    text = checked.regional_text()
    values = [float(v) for pair in re.findall(r'g[xyz]{2} ([+-][\d.]+) \+- ([\d.]+)', text) for v in pair]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    assert values[0::2] == pytest.approx([g_world[i, j] / NT for i, j in pairs], abs=3 * sigma.max() / NT + 5e-4)
    assert values[1::2] == pytest.approx([sigma[i, j] / NT for i, j in pairs], abs=5e-4)


def test_joint_attitude_needs_every_sample():
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (10, 1))
    quats[[2, 5, 7]] = np.nan
    orientation, note = joint_attitude(quats)
    assert orientation is None
    assert note.startswith('3 of 10 samples have no /odom message within 0.5 s')


def test_forced_raises_the_first_refusal_unless_forced():
    first, second = AssumptionError('first'), AssumptionError('second')
    assert forced([None, None], False) == ()
    with pytest.raises(AssumptionError, match='^first$'):
        forced([None, first, second], False)
    assert forced([first, None, second], True, 'force:=true') == (
        'WARNING (force:=true): first', 'WARNING (force:=true): second')


# ------------------------------------------------------------- the manoeuvring spans


def test_excited_spans_follow_the_field_direction():
    """Analytic: a field direction fixed for 100 s, swinging +-30 deg for 60 s, fixed again;
    then a 20 s swing (shorter than the 30 s minimum) is not a span."""
    t = np.arange(0, 300, 0.1)
    angle = np.where((t >= 100) & (t < 160), np.radians(30) * np.sin(2 * np.pi * t / 7), 0.0)
    angle = np.where((t >= 200) & (t < 220), np.radians(30) * np.sin(2 * np.pi * t / 7), angle)
    b = np.stack([np.sin(angle), np.zeros_like(t), np.cos(angle)], axis=1) * 5e-5
    assert excited_spans(t, b) == [(pytest.approx(100.0), pytest.approx(159.9))]
    assert excited_spans(t, np.tile([0.0, 2e-5, -4.5e-5], (len(t), 1))) == []


def test_a_gentle_trim_between_rough_sea_lines_is_one_span():
    """Body-frame fields of an Earth field (inclination 73 deg) seen on straight legs rolling
    +-5 deg and pitching +-3 deg (periods 8 and 11 s), and 100-300 s on a gentle trim
    (2 deg/s heading, roll +-8 deg, pitch +-6 deg): its 30 s spread is ~2x the legs', not
    10x. The span found is the trim's, to a block."""
    t = np.arange(0, 400, 0.1)
    trim = (t >= 100) & (t < 300)
    heading = np.where(trim, 2.0 * (t - 100), 0.0)
    roll = np.where(trim, 8 * np.sin(2 * np.pi * t / 15), 5 * np.sin(2 * np.pi * t / 8))
    pitch = np.where(trim, 6 * np.sin(2 * np.pi * t / 23), 3 * np.sin(2 * np.pi * t / 11))
    body_to_world = Rotation.from_euler('ZYX', np.stack([heading, pitch, roll], 1), degrees=True)
    b = body_to_world.inv().apply(np.array([0.0, 15000.0, -48000.0]) * 1e-9)
    spans = excited_spans(t, b)
    assert len(spans) == 1
    assert abs(spans[0][0] - 100) <= 10 and abs(spans[0][1] - 299.9) <= 10
