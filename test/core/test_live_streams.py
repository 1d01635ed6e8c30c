"""Messages lost before the tensor node are counted from the gaps in each sensor's stamps
(core/live_streams.LiveStreamCheck.missing). Truth: the messages the test withheld."""
import numpy as np

from tetra_gradiometer.core.live_streams import LiveStreamCheck

START = 1_767_225_600 * 10**9


def _feed(check, period_ns, keep, jitter_ns=0, seed=0):
    rng = np.random.default_rng(seed)
    for k in np.flatnonzero(keep):
        stamp = START + int(k) * period_ns + int(rng.normal(0, jitter_ns)) if jitter_ns else START + int(k) * period_ns
        for sensor in range(4):
            assert check.accept(sensor, stamp, stamp, 0.0, 2e-5, -4.5e-5)


def test_a_stream_that_loses_39_percent_at_1_khz_counts_each_lost_message():
    keep = np.random.default_rng(1).random(20_000) > 0.39
    keep[:40] = True  # the period is learnt on the first intervals
    check = LiveStreamCheck()
    _feed(check, 1_000_000, keep)
    lost = int(np.sum(~keep[: np.flatnonzero(keep)[-1]]))
    assert check.missing == [lost] * 4
    text = check.missing_text(0, int(keep.sum()))
    assert f'{lost} messages missing by their stamps' in text and 'lost before the node' in text


def test_a_complete_jittered_stream_misses_nothing():
    check = LiveStreamCheck()
    _feed(check, 10_000_000, np.ones(5000, bool), jitter_ns=300_000, seed=2)
    assert check.missing == [0] * 4 and check.missing_text(0, 5000) == ''
