"""core/guidance: trim guidance against the simulator's truth. Deliberately poor trims get
the advice the physics asks for, following it reaches "enough", and the predicted errors
match what a calibration on those samples achieves on a simulated survey (fresh noise), and
the scatter of the parameters over noise seeds. The statistics equal the fit's own numbers
(noise estimate, standard errors), computed there by a QR of all the samples."""
import json

import numpy as np
import pytest

from tetra_gradiometer import core
from tetra_gradiometer.core import guidance
from tetra_gradiometer.core.identification import known_gradient_lstsq
from tetra_gradiometer.core.simulator import Scenario, SurveyLine, TrimManoeuvre, random_interference, simulate
from tetra_gradiometer.errors import InputError

GEOMETRY = core.TetraGeometry.regular(0.5)
EARTH = np.array([0.0, 2.0e-5, -4.5e-5])  # ENU, T: 20 000 nT north, 45 000 nT down
NOISE_T = 0.1e-9
RATE_HZ = 10.0
VEHICLE = random_interference(np.random.default_rng(1), reference_clean=False)


def fly(segments, seed):
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH, segments=tuple(segments), interference=VEHICLE,
                        noise_t=NOISE_T, sample_rate_hz=RATE_HZ)
    return simulate(scenario, np.random.default_rng(seed))


def measured(mission):
    return core.difference_tensor(mission.fields_measured, GEOMETRY), mission.fields_measured[:, 0]


def statistics(mission, attitude=True):
    g, b = measured(mission)
    return guidance.trim_statistics(b, g, GEOMETRY, orientation_xyzw=mission.orientation_xyzw if attitude else None)


def assess(stats):
    return guidance.assess(stats, GEOMETRY, EARTH, sample_rate_hz=RATE_HZ, sensor_noise_t=NOISE_T)


def survey_mission(seed):
    """Level lines on the 12 survey headings, rolling and pitching ±5° (the assessment's
    representative survey), fresh noise."""
    lines = []
    for heading in range(0, 360, 30):
        d = np.array([np.sin(np.radians(heading)), np.cos(np.radians(heading)), 0.0])  # compass -> ENU
        lines.append(SurveyLine(tuple(-30 * d + [0, 0, -50]), tuple(30 * d + [0, 0, -50]), speed_m_s=2.0,
                                roll_amplitude_deg=5.0, pitch_amplitude_deg=5.0, sway_period_s=7.0))
    return fly(lines, seed)


def achieved_rms(trim_mission, survey):
    """RMS of (compensated - g_true) over the survey with a calibration on the trim."""
    g, b = measured(trim_mission)
    fit = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=False)
    compensated = core.compensate_fields(survey.fields_measured, fit.parameters, GEOMETRY)
    return float(np.sqrt(np.mean((compensated - survey.g_true) ** 2))), fit


def test_a_trim_pitched_on_one_heading_without_roll_asks_for_roll_and_following_the_advice_is_enough():
    # Pitching on heading north keeps the body-frame field in the x-z plane (B_y = 0 on north
    # and south alike): the data cannot separate the y column of K from the offsets, and the
    # solver refuses them. Rolling puts 45 000 nT x sin(15°) across the vehicle on any heading.
    trim = TrimManoeuvre(60.0, roll_amplitude_deg=0.0, pitch_amplitude_deg=20.0, heading_rate_deg_s=0.0,
                         initial_heading_deg=90.0)  # simulator yaw 90° = compass north
    stats = statistics(fly([trim], 2))
    first = assess(stats)
    assert not first.enough and first.ratio > 100, first.text()
    assert first.advice is not None and first.advice.kind == 'roll', first.text()
    assert first.advice.text.startswith('roll ±15° on heading ')
    assert 'heading 1/12' in first.coverage.text and 'roll -5…5°' in first.coverage.text
    # Roll is worth clearly more than the best pitch or level-turn candidate.
    other = min(c.worst_sigma for c in first.candidates if c.kind != 'roll')
    floor2 = first.noise_floor**2
    assert (other**2 - floor2) > 1.3 * (first.advice.worst_sigma**2 - floor2)

    # Follow the advice in the simulator (fresh noise) until enough: one manoeuvre suffices.
    segments, assessment = [trim], first
    for step in range(3):
        if assessment.enough:
            break
        manoeuvre = assessment.advice.manoeuvre()
        segments.append(manoeuvre)
        stats = stats.plus(statistics(fly([manoeuvre], 10 + step)))
        assessment = assess(stats)
    assert assessment.enough and len(segments) == 2, assessment.text()
    assert assessment.ratio <= guidance.ENOUGH_RATIO and assessment.advice is None
    assert 'roll -15…15°' in assessment.coverage.text

    # At "enough", the predicted sigma is what a calibration on those samples achieves on a
    # survey flown with fresh noise (the noise floor there included).
    trim_mission = fly(segments, 3)
    achieved, fit = achieved_rms(trim_mission, survey_mission(99))
    predicted = assess(statistics(trim_mission)).predicted_sigma
    assert abs(predicted / achieved - 1.0) < 0.2, (predicted, achieved)
    assert fit.rank == 36


