"""core/clocks.py and the simulator's sensor clocks and regional gradient, against truth
from outside the code: the requested clock parameters measured back from the stamps, the
binomial law of message loss, the field model ``R^T (B_earth + G_w x)`` evaluated here with
scipy, and ``R^T G_w R`` for the gradient. Also the scenario file keys of both."""

import copy
import dataclasses
import textwrap

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

import tetra_gradiometer.io.scenario as scenario_io
from tetra_gradiometer.core import (
    Dipole,
    Effects,
    Scenario,
    SensorClocks,
    SensorStream,
    SurveyLine,
    TetraGeometry,
    TrimManoeuvre,
    dipole_field,
    simulate,
)
from tetra_gradiometer.errors import InputError, ScenarioError
from tetra_gradiometer.io.scenario import (
    DEFAULT_SCENARIO,
    load_scenario,
    load_scenario_or_default,
    scenario_from_dict,
)

EARTH = np.array([1.2e-6, 1.5e-5, -4.9e-5])
#: A regional gradient, T/m: symmetric and traceless.
G_WORLD = np.array([[2.0, 0.7, -0.4], [0.7, -3.0, 1.1], [-0.4, 1.1, 1.0]]) * 1e-9
IRREGULAR = TetraGeometry(
    np.array([[0.0, 0.0, 0.0], [0.55, 0.02, 0.05], [0.1, 0.62, -0.03], [0.2, 0.15, 0.45]])
)


def _scenario(**overrides):
    base = dict(
        geometry=TetraGeometry.regular(0.5),
        earth_field_enu=EARTH,
        sample_rate_hz=100.0,
        noise_t=0.0,
        segments=[TrimManoeuvre(60.0, center=(300.0, -200.0, -30.0))],
    )
    base.update(overrides)
    return Scenario(**base)


def _segments_at(scenario, t):
    """Index of the segment flown at absolute times ``t`` (s), and the segments' starts."""
    starts = np.cumsum([0.0] + [s.duration_s for s in scenario.segments])
    which = np.clip(np.searchsorted(starts, t, side='right') - 1, 0, len(scenario.segments) - 1)
    return which, starts


def _clean_reading(scenario, t, sensor, delay=0.0):
    """``R^T (B_earth + G_w x_s + dipoles(x_s))`` (n, 3) T of ``sensor`` at ``t - delay``,
    posed by the segment flown at ``t`` (its own ``pose``, as the simulator's time skew keeps
    to one segment): the field model written out independently of the simulator."""
    which, starts = _segments_at(scenario, t)
    out = np.empty((len(t), 3))
    for n, (time, segment) in enumerate(zip(t, which, strict=True)):
        local = np.array([time - delay - starts[segment]])
        position, euler = scenario.segments[segment].pose(local)
        body_to_world = Rotation.from_euler('ZYX', euler[0])
        x = position[0] + body_to_world.apply(np.array(scenario.geometry.positions[sensor]))
        world = EARTH + G_WORLD @ x
        for dipole in scenario.dipoles:
            world = world + dipole_field(x[None], dipole.moment, dipole.position)[0]
        out[n] = body_to_world.inv().apply(world)
    return out


# -- clocks: instants, loss, rates ---------------------------------------------------------


