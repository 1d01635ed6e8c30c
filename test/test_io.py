"""Files and messages: round trips, atomicity, matching, and errors that name the problem."""
import os

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.core import (InterferenceParameters, Scenario, TetraGeometry, TrimManoeuvre,
                                    known_gradient_lstsq, difference_tensor, random_interference, simulate)
from tetra_gradiometer.io.outputs import CALIBRATION, OutputError, atomic_write_text
from tetra_gradiometer.io.bag import BagError, BagWriter, MagneticBag
from tetra_gradiometer.io.calibration import (CalibrationFile, CalibrationFileError, load_calibration,
                                              save_calibration)
from tetra_gradiometer.io.params import ParamsError, geometry_from_params, load_params, params_document
from tetra_gradiometer.io.recording import read_recording, write_mission_bag
from tetra_gradiometer.io.matching import StampMatcher

GEOMETRY = TetraGeometry.regular(0.5)


def test_tensor_message_round_trip_through_rosbags_cdr():
    store = get_typestore(Stores.ROS2_JAZZY)
    types = cv.rosbags_types(store)
    g = np.arange(9.0).reshape(3, 3) * 1e-9
    msg = cv.tensor_msg(types, g, 1_700_000_000_123_456_789)
    back = store.deserialize_cdr(store.serialize_cdr(msg, cv.JOINT_STATE), cv.JOINT_STATE)
    np.testing.assert_array_equal(cv.tensor_from_msg(back), g)
    assert cv.stamp_to_ns(back.header.stamp) == 1_700_000_000_123_456_789
    back.name = list(reversed(back.name))
    back.position = back.position[::-1]
    np.testing.assert_array_equal(cv.tensor_from_msg(back), g)  # order by name, not position
    back.name[0] = 'gxq'
    with pytest.raises(cv.MessageError, match='gxx'):
        cv.tensor_from_msg(back)


def test_matcher_pairs_by_stamp_and_counts_incomplete_sets():
    matcher = StampMatcher(tolerance_ns=1_000)
    emitted = []
    for stamp in range(0, 10_000_000, 1_000_000):
        for sensor in range(4):
            if sensor == 2 and stamp == 3_000_000:
                continue  # sensor 3 loses one sample
            jitter = 200 * sensor  # within tolerance
            emitted += matcher.add(sensor, stamp + jitter, np.full(3, sensor, float))
    assert [s for s, _ in emitted] == [s for s in range(0, 10_000_000, 1_000_000) if s != 3_000_000]
    np.testing.assert_array_equal(emitted[0][1][:, 0], [0, 1, 2, 3])
    assert matcher.counters.matched == 9
    assert matcher.counters.dropped_messages == 3  # the other three readings of that set
    assert matcher.add(0, 5, np.zeros(3)) == [] and matcher.counters.out_of_order == 1


def test_atomic_write_never_leaves_a_partial_file(tmp_path, monkeypatch):
    target = tmp_path / 'calibration.yaml'
    old = 'tetra_gradiometer_calibration: 1\nold: 1\n'
    atomic_write_text(target, old, CALIBRATION)

    def fail(*args):
        raise OSError('disk full')
    monkeypatch.setattr(os, 'replace', fail)
    with pytest.raises(OutputError, match='disk full'):
        atomic_write_text(target, 'tetra_gradiometer_calibration: 1\n' + 'new: 2\n' * 1000, CALIBRATION,
                          force=True)
    assert target.read_text() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ['calibration.yaml']


def test_calibration_file_round_trip_and_corruption(tmp_path):
    rng = np.random.default_rng(0)
    parameters = InterferenceParameters(rng.normal(0, 1e-2, (3, 3, 3)), rng.normal(0, 1e-7, (3, 3)))
    original = CalibrationFile(parameters, 'known_gradient_lstsq_general', False, GEOMETRY.to_flat(),
                               {'rank': 36, 'condition_number': 12.5})
    path = save_calibration(tmp_path / 'c.yaml', original)
    loaded = load_calibration(path)
    np.testing.assert_array_equal(loaded.parameters.k_soft, parameters.k_soft)
    np.testing.assert_array_equal(loaded.parameters.b_hard, parameters.b_hard)
    assert loaded.method == original.method and loaded.diagnostics['rank'] == 36
    path.write_text(path.read_text()[:200])  # truncated
    with pytest.raises(CalibrationFileError):
        load_calibration(path)
    with pytest.raises(CalibrationFileError, match='cannot read'):
        load_calibration(tmp_path / 'absent.yaml')


def test_calibration_file_from_a_fit(tmp_path):
    rng = np.random.default_rng(1)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5],
                                segments=[TrimManoeuvre(60.0)], interference=random_interference(rng)), rng)
    fit = known_gradient_lstsq(difference_tensor(mission.fields_measured, GEOMETRY),
                               mission.fields_measured[:, 0], GEOMETRY, symmetric_k=False)
    loaded = load_calibration(save_calibration(tmp_path / 'c.yaml', CalibrationFile.from_calibration(fit, GEOMETRY)))
    assert loaded.symmetric_k is False and loaded.diagnostics['rank'] == 36
    np.testing.assert_array_equal(loaded.parameters.k_soft, fit.parameters.k_soft)


def test_params_file_errors_name_the_problem(tmp_path):
    good = tmp_path / 'p.yaml'
    good.write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    assert geometry_from_params(load_params(good)).condition_number == pytest.approx(2.0)
    bad = tmp_path / 'bad.yaml'
    bad.write_text(params_document({'sensor_positions': [0.0] * 9}))
    with pytest.raises(ParamsError, match='sensor_positions must be 12'):
        geometry_from_params(load_params(bad))
    flat = tmp_path / 'flat.yaml'
    flat.write_text(params_document({'sensor_positions': [0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0]}))
    with pytest.raises(ParamsError, match='condition number'):
        geometry_from_params(load_params(flat))
    with pytest.raises(ParamsError, match='not found'):
        load_params(tmp_path / 'none.yaml')


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_mission_bag_round_trip(tmp_path, storage):
    rng = np.random.default_rng(2)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5],
                                segments=[TrimManoeuvre(20.0)], noise_t=1e-10), rng)
    write_mission_bag(tmp_path / 'run', mission, storage=storage, battery=False)
    recording = read_recording(tmp_path / 'run')
    np.testing.assert_array_equal(recording.fields, mission.fields_measured)
    np.testing.assert_allclose(recording.t_s, mission.t, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(recording.orientation_xyzw * mission.orientation_xyzw, axis=1)), 1.0,
                               atol=1e-12)
    np.testing.assert_allclose(recording.temperature_c, mission.temperature_c)
    assert recording.current_a is None and '/battery_state' in recording.missing


def test_bag_without_magnetometers_is_refused(tmp_path):
    with BagWriter(tmp_path / 'odd') as writer:
        writer.write_tensors('/tetra/gradient/raw', np.array([1, 2]), np.zeros((2, 3, 3)))
    with MagneticBag(tmp_path / 'odd') as bag, pytest.raises(BagError, match='missing topic'):
        bag.check_contract()
    with pytest.raises(BagError, match='not found'):
        MagneticBag(tmp_path / 'nothing')