def test_a_level_turn_without_roll_or_pitch_asks_for_a_tilt():
    trim = TrimManoeuvre(60.0, roll_amplitude_deg=0.0, pitch_amplitude_deg=0.0, heading_rate_deg_s=6.0)
    result = assess(statistics(fly([trim], 4)))
    assert not result.enough and result.ratio > 10
    assert result.advice.kind in ('roll', 'pitch'), result.text()
    assert 'heading 12/12' in result.coverage.text and 'pitch -5…5°' in result.coverage.text


@pytest.mark.parametrize('trim', [
    TrimManoeuvre(10.0, heading_rate_deg_s=6.0),  # rich but short
    TrimManoeuvre(30.0, roll_amplitude_deg=0.0, heading_rate_deg_s=1.0, initial_heading_deg=45.0),  # narrow
])
def test_predicted_errors_of_a_short_trim_match_the_survey_error_and_the_parameter_scatter_over_seeds(trim):
    survey = survey_mission(99)
    squares, thetas, predicted = [], [], []
    for seed in range(20, 32):
        mission = fly([trim], seed)
        achieved, fit = achieved_rms(mission, survey)
        squares.append(achieved**2)
        thetas.append(fit.parameters.to_vector(symmetric=False))
        predicted.append(assess(statistics(mission)))
    sigma = np.sqrt(np.mean([p.predicted_sigma**2 for p in predicted]))
    achieved = np.sqrt(np.mean(squares))
    floor = predicted[0].noise_floor
    assert achieved > 1.1 * floor  # a calibration error the prediction must account for
    assert not any(p.enough for p in predicted)
    assert abs(sigma / achieved - 1.0) < 0.2, (sigma, achieved, floor)
    # Predicted parameter sigma against the scatter over 12 seeds (each ±21 %): the median.
    ratio = np.median(predicted[0].parameter_sigma / np.std(thetas, axis=0, ddof=1))
    assert 0.8 < ratio < 1.25, ratio


def test_the_statistics_give_the_fits_noise_estimate_and_standard_errors():
    mission = fly([TrimManoeuvre(40.0)], 5)
    g, b = measured(mission)
    fit = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=False)
    result = assess(statistics(mission))
    assert result.noise_source == 'fit residual'
    assert result.sensor_noise * 1e9 == pytest.approx(fit.details['sensor_noise_nT'], rel=1e-6)
    assert result.sensor_noise == pytest.approx(NOISE_T, rel=0.05)  # and the simulator's
    # The prior only bounds unseen directions: on a rich trim the fit's covariance stands.
    np.testing.assert_allclose(result.parameter_sigma, fit.standard_errors, rtol=1e-4)
    assert result.condition_number == pytest.approx(fit.details['attitude_coverage_condition'], rel=1e-6)
    symmetric = guidance.assess(statistics(mission), GEOMETRY, EARTH, sample_rate_hz=RATE_HZ,
                                sensor_noise_t=NOISE_T, symmetric=True)
    fit27 = known_gradient_lstsq(g, b, GEOMETRY, symmetric_k=True)
    np.testing.assert_allclose(symmetric.parameter_sigma, fit27.standard_errors, rtol=1e-4)


