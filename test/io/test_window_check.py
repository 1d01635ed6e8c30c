"""pipelines/window_check.py's attitude from /odom against scipy's rotations: a vehicle yawing at a
constant rate (slerp between messages is then exact), gaps in /odom, and the live history."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from tetra_gradiometer.pipelines.window_check import MAX_ODOM_GAP_S, AttitudeHistory, orientation_at

NS = 10**9
T0 = 1_800_000_000 * NS
RATE_DEG_S = 10.0


def yaw(t_ns):
    return Rotation.from_euler('z', (RATE_DEG_S * (np.asarray(t_ns) - T0) / NS)[:, None], degrees=True)


def odom(period_s=0.05, duration_s=10.0):
    stamps = T0 + np.round(np.arange(0.0, duration_s, period_s) * NS).astype(np.int64)
    return stamps, yaw(stamps).as_quat()


def angle_deg(q, truth):
    return np.degrees((Rotation.from_quat(q) * truth.inv()).magnitude())


def test_orientation_between_messages_is_the_true_attitude():
    stamps, quats = odom()
    samples = T0 + np.round(np.linspace(0.1, 9.8, 500) * NS).astype(np.int64) + 7_000_000
    assert angle_deg(orientation_at(stamps, quats, samples), yaw(samples)).max() < 1e-9


def test_gaps_and_ends_beyond_the_limit_are_unknown():
    stamps, quats = odom()
    keep = (stamps < T0 + 4 * NS) | (stamps > T0 + 6 * NS)  # a 2 s hole in /odom
    edge = int(MAX_ODOM_GAP_S * NS)
    samples = np.array([T0 + 5 * NS, T0 + 4 * NS + edge // 2, stamps[-1] + edge + 1, T0 - edge // 2])
    got = orientation_at(stamps[keep], quats[keep], samples)
    assert np.all(np.isnan(got[[0, 2]]))
    assert np.all(np.isfinite(got[[1, 3]]))  # within the limit: held or slerped across
    assert np.all(np.isnan(orientation_at(stamps[:0], quats[:0], samples)))


def test_the_live_history_gives_the_nearest_message_and_all_samples_at_the_end():
    stamps, quats = odom()
    history = AttitudeHistory()
    for stamp, quat in zip(stamps, quats, strict=True):
        history.add(int(stamp), quat)
    sample = int(stamps[40]) + 20_000_000  # 20 ms after a message, 30 ms before the next
    np.testing.assert_allclose(history.at(sample), quats[40], rtol=0, atol=1e-15)  # normalized: 1 ulp
    samples = stamps[5:-5] + 13_000_000
    np.testing.assert_allclose(history.over(samples), orientation_at(stamps, quats, samples))
    assert np.all(np.isnan(history.at(int(stamps[-1]) + 2 * NS)))
    history.add(int(stamps[0]), quats[0])  # time went back (a replay restarted): the rest is stale
    assert np.all(np.isnan(history.at(int(stamps[100]))))


def test_the_live_history_drops_zero_norm_and_normalizes_unnormalized_quaternions():
    """Issue 30 item 2, live: an unfilled orientation (all zeros), a NaN one and one scaled by 3
    among the messages. The first two are dropped and counted (the samples around them take the
    neighbouring messages, as if they had not come), the third normalized: the attitudes equal
    the true yaw's, never an error (was `ValueError: Found zero norm quaternions` at ~/calibrate)."""
    stamps, quats = odom()
    fed = quats.copy()
    fed[40] = 0.0
    fed[41, 2] = np.nan
    fed[60] *= 3.0
    history = AttitudeHistory()
    for stamp, quat in zip(stamps, fed, strict=True):
        history.add(int(stamp), quat)
    samples = stamps[5:-5] + 13_000_000
    assert angle_deg(history.over(samples), yaw(samples)).max() < 1e-9
    assert angle_deg(history.at(int(stamps[40]))[None], yaw(stamps[40:41])).max() < 0.6  # a neighbour, 50 ms away
    np.testing.assert_allclose(history.at(int(stamps[60])), quats[60], atol=1e-12)
    assert (history.check.dropped, history.check.normalized) == (2, 1)
    report = history.check.report()
    assert '2 odometry messages with a zero-norm or non-finite orientation dropped' in report, report
    assert '1 odometry orientation not of unit norm (norm 3) normalized' in report, report
    assert history.check.report() == ''  # nothing new since