def test_stream_instants_follow_the_requested_offset_rate_drift_and_jitter():
    offset = np.array([0.0, 0.5e-3, 2e-3, 4e-3])
    drift = np.array([0.0, 0.0, -30.0, 50.0])
    jitter = 0.2e-3
    clocks = SensorClocks(offset_s=offset, jitter_s=jitter, drift_ppm=drift)
    mission = simulate(_scenario(clocks=clocks), np.random.default_rng(11))
    streams = mission.streams
    assert len(streams) == 4
    np.testing.assert_array_equal(mission.t, streams[0].t)  # no loss: sensor 1 is t
    for sensor, stream in enumerate(streams):
        t = stream.t
        assert np.all(np.diff(t) > 0) and t[0] >= 0 and t[-1] < 60.0
        # Fit t = a + b k: a is the offset, 1/b the rate, the residual the jitter.
        k = np.round((t - offset[sensor]) * 100.0)
        b, a = np.polyfit(k, t, 1)
        residual = t - (a + b * k)
        n = len(t)
        assert n == pytest.approx(6000, abs=2)
        assert abs(a - offset[sensor]) < 5 * 2 * jitter / np.sqrt(n)
        measured_ppm = (1.0 / b / 100.0 - 1.0) * 1e6
        assert measured_ppm == pytest.approx(drift[sensor], abs=1.0)
        assert np.std(residual) == pytest.approx(jitter, rel=0.06)
        assert abs(np.median(residual)) < 5 * 1.26 * jitter / np.sqrt(n)
    # Sensor 2 against sensor 1, sample by sample (same rate, no drift): the median offset
    # is the requested 0.5 ms, the spread the two jitters combined.
    first, second = streams[0].t, streams[1].t
    _, i, j = np.intersect1d(np.round(first * 100.0), np.round((second - 0.5e-3) * 100.0),
                             return_indices=True)
    difference = second[j] - first[i]
    spread = np.sqrt(2) * jitter
    assert len(difference) > 5990
    assert np.median(difference) == pytest.approx(0.5e-3, abs=5 * 1.26 * spread / np.sqrt(5990))
    assert np.std(difference) == pytest.approx(spread, rel=0.06)


def test_message_loss_is_random_within_binomial_bounds_and_t_keeps_sensor_1s_lost_instants():
    loss = np.array([0.02, 0.005, 0.0, 0.3])
    clocks = SensorClocks(offset_s=[0.0, 1e-3, 2e-3, 3e-3], loss_fraction=loss)
    mission = simulate(_scenario(segments=[TrimManoeuvre(120.0)], noise_t=0.1e-9, clocks=clocks),
                       np.random.default_rng(12))
    n = 12_000  # 120 s at 100 Hz: every instant is inside the mission
    assert len(mission) == n
    for sensor, stream in enumerate(mission.streams):
        lost = n - len(stream)
        p = loss[sensor]
        assert abs(lost - n * p) <= 4.5 * np.sqrt(n * p * (1 - p)), (sensor, lost)
        if p > 0:  # lost at random, not in a block: both halves lose alike
            gaps = np.diff(stream.t) > 0.015
            early = np.count_nonzero(gaps[stream.t[1:] < 60.0])
            assert early == pytest.approx(np.count_nonzero(gaps) / 2, abs=5 * np.sqrt(n * p))
    # Sensor 1's stream: the measured readings at those of t whose message arrived.
    kept = np.isin(mission.t, mission.streams[0].t)
    assert np.count_nonzero(kept) == len(mission.streams[0])
    np.testing.assert_array_equal(mission.streams[0].fields, mission.fields_measured[kept, 0])


def test_per_sensor_rates_on_an_irregular_geometry_read_the_clean_field_model_with_time_skew():
    skew = np.array([0.0, 0.0, 0.012, 0.005])
    scenario = _scenario(
        geometry=IRREGULAR,
        segments=[TrimManoeuvre(20.0, center=(200.0, 0.0, -30.0)),
                  SurveyLine((-20.0, 25.0, -30.0), (20.0, 25.0, -30.0))],
        dipoles=[Dipole([0.0, 0.0, -60.0], [2e4, -1e4, 3e4])],
        regional_gradient_enu=G_WORLD,
        effects=Effects(time_skew=skew),
        clocks=SensorClocks(offset_s=[0.0, 1e-3, 3e-3, 2.5e-3], jitter_s=0.2e-3,
                            rate_hz=[25.0, 25.0, 50.0, 100.0]),
    )
    mission = simulate(scenario, np.random.default_rng(13))
    for sensor, (stream, rate) in enumerate(zip(mission.streams, [25, 25, 50, 100], strict=True)):
        assert len(stream) == pytest.approx(40.0 * rate, abs=1)
        assert np.median(np.diff(stream.t)) == pytest.approx(1.0 / rate, abs=2e-5)
        expected = _clean_reading(scenario, stream.t, sensor, skew[sensor])
        np.testing.assert_allclose(stream.fields, expected, rtol=0, atol=1e-15)
        # What each sensor would read at sensor 1's instants (the mission's common arrays).
        np.testing.assert_allclose(mission.fields_measured[:, sensor],
                                   _clean_reading(scenario, mission.t, sensor, skew[sensor]),
                                   rtol=0, atol=1e-15)
    # The join is exercised: a skewed sample just after it reads the line, earlier.
    assert np.any((mission.streams[2].t >= 20.0) & (mission.streams[2].t < 20.0 + skew[2]))
    np.testing.assert_array_equal(mission.t, mission.streams[0].t)
    np.testing.assert_allclose(mission.fields_true[:, 0], _clean_reading(scenario, mission.t, 0),
                               rtol=0, atol=1e-15)


