"""Metrics by hand and by Monte Carlo; the simulator against physics it must obey."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (Dipole, Effects, Scenario, SurveyLine, TetraGeometry, TrimManoeuvre,
                                    compensated_percent, difference_tensor, dipole_field, dipole_gradient,
                                    epsilon, improvement_ratio, noise_floor, random_interference,
                                    rms_residual, simulate)

GEOMETRY = TetraGeometry.regular(0.5)
EARTH = np.array([1.2e-6, 1.5e-5, -4.9e-5])


def _diag(values):
    return np.array([np.diag(v) for v in values], dtype=float)


def test_epsilon_and_percent_by_hand():
    g_true = _diag([[1, 0, 0], [0, 2, 0]])
    g_before = _diag([[3, 0, 0], [0, 4, 0]])   # norms 3, 4 vs true 1, 2
    g_after = _diag([[1.5, 0, 0], [0, 2.2, 0]])  # norms 1.5, 2.2
    expected = np.mean([0.5 / 2.0, 0.2 / 2.0])
    assert epsilon(g_before, g_after, g_true) == pytest.approx(expected)
    assert compensated_percent(expected) == pytest.approx(100 * (1 - expected))
    assert rms_residual(g_after, g_true) == pytest.approx(np.sqrt((0.25 + 0.04) / 18))
    assert improvement_ratio(g_before, g_after, g_true) == pytest.approx(np.sqrt((4 + 4) / (0.25 + 0.04)))


def test_epsilon_refuses_an_undefined_ratio():
    g = _diag([[1, 0, 0]])
    with pytest.raises(ValueError, match='undefined'):
        epsilon(g, g, g)


def test_noise_floor_matches_monte_carlo_and_the_regular_tetrahedron_rule():
    rng = np.random.default_rng(0)
    sigma = 0.1e-9
    noise = rng.normal(0, sigma, (200_000, 4, 3))
    simulated = np.sqrt(np.mean(difference_tensor(noise, GEOMETRY) ** 2))
    assert noise_floor(sigma, GEOMETRY) == pytest.approx(simulated, rel=0.01)
    assert noise_floor(sigma, GEOMETRY) == pytest.approx(1.42 * sigma / 0.5, rel=0.01)


def _scenario(**overrides):
    base = dict(geometry=GEOMETRY, earth_field_enu=EARTH, sample_rate_hz=10.0, noise_t=0.0,
                segments=[TrimManoeuvre(60.0, center=(5000.0, 0.0, -30.0)),
                          SurveyLine((-100.0, 25.0, -30.0), (100.0, 25.0, -30.0))],
                dipoles=[Dipole([0.0, 0.0, -60.0], [2e4, -1e4, 3e4])])
    base.update(overrides)
    return Scenario(**base)


def test_clean_mission_is_earth_rotated_into_the_body_far_from_targets():
    mission = simulate(_scenario(), np.random.default_rng(1))
    trim = mission.select(mission.segment == 0)
    rotation = Rotation.from_quat(trim.orientation_xyzw)
    np.testing.assert_allclose(trim.b_background, rotation.inv().apply(EARTH), atol=1e-12)
    np.testing.assert_allclose(trim.fields_measured, trim.fields_true)
    # The trim manoeuvre covers headings and rolls/pitches of its stated amplitudes.
    yaw, pitch, roll = rotation.as_euler('ZYX', degrees=True).T
    assert np.ptp(np.unwrap(np.radians(yaw))) > np.radians(300)
    assert roll.max() == pytest.approx(25.0, abs=0.5) and pitch.max() == pytest.approx(20.0, abs=0.5)


def test_truth_tensors_agree_with_independent_dipole_physics():
    mission = simulate(_scenario(), np.random.default_rng(2))
    survey = mission.select(mission.segment == 1)
    np.testing.assert_allclose(survey.g_true, difference_tensor(survey.fields_true, GEOMETRY))
    moment, source = np.array([2e4, -1e4, 3e4]), np.array([0.0, 0.0, -60.0])
    for n in range(0, len(survey), 37):
        # Independent route: put the dipole in the body frame (moment and position rotated
        # by R^T) and evaluate there; the simulator works in the world frame and rotates after.
        body_to_world = Rotation.from_quat(survey.orientation_xyzw[n])
        sensors_world = survey.position_enu[n] + body_to_world.apply(np.array(GEOMETRY.positions))
        source_body = body_to_world.inv().apply(source - survey.position_enu[n])
        moment_body = body_to_world.inv().apply(moment)
        np.testing.assert_allclose(
            survey.g_analytic[n], dipole_gradient(GEOMETRY.positions.mean(axis=0)[None], moment_body, source_body)[0],
            rtol=1e-9, atol=1e-15)
        expected_fields = body_to_world.inv().apply(EARTH + dipole_field(sensors_world, moment, source))
        np.testing.assert_allclose(survey.fields_true[n], expected_fields, rtol=1e-12, atol=1e-15)
    # Differencing truncation is small against the signal at 30 m or more.
    assert rms_residual(survey.g_true, survey.g_analytic) < 0.05 * np.sqrt(np.mean(survey.g_analytic ** 2))


def test_interference_and_noise_are_applied_as_specified():
    interference = random_interference(np.random.default_rng(3), reference_clean=False)
    mission = simulate(_scenario(interference=interference, noise_t=0.2e-9), np.random.default_rng(4))
    expected = interference.apply(mission.fields_true, mission.b_background)
    residual = mission.fields_measured - expected
    assert np.std(residual) == pytest.approx(0.2e-9, rel=0.05)
    assert abs(np.mean(residual)) < 0.02e-9


def test_each_effect_matches_its_definition():
    rng = np.random.default_rng(5)
    base = simulate(_scenario(), np.random.default_rng(6))
    # The delayed sensor reads now what it read 0.25 s ago without delay (40 Hz: 10 samples).
    fast = simulate(_scenario(sample_rate_hz=40.0), np.random.default_rng(6))
    skew = simulate(_scenario(sample_rate_hz=40.0, effects=Effects(time_skew_s=[0, 0, 0.25, 0])),
                    np.random.default_rng(6))
    np.testing.assert_allclose(skew.fields_measured[10:2000, 2], fast.fields_measured[:1990, 2], rtol=1e-12)
    np.testing.assert_array_equal(skew.fields_measured[:, 1], fast.fields_measured[:, 1])

    angle = np.zeros((4, 3))
    angle[3] = np.radians([0.5, -0.3, 0.2])
    tilted = simulate(_scenario(effects=Effects(sensor_misalignment=angle)), np.random.default_rng(6))
    np.testing.assert_allclose(np.linalg.norm(tilted.fields_measured, axis=2),
                               np.linalg.norm(base.fields_measured, axis=2), rtol=1e-12)
    assert np.abs(tilted.fields_measured[:, 3] - base.fields_measured[:, 3]).max() > 1e-7

    drift = rng.normal(0, 1e-9, (4, 3))
    warm = simulate(_scenario(effects=Effects(thermal_drift=drift)), np.random.default_rng(6))
    excess = warm.temperature_c - 10.0
    np.testing.assert_allclose(warm.fields_measured - base.fields_measured,
                               excess[:, None, None] * drift[None], atol=1e-18)

    per_amp = rng.normal(0, 1e-9, (4, 3))
    loaded = simulate(_scenario(effects=Effects(vehicle_current=per_amp)), np.random.default_rng(6))
    np.testing.assert_allclose(loaded.fields_measured - base.fields_measured,
                               loaded.current_a[:, None, None] * per_amp[None], atol=1e-18)
    assert np.all(loaded.current_a < 0)

    eddy = np.zeros((4, 3, 3))
    eddy[1] = np.eye(3) * 0.05
    swirled = simulate(_scenario(effects=Effects(eddy_current=eddy)), np.random.default_rng(6))
    rate = np.gradient(base.b_background, base.t, axis=0)
    inner = slice(5, 595)  # inside the trim, away from the segment boundary
    np.testing.assert_allclose((swirled.fields_measured - base.fields_measured)[inner, 1],
                               0.05 * rate[inner], atol=0.05 * np.abs(rate).max() * 0.02)


def test_scenario_validation():
    with pytest.raises(ValueError, match='at least one segment'):
        _scenario(segments=[])
    with pytest.raises(ValueError, match=r'time_skew_s must have shape \(4,\)'):
        Effects(time_skew_s=[0.1, 0.2])
    with pytest.raises(ValueError, match='TrimManoeuvre.duration_s must be positive'):
        TrimManoeuvre(0.0)
    with pytest.raises(ValueError, match='SurveyLine.length_m must be positive'):
        SurveyLine((1.0, 2.0, 3.0), (1.0, 2.0, 3.0))
