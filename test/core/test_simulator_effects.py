"""The simulator's vehicle effects against independent truth: currents per channel (the
battery carries the thrusters and the hotel load; a thruster follows speed and manoeuvre),
the field of each current channel, each sensor's 3x3 response (scale factor,
non-orthogonality, misalignment) written out by hand, the registry as the one source of the
operational effects' physics, and old scenarios meaning what they meant."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (CurrentProfile, Effects, Scenario, SurveyLine, TetraGeometry, Thruster,
                                    TrimManoeuvre, simulate)
from tetra_gradiometer.core.effects import EFFECTS
from tetra_gradiometer.core.simulated_effects import ADDITIVE, EFFECT_SPECS, axes_matrix, sensor_matrices
from tetra_gradiometer.errors import InputError, ScenarioError
from tetra_gradiometer.io.scenario import scenario_from_dict

GEOMETRY = TetraGeometry.regular(0.5)
EARTH = np.array([1.2e-6, 1.5e-5, -4.9e-5])
TRIM = TrimManoeuvre(40.0, center=(5000.0, 0.0, -30.0))
LINE = SurveyLine((4000.0, 100.0, -30.0), (4100.0, 100.0, -30.0), speed_m_s=2.0)
THRUSTERS = (Thruster('/thruster_1/battery_state', turn_a_per_deg_s=-0.04),
             Thruster('/thruster_2/battery_state', turn_a_per_deg_s=0.04, speed_a_per_m2_s2=-2.6,
                      step_amplitude_a=1.5, step_s=13.0))


def _scenario(**overrides):
    base = dict(geometry=GEOMETRY, earth_field_enu=EARTH, sample_rate_hz=10.0, noise_t=0.0,
                segments=(TRIM, LINE))
    base.update(overrides)
    return Scenario(**base)


def _hotel(seed, profile, duration_s):
    """The hotel load as scenarios always drew it: levels every step_s, linearly joined."""
    knots = np.arange(0.0, duration_s + 2 * profile.step_s, profile.step_s) - profile.step_s
    levels = profile.base_a + profile.step_amplitude_a * np.random.default_rng(seed).uniform(-1, 1, len(knots))
    return lambda t: np.interp(t, knots, levels)


def test_an_old_scenario_draws_the_same_battery_current_and_has_one_channel():
    mission = simulate(_scenario(), np.random.default_rng(4))
    assert mission.current_topics == ('/battery_state',)
    assert mission.currents_a.shape == (len(mission), 1)
    np.testing.assert_array_equal(mission.currents_a[:, 0], mission.current_a)
    np.testing.assert_array_equal(mission.current_a, _hotel(4, CurrentProfile(), 90.0)(mission.t))


def test_the_battery_carries_the_thrusters_and_the_hotel_load():
    profile = CurrentProfile(base_a=-3.0, step_amplitude_a=1.0, step_s=20.0)
    alone = simulate(_scenario(current=profile), np.random.default_rng(5))
    driven = simulate(_scenario(current=CurrentProfile(-3.0, 1.0, 20.0, THRUSTERS)), np.random.default_rng(5))
    assert driven.current_topics == ('/battery_state', '/thruster_1/battery_state', '/thruster_2/battery_state')
    battery, thrusters = driven.currents_a[:, 0], driven.currents_a[:, 1:]
    np.testing.assert_array_equal(battery, driven.current_a)
    # The hotel load is drawn first: without thrusters it is the whole battery current.
    np.testing.assert_allclose(battery - thrusters.sum(axis=1), alone.current_a, rtol=0, atol=1e-12)
    assert np.all(thrusters <= 0) and np.all(thrusters < -1.0)
    # The thrusters' channels are not one signal scaled: each has its own steps and turn.
    assert abs(np.corrcoef(thrusters.T)[0, 1]) < 0.99
    # The rest of the mission is the same: the thrusters' draws come after the hotel load's.
    np.testing.assert_array_equal(driven.fields_true, alone.fields_true)


def test_a_thruster_follows_the_speed_and_the_manoeuvre():
    thruster = Thruster('/t', idle_a=-0.4, speed_a_per_m2_s2=-2.0, activity_a_per_deg_s=(-0.1, -0.07, -0.05),
                        turn_a_per_deg_s=-0.02, step_amplitude_a=0.0)
    mission = simulate(_scenario(current=CurrentProfile(thrusters=(thruster,))), np.random.default_rng(1))
    current = mission.currents_a[:, 1]
    t, trim = mission.t, mission.segment == 0
    # On the trim (speed 1 m/s): a constant 6 deg/s turn, roll and pitch sinusoids whose
    # rates are written here from the manoeuvre's amplitudes and periods.
    roll_rate = 25.0 * 2 * np.pi / 11.0 * np.cos(2 * np.pi * t / 11.0)
    pitch_rate = 20.0 * 2 * np.pi / 17.0 * np.cos(2 * np.pi * t / 17.0)
    expected = -0.4 - 2.0 * 1.0**2 - 0.1 * 6.0 - 0.07 * np.abs(pitch_rate) - 0.05 * np.abs(roll_rate) - 0.02 * 6.0
    np.testing.assert_allclose(current[trim], expected[trim], atol=1e-5)
    # On the straight line at 2 m/s, no sway: idle plus the speed's share.
    np.testing.assert_allclose(current[~trim], -0.4 - 2.0 * 2.0**2, atol=1e-9)


def test_a_thruster_never_charges_the_battery_and_steps_are_held():
    thruster = Thruster('/t', idle_a=0.0, speed_a_per_m2_s2=0.0, activity_a_per_deg_s=(0, 0, 0),
                        step_amplitude_a=2.0, step_s=10.0, ramp_s=0.5)
    mission = simulate(_scenario(current=CurrentProfile(thrusters=(thruster,))), np.random.default_rng(2))
    current = mission.currents_a[:, 1]
    assert np.all(current <= 0) and np.any(current == 0) and np.any(current < -0.5)
    # Held between ramps: 0.5 s after each 10 s boundary to the next boundary.
    for k in range(1, 8):
        held = (mission.t >= 10.0 * k - 10.0 + 0.5 + 1e-9) & (mission.t <= 10.0 * k)
        assert np.ptp(current[held]) == 0.0


def test_each_current_channel_has_its_own_field():
    per_amp = np.random.default_rng(3).normal(0, 1e-9, (4, 3, 3))
    profile = CurrentProfile(-3.0, 1.0, 20.0, THRUSTERS)
    base = simulate(_scenario(current=profile), np.random.default_rng(6))
    loaded = simulate(_scenario(current=profile, effects=Effects(vehicle_current=per_amp)), np.random.default_rng(6))
    expected = np.zeros_like(base.fields_measured)
    for j in range(3):
        expected += loaded.currents_a[:, j, None, None] * per_amp[None, :, :, j]
    np.testing.assert_allclose(loaded.fields_measured - base.fields_measured, expected, rtol=0, atol=1e-20)


def test_vehicle_current_needs_one_column_per_channel():
    with pytest.raises(InputError, match=r'2 column\(s\) .* 3 current channel\(s\)'):
        _scenario(current=CurrentProfile(thrusters=THRUSTERS), effects=Effects(vehicle_current=np.zeros((4, 3, 2))))
    with pytest.raises(InputError, match=r'vehicle_current must have shape \(4, 3, m\) or \(4, 3\)'):
        Effects(vehicle_current=np.zeros((4, 2)))
    with pytest.raises(InputError, match='distinct topics'):
        CurrentProfile(thrusters=(Thruster('/battery_state'),))
    with pytest.raises(InputError, match='starting with /'):
        Thruster('thruster_1')


def test_scale_and_non_orthogonality_are_the_hand_written_matrix():
    scale = np.zeros((4, 3))
    angles = np.zeros((4, 3))
    scale[2] = [1.5e-3, -2.0e-3, 0.7e-3]
    angles[2] = np.radians([0.8, -1.1, 0.4])
    a, b, c = (math.sin(math.radians(x)) for x in (0.8, -1.1, 0.4))
    by_hand = np.array([[1.0015, 0.0, 0.0],
                        [0.998 * a, 0.998 * math.sqrt(1 - a * a), 0.0],
                        [1.0007 * b, 1.0007 * c, 1.0007 * math.sqrt(1 - b * b - c * c)]])
    effects = Effects(scale_factor=scale, non_orthogonality=angles)
    np.testing.assert_allclose(sensor_matrices(effects)[2], by_hand, rtol=1e-15, atol=1e-18)
    np.testing.assert_array_equal(sensor_matrices(effects)[0], np.eye(3))
    mission = simulate(_scenario(effects=effects), np.random.default_rng(0))
    np.testing.assert_allclose(mission.fields_measured[:, 2], mission.fields_true[:, 2] @ by_hand.T,
                               rtol=0, atol=1e-18)
    np.testing.assert_array_equal(mission.fields_measured[:, [0, 1, 3]], mission.fields_true[:, [0, 1, 3]])
    # Each row is the unit vector of one of the sensor's axes.
    np.testing.assert_allclose(np.linalg.norm(axes_matrix(angles[2]), axis=1), 1.0, rtol=1e-15)


def test_the_sensor_matrix_is_scale_times_axes_times_misalignment():
    rng = np.random.default_rng(9)
    scale, angles, rotation = rng.normal(0, 1e-3, (4, 3)), rng.normal(0, 0.01, (4, 3)), rng.normal(0, 0.01, (4, 3))
    effects = Effects(scale_factor=scale, non_orthogonality=angles, sensor_misalignment=rotation)
    field = np.array([1e-5, -2e-5, 4e-5])
    for s in range(4):
        rotated = Rotation.from_rotvec(rotation[s]).apply(field)   # the misaligned triad's frame
        axes = axes_matrix(angles[s])
        reading = (1 + scale[s]) * (axes @ rotated)                 # each axis along its unit vector
        np.testing.assert_allclose(sensor_matrices(effects)[s] @ field, reading, rtol=1e-14)
    assert sensor_matrices(Effects()) is None
    with pytest.raises(InputError, match='scale_factor must be > -1'):
        Effects(scale_factor=np.full((4, 3), -1.0))
    with pytest.raises(InputError, match='within 45 deg'):
        Effects(non_orthogonality=np.full((4, 3), 1.0))


def test_the_operational_effects_are_the_registrys(monkeypatch):
    assert set(ADDITIVE) == {name for name, effect in EFFECTS.items() if effect.simulation is not None}
    for name in ADDITIVE:
        assert EFFECT_SPECS[name] is EFFECTS[name].simulation
    # The simulator adds what the registry's effect says, nothing of its own.
    drift = np.full((4, 3), 1e-10)
    warm = _scenario(effects=Effects(thermal_drift=drift))
    effect = EFFECTS['thermal_drift']
    monkeypatch.setattr(type(effect), 'simulated_regressors', lambda self, truth: np.full((len(truth.t_s), 1), 2.0))
    mission = simulate(warm, np.random.default_rng(0))
    np.testing.assert_allclose(mission.fields_measured - mission.fields_true, 2e-10, rtol=1e-6)


def test_scenario_files_give_thrusters_and_per_channel_coefficients():
    document = {
        'segments': [{'trim': {'duration_s': 30}}],
        'current': {'base_a': -2.0, 'thrusters': [{'topic': '/thruster_1/battery_state', 'idle_a': -0.3},
                                                  {'topic': '/thruster_2/battery_state',
                                                   'activity_a_per_deg_s': [-0.1, 0, 0]}]},
        'effects': {'vehicle_current': {'nT_per_A': np.full((4, 3, 3), 0.5).tolist()},
                    'scale_factor': {'error_ppm': np.full((4, 3), 800.0).tolist()},
                    'non_orthogonality': {'angles_deg': np.full((4, 3), 0.2).tolist()}},
    }
    scenario, _ = scenario_from_dict(document)
    assert scenario.current.topics == ('/battery_state', '/thruster_1/battery_state', '/thruster_2/battery_state')
    assert scenario.current.thrusters[1].activity_a_per_deg_s == (-0.1, 0.0, 0.0)
    np.testing.assert_allclose(scenario.effects.vehicle_current, 0.5e-9)
    np.testing.assert_allclose(scenario.effects.scale_factor, 8e-4)
    np.testing.assert_allclose(scenario.effects.non_orthogonality, np.radians(0.2))
    # An old file: one current profile, 4x3 nT/A, is the battery's channel alone.
    old = {'segments': [{'trim': {'duration_s': 30}}], 'current': {'base_a': -5.0},
           'effects': {'vehicle_current': {'nT_per_A': np.full((4, 3), 0.5).tolist()}}}
    old_scenario, _ = scenario_from_dict(old)
    assert old_scenario.current.topics == ('/battery_state',)
    as_columns = scenario_from_dict({**old, 'effects': {'vehicle_current': {
        'nT_per_A': np.full((4, 3, 1), 0.5).tolist()}}})[0]
    np.testing.assert_array_equal(simulate(old_scenario, np.random.default_rng(1)).fields_measured,
                                  simulate(as_columns, np.random.default_rng(1)).fields_measured)


@pytest.mark.parametrize('current, message', [
    ({'thrusters': [{'topic': '/odom'}]}, r'thrusters\[0\].topic: /odom is a topic of the data contract'),
    ({'thrusters': [{'topic': '/t', 'rpm': 3}]}, r"thrusters\[0\]: unknown \['rpm'\]"),
    ({'thrusters': [{'idle_a': -1}]}, r'thrusters\[0\]: expected a mapping with a "topic"'),
    ({'thrusters': [{'topic': '/t', 'step_s': 0}]}, r'thrusters\[0\]: .*step_s must be positive'),
    ({'thrusters': {'topic': '/t'}}, 'current.thrusters: expected a list'),
])
def test_scenario_files_refuse_bad_thrusters(current, message):
    with pytest.raises(ScenarioError, match=message):
        scenario_from_dict({'segments': [{'trim': {'duration_s': 30}}], 'current': current})


def test_scenario_files_refuse_coefficients_for_other_channels():
    document = {'segments': [{'trim': {'duration_s': 30}}],
                'current': {'thrusters': [{'topic': '/t'}]},
                'effects': {'vehicle_current': {'nT_per_A': np.full((4, 3), 0.5).tolist()}}}
    with pytest.raises(ScenarioError, match=r'1 column\(s\) per sensor and axis for 2 current channel'):
        scenario_from_dict(document)


def test_the_shipped_scenario_has_every_effect_and_three_current_channels():
    from pathlib import Path

    from tetra_gradiometer.io.scenario import load_scenario

    scenario, _ = load_scenario(Path(__file__).parents[2] / 'config/scenarios/thrusters_and_sensor_errors.yaml')
    assert set(scenario.effects.active()) == set(EFFECT_SPECS) - {'time_skew'}
    assert scenario.current.topics == ('/battery_state', '/thruster_port/battery_state',
                                       '/thruster_starboard/battery_state')
    assert scenario.effects.vehicle_current.shape == (4, 3, 3)
