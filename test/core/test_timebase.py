"""core/timebase.py: four streams on their own clocks resampled to common instants, against
analytic signals (the truth at any instant is known exactly)."""
from __future__ import annotations

import numpy as np
import pytest

from tetra_gradiometer.core.timebase import Resampler, TimeBase
from tetra_gradiometer.errors import InputError

NS = 1_000_000_000
NT = 1e-9
B0 = np.array([0.0, 20000.0, -45000.0]) * NT


def _field(t_s: np.ndarray) -> np.ndarray:
    """A trim-like body-frame field (n, 3) T: the Earth's field turned at 0.25 rad/s (roll)
    and 0.1 rad/s (heading), smooth and with |B''| ~ omega^2 |B|."""
    roll = 0.44 * np.sin(2 * np.pi * t_s / 11.0)
    yaw = 0.105 * t_s
    c, s = np.cos(yaw), np.sin(yaw)
    x = c * B0[0] + s * B0[1]
    y = -s * B0[0] + c * B0[1]
    z = np.full_like(t_s, B0[2])
    return np.column_stack([x, np.cos(roll) * y + np.sin(roll) * z, -np.sin(roll) * y + np.cos(roll) * z])


def _streams(rng, *, rate=50.0, duration=60.0, offsets_s=(0.0, 0.5e-3, 2.1e-3, 4.0e-3),
             jitter_s=0.2e-3, loss=0.005, rates=None):
    """Per-sensor (stamps ns, fields) with the true field at each true sample time."""
    streams = []
    for s in range(4):
        r = rate if rates is None else rates[s]
        t = offsets_s[s] + np.arange(int(duration * r)) / r + rng.normal(0, jitter_s, int(duration * r))
        t = np.sort(t[t >= 0])
        keep = rng.random(len(t)) >= (loss if s else 0.0)  # sensor 1 keeps all: truth lines up
        t = t[keep]
        stamps = 10 * NS + np.round(t * NS).astype(np.int64)
        streams.append((stamps, _field(t)))
    return streams


def _feed(resampler, streams, chunk=None):
    """Offline style: each sensor's stream in chunks, round-robin; returns all sets."""
    n = max(len(s[0]) for s in streams)
    chunk = chunk or n
    out_t, out_v = [], []
    for start in range(0, n, chunk):
        for sensor, (t, v) in enumerate(streams):
            got_t, got_v = resampler.add(sensor, t[start:start + chunk], v[start:start + chunk])
            out_t.append(got_t)
            out_v.append(got_v)
    return np.concatenate(out_t), np.concatenate(out_v)


def test_synchronous_streams_give_exactly_the_recorded_readings():
    stamps = 5 * NS + np.arange(500) * 10_000_000
    fields = np.random.default_rng(1).normal(size=(4, 500, 3)) * 3e-5
    resampler = Resampler(TimeBase())
    t, v = _feed(resampler, [(stamps, fields[s]) for s in range(4)], chunk=77)
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_array_equal(v, np.swapaxes(fields, 0, 1))
    assert resampler.counters.sets == 500 and resampler.counters.skipped == 0
    assert all(abs(c.offset_s) == 0 and c.jitter_s == 0 and c.rate_hz == pytest.approx(100) for c in resampler.clocks())


@pytest.mark.parametrize('rate', [25.0, 50.0, 100.0])
def test_async_resampling_error_is_far_below_the_noise_and_below_linear(rate):
    rng = np.random.default_rng(int(rate))
    streams = _streams(rng, rate=rate)
    resampler = Resampler(TimeBase())
    t, v = _feed(resampler, streams, chunk=333)
    t_s = (t - 10 * NS) / NS
    truth = _field(t_s)
    error = np.abs(v - truth[:, None, :]).max(axis=2) / NT  # (m, 4) nT
    # Independent linear interpolation (numpy) at the same instants, for comparison.
    linear = max(np.abs(np.interp(t, streams[s][0], streams[s][1][:, k]) - truth[:, k]).max()
                 for s in range(1, 4) for k in range(3)) / NT
    # Quadratic: ~0.1 h^3 |B'''|, 1e-3 nT at 50 Hz; a few sets (the first one, and next to a
    # lost message, where the nodes are two periods apart) err more, still below the noise.
    assert np.percentile(error, 99) < 0.005 * (50.0 / rate) ** 3, np.percentile(error, 99, axis=0)
    assert error.max() < 0.15 * (25.0 / rate) ** 2, error.max(axis=0)
    assert np.percentile(error, 99) < 0.05 * linear, (error.max(axis=0), linear)
    # Nothing lost but the sets around real gaps and the start.
    c = resampler.counters
    assert c.sets == len(t) and c.sets + c.skipped >= len(streams[0][0]) - 2


