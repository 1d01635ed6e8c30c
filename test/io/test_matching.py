"""io/matching.py: sets matched by stamp from hand-made streams (one loss, jitter, one
out-of-order message)."""
import numpy as np

from tetra_gradiometer.io.matching import StampMatcher


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