def test_sums_of_statistics_are_the_statistics_of_the_union_and_removal_undoes_addition():
    mission = fly([TrimManoeuvre(30.0)], 6)
    g, b = measured(mission)
    q = mission.orientation_xyzw
    whole = guidance.trim_statistics(b, g, GEOMETRY, orientation_xyzw=q)
    first = guidance.trim_statistics(b[:100], g[:100], GEOMETRY, orientation_xyzw=q[:100])
    rest = guidance.trim_statistics(b[100:], g[100:], GEOMETRY, orientation_xyzw=q[100:])  # its own reference
    joined = first.plus(rest)
    removed = whole.minus(guidance.trim_statistics(b[:100], g[:100], GEOMETRY, orientation_xyzw=q[:100]))
    for got, want in ((joined, whole), (removed, rest._aligned(whole.reference))):
        assert got.n == want.n
        np.testing.assert_allclose(got.gram, want.gram, rtol=1e-12)
        np.testing.assert_allclose(got.cross, want.cross, rtol=1e-9, atol=1e-12 * np.abs(want.cross).max())
        assert got.sum_sq == pytest.approx(want.sum_sq, rel=1e-9)
        assert np.array_equal(got.attitude_counts, want.attitude_counts)
    assert assess(removed).sensor_noise == pytest.approx(assess(rest).sensor_noise, rel=1e-6)
    assert whole.attitude_counts.sum() == len(b) and whole.direction_counts.sum() == len(b)


def test_without_attitude_coverage_is_of_the_field_direction_and_says_so():
    mission = fly([TrimManoeuvre(30.0)], 7)
    result = assess(statistics(mission, attitude=False))
    assert result.coverage.source == 'field direction'
    assert result.coverage.text.startswith('no attitude (no /odom)')
    # NaN rows (odom missing for those samples) count as unknown attitude, not as a bin.
    q = mission.orientation_xyzw.copy()
    q[::2] = np.nan
    g, b = measured(mission)
    assert guidance.trim_statistics(b, g, GEOMETRY, orientation_xyzw=q).attitude_counts.sum() == len(b) // 2


def test_compass_heading_roll_and_pitch_of_the_simulators_attitudes():
    # A vehicle heading north-east (compass 45°): its body x axis points to (east, north) > 0.
    rotation = guidance.attitude_rotation(45.0, 10.0, -7.0)
    np.testing.assert_allclose(rotation.apply([1.0, 0.0, 0.0])[0][:2], [np.cos(np.radians(7))] * 2 / np.sqrt(2),
                               atol=1e-12)
    angles = guidance.heading_roll_pitch(rotation.as_quat())
    np.testing.assert_allclose(angles, [[45.0, 10.0, -7.0]], atol=1e-9)
    # The simulator's yaw is counter-clockwise from east: a trim started at yaw 0 heads east.
    mission = fly([TrimManoeuvre(1.0, heading_rate_deg_s=0.0, roll_amplitude_deg=0.0, pitch_amplitude_deg=0.0)], 1)
    np.testing.assert_allclose(guidance.heading_roll_pitch(mission.orientation_xyzw)[:, 0], 90.0)


def test_the_assessment_is_plain_json_in_report_units():
    result = assess(statistics(fly([TrimManoeuvre(20.0, roll_amplitude_deg=0.0, heading_rate_deg_s=0.0)], 8)))
    document = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert document['enough'] is False and document['advice']['text'] == result.advice.text
    assert document['noise_floor_nT_per_m'] == pytest.approx(result.noise_floor * 1e9)
    assert len(document['survey']['sigma_per_heading_nT_per_m']) == 12
    assert np.array(document['coverage']['counts']).shape == (12, 5, 5)
    assert np.array(document['parameter_sigma']['k_soft']).shape == (3, 3, 3)
    empty = assess(guidance.TrimStatistics.empty())
    assert empty.noise_source == 'configured' and empty.to_dict()['condition_number'] is None


def test_mismatched_samples_are_refused_naming_them():
    g, b = measured(fly([TrimManoeuvre(2.0)], 9))
    with pytest.raises(InputError, match='sample counts differ'):
        guidance.trim_statistics(b[:-1], g, GEOMETRY)
    with pytest.raises(InputError, match=r'earth_field_enu must have shape \(3,\)'):
        guidance.assess(guidance.trim_statistics(b, g, GEOMETRY), GEOMETRY, [0.0, 1.0], sample_rate_hz=10.0,
                        sensor_noise_t=NOISE_T)
