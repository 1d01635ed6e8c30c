"""nodes/target.py and its outputs (nodes/target_messages.py, nodes/track.py).

Truth: hand-built fits and tracks for the messages (read back through rclpy's own
serialization) and scipy's rotations for the pose orientation; the simulator's dipole for the
node fed a simulated survey over real DDS (the compensated tensor and the odometry a
compensator and a navigation would publish, faster than real time); counts fixed by the
construction of the bad input."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from in_process import last_status, node_in_process
from scipy.spatial.transform import Rotation

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.nodes import target_messages as tm

T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
PERIOD_NS = 10**8  # 10 Hz, the node's default sample rate: one sample per bin


def _round_trip(msg):
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


# --------------------------------------------------------------------------- messages


def test_x_axis_onto_rotates_x_onto_each_direction_as_scipy_applies_it():
    rng = np.random.default_rng(1)
    directions = np.vstack([rng.normal(size=(20, 3)) * 1e4, [[-3.0, 0, 0], [5.0, 0, 0], [-1, 1e-12, 0]]])
    q = tm.x_axis_onto(directions)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-12)
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    np.testing.assert_allclose(Rotation.from_quat(q).apply([1.0, 0.0, 0.0]), unit, atol=1e-9)
    np.testing.assert_array_equal(tm.x_axis_onto(np.zeros((1, 3))), [[0.0, 0.0, 0.0, 1.0]])


def _target(position, sigma, moment, detection):
    from tetra_gradiometer.core.targets import DipoleFit, Target

    covariance = np.diag(np.r_[np.square(sigma), np.full(3, 25.0)])
    fit = DipoleFit(np.array(position, float), np.array(moment, float), covariance, np.zeros((1, 3, 3)),
                    rms=2e-11, chi2_reduced=1.1, misfit_fraction=0.01, n_samples=300)
    return Target(fit, [detection], first_seen_s=1.5, last_seen_s=9.5, dipolar=True)


def _located():
    """Two finite targets and one with a NaN covariance, on a 10-sample track."""
    from tetra_gradiometer.core.targets import Detection, DetectionResult, Survey
    from tetra_gradiometer.nodes.track import TrackSnapshot

    n = 10
    t = np.arange(n) * 0.1
    positions = np.column_stack([2.0 * t, np.full(n, 3.0), np.full(n, -25.0)])
    orientations = Rotation.from_euler('z', np.linspace(0, 30, n)[:, None], degrees=True).as_quat()
    track = TrackSnapshot(Survey(t, positions, Rotation.from_quat(orientations).as_matrix(), np.zeros((n, 3, 3))),
                          orientations, T0 + 30_000_000, T0 + 30_000_000 + 9 * PERIOD_NS)
    detections = [Detection(1, 4, 2, 50.0, 0, n), Detection(5, 9, 7, 40.0, 0, n)]
    targets = [_target([10.0, 3.0, -45.0], [0.01, 0.02, 0.03], [1.2e4, -1e4, -2.5e4], detections[0]),
               _target([-4.0, 1.0, -40.0], [0.3, 0.2, 0.5], [0.0, 3e3, 0.0], detections[1]),
               _target([1.0, 1.0, -30.0], [np.nan, 0.1, 0.1], [1.0, 0.0, 0.0], detections[1])]
    result = DetectionResult(detections, np.zeros(n), 1.0, None, np.zeros((n, 3, 3)), [(0, n)], None)
    return tm.located_targets(track, targets, result, false_alarms_per_hour=0.1), positions, orientations


def test_located_targets_leave_out_the_non_finite_fit_and_place_detections_on_the_track():
    located, positions, orientations = _located()
    assert located.dropped_non_finite == 1 and located.samples == 10
    np.testing.assert_array_equal(located.positions, [[10.0, 3.0, -45.0], [-4.0, 1.0, -40.0]])
    np.testing.assert_allclose(located.position_sigmas, [[0.01, 0.02, 0.03], [0.3, 0.2, 0.5]], rtol=1e-12)
    np.testing.assert_array_equal(located.moments, [[1.2e4, -1e4, -2.5e4], [0.0, 3e3, 0.0]])
    np.testing.assert_array_equal(located.detection_positions, positions[[2, 7]])
    np.testing.assert_array_equal(located.detection_orientations, orientations[[2, 7]])
    assert located.stamp_ns == T0 + 30_000_000 + 9 * PERIOD_NS


def test_pose_array_marker_array_and_json_string_read_back_through_rclpy():
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker

    from tetra_gradiometer.io.targets import FRAME, TARGET_KEYS

    located, _, _ = _located()
    types, stamp = cv.rclpy_types(), located.stamp_ns
    orientation = tm.x_axis_onto(located.moments)
    poses = _round_trip(tm.pose_array_msg(types, located.positions, orientation, stamp, 'auv1/odom'))
    assert (cv.stamp_to_ns(poses.header.stamp), poses.header.frame_id) == (stamp, 'auv1/odom')
    got = [(p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
            p.orientation.w) for p in poses.poses]
    np.testing.assert_array_equal(got, np.hstack([located.positions, orientation]))

    markers = _round_trip(tm.target_markers_msg(types, located.positions, located.position_sigmas,
                                                located.moments, stamp)).markers
    assert [m.action for m in markers] == [Marker.DELETEALL] + [Marker.ADD] * 4
    assert [m.id for m in markers[1:]] == [0, 1, 2, 3]
    assert [m.type for m in markers[1:]] == [Marker.SPHERE, Marker.TEXT_VIEW_FACING] * 2
    assert {m.ns for m in markers} == {'targets'} and {m.header.frame_id for m in markers} == {'odom'}
    for k, (sphere, label) in enumerate(zip(markers[1::2], markers[2::2])):
        centre = located.positions[k]
        assert [sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z] == list(centre)
        # 3-sigma half-axes: 6 sigma wide, at least 0.1 m (the first target's 0.06 m axis).
        expected = np.maximum(6 * located.position_sigmas[k], 0.1)
        np.testing.assert_allclose([sphere.scale.x, sphere.scale.y, sphere.scale.z], expected, rtol=1e-12)
        assert 0 < sphere.color.a < 1
        assert label.pose.position.z > centre[2] + expected[2] / 2
        assert label.text == f'T{k + 1} {np.linalg.norm(located.moments[k]):.3g} A m^2'
    assert markers[2].text == 'T1 2.95e+04 A m^2'  # sqrt(1.44 + 1 + 6.25) = 2.948, x 1e4

    text = _round_trip(String(data=located.document)).data
    document = json.loads(text, parse_constant=lambda name: pytest.fail(f'{name} in the JSON'))
    assert (document['frame'], document['tensor'], document['detections']) == (FRAME, 'compensated', 2)
    assert document['t0_stamp_s'] == pytest.approx(1_700_000_000.03, abs=1e-6)
    assert len(document['targets']) == 2
    for entry, position, moment in zip(document['targets'], located.positions, located.moments):
        assert set(TARGET_KEYS) <= set(entry)
        assert entry['position_m'] == list(position) and entry['moment_Am2'] == list(moment)
        assert entry['moment_sigma_Am2'] == [5.0, 5.0, 5.0]
        assert (entry['first_seen_s'], entry['last_seen_s'], entry['passes']) == (1.5, 9.5, 1)
        assert entry['fit_rms_nT_per_m'] == pytest.approx(0.02)


# --------------------------------------------------------------------------- the node


def _tensor_msg(types, g, stamp_ns: int):
    """A compensated GradientTensor of ``g`` (3, 3) T/m at ``stamp_ns``."""
    return gt.gradient_tensor_msg(types, gt.TensorSet(stamp_ns, g, state=gt.COMPENSATED))


STATUS = 'tetra/target: targets'
DIPOLE = {'position_m': [10.0, 3.0, -45.0], 'moment_Am2': [1.2e4, -1.0e4, -2.5e4]}  # |m| 2.95e4 A m^2


def _target_node(monkeypatch, **params):
    """``(node, published)`` of a target node in this process (test/ros/in_process.py)."""
    from tetra_gradiometer.nodes.target import TargetNode

    return node_in_process(TargetNode, monkeypatch, warn_throttle_s=30.0, **params)


def _searched(node, published, expected: int) -> dict:
    """Tick the node (its timer) until its search has taken ``expected`` samples and is done
    (the search runs on a worker thread); its /diagnostics status then."""
    deadline = time.monotonic() + 60.0
    while True:
        node._tick()
        node._publish_diagnostics()
        status = last_status(published, STATUS)
        if status.get('searched_samples') == str(expected) and status.get('searching') == 'False':
            return status
        assert time.monotonic() < deadline, status
        time.sleep(0.05)


def _latest(published, topic: str):
    found = [m for t, m in published if t == topic]
    return found[-1] if found else None


def _simulated_survey():
    """Two 120 s lines 20 m above the dipole, 16 m apart, at 10 Hz: stamps (ns), the
    compensated tensor (clean fields plus 0.05 nT sensor noise), positions and orientations."""
    from tetra_gradiometer.core import difference_tensor, simulate
    from tetra_gradiometer.io.scenario import scenario_from_dict

    segments = [{'line': {'start_m': [a, y, -25.0], 'end_m': [b, y, -25.0], 'speed_m_s': 2.0,
                          'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}}
                for a, b, y in ((-110.0, 130.0, -8.0), (130.0, -110.0, 8.0))]
    scenario, _ = scenario_from_dict({'seed': 4, 'sample_rate_hz': 10.0, 'noise_nT': 0.05, 'dipoles': [DIPOLE],
                                      'segments': segments})
    rng = np.random.default_rng(4)
    mission = simulate(scenario, rng)
    noisy = mission.fields_true + rng.normal(0.0, scenario.noise_t, mission.fields_true.shape)
    stamps = T0 + np.round(mission.t * 1e9).astype(np.int64)
    return stamps, difference_tensor(noisy, scenario.geometry), mission.position_enu, mission.orientation_xyzw


def test_the_node_locates_the_simulated_dipole_and_latches_its_outputs(monkeypatch):
    from rclpy.qos import DurabilityPolicy
    from rclpy.serialization import serialize_message

    stamps, tensors, positions, orientations = _simulated_survey()
    n = len(stamps)
    types = cv.rclpy_types()
    with _target_node(monkeypatch, update_period_s=2.0) as (node, published):
        for i, stamp in enumerate(stamps):
            node._on_tensor(serialize_message(_tensor_msg(types, tensors[i], int(stamp))))
            node._on_odom(cv.odometry_msg(types, positions[i], orientations[i], int(stamp)))
        status = _searched(node, published, n - 1)  # the last sample's bin stays open
        # A subscriber that joins late gets the results: the outputs are latched.
        for topic in ('targets', 'targets/markers', 'targets/json', 'detections'):
            (publisher,) = [p for p in node.publishers if p.topic_name == f'/tetra/{topic}']
            assert publisher.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL, topic
    poses, document = _latest(published, '/tetra/targets'), json.loads(_latest(published, '/tetra/targets/json').data)
    markers, detections = _latest(published, '/tetra/targets/markers').markers, _latest(published, '/tetra/detections')
    final = int(stamps[-2])
    assert cv.stamp_to_ns(poses.header.stamp) == final and cv.stamp_to_ns(detections.header.stamp) == final
    assert status['level'] == 0 and status['received'] == str(n)
    for name in ('dropped_malformed', 'dropped_non_finite', 'dropped_out_of_order', 'dropped_no_odom'):
        assert status[name] == '0', (name, status)
    assert int(status['passes']) >= 1  # the first line ended with the turn onto the second
    assert poses.header.frame_id == 'odom' and len(poses.poses) == 1
    pose = poses.poses[0]
    found = np.array([pose.position.x, pose.position.y, pose.position.z])
    assert np.linalg.norm(found - DIPOLE['position_m']) < 0.5, found
    moment = np.array(document['targets'][0]['moment_Am2'])
    assert np.linalg.norm(moment - DIPOLE['moment_Am2']) < 0.05 * np.linalg.norm(DIPOLE['moment_Am2'])
    x_axis = Rotation.from_quat([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                                 pose.orientation.w]).apply([1.0, 0.0, 0.0])
    np.testing.assert_allclose(x_axis, moment / np.linalg.norm(moment), atol=1e-9)
    entry = document['targets'][0]
    assert all(0 < s < 0.5 for s in entry['position_sigma_m']) and entry['dipolar']
    assert document['t0_stamp_s'] == pytest.approx(stamps[0] * 1e-9)
    assert markers[0].action == markers[0].DELETEALL and len(markers) == 3
    assert markers[1].pose.position.x == pose.position.x
    peaks = np.array([[p.position.x, p.position.y, p.position.z] for p in detections.poses])
    assert document['detections'] == len(peaks) >= 2  # the target seen from both lines
    assert np.min(np.linalg.norm(peaks[:, :2] - found[:2], axis=1)) < 15.0  # abeam of it


def test_bad_input_is_dropped_and_counted_and_never_searched(monkeypatch):
    """A 90 s straight leg over nothing: four non-finite tensors, two stamps out of order, a
    malformed tensor message, a 3 s odometry outage, a NaN odometry message, an unfilled
    (zero-norm) orientation, dropped, and one scaled by 3, normalized."""
    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(9)
    n = 900
    t_s = np.arange(n) * 0.1
    positions = np.column_stack([2.0 * t_s, np.zeros(n), np.full(n, -25.0)])
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    tensors = rng.normal(0.0, 0.1e-9, (n, 3, 3))
    tensors[50:53, 0, 0] = np.nan
    tensors[53, 1, 1] = np.inf
    # The tensors 30 ms after the odometry (no tie in the nearest-message rule): without
    # odometry for stamps 70.0-72.9 s, the tensors 70.43 .. 72.43 s are over 0.5 s from any.
    tensor_stamps = T0 + np.arange(n) * PERIOD_NS + 30_000_000
    types = cv.rclpy_types()
    with _target_node(monkeypatch, update_period_s=1.0) as (node, published):
        orientations = identity * np.where(np.arange(n) == 810, 0.0, np.where(np.arange(n) == 820, 3.0, 1.0))[:, None]
        for i in range(n):
            node._on_tensor(serialize_message(_tensor_msg(types, tensors[i], int(tensor_stamps[i]))))
            if i == 60:  # an older and an equal stamp
                for stamp in (tensor_stamps[58], tensor_stamps[60]):
                    node._on_tensor(serialize_message(_tensor_msg(types, tensors[0], int(stamp))))
                whole = serialize_message(_tensor_msg(types, tensors[0], int(tensor_stamps[60])))
                node._on_tensor(whole[:100])  # cut inside the doubles: malformed
            if not 700 <= i < 730:
                position = positions[i] * (np.nan if i == 800 else 1.0)
                node._on_odom(cv.odometry_msg(types, position, orientations[i], T0 + i * PERIOD_NS))
            if i % 100 == 99:
                node._tick()  # its timer: poses resolved as the samples come
                node._publish_diagnostics()
        expected = n - 4 - 21 - 1  # non-finite, no odometry, the last bin (still open)
        status = _searched(node, published, expected)
    poses, text = _latest(published, '/tetra/targets'), _latest(published, '/tetra/targets/json')
    detections = _latest(published, '/tetra/detections')
    warnings = [s.message for topic, m in published if topic == '/diagnostics' for s in m.status
                if s.name == STATUS and s.level == bytes([1])]
    counts = {name: int(status[name]) for name in (
        'received', 'buffered_samples', 'pending_samples', 'dropped_malformed', 'dropped_non_finite',
        'dropped_out_of_order', 'dropped_no_odom', 'odom_dropped', 'odom_dropped_zero_norm', 'odom_normalized',
        'restarts')}
    assert counts == {'received': n + 2, 'buffered_samples': expected, 'pending_samples': 1,
                      'dropped_malformed': 1, 'dropped_non_finite': 4, 'dropped_out_of_order': 2,
                      'dropped_no_odom': 21, 'odom_dropped': 2, 'odom_dropped_zero_norm': 2,
                      'odom_normalized': 1, 'restarts': 0}
    warned = ' '.join(warnings)
    assert 'with a zero-norm or non-finite orientation or position dropped (an unfilled orientation; 2 in all)' in warned, warned
    assert '1 odometry orientation not of unit norm (norm 3) normalized' in warned, warned
    assert status['level'] == 0  # no sample lacked odometry since the previous report
    document = json.loads(text.data, parse_constant=lambda name: pytest.fail(f'{name} in the JSON'))
    assert document['targets'] == [] and poses.poses == []
    assert all(np.isfinite([p.position.x, p.position.y, p.position.z]).all() for p in detections.poses)
