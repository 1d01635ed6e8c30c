"""Sensors at different rates (sensor 1 at 100 Hz, the others at 10 Hz) are resampled to a grid
at the slowest one's rate, and the line says so: calibrated and compensated to the noise floor
instead of refused as an effect the model lacks.

Truth: the simulator's exact tensor at the grid instants (each one of sensor 1's instants).
"""
from __future__ import annotations

import numpy as np

import tetra_gradiometer.core as core
from tetra_gradiometer.core.units import NS_PER_S
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.recording import write_mission_bag
from tetra_gradiometer.pipelines.calibration import calibrate_bag

START_NS = 1_767_225_600 * NS_PER_S
TRIM_S = 120.0


def test_one_fast_sensor_and_three_slow_ones_reach_the_floor(tmp_path):
    rng = np.random.default_rng(3)
    geometry = core.TetraGeometry.regular(0.5)
    scenario = core.Scenario(
        geometry=geometry, earth_field_enu=[0.0, 2e-5, -4.5e-5], sample_rate_hz=100.0,
        segments=(core.TrimManoeuvre(TRIM_S), core.SurveyLine((-60.0, 20.0, -50.0), (60.0, 20.0, -50.0))),
        interference=core.random_interference(rng), noise_t=1e-10,
        clocks=core.SensorClocks(rate_hz=[100.0, 10.0, 10.0, 10.0]))
    mission = core.simulate(scenario, rng)
    write_mission_bag(tmp_path / 'bag', mission, start_ns=START_NS, progress=False)
    result = calibrate_bag(tmp_path / 'bag', geometry, window=(0.0, TRIM_S - 1.0))
    assert 'sensors at different rates (1: 100 Hz, 2: 10 Hz' in result.skipped_summary
    assert 'resampled to a 10 Hz grid' in result.skipped_summary
    with MagneticBag(tmp_path / 'bag') as bag:
        stamps, fields = bag.read_sets(window_s=(TRIM_S + 1.0, 1e9))
    g_comp = core.compensate(core.difference_tensor(fields, geometry), fields[:, 0],
                             result.calibration.parameters, geometry)
    truth_stamps = START_NS + np.round(mission.t * NS_PER_S).astype(np.int64)
    index = np.searchsorted(truth_stamps, stamps)
    assert np.array_equal(truth_stamps[index], stamps)  # the 10 Hz grid: every 10th instant of sensor 1
    residual = core.rms_residual(g_comp, mission.g_true[index])
    assert residual <= 1.2 * core.noise_floor(scenario.noise_t, geometry), residual