def test_offsets_and_jitter_are_estimated():
    rng = np.random.default_rng(3)
    offsets = (0.0, 0.5e-3, -2.0e-3, 4.0e-3)
    resampler = Resampler(TimeBase())
    _feed(resampler, _streams(rng, offsets_s=offsets, jitter_s=0.2e-3), chunk=1000)
    clocks = resampler.clocks()
    for s in range(1, 4):
        assert clocks[s].offset_s == pytest.approx(offsets[s], abs=0.02e-3)
        assert clocks[s].jitter_s == pytest.approx(np.sqrt(2) * 0.2e-3, rel=0.1)  # both clocks jitter
        assert clocks[s].rate_hz == pytest.approx(50.0, rel=0.01)
    assert clocks[0].offset_s == 0.0 and clocks[0].jitter_s == 0.0


def test_message_by_message_gives_the_same_sets_as_batches():
    streams = _streams(np.random.default_rng(4), duration=10.0)
    batch = _feed(Resampler(TimeBase()), streams, chunk=100)
    live = Resampler(TimeBase())
    events = sorted((int(t), s, i) for s, (ts, _) in enumerate(streams) for i, t in enumerate(ts))
    got_t, got_v = [], []
    for _, s, i in events:  # arrival in stamp order, one message at a time
        t, v = live.add(s, streams[s][0][i:i + 1], streams[s][1][i:i + 1])
        got_t.append(t)
        got_v.append(v)
    np.testing.assert_array_equal(np.concatenate(got_t), batch[0])
    np.testing.assert_allclose(np.concatenate(got_v), batch[1], rtol=0, atol=1e-20)


@pytest.mark.parametrize('reference_rate_hz', [0.0, 20.0])
def test_add_one_gives_the_same_sets_and_counts_as_add(reference_rate_hz):
    """The live path (Python scalars) against the array path, with a spike, an implausible
    reading, a repeated stamp and a lost message in the stream."""
    streams = _streams(np.random.default_rng(9), duration=5.0)
    fields = streams[1][1].copy()
    fields[40], fields[90] = [np.inf, 0.0, 0.0], [2e-3, 0.0, 0.0]
    streams[1] = (streams[1][0], fields)
    events = sorted((int(t), s, i) for s, (ts, _) in enumerate(streams) for i, t in enumerate(ts))
    events.insert(300, events[299])  # the same message again: out of order
    base = TimeBase(reference_rate_hz=reference_rate_hz)
    array_path, scalar_path = Resampler(base, max_field_t=1e-4), Resampler(base, max_field_t=1e-4)
    got: list[list] = [[], []]
    for _, s, i in events:
        stamps, values = streams[s][0][i:i + 1], streams[s][1][i:i + 1]
        got[0].append(array_path.add(s, stamps, values))
        got[1].append(scalar_path.add_one(s, int(stamps[0]), values[0]))
    for k in (0, 1):  # stamps, then values
        np.testing.assert_array_equal(np.concatenate([g[k] for g in got[1]]),
                                      np.concatenate([g[k] for g in got[0]]))
    assert scalar_path.counters == array_path.counters
    assert scalar_path.counters.out_of_order == 1


def test_live_latency_is_one_sample_of_the_latest_sensor():
    """An instant is emitted by the first message of every sensor at or after it."""
    streams = _streams(np.random.default_rng(5), duration=5.0, loss=0.0, jitter_s=0.0)
    live = Resampler(TimeBase())
    events = sorted((int(t), s, i) for s, (ts, _) in enumerate(streams) for i, t in enumerate(ts))
    delays = []
    for stamp, s, i in events:
        t, _ = live.add(s, streams[s][0][i:i + 1], streams[s][1][i:i + 1])
        delays += [(stamp - x) / NS for x in t]
    assert max(delays) == pytest.approx(4.0e-3, abs=1e-6)  # the latest sensor's offset


