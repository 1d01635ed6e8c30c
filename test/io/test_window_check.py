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
    np.testing.assert_array_equal(history.at(sample), quats[40])
    samples = stamps[5:-5] + 13_000_000
    np.testing.assert_allclose(history.over(samples), orientation_at(stamps, quats, samples))
    assert np.all(np.isnan(history.at(int(stamps[-1]) + 2 * NS)))
    history.add(int(stamps[0]), quats[0])  # time went back (a replay restarted): the rest is stale
    assert np.all(np.isnan(history.at(int(stamps[100]))))
