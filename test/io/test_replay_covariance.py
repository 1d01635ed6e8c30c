"""nodes/replay.py and io/conversions.py: the magnetometers' ``magnetic_field_covariance``
(REP 145) in the driver's frames. Simulated: ``diag(sigma^2)`` of the scenario's noise;
replayed: the recorded covariance kept when it is usable, else ``diag(sensor_noise_t^2)``,
else REP 145's unknown (-1 in the first element). Through rosbags' own CDR (no ROS graph)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from rosbags.typesys import Stores, get_typestore

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter, typestore
from tetra_gradiometer.nodes import replay

T0 = 1_767_225_600 * 10**9
FIELD = np.array([1e-6, 2e-5, -4.5e-5])
UNKNOWN = [-1.0, 0, 0, 0, 0, 0, 0, 0, 0]  # REP 145
TYPES = cv.rosbags_types(typestore())  # with our interfaces: the simulated truth is a GradientTensor


def _bag(path, covariance_of_sensor):
    """Ten sets; sensor ``s`` recorded with ``covariance_of_sensor(s)`` (9,) T^2, or None for
    the fast writer's zeros."""
    with BagWriter(path) as writer:
        for i in range(10):
            stamp = T0 + i * 100_000_000
            for s, topic in enumerate(cv.BAG_MAG_TOPICS):
                covariance = covariance_of_sensor(s)
                msg = cv.magnetic_field_msg(writer.types, FIELD + s * 1e-7, stamp, cv.MAG_FRAMES[s], covariance)
                writer.write(topic, msg, stamp)
    return path


def _covariances(path, **options):
    """{sensor: [(9,) covariance of each replayed message]}."""
    found: dict[int, list[np.ndarray]] = {s: [] for s in range(4)}
    for frame in replay.iter_frames(path, TYPES, **options):
        for key, sensor, msg in frame.items:
            assert key == replay.MAG
            found[sensor].append(np.asarray(msg.magnetic_field_covariance, dtype=float))
    return found


@pytest.mark.parametrize('recorded', [None, np.zeros(9)], ids=['rep145-unknown', 'all-zero'])
def test_a_bag_recorded_without_covariance_gets_the_parameter_or_stays_unknown(tmp_path, recorded):
    bag = _bag(tmp_path / 'bag', lambda s: recorded)
    for found in (_covariances(bag), _covariances(bag, sensor_noise_t=0.0)):
        for values in found.values():
            np.testing.assert_array_equal(values, [UNKNOWN] * 10)
    found = _covariances(bag, sensor_noise_t=2e-10)
    expected = [4e-20, 0, 0, 0, 4e-20, 0, 0, 0, 4e-20]  # T^2, row-major diag(sigma^2)
    for values in found.values():
        np.testing.assert_allclose(values, [expected] * 10, rtol=1e-12, atol=0)


def test_a_recorded_covariance_is_kept_and_a_non_finite_one_replaced(tmp_path):
    recorded = np.array([[1.0, 0.1, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 3.0]]).reshape(9) * 1e-20
    bag = _bag(tmp_path / 'bag', lambda s: np.full(9, np.nan) if s == 3 else recorded * (s + 1))
    found = _covariances(bag, sensor_noise_t=5e-10)
    for s in range(3):
        np.testing.assert_array_equal(found[s], [recorded * (s + 1)] * 10)
    np.testing.assert_allclose(found[3], [np.diag([25e-20] * 3).reshape(9)] * 10, rtol=1e-12, atol=0)


@pytest.mark.parametrize('noise_nt', [0.0, 0.3])
def test_simulated_frames_carry_the_scenario_noise(tmp_path, noise_nt):
    scenario = tmp_path / 'scenario.yaml'
    scenario.write_text(yaml.safe_dump({
        'seed': 3, 'sample_rate_hz': 10, 'noise_nT': noise_nt, 'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45000.0]},
        'segments': [{'trim': {'duration_s': 1.0}}]}))
    frames, info = replay.simulate(str(scenario), -1, TYPES, start_ns=T0)
    assert info['sensor_noise_t'] == pytest.approx(noise_nt * 1e-9)
    mags = [msg for frame in frames for key, _, msg in frame.items if key == replay.MAG]
    assert len(mags) == 40
    expected = np.diag([(noise_nt * 1e-9) ** 2] * 3).reshape(9) if noise_nt else UNKNOWN  # REP 145
    for msg in mags:
        np.testing.assert_allclose(msg.magnetic_field_covariance, expected, rtol=1e-12, atol=0)


def test_magnetic_field_covariance_round_trips_through_rosbags_cdr():
    store = get_typestore(Stores.ROS2_JAZZY)
    covariance = np.arange(1.0, 10.0) * 1e-21
    msg = cv.magnetic_field_msg(TYPES, FIELD, T0, 'tetra_mag1', covariance)
    back = store.deserialize_cdr(store.serialize_cdr(msg, cv.MAGNETIC_FIELD), cv.MAGNETIC_FIELD)
    np.testing.assert_array_equal(cv.magnetic_field_covariance(back), covariance)
    np.testing.assert_array_equal(cv.magnetic_field_reading(back), np.r_[FIELD, covariance])
    np.testing.assert_array_equal(
        cv.magnetic_field_covariance(cv.magnetic_field_msg(TYPES, FIELD, T0, 'tetra_mag1')), UNKNOWN)
