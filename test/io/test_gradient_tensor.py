"""io/gradient_tensor.py: tetra_gradiometer_msgs/GradientTensor through rosbags (a bag written
and read back, values equal), its hand CDR against rosbags' codec, and the tensor topic of the
bags recorded with sensor_msgs/JointState read and replayed as one, beside bags that hold
GradientTensor. No ROS graph."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tetra_gradiometer.errors import BagError, MessageError
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.io.bag import BagWriter, MagneticBag, typestore
from tetra_gradiometer.io.topics import checked_remap, namespaced
from tetra_gradiometer.nodes import replay

T0 = 1_767_225_600 * 10**9
PERIOD_NS = 100_000_000
TRUTH = f'{cv.NAMESPACE}/gradient/truth'
STORE = typestore()
TYPES = cv.rosbags_types(STORE)
TRIM_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'trim'


def _sets(n: int = 6) -> list[gt.TensorSet]:
    """Sets with every field set apart: NaN sigma elements, each state, calibration ids of
    every length modulo 4 (the CDR's string alignment)."""
    rng = np.random.default_rng(11)
    sets = []
    for i in range(n):
        sigma = rng.uniform(0.01e-9, 0.1e-9, (3, 3))
        sigma[i % 3, (i + 1) % 3] = np.nan
        sets.append(gt.TensorSet(
            T0 + i * PERIOD_NS + 17, rng.normal(0.0, 1e-7, (3, 3)), sigma, rng.normal(0.0, 3e-5, 3),
            rng.normal(0.0, 1e-19, 9), (gt.RAW, gt.COMPENSATED, gt.UNCOMPENSATED)[i % 3],
            '2026-11-28T09:30:00Z'[: 17 + i] if i % 3 == 1 else ''))
    return sets


def _assert_same(got: gt.TensorSet, want: gt.TensorSet) -> None:
    assert (got.stamp_ns, got.state, got.calibration_id, got.frame_id) == (
        want.stamp_ns, want.state, want.calibration_id, want.frame_id)
    for name in ('g', 'g_sigma', 'reference_field', 'reference_covariance'):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)  # NaN where NaN


def test_a_gradient_tensor_bag_round_trips_through_rosbags(tmp_path):
    sets = _sets()
    with BagWriter(tmp_path / 'bag') as writer:
        for tensor in sets:
            writer.write('/tetra/gradient/compensated', gt.gradient_tensor_msg(writer.types, tensor), tensor.stamp_ns)
    with AnyReader([tmp_path / 'bag'], default_typestore=typestore()) as reader:
        (connection,) = reader.connections
        back = [gt.tensor_set_from_msg(reader.deserialize(raw, connection.msgtype), connection.msgtype)
                for _, _, raw in reader.messages()]
    assert connection.msgtype == gt.GRADIENT_TENSOR
    assert len(back) == len(sets)
    for got, want in zip(back, sets, strict=True):
        _assert_same(got, want)


@pytest.mark.parametrize('frame', ['tetra_array', '', 'a', 'ab', 'abc', 'abcd', 'abcde'])
def test_the_hand_cdr_is_rosbags_cdr_both_ways(frame):
    for tensor in _sets():
        tensor = replace(tensor, frame_id=frame)
        expected = bytes(STORE.serialize_cdr(gt.gradient_tensor_msg(TYPES, tensor), gt.GRADIENT_TENSOR))
        written = gt.GradientTensorCdr(frame).write(tensor.stamp_ns, gt.pack(tensor), tensor.state,
                                                    tensor.calibration_id)
        assert written == expected
        stamp, values, state, ident = gt.GradientTensorCdr('another_frame').read(expected)  # any frame
        _assert_same(replace(gt.unpack(stamp, values, state, ident), frame_id=frame), tensor)


def test_a_payload_padded_to_four_bytes_is_read_without_rclpy(monkeypatch):
    """Between processes Fast DDS pads the payload to a multiple of 4 bytes (277 bytes arrive
    as 280): the hand reader takes it as it is, never the slow object path."""
    def no_fallback(data):
        raise AssertionError('rclpy deserialization used')

    monkeypatch.setattr(gt, '_deserialize', no_fallback)
    for tensor in _sets(4):
        for ident in ('', 'a', 'ab', 'abc'):
            data = gt.GradientTensorCdr(cv.ARRAY_FRAME).write(tensor.stamp_ns, gt.pack(tensor),
                                                              gt.COMPENSATED, ident)
            padded = data + bytes(-len(data) % 4)
            stamp, values, state, got = gt.GradientTensorCdr(cv.ARRAY_FRAME).read(padded)
            assert (stamp, state, got) == (tensor.stamp_ns, gt.COMPENSATED, ident)
            np.testing.assert_array_equal(values, gt.pack(tensor))