def test_ideal_clocks_reproduce_the_synchronous_mission():
    base = _scenario(segments=[TrimManoeuvre(30.0)], noise_t=0.1e-9,
                     effects=Effects(time_skew=[0.0, 0.02, 0.0, 0.0]))
    plain = simulate(base, np.random.default_rng(14))
    ideal = simulate(dataclasses.replace(base, clocks=SensorClocks()), np.random.default_rng(14))
    for name in ('t', 'position_enu', 'fields_true', 'fields_measured', 'g_true', 'current_a'):
        np.testing.assert_array_equal(getattr(ideal, name), getattr(plain, name), err_msg=name)
    assert plain.streams is None
    for sensor, stream in enumerate(ideal.streams):
        np.testing.assert_array_equal(stream.t, plain.t)
        # Fresh noise on sensors 2-4: equal to the common readings within the noise only.
        difference = stream.fields - plain.fields_measured[:, sensor]
        expected_std = 0.0 if sensor == 0 else np.sqrt(2) * 0.1e-9
        assert np.std(difference) == pytest.approx(expected_std, rel=0.05, abs=1e-18)


def test_select_keeps_the_stream_messages_of_the_selected_span():
    rates = [100.0, 50.0, 100.0, 200.0]
    scenario = _scenario(
        segments=[TrimManoeuvre(20.0), SurveyLine((-20.0, 0.0, -30.0), (20.0, 0.0, -30.0))],
        clocks=SensorClocks(offset_s=[0.0, 4e-3, 2e-3, -3e-3], rate_hz=rates),
    )
    mission = simulate(scenario, np.random.default_rng(15))
    line = mission.select(mission.segment == 1)
    assert line.t[0] == 20.0 and line.t[-1] == pytest.approx(39.99)
    start, end = 20.0 - 0.005, 39.99 + 0.005  # the line's span, +- half of sensor 1's period
    for full, part, rate in zip(mission.streams, line.streams, rates, strict=True):
        keep = (full.t >= start) & (full.t <= end)
        np.testing.assert_array_equal(part.t, full.t[keep])
        np.testing.assert_array_equal(part.fields, full.fields[keep])
        assert len(part) == pytest.approx(20.0 * rate, abs=1) and len(full) > len(part)
    nothing = mission.select(np.zeros(len(mission), dtype=bool))
    assert len(nothing) == 0 and [len(s) for s in nothing.streams] == [0, 0, 0, 0]
    assert simulate(_scenario(), np.random.default_rng(0)).select(slice(3, 9)).streams is None


