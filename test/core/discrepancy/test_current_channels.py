"""The discrepancy search's vehicle_current with several current channels: the battery's
and each thruster's BatteryState, as the simulator makes them; and its regressors as the
registry's (one definition of each operational effect)."""
import numpy as np
import pytest

from tetra_gradiometer.core import (
    CurrentProfile,
    Effects,
    Scenario,
    Thruster,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.discrepancy import LIBRARY, analyze
from tetra_gradiometer.core.discrepancy.candidate import Context
from tetra_gradiometer.core.discrepancy import effects as candidates
from tetra_gradiometer.core.discrepancy.prepare import RecordedRun, prepare
from tetra_gradiometer.core.discrepancy.synthetic import (
    random_earth_field,
    random_geometry,
    random_trim,
)
from tetra_gradiometer.core.effects import EFFECTS

THRUSTERS = (Thruster('/thruster_1/battery_state', turn_a_per_deg_s=-0.05, step_s=11.0),
             Thruster('/thruster_2/battery_state', turn_a_per_deg_s=0.05, step_s=17.0, step_amplitude_a=2.0))
NOISE_T = 0.05e-9


def _mission(seed):
    rng = np.random.default_rng(seed)
    per_amp = np.zeros((4, 3, 3))
    # Each channel its own wiring: a different field per ampere at sensors 2 and 3.
    per_amp[1:3] = rng.normal(0, 0.2e-9, (2, 3, 3))
    scenario = Scenario(
        geometry=random_geometry(rng), earth_field_enu=random_earth_field(rng),
        segments=(random_trim(rng, 150.0),), noise_t=NOISE_T,
        interference=random_interference(rng, k_scale=5e-3, b_scale_t=100e-9),
        current=CurrentProfile(-3.0, 1.5, 20.0, THRUSTERS),
        effects=Effects(vehicle_current=per_amp))
    return scenario, simulate(scenario, rng)


def _run(mission, extra=True):
    extra_currents = dict(zip(mission.current_topics[1:], mission.currents_a[:, 1:].T, strict=True))
    return RecordedRun(mission.t, mission.fields_measured, mission.orientation_xyzw, mission.temperature_c,
                       mission.current_a, {}, extra_currents if extra else {})


@pytest.mark.parametrize('seed', [3, 4])
def test_every_current_channel_enters_vehicle_current(seed):
    scenario, mission = _mission(seed)
    report = analyze(_run(mission), scenario.geometry, scenario.earth_field_enu, keep_series=False)
    assert report.named_effects == ['vehicle_current']
    assert report.gap_final_nT <= 1.2 * report.noise_floor_nT
    step = report.steps[0]
    assert sorted(step.parameters['per_sensor']) == ['sensor_2', 'sensor_3']
    # One coefficient per axis and channel, each named by its topic.
    labels = step.parameters['per_sensor']['sensor_2']
    assert len(labels) == 9 and all('battery_state]' in label for label in labels)
    # The battery alone cannot explain three circuits' fields: the search is left short, and
    # reaches for look-alikes (a drift, a step) to make up for the thrusters' share.
    battery_only = analyze(_run(mission, extra=False), scenario.geometry, scenario.earth_field_enu,
                           keep_series=False)
    assert battery_only.gap_final_nT > 1.3 * report.gap_final_nT
    assert battery_only.named_effects[0] == 'vehicle_current' and len(battery_only.named_effects) > 1


def test_the_columns_are_the_registrys_regressors_per_sensor():
    scenario, mission = _mission(5)
    prep = prepare(_run(mission), scenario.earth_field_enu, max_samples=10_000)
    assert [topic for topic, _ in prep.extra_currents] == list(mission.current_topics[1:])
    ctx = Context(prep.t, prep.sensors, prep.absolute, prep.b_background, prep.b_rate, prep.fields,
                  prep.temperature_c, prep.current_a, extra_currents=prep.extra_currents)
    cols, offset, labels = LIBRARY['vehicle_current'].build(ctx, None)
    assert offset is None and cols.shape[-1] == 9 * len(prep.sensors)
    currents = np.column_stack([prep.current_a] + [values for _, values in prep.extra_currents])
    for k, (s, label) in enumerate(labels):
        axis, channel = 'xyz'.index(label[0]), k % 3
        np.testing.assert_array_equal(cols[:, s, axis, k], currents[:, channel])
        assert np.count_nonzero(cols[..., k]) == np.count_nonzero(currents[:, channel])
    # The thermal family's regressor: the registry's T - T_ref with the run's mean as T_ref.
    thermal, _, thermal_labels = LIBRARY['thermal_drift'].build(ctx, None)
    np.testing.assert_array_equal(thermal[:, 1, 0, thermal_labels.index((1, 'x[T-T_ref_degC]_nT/degC'))],
                                  prep.temperature_c - np.mean(prep.temperature_c))
    # One physics text per effect: the registry's.
    for name in ('vehicle_current', 'thermal_drift'):
        assert LIBRARY[name].physics == EFFECTS[name].physics
    assert EFFECTS['eddy_current'].physics.startswith(LIBRARY['eddy_current'].physics[:-1])


def test_thruster_channels_alone_make_vehicle_current_testable():
    _, mission = _mission(6)
    run = _run(mission)
    without_battery = RecordedRun(run.t_s, run.fields, run.orientation_xyzw, run.temperature_c, None,
                                  {'/battery_state': 'not recorded'}, run.extra_currents)
    prep = prepare(without_battery, None, max_samples=10_000)
    names = [c.name for c in candidates.testable(prep, (LIBRARY['vehicle_current'],))[0]]
    assert names == ['vehicle_current']
    nothing = prepare(RecordedRun(run.t_s, run.fields, run.orientation_xyzw), None, max_samples=10_000)
    _, untestable = candidates.testable(nothing, (LIBRARY['vehicle_current'],))
    assert '/battery_state' in untestable['vehicle_current']
    # An unknown current (NaN) leaves those samples out, as for the battery's.
    gappy = dict(run.extra_currents)
    gappy['/thruster_1/battery_state'] = gappy['/thruster_1/battery_state'].copy()
    gappy['/thruster_1/battery_state'][100:150] = np.nan
    prep = prepare(RecordedRun(run.t_s, run.fields, run.orientation_xyzw, None, run.current_a, {}, gappy), None,
                   max_samples=10_000)
    battery = run.current_a.copy()
    battery[100:150] = np.nan
    same = prepare(RecordedRun(run.t_s, run.fields, run.orientation_xyzw, None, battery, {}, run.extra_currents),
                   None, max_samples=10_000)
    assert len(prep.t) < len(run.t_s) - 50 + 1
    np.testing.assert_array_equal(prep.t, same.t)
