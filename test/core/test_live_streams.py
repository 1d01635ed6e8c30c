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


def test_a_stream_that_loses_39_percent_at_1_khz_counts_the_lost_messages():
    keep = np.random.default_rng(1).random(20_000) > 0.39
    keep[:40] = True  # the period is learnt on the first intervals
    check = LiveStreamCheck()
    _feed(check, 1_000_000, keep)
    lost = int(np.sum(~keep[: np.flatnonzero(keep)[-1]]))
    assert all(0.97 * lost <= m <= lost for m in check.missing), (check.missing, lost)
    text = check.missing_text(0, int(keep.sum()))
    assert f'{check.missing[0]} messages missing by their stamps' in text and 'lost before the node' in text


def test_a_complete_jittered_stream_misses_nothing():
    check = LiveStreamCheck()
    _feed(check, 10_000_000, np.ones(5000, bool), jitter_ns=300_000, seed=2)
    assert check.missing == [0] * 4 and check.missing_text(0, 5000) == ''


def _bursts(n_bursts, keep_burst, size=5, period_ns=1_000_000, spacing_ns=10_000):
    """Stamps taken on arrival: each ``size`` messages of a 1 kHz sensor arrive together
    every ``size`` ms (a USB driver's transfers), ``spacing_ns`` apart."""
    return [START + b * size * period_ns + i * spacing_ns
            for b in range(n_bursts) if keep_burst[b] for i in range(size)]


def test_stamps_taken_on_arrival_in_bursts_are_no_loss_and_lost_bursts_are_counted():
    complete = LiveStreamCheck()
    for stamp in _bursts(2000, np.ones(2000, bool)):
        complete.accept(0, stamp, stamp, 0.0, 2e-5, -4.5e-5)
    assert complete.missing[0] == 0
    keep = np.random.default_rng(4).random(2000) > 0.1
    keep[:20] = True
    lossy = LiveStreamCheck()
    for stamp in _bursts(2000, keep):
        lossy.accept(0, stamp, stamp, 0.0, 2e-5, -4.5e-5)
    lost = 5 * int(np.sum(~keep[: np.flatnonzero(keep)[-1]]))
    assert 0 < lossy.missing[0] <= lost  # bursts: named, fewer than were lost, never more


def test_a_publisher_that_stalls_and_catches_up_loses_nothing():
    """Stamps taken on sending: a 1 kHz driver stalls 20 ms every 0.5 s, then sends its late
    sets back to back (50 us apart), or drops them. Truth by conservation: the 1 ms slots
    the span holds less the messages received."""
    for catch_up in (20, 19, 0):
        check, stamp, received = LiveStreamCheck(), START, 0
        for k in range(20_000):
            if k % 500 == 499:
                stamp += 20_000_000 - catch_up * 50_000
                for _ in range(catch_up):
                    stamp += 50_000
                    check.accept(0, stamp, stamp, 0.0, 2e-5, -4.5e-5)
                    received += 1
            stamp += 1_000_000
            check.accept(0, stamp, stamp, 0.0, 2e-5, -4.5e-5)
            received += 1
        lost = round((stamp - START) / 1e6) - received
        assert abs(check.missing[0] - lost) <= max(0.05 * lost, 2), (catch_up, check.missing[0], lost)