def test_clocks_and_streams_refuse_bad_values_naming_them():
    assert SensorClocks(jitter_s=1e-4).jitter_s.tolist() == [1e-4] * 4
    with pytest.raises(InputError, match=r'jitter_s must be >= 0'):
        SensorClocks(jitter_s=[0.0, -1e-4, 0.0, 0.0])
    with pytest.raises(InputError, match=r'rate_hz must be positive'):
        SensorClocks(rate_hz=[25.0, 0.0, 50.0, 100.0])
    with pytest.raises(InputError, match=r'loss_fraction must be in \[0, 0.5\)'):
        SensorClocks(loss_fraction=0.5)
    with pytest.raises(InputError, match=r'offset_s must have shape \(4,\)'):
        SensorClocks(offset_s=[0.0, 1e-3, 2e-3])
    with pytest.raises(InputError, match=r'drift_ppm has a non-finite value'):
        SensorClocks(drift_ppm=[0.0, np.nan, 0.0, 0.0])
    with pytest.raises(InputError, match='3 instants but 2 readings'):
        SensorStream(np.arange(3.0), np.zeros((2, 3)))
    with pytest.raises(InputError, match='shorter than one sample period'):
        simulate(_scenario(clocks=SensorClocks(offset_s=100.0)), np.random.default_rng(0))


# -- regional gradient ---------------------------------------------------------------------