def test_gaps_longer_than_the_limit_are_skipped_and_counted():
    stamps = np.arange(1000) * 20_000_000
    fields = _field(stamps / NS)
    gap = (stamps < 5 * NS) | (stamps > 5.1 * NS)            # sensor 3 silent 100 ms = 5 periods
    one_lost = stamps != 8 * NS                              # sensor 4 loses one message
    streams = [(stamps + 1_000_000 * s, _field((stamps + 1_000_000 * s) / NS)) for s in range(4)]
    streams[2] = (streams[2][0][gap], streams[2][1][gap])
    streams[3] = (streams[3][0][one_lost], streams[3][1][one_lost])
    resampler = Resampler(TimeBase())
    t, v = _feed(resampler, streams, chunk=64)
    skipped = np.setdiff1d(stamps, t)
    # Sensor 3 jumps 4.982 -> 5.122 s: no sample within 3 periods before 5.00-5.12 s, and
    # 5.14 s has only one earlier sample after the gap (quadratic needs two).
    expected_gap = stamps[(stamps >= 5.0 * NS) & (stamps <= 5.14 * NS)]
    np.testing.assert_array_equal(skipped, np.concatenate([[0, 20_000_000], expected_gap]))
    assert resampler.counters.skipped_gap == len(expected_gap)
    assert resampler.counters.skipped_start == 2  # sensors 2-4 have < 2 samples before 0 and 20 ms
    assert 8 * NS in t                                       # one lost message: interpolated across
    np.testing.assert_allclose(v[:, 3], fields[np.isin(stamps, t)], atol=0.05 * NT)
    # A limit of 8 periods interpolates across its 140 ms silence too.
    wide = Resampler(TimeBase(max_gap_periods=8.0))
    t_wide, _ = _feed(wide, streams, chunk=64)
    assert len(t_wide) == len(stamps) - 2


def test_grid_reference_instants():
    streams = _streams(np.random.default_rng(6), rate=50.0, duration=20.0)
    resampler = Resampler(TimeBase(reference_rate_hz=20.0))
    t, v = _feed(resampler, streams, chunk=200)
    assert np.all(t % 50_000_000 == 0) and np.all(np.diff(t) == 50_000_000)
    truth = _field((t - 10 * NS) / NS)
    assert np.abs(v - truth[:, None, :]).max() < 0.02 * NT


def test_out_of_order_and_a_silent_sensor_are_bounded_and_counted():
    resampler = Resampler(TimeBase(), max_pending=100)
    stamps = np.arange(1000) * 10_000_000
    for s in range(3):                                       # sensor 4 never speaks
        resampler.add(s, stamps, np.zeros((1000, 3)))
    assert resampler.pending == 100 and resampler.counters.evicted == 900
    assert all(len(t) <= 1000 for t in resampler._t)
    resampler.add(0, stamps[:5], np.zeros((5, 3)))
    assert resampler.counters.out_of_order == 5


def test_bad_time_base_is_refused():
    with pytest.raises(InputError, match='max_gap_periods'):
        TimeBase(max_gap_periods=0.5)
    with pytest.raises(InputError, match='sync'):
        TimeBase(sync='spline')
    with pytest.raises(InputError, match='interpolate'):
        Resampler(TimeBase(sync='nearest'))


def test_a_spike_costs_its_own_set_and_never_leaks_into_the_neighbours():
    streams = _streams(np.random.default_rng(8), duration=10.0, loss=0.0)
    spike_at = 200
    fields = streams[2][1].copy()
    fields[spike_at] = [np.nan, 0.0, 0.0]
    streams[2] = (streams[2][0], fields)
    resampler = Resampler(TimeBase())
    t, v = _feed(resampler, streams, chunk=64)
    nearest = int(np.argmin(np.abs(t - streams[2][0][spike_at])))
    assert np.isnan(v[nearest, 2, 0])                  # the caller's plausibility check drops it
    finite = np.delete(np.arange(len(t)), nearest)
    assert np.all(np.isfinite(v[finite]))
    truth = _field((t[finite] - 10 * NS) / NS)
    assert np.abs(v[finite, 2] - truth).max() < 0.05 * NT  # interpolated across, as a lost message
