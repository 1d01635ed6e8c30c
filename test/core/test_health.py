"""core/health.py against simulator truth: survey lines over a magnetized target after a trim
calibration; a known offset jump (or drift) is injected into one sensor's readings at a
known time, so the alarm's time and sensor are checked against what was done."""

import numpy as np
import pytest

from tetra_gradiometer.core import (
    Dipole,
    Scenario,
    SurveyLine,
    TetraGeometry,
    TrimManoeuvre,
    compensate,
    difference_tensor,
    known_gradient_lstsq,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.health import HealthConfig, HealthMonitor, alarm_threshold
from tetra_gradiometer.errors import InputError

GEOMETRY = TetraGeometry.regular(0.5)
EARTH = np.array([0.0, 21000e-9, -45376.2e-9])
TARGET = Dipole(position=[0.0, 0.0, -80.0], moment=[30000.0, 20000.0, -33000.0])  # 30 m below
LINES = tuple(
    SurveyLine(
        (-200.0 * d, y, -50.0),
        (200.0 * d, y, -50.0),
        roll_amplitude_deg=2.0,
        pitch_amplitude_deg=1.0,
    )
    for d, y in ((1, 0.0), (-1, 15.0), (1, -15.0))
)  # 600 s over the target, the closest pass 30 m above it


def _mission(seed: int, rate_hz: float = 10.0):
    rng = np.random.default_rng(seed)
    scenario = Scenario(
        geometry=GEOMETRY,
        earth_field_enu=EARTH,
        segments=(TrimManoeuvre(duration_s=300.0, center=(3000.0, 3000.0, -50.0)), *LINES),
        sample_rate_hz=rate_hz,
        dipoles=(TARGET,),
        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9),
        noise_t=0.05e-9,
    )
    data = simulate(scenario, rng)
    trim = data.segment == 0
    g_measured = difference_tensor(data.fields_measured, GEOMETRY)
    calibration = known_gradient_lstsq(
        g_measured[trim], data.fields_measured[trim, 0], GEOMETRY, symmetric_k=False
    )
    return data, calibration


def _monitor(data, calibration, fields, chunk: int = 50, config: HealthConfig | None = None):
    """Run the monitor over the survey (after the trim), in chunks; return it and its traces."""
    survey = data.segment > 0
    t, fields = data.t[survey], fields[survey]
    g = compensate(
        difference_tensor(fields, GEOMETRY), fields[:, 0], calibration.parameters, GEOMETRY
    )
    noise = calibration.details['sensor_noise_nT'] * 1e-9
    monitor = HealthMonitor(
        GEOMETRY, calibration.parameters, noise, calibration.covariance, config
    )
    traces = [
        monitor.update(t[i : i + chunk], g[i : i + chunk], fields[i : i + chunk, 0])
        for i in range(0, len(t), chunk)
    ]
    return monitor, traces


@pytest.fixture(scope='module')
def missions():
    return [_mission(seed) for seed in (11, 12)]


def test_no_alarm_over_a_target_without_a_change(missions):
    for data, calibration in missions:
        monitor, traces = _monitor(data, calibration, data.fields_measured)
        assert monitor.alarms == []
        glr = np.concatenate([t.glr for t in traces])
        assert np.nanmax(glr) < monitor.threshold
        # The statistics are live over the whole survey (not NaN after start-up).
        assert np.isfinite(glr[100:]).all()


@pytest.mark.parametrize('sensor', [0, 1, 2, 3])
def test_a_2nt_offset_jump_is_alarmed_within_5s_and_names_the_sensor(missions, sensor):
    rng = np.random.default_rng(100 + sensor)
    for data, calibration in missions:
        t_change = float(rng.uniform(320.0, 820.0))  # anywhere on the lines, targets included
        direction = rng.normal(size=3)
        jump = 2e-9 * direction / np.linalg.norm(direction)
        fields = data.fields_measured.copy()
        fields[data.t >= t_change, sensor] += jump
        monitor, _ = _monitor(data, calibration, fields)
        assert monitor.alarms, f'no alarm for a jump at {t_change:.1f} s'
        alarm = monitor.alarms[0]
        assert t_change <= alarm.t_s <= t_change + 5.0
        # Named among the sensors whose offset jump fits (the four signatures share
        # directions, so a jump can fit two); bench/bench_health.py measures how often it is
        # named first.
        assert sensor + 1 in alarm.sensors, alarm
        assert alarm.settled and alarm.statistic > alarm.threshold
        assert len(monitor.alarms) == 1


def test_chunking_does_not_change_the_result(missions):
    data, calibration = missions[0]
    fields = data.fields_measured.copy()
    fields[data.t >= 555.0, 2] += [1.0e-9, 0.0, -1.5e-9]
    big, _ = _monitor(data, calibration, fields, chunk=100_000)
    small, _ = _monitor(data, calibration, fields, chunk=7)
    assert len(big.alarms) == len(small.alarms) == 1
    one, other = big.alarms[0].to_dict(), small.alarms[0].to_dict()
    for key in ('t_s', 'onset_s', 'statistic', 'threshold'):
        assert one[key] == pytest.approx(other[key], rel=1e-9)
    assert (one['kind'], one['sensors']) == (other['kind'], other['sensors'])
    assert 3 in one['sensors'] and 554.9 < one['t_s'] < 560.0


def test_a_slow_drift_is_alarmed_not_absorbed(missions):
    data, calibration = missions[0]
    fields = data.fields_measured.copy()
    ramp = np.clip((data.t - 350.0) / 500.0, 0.0, None)  # 0 -> 2 nT over 500 s on sensor 4
    fields[:, 3] += ramp[:, None] * np.array([0.0, 2e-9, 0.0])
    monitor, _ = _monitor(data, calibration, fields)
    assert monitor.alarms
    assert monitor.alarms[0].t_s > 350.0
    assert 4 in monitor.alarms[0].sensors


def test_threshold_is_chi2_at_the_bonferroni_level():
    from scipy.stats import chi2

    rate, per_sample = 0.01, 10.0
    expected = chi2.isf(rate / (3600 * per_sample * 17), 4)
    assert alarm_threshold(rate, per_sample, 17) == pytest.approx(expected)


def test_bad_settings_are_named():
    with pytest.raises(InputError, match='min_source_range_edges'):
        HealthConfig(min_source_range_edges=5.0)
    with pytest.raises(InputError, match='false_alarms_per_hour'):
        HealthConfig(false_alarms_per_hour=0.0)
    data, calibration = _mission(3)
    with pytest.raises(InputError, match='sensor_noise_t'):
        HealthMonitor(GEOMETRY, calibration.parameters, 0.0)


def test_history_window_sums_equal_a_plain_cumsum_across_compactions():
    """The monitor's running history (prefix sums, re-based when compacted) against numpy's
    cumsum over the rows it reports holding."""
    from tetra_gradiometer.core.health import N_FEATURES, _History

    rng = np.random.default_rng(11)
    history, everything = _History(keep=50), []
    for size in rng.integers(1, 40, 200):
        rows = rng.normal(1e-9, 1e-9, (size, N_FEATURES))
        held = history.append(rows)
        everything.append(rows)
        seen = np.concatenate(everything)[-len(history):]
        assert held == len(history) - size and len(history) >= min(50, len(seen))
        np.testing.assert_array_equal(history.rows, seen)
        expected = np.vstack([np.zeros((1, N_FEATURES)), np.cumsum(seen, axis=0)])
        np.testing.assert_allclose(history.sums, expected, rtol=0, atol=1e-20)
    assert len(history) < 200 * 40 / 2  # compacted, not grown without bound