def test_a_truncated_gradient_tensor_is_a_message_error():
    tensor = _sets(1)[0]
    data = gt.GradientTensorCdr(cv.ARRAY_FRAME).write(tensor.stamp_ns, gt.pack(tensor))
    for cut in (10, 100, len(data) - 3):
        with pytest.raises(MessageError):
            gt.GradientTensorCdr(cv.ARRAY_FRAME).read(data[:cut])


def _bag_with_truth(path, truth_type: str, truth_topic: str = TRUTH):
    """Five sets of magnetometers and their true tensor, the latter as ``truth_type``."""
    g = np.random.default_rng(3).normal(0.0, 1e-7, (5, 3, 3))
    with BagWriter(path) as writer:
        for i in range(5):
            stamp = T0 + i * PERIOD_NS
            for s, topic in enumerate(cv.BAG_MAG_TOPICS):
                writer.write(topic, cv.magnetic_field_msg(writer.types, np.full(3, 1e-6 * (s + 1)), stamp,
                                                          cv.MAG_FRAMES[s]), stamp)
            if truth_type == cv.JOINT_STATE:
                msg = cv.tensor_msg(writer.types, g[i], stamp)
            else:
                msg = gt.gradient_tensor_msg(writer.types, gt.TensorSet(stamp, g[i]))
            writer.write(truth_topic, msg, stamp)
    return g


@pytest.mark.parametrize('truth_type', [cv.JOINT_STATE, gt.GRADIENT_TENSOR])
def test_the_replay_plays_either_recorded_tensor_type_as_gradient_tensor(tmp_path, truth_type):
    g = _bag_with_truth(tmp_path / 'bag', truth_type)
    with MagneticBag(tmp_path / 'bag') as bag:
        assert bag.check_contract() == 20
        assert dict((c.topic, c.msgtype) for c in bag.reader.connections)[TRUTH] == truth_type
    truth = [item[2] for frame in replay.iter_frames(tmp_path / 'bag', TYPES) for item in frame.items
             if item[0] == replay.TRUTH]
    assert len(truth) == 5
    for i, msg in enumerate(truth):
        assert type(msg).__name__ == 'tetra_gradiometer_msgs__msg__GradientTensor'
        played = gt.tensor_set_from_msg(msg)
        assert played.stamp_ns == T0 + i * PERIOD_NS and played.state == gt.RAW
        np.testing.assert_array_equal(played.g, g[i])
        assert np.isnan(played.g_sigma).all()  # unknown: the recording has none


def test_the_shipped_bags_jointstate_truth_replays_as_gradient_tensor():
    with AnyReader([TRIM_BAG], default_typestore=typestore()) as reader:
        (connection,) = [c for c in reader.connections if c.topic == TRUTH]
        first = next(reader.messages(connections=[connection]))
        recorded = cv.tensor_from_msg(reader.deserialize(first[2], connection.msgtype))
    assert connection.msgtype == cv.JOINT_STATE
    frames = replay.iter_frames(TRIM_BAG, TYPES)
    played = next(item[2] for frame in frames for item in frame.items if item[0] == replay.TRUTH)
    frames.close()
    np.testing.assert_array_equal(gt.tensor_set_from_msg(played).g, recorded)


def test_the_contract_takes_either_tensor_type_under_a_namespace_and_names_both_when_refusing(tmp_path):
    recorded = {'/auv1/tetra/gradient/truth': gt.GRADIENT_TENSOR, '/auv1/tetra/mag1': cv.MAGNETIC_FIELD}
    assert namespaced(recorded)['/auv1/tetra/gradient/truth'] == TRUTH
    recorded = {'/auv1/tetra/gradient/truth': cv.JOINT_STATE}
    assert namespaced(recorded) == {'/auv1/tetra/gradient/truth': TRUTH}
    assert checked_remap('bag', {'/t': TRUTH}, {'/t': gt.GRADIENT_TENSOR}) == {'/t': TRUTH}
    with pytest.raises(BagError, match=f'/t holds std_msgs/msg/Float64, not {gt.GRADIENT_TENSOR} or {cv.JOINT_STATE}'):
        checked_remap('bag', {'/t': TRUTH}, {'/t': 'std_msgs/msg/Float64'})
