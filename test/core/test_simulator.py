"""core/simulator.py: the simulator against physics it must obey (Earth's field rotated into
the body, independent dipole physics, eq. 10 written out here, each effect by its definition),
also across the joins between segments (where the pose jumps)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (Dipole, Effects, Scenario, SurveyLine, TetraGeometry, TrimManoeuvre,
                                    dipole_field, dipole_gradient, random_interference, rms_residual,
                                    simulate)
from tetra_gradiometer.io.scenario import scenario_from_dict

GEOMETRY = TetraGeometry.regular(0.5)
EARTH = np.array([1.2e-6, 1.5e-5, -4.9e-5])
EDDY_S = 3e-4


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
        # g_true by its definition (eq. 7 is the exact gradient of a field linear across the
        # array): fit B_s = B0 + G r_s to those four independent readings by least squares.
        design = np.column_stack([np.ones(4), GEOMETRY.positions])
        coef, *_ = np.linalg.lstsq(design, expected_fields, rcond=None)
        np.testing.assert_allclose(survey.g_true[n], coef[1:].T, rtol=1e-9,
                                   atol=1e-9 * np.abs(coef[1:]).max())
    # Differencing truncation is small against the signal at 30 m or more.
    assert rms_residual(survey.g_true, survey.g_analytic) < 0.05 * np.sqrt(np.mean(survey.g_analytic ** 2))


def _eq_10(interference, fields_true):
    """Eq. 10 written out: B_i' = B_i + K_i B^b + B_i^h, with B^b the clean field at sensor 1."""
    k, h = np.array(interference.k_soft), np.array(interference.b_hard)
    out = np.empty_like(fields_true)
    for n in range(len(fields_true)):
        for s in range(4):
            out[n, s] = fields_true[n, s] + k[s] @ fields_true[n, 0] + h[s]
    return out


def test_interference_and_noise_are_applied_as_specified():
    interference = random_interference(np.random.default_rng(3), reference_clean=False)
    clean = simulate(_scenario(interference=interference), np.random.default_rng(4))
    np.testing.assert_array_equal(clean.b_background, clean.fields_true[:, 0])
    expected = _eq_10(interference, clean.fields_true)
    assert np.abs(expected - clean.fields_true).max() > 100e-9  # the interference is there ...
    np.testing.assert_allclose(clean.fields_measured, expected, rtol=0, atol=1e-18)  # ... as eq. 10
    mission = simulate(_scenario(interference=interference, noise_t=0.2e-9), np.random.default_rng(4))
    residual = mission.fields_measured - _eq_10(interference, mission.fields_true)
    assert np.std(residual) == pytest.approx(0.2e-9, rel=0.05)
    assert abs(np.mean(residual)) < 0.02e-9