def test_regional_gradient_is_in_the_fields_and_both_truth_tensors():
    segments = [TrimManoeuvre(40.0, center=(800.0, -600.0, -40.0)),
                SurveyLine((-50.0, 10.0, -30.0), (50.0, 10.0, -30.0))]
    scenario = _scenario(sample_rate_hz=5.0, segments=segments, regional_gradient_enu=G_WORLD)
    mission = simulate(scenario, np.random.default_rng(16))
    rotation = Rotation.from_quat(mission.orientation_xyzw).as_matrix()
    expected = np.einsum('nji,jk,nkl->nil', rotation, G_WORLD, rotation)  # R^T G_w R
    scale = np.abs(G_WORLD).max()
    np.testing.assert_allclose(mission.g_analytic, expected, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(mission.g_true, expected, rtol=0, atol=1e-6 * scale)
    positions = TetraGeometry.regular(0.5).positions
    sensors_world = mission.position_enu[:, None] + np.einsum('nij,sj->nsi', rotation, positions)
    world = EARTH + sensors_world @ G_WORLD.T
    np.testing.assert_allclose(mission.fields_true, np.einsum('nji,nsj->nsi', rotation, world),
                               rtol=0, atol=1e-15)
    assert np.abs(world - EARTH).max() > 1e-6  # the gradient's field is there (~1000 m out)


def test_regional_gradient_must_be_symmetric_and_traceless():
    with pytest.raises(InputError, match='regional_gradient_enu must be symmetric'):
        _scenario(regional_gradient_enu=G_WORLD + np.triu(np.full((3, 3), 1e-10), 1))
    with pytest.raises(InputError, match='regional_gradient_enu must be traceless'):
        _scenario(regional_gradient_enu=G_WORLD + np.eye(3) * 1e-10)
    with pytest.raises(InputError, match=r'regional_gradient_enu must have shape \(3, 3\)'):
        _scenario(regional_gradient_enu=np.zeros(3))
    # Within the relative tolerance (1e-9 of the norm): accepted.
    _scenario(regional_gradient_enu=G_WORLD + np.eye(3) * 1e-21)


def test_default_scenario_is_unchanged_by_the_new_options():
    scenario, seed = load_scenario_or_default()
    assert scenario.clocks is None and not np.any(scenario.regional_gradient_enu)
    mission = simulate(scenario, np.random.default_rng(seed))
    explicit = dataclasses.replace(scenario, clocks=None, regional_gradient_enu=np.zeros((3, 3)))
    again = simulate(explicit, np.random.default_rng(seed))
    assert mission.streams is None and again.streams is None
    for field in dataclasses.fields(mission):
        if field.name != 'streams':
            np.testing.assert_array_equal(getattr(mission, field.name), getattr(again, field.name))
    # Values recorded with the simulator before clocks and the regional gradient existed:
    # the generator is consumed as before (a changed draw order moves the noise by ~0.1 nT).
    recorded = [2.0843744111189187e-05, 1.4575594546379735e-06, -3.787602573268276,
                2.553735427054413e-08]
    now = [mission.fields_measured[100, 2, 1], mission.fields_measured[-1, 3, 0],
           mission.current_a[57], mission.g_true[2000, 0, 1]]
    np.testing.assert_allclose(now, recorded, rtol=1e-12)


# -- scenario files ------------------------------------------------------------------------


def _document(**extra):
    document = copy.deepcopy(DEFAULT_SCENARIO)
    document['segments'] = [{'trim': {'duration_s': 5.0}}]
    document.update(extra)
    return document


def test_scenario_file_keys_round_trip_into_si(tmp_path):
    g_nT = (G_WORLD * 1e9).tolist()
    clocks = {'offset_ms': [0, 0.5, 2, 4], 'jitter_ms': 0.2, 'drift_ppm': [0, 20, -30, 50],
              'rate_hz': [25, 25, 50, 100], 'loss_fraction': 0.005}
    path = tmp_path / 'scenario.yaml'
    path.write_text(yaml.safe_dump(_document(regional_gradient_nT_per_m=g_nT, clocks=clocks)))
    scenario, _ = load_scenario(path)
    np.testing.assert_allclose(scenario.regional_gradient_enu, G_WORLD, rtol=1e-15)
    assert scenario.clocks.offset_s.tolist() == pytest.approx([0, 0.5e-3, 2e-3, 4e-3], rel=1e-15)
    assert scenario.clocks.jitter_s.tolist() == pytest.approx([0.2e-3] * 4, rel=1e-15)
    assert scenario.clocks.drift_ppm.tolist() == [0, 20, -30, 50]
    assert scenario.clocks.rate_hz.tolist() == [25, 25, 50, 100]
    assert scenario.clocks.loss_fraction.tolist() == [0.005] * 4
    # Missing keys are the defaults; no clocks section: no clocks.
    partial, _ = scenario_from_dict(_document(clocks={'jitter_ms': [0, 0.1, 0.1, 0.1]}))
    assert partial.clocks.rate_hz is None and partial.clocks.offset_s.tolist() == [0.0] * 4
    assert scenario_from_dict(_document())[0].clocks is None


def test_the_module_docstring_example_is_a_valid_scenario():
    text = scenario_io.__doc__.split('Example::')[1]
    scenario, seed = scenario_from_dict(yaml.safe_load(textwrap.dedent(text)))
    assert seed == 7 and scenario.clocks is not None
    assert scenario.clocks.offset_s.tolist() == pytest.approx([0, 0.5e-3, 2e-3, 4e-3])
    assert scenario.regional_gradient_enu[0, 1] == pytest.approx(0.2e-9)


@pytest.mark.parametrize('extra, message', [
    ({'clocks': {'jitter_s': 0.2}}, r"clocks: unknown \['jitter_s'\]"),
    ({'clocks': {'jitter_ms': -0.2}}, r'clocks.jitter_ms = -0.2: .*jitter_s must be >= 0'),
    ({'clocks': {'rate_hz': [25, 50]}}, r'clocks.rate_hz: expected a number or 4 numbers'),
    ({'clocks': {'offset_ms': 'late'}}, r'clocks.offset_ms: not numeric'),
    ({'clocks': {'loss_fraction': 0.7}}, r'clocks.loss_fraction = 0.7: .*\[0, 0.5\)'),
    ({'clocks': [1, 2]}, r'clocks: expected a mapping'),
    ({'regional_gradient_nT_per_m': [[1, 2, 0], [0, -1, 0], [0, 0, 0]]},
     r'regional_gradient_nT_per_m must be symmetric'),
    ({'regional_gradient_nT_per_m': [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
     r'regional_gradient_nT_per_m must be traceless'),
    ({'regional_gradient_nT_per_m': [1, 0, 0]},
     r'scenario.regional_gradient_nT_per_m: expected shape \(3, 3\)'),
    ({'regional_gradient_T_per_m': [[0] * 3] * 3},
     r"unknown key\(s\) \['regional_gradient_T_per_m'\]"),
])
def test_scenario_file_refusals_name_the_key(extra, message):
    with pytest.raises(ScenarioError, match=message):
        scenario_from_dict(_document(**extra))
