"""nodes/track.py: the target node's live track against a known trajectory (straight lines at
constant speed: linear interpolation is exact; a constant yaw rate: slerp is exact) and
counts fixed by construction."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core.targets import DetectorSettings
from tetra_gradiometer.nodes.track import SurveyTrack

T0 = 1_800_000_000 * 10**9
MS = 1_000_000


def _track(**kwargs) -> SurveyTrack:
    return SurveyTrack(sample_rate_hz=kwargs.pop('rate', 10.0), history_s=kwargs.pop('history', 3600.0),
                       legs=DetectorSettings(**kwargs))


def _pose(t_s: float, yaw_rate_deg_s: float = 0.0) -> np.ndarray:
    q = Rotation.from_euler('z', yaw_rate_deg_s * t_s, degrees=True).as_quat()
    return np.r_[2.0 * t_s, -3.0 + 0.5 * t_s, -25.0, q]


def test_bins_average_the_tensor_and_take_the_pose_at_their_mean_stamp():
    track = _track(rate=10.0)
    rng = np.random.default_rng(1)
    g = rng.normal(size=(40, 3, 3))
    stamps = T0 + np.arange(40) * 25 * MS + 5 * MS  # 40 Hz: four samples per 0.1 s bin
    for k in range(21):  # odometry at 20 Hz, turning at 10 deg/s
        assert track.add_odom(T0 + k * 50 * MS, _pose(k * 0.05, 10.0)) is None
    for stamp, tensor in zip(stamps, g):
        assert track.add_tensor(int(stamp), tensor) is None
    assert track.resolve() == 9  # the tenth bin is still open
    snapshot = track.snapshot()
    np.testing.assert_allclose(snapshot.survey.tensors, g[:36].reshape(9, 4, 3, 3).mean(axis=1), rtol=1e-12)
    mean_ns = (stamps[:36] - T0).reshape(9, 4).mean(axis=1)  # 42.5 ms + k 100 ms: exact
    assert snapshot.t0_ns == T0 + mean_ns[0] and snapshot.last_ns == T0 + mean_ns[-1]
    t_s = mean_ns * 1e-9
    np.testing.assert_allclose(snapshot.survey.t_s, t_s - t_s[0], atol=1e-12)
    np.testing.assert_allclose(snapshot.survey.positions, [_pose(t)[:3] for t in t_s], atol=1e-9)
    expected = Rotation.from_euler('z', 10.0 * t_s[:, None], degrees=True)
    np.testing.assert_allclose(snapshot.survey.rotations, expected.as_matrix(), atol=1e-9)
    assert track.pending == 4 and len(track) == 9


def test_drops_are_counted_and_a_new_replay_restarts_the_track():
    track = _track()
    for k in range(50):
        track.add_odom(T0 + k * 100 * MS, _pose(k * 0.1))
    assert track.add_odom(T0 + 49 * 100 * MS, _pose(4.9)) is not None  # not after the previous
    assert track.add_odom(T0 + 50 * 100 * MS, np.r_[_pose(5.0)[:3], 0, 0, 0, 0]) is not None
    assert track.add_odom(T0 + 51 * 100 * MS, np.r_[np.nan, _pose(5.1)[1:]]) is not None
    for k in range(30):
        track.add_tensor(T0 + k * 100 * MS, np.full((3, 3), np.nan if k == 3 else 1e-9))
    assert track.add_tensor(T0 + 20 * 100 * MS, np.zeros((3, 3))) is not None
    track.resolve()
    counts = track.counts
    assert (counts.received, counts.dropped_non_finite, counts.dropped_out_of_order, counts.odom_dropped) == (
        31, 1, 1, 3)
    assert len(track) == 28  # 30 - the NaN one - the open bin
    # Two seconds back: a new replay, the track starts again (the odometry too).
    assert track.add_tensor(T0, np.zeros((3, 3))) is None
    assert track.add_odom(T0, _pose(0.0)) is None
    assert counts.restarts == 1 and len(track) == 0 and track.pending == 1


def test_without_odometry_a_bin_waits_ten_seconds_of_tensors_then_is_dropped():
    track = _track()
    for k in range(101):
        track.add_tensor(T0 + k * 100 * MS, np.zeros((3, 3)))
    assert track.resolve() == 0 and track.counts.dropped_no_odom == 0  # 10.0 s: still waiting
    track.add_tensor(T0 + 10_100 * MS, np.zeros((3, 3)))
    track.add_tensor(T0 + 10_200 * MS, np.zeros((3, 3)))  # closes the 10.1 s bin
    assert track.resolve() == 0 and track.counts.dropped_no_odom == 1  # bin 0 gave up
    # Odometry from 0.73 s on: the waiting bins are resolved, those of 0.1 and 0.2 s (over
    # 0.5 s from it) dropped, the others (up to 10.1 s) kept.
    for k in range(7, 103):
        track.add_odom(T0 + k * 100 * MS + 30 * MS, _pose(k * 0.1))
    assert track.resolve() == 101 - 2
    assert track.counts.dropped_no_odom == 3


def test_a_pass_completes_when_a_straight_leg_of_min_leg_s_ends():
    track = _track(min_leg_s=60.0)
    k = 0
    for heading, seconds in ((0.0, 70.0), (90.0, 30.0), (0.0, 61.0), (180.0, 5.0)):
        for _ in range(int(seconds * 10)):
            q = Rotation.from_euler('z', heading, degrees=True).as_quat()
            track.add_odom(T0 + k * 100 * MS, np.r_[0.2 * k, 0.0, -25.0, q])  # steps of 0.2 m
            track.add_tensor(T0 + k * 100 * MS, np.zeros((3, 3)))
            k += 1
        track.resolve()
    assert track.counts.passes == 2  # the 70 s and the 61 s legs, not the 30 s one


def test_the_history_keeps_the_last_history_s():
    track = _track(history=60.0)
    for k in range(1000):
        track.add_odom(T0 + k * 100 * MS, _pose(k * 0.1))
        track.add_tensor(T0 + k * 100 * MS, np.zeros((3, 3)))
        if k % 7 == 0:
            track.resolve()
    track.resolve()
    snapshot = track.snapshot()
    assert snapshot.last_ns - snapshot.t0_ns == 60 * 10**9
    assert len(track) == 601 and track.added == 999


def test_odometry_is_checked_on_the_offline_rule():
    """An unfilled (zero-norm) orientation is dropped and counted; one scaled by 3 (or by
    1.05: within the old 0.1 tolerance, kept unnormalized) is normalized, as core/odometry.py
    does offline, and its rotation is the true one (was dropped: `odom_dropped`)."""
    track = _track()
    for k in range(30):
        pose = _pose(k * 0.1, 10.0)
        if k == 10:
            pose[3:] = 0.0
        if k in (20, 21):
            pose[3:] *= 3.0 if k == 20 else 1.05
        assert (track.add_odom(T0 + k * 100 * MS, pose) is None) == (k != 10)
        track.add_tensor(T0 + k * 100 * MS, np.zeros((3, 3)))
    track.resolve()
    snapshot = track.snapshot()
    t_s = (snapshot.t0_ns - T0) * 1e-9 + snapshot.survey.t_s
    expected = Rotation.from_euler('z', 10.0 * t_s[:, None], degrees=True)
    np.testing.assert_allclose(snapshot.survey.rotations, expected.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(snapshot.orientation_xyzw, axis=1), 1.0, atol=1e-12)
    assert len(track) == 29 and track.counts.odom_dropped == 1
    assert (track.odom_check.dropped, track.odom_check.normalized) == (1, 2)
    report = track.odom_check.report()
    assert report.startswith('1 odometry message with a zero-norm or non-finite orientation or position dropped')
    assert '2 odometry orientations not of unit norm (norm 1.05-3) normalized' in report, report