def test_each_effect_matches_its_definition():
    rng = np.random.default_rng(5)
    base = simulate(_scenario(), np.random.default_rng(6))
    # The delayed sensor reads now what it read 0.25 s ago without delay (40 Hz: 10 samples).
    fast = simulate(_scenario(sample_rate_hz=40.0), np.random.default_rng(6))
    skew = simulate(_scenario(sample_rate_hz=40.0, effects=Effects(time_skew=[0, 0, 0.25, 0])),
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
    with pytest.raises(ValueError, match=r'time_skew must have shape \(4,\)'):
        Effects(time_skew=[0.1, 0.2])
    with pytest.raises(ValueError, match='TrimManoeuvre.duration_s must be positive'):
        TrimManoeuvre(0.0)
    with pytest.raises(ValueError, match='SurveyLine.length_m must be positive'):
        SurveyLine((1.0, 2.0, 3.0), (1.0, 2.0, 3.0))


def _joined_scenario(eddy: bool):
    document = {
        'seed': 1, 'sample_rate_hz': 10, 'noise_nT': 0.0,
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'segments': [{'trim': {'duration_s': 30, 'center_m': [3000.0, 3000.0, -50.0]}},
                     {'line': {'start_m': [-50.0, 0.0, -50.0], 'end_m': [50.0, 0.0, -50.0]}},
                     {'trim': {'duration_s': 20, 'center_m': [0.0, 3000.0, -50.0], 'initial_heading_deg': 90}}],
    }
    if eddy:
        document['effects'] = {'eddy_current': {'coefficients_s': (np.eye(3)[None] * EDDY_S
                                                                   * np.ones((4, 1, 1))).tolist()}}
    return scenario_from_dict(document)[0]


def test_eddy_current_term_is_bounded_by_the_rotation_rate_also_at_segment_joins():
    with_eddy = simulate(_joined_scenario(True), np.random.default_rng(0))
    without = simulate(_joined_scenario(False), np.random.default_rng(0))
    eddy = with_eddy.fields_measured - without.fields_measured
    # Physics bound: in a uniform field the body-frame field only turns, |dB/dt| <= |B| w_max,
    # with w_max <= heading 6 deg/s + roll 25 deg * 2 pi / 11 s + pitch 20 deg * 2 pi / 17 s.
    w_max = np.radians(6.0 + 25.0 * 2 * np.pi / 11.0 + 20.0 * 2 * np.pi / 17.0)
    bound = EDDY_S * 50_000e-9 * w_max
    assert np.abs(eddy).max() <= bound
    assert np.abs(eddy).max() > 0.1 * bound
    # The term itself, sample by sample: EDDY_S dB^b/dt, the rate taken here by second-order
    # finite differences of the clean reference field within each segment (one-sided at the
    # joins), so a derivative across a join (a jump in pose) cannot pass.
    assert np.count_nonzero(np.diff(with_eddy.segment)) == 2
    for segment in np.unique(with_eddy.segment):
        rows = with_eddy.segment == segment
        rate = np.gradient(without.fields_true[rows, 0], with_eddy.t[rows], axis=0, edge_order=2)
        np.testing.assert_allclose(eddy[rows], np.broadcast_to(EDDY_S * rate[:, None], eddy[rows].shape),
                                   rtol=0, atol=0.01 * bound)


def test_time_skew_reads_the_same_trajectory_also_at_segment_joins():
    skew_s = 0.05
    scenario = _joined_scenario(False)
    document_skew = scenario_from_dict({
        'seed': 1, 'sample_rate_hz': 10, 'noise_nT': 0.0, 'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'segments': [{'trim': {'duration_s': 30, 'center_m': [3000.0, 3000.0, -50.0]}},
                     {'line': {'start_m': [-50.0, 0.0, -50.0], 'end_m': [50.0, 0.0, -50.0]}},
                     {'trim': {'duration_s': 20, 'center_m': [0.0, 3000.0, -50.0], 'initial_heading_deg': 90}}],
        'effects': {'time_skew': {'delay_s': [0.0, 0.0, 0.0, skew_s]}}})[0]
    skewed = simulate(document_skew, np.random.default_rng(0))
    plain = simulate(scenario, np.random.default_rng(0))
    change = skewed.fields_measured - plain.fields_measured
    assert np.abs(change[:, :3]).max() == 0.0
    # |B(t - tau) - B(t)| <= tau |B| w_max in a uniform field (as above).
    w_max = np.radians(6.0 + 25.0 * 2 * np.pi / 11.0 + 20.0 * 2 * np.pi / 17.0)
    assert np.abs(change[:, 3]).max() <= skew_s * 50_000e-9 * w_max
    assert np.abs(change[:, 3]).max() > 0.0


def test_effect_names_are_spelled_once_for_simulator_scenarios_and_the_discrepancy_library():
    import dataclasses

    from tetra_gradiometer.core.discrepancy import CANDIDATES
    from tetra_gradiometer.core.simulator import EFFECT_SPECS
    from tetra_gradiometer.io.scenario import EFFECT_KEYS

    assert [f.name for f in dataclasses.fields(Effects)] == list(EFFECT_SPECS)
    assert set(EFFECT_KEYS) == set(EFFECT_SPECS)
    rng = np.random.default_rng(0)
    for candidate in CANDIDATES:
        if candidate.simulated is not None:
            hidden = candidate.simulated.draw(rng, np.ones(4))
            assert set(hidden.effects) <= set(EFFECT_SPECS), candidate.name
            assert set(hidden.effects) <= {candidate.name}, candidate.name
