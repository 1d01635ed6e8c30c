"""nodes/channels.LiveEffects without a graph: the compensator holds a set that arrives before
its channels' messages at or after its stamp, so that its value is interpolated as offline
(io/channels.ChannelSeries.on), for at most two periods of the lagging channel of later sets'
stamps (on the steady clock only once the sets stop); a channel that stops releases its sets at that bound, a
restarted replay releases the queue, nothing is lost or reordered."""
from __future__ import annotations

import numpy as np
from channel_helpers import BATTERY, example_terms

from tetra_gradiometer.core.effects import TEMPERATURE, term_regressors
from tetra_gradiometer.core.effects.eddy_current import WINDOW_PERIODS
from tetra_gradiometer.io.channels import ChannelSeries
from tetra_gradiometer.nodes.channels import LiveEffects
from tetra_gradiometer.pipelines.terms import channels_on

T0 = 1_767_225_600 * 10**9
SET_NS = 5 * 10**7  # 20 Hz


def _run(n: int, series: dict[str, ChannelSeries], latency_ns: int, restart_at: int | None = None):
    """Feed ``n`` 20 Hz sets to a LiveEffects as the compensator does, each channel message
    delivered ``latency_ns`` after its stamp (after the sets before that instant); the
    steady clock is the stamps'. Returns the live regressors per set (None: dropped), the
    stamp the newest set had when each set was released, and the LiveEffects."""
    sets = T0 + np.arange(n, dtype=np.int64) * SET_NS
    if restart_at is not None:  # a replay started again: stamps go back
        sets[restart_at:] -= sets[restart_at] - sets[0] + 7 * SET_NS
    angle = np.linspace(0.0, 3.0, n)
    b = 5e-5 * np.stack([np.cos(angle), np.sin(angle), 0.3 * np.ones(n)], axis=1)
    messages = sorted(
        (int(stamp) + latency_ns, name, int(stamp), float(value))
        for name, s in series.items()
        for stamp, value in zip(s.stamps_ns, s.values)
    )
    live = LiveEffects(example_terms())
    out: dict[int, np.ndarray | None] = {}
    released_when: dict[int, int] = {}
    newest = [0]

    def compensate(items):
        for i in items:
            out[i] = live.regressors(int(sets[i]), b[i])
            released_when[i] = newest[0]

    k = 0
    for i, stamp in enumerate(sets):
        now = int(stamp) if restart_at is None or i < restart_at else int(stamp) + 10**12
        while k < len(messages) and messages[k][0] <= now:
            _, name, message_stamp, value = messages[k]
            live.add(name, message_stamp, value)
            compensate(live.release(now * 1e-9))
            k += 1
        newest[0] = int(stamp)
        compensate(live.submit(int(stamp), i, now * 1e-9))
    compensate(live.release(1e12))  # the steady clock runs on after the last set
    return sets, b, out, released_when, live


def test_a_held_set_gets_the_offline_value_when_its_channels_come_late():
    rng = np.random.default_rng(8)
    n = 800
    sets = T0 + np.arange(n, dtype=np.int64) * SET_NS
    # A 1 Hz battery current that ramps (a BatteryState's usual rate) and a 0.5 Hz temperature,
    # each delivered 0.3 s after its stamp: every set arrives before its next message.
    stamps = sets[::20] + 13 * 10**6
    current = ChannelSeries(BATTERY, stamps, -15.0 + 6.0 * np.sin(np.arange(len(stamps)) / 3.0))
    temperature = ChannelSeries(TEMPERATURE, sets[::40] + 7 * 10**6, 15.0 + rng.normal(0, 0.2, n // 40))
    series = {BATTERY: current, TEMPERATURE: temperature}
    sets, b, out, released_when, live = _run(n, series, 3 * 10**8)
    offline = term_regressors(example_terms(), channels_on(sets, b, series))
    assert sorted(out) == list(range(n))  # every set released once
    # Before the battery's first message arrives (0.313 s) a set has no value to wait for:
    # dropped, as before (offline takes the first message within 2 s).
    start = int(np.searchsorted(sets, stamps[0] + 3 * 10**8))
    assert all(out[i] is None for i in range(start)) and live.dropped[BATTERY] == start
    dropped = np.array([out[i] is None for i in range(start, n)])
    np.testing.assert_array_equal(dropped, ~np.all(np.isfinite(offline[start:]), axis=1))
    got = np.array([out[i] for i in range(start, n) if out[i] is not None])
    np.testing.assert_allclose(got, offline[start:][~dropped], rtol=1e-9, atol=1e-15)
    # Held: nearly every set. Released at the bound: only those after a channel's last message
    # (the steady clock ran on), with the value offline has there (the last message's).
    last = min(c.stamps_ns[-1] for c in series.values())
    assert live.held > 0.9 * n and live.released_at_bound == np.sum(sets > last) > 0
    # A set waited only until its channels' next messages were delivered (0.3 s after their
    # stamps: the next set after that released it), never longer.
    waited = np.array([released_when[i] - sets[i] for i in range(start, n)]) * 1e-9
    covered = sets[start:] <= last
    due = np.max([c.stamps_ns[np.searchsorted(c.stamps_ns, sets[start:][covered])] for c in series.values()], axis=0)
    needed = (due + 3 * 10**8 - sets[start:][covered]) * 1e-9
    assert np.all(waited[covered] <= needed + 0.05 + 1e-9) and np.all(waited[covered] >= needed - 0.05 - 1e-9)
    assert waited.max() > 2.0  # just after a temperature message: its next one 2 s later

    # Without the hold (each set on arrival, the last message held): far from offline.
    eager = LiveEffects(example_terms())
    messages = sorted((int(s) + 3 * 10**8, name, int(s), float(v))
                      for name, c in series.items() for s, v in zip(c.stamps_ns, c.values))
    k, eager_x = 0, []
    for i, stamp in enumerate(sets):
        while k < len(messages) and messages[k][0] <= stamp:
            eager.add(messages[k][1], messages[k][2], messages[k][3])
            k += 1
        eager_x.append(eager.regressors(int(stamp), b[i]))
    both = [i for i in range(n) if eager_x[i] is not None and out[i] is not None]
    difference = np.abs(np.array([eager_x[i][0] - out[i][0] for i in both]))
    assert difference.max() > 1.0  # A: the battery current one message behind


def test_a_channel_that_stops_releases_its_sets_at_the_bound_and_they_are_dropped_as_offline():
    n = 600
    sets = T0 + np.arange(n, dtype=np.int64) * SET_NS
    stamps = sets[:200:10]  # 2 Hz, stops at 9.5 s; the sets go on to 30 s
    current = ChannelSeries(BATTERY, stamps, np.linspace(-10.0, -5.0, len(stamps)))
    temperature = ChannelSeries(TEMPERATURE, sets[::20], np.full(n // 20, 15.0))
    series = {BATTERY: current, TEMPERATURE: temperature}
    sets, b, out, released_when, live = _run(n, series, 10**8)
    offline = term_regressors(example_terms(), channels_on(sets, b, series))
    start = 2  # the sets before the first messages are delivered (0.1 s): no value, dropped
    dropped = np.array([out[i] is None for i in range(n)])
    np.testing.assert_array_equal(dropped[start:], ~np.all(np.isfinite(offline[start:]), axis=1))
    assert dropped[:start].all() and dropped.sum() > 300
    assert live.dropped[BATTERY] + live.dropped.get('reference_rate', 0) == dropped.sum()
    waited = np.array([released_when[i] - sets[i] for i in range(n)]) * 1e-9
    assert waited.max() <= 2 * 0.5 + 0.05  # two of the battery's periods
    assert live.released_at_bound > 0
    values = live.report()[2]
    assert values['sets released at the hold bound'] == live.released_at_bound
    assert values['sets held for a channel message'] == live.held


def test_a_restarted_replay_releases_the_queue_in_order():
    n = 400
    sets = T0 + np.arange(n, dtype=np.int64) * SET_NS
    current = ChannelSeries(BATTERY, sets[::20], np.linspace(-10.0, -5.0, n // 20))
    series = {BATTERY: current, TEMPERATURE: ChannelSeries(TEMPERATURE, sets[::20], np.full(n // 20, 15.0))}
    _, _, out, _, live = _run(n, series, 2 * 10**8, restart_at=250)
    assert sorted(out) == list(range(n)) and live.resets == 1


def test_a_node_behind_its_queue_waits_for_a_received_message_and_lets_the_sets_go_once_they_stop():
    """The compensator's timer runs before the messages waiting in its queue when it falls
    behind: a set is released on the steady clock only once no set has come for
    IDLE_RELEASE_S (and the hold bound), never while the sets flow; then it takes the value
    of the message that was waiting, as offline."""
    from tetra_gradiometer.nodes.channels import IDLE_RELEASE_S

    sets = T0 + np.arange(40, dtype=np.int64) * SET_NS
    b = np.tile([2e-5, 1e-5, -4e-5], (len(sets), 1))
    current = ChannelSeries(BATTERY, sets, np.linspace(-10.0, -5.0, len(sets)))  # 20 Hz
    temperature = ChannelSeries(TEMPERATURE, sets, np.full(len(sets), 15.0))
    offline = term_regressors(example_terms(), channels_on(sets, b, {BATTERY: current, TEMPERATURE: temperature}))
    live = LiveEffects(example_terms())
    out: dict[int, np.ndarray | None] = {}
    for i in range(20):  # the channels' messages for sets 0..19 came first
        live.add(BATTERY, int(sets[i]), float(current.values[i]))
        live.add(TEMPERATURE, int(sets[i]), 15.0)
        for j in live.submit(int(sets[i]), i, 100.0 + 0.05 * i):
            out[j] = live.regressors(int(sets[j]), b[j])
    # Set 20 before its messages; the node, descheduled for 0.9 s, runs its timer first.
    assert live.submit(int(sets[20]), 20, 101.0) == []
    assert live.release(101.9) == []  # the bound is 0.1 s, but the sets have not stopped
    live.add(BATTERY, int(sets[20]), float(current.values[20]))
    live.add(TEMPERATURE, int(sets[20]), 15.0)
    assert live.release(101.9) == [20]
    out[20] = live.regressors(int(sets[20]), b[20])
    assert live.released_at_bound == 0
    # Set 21 whose messages never come: held until the sets stop for IDLE_RELEASE_S.
    assert live.submit(int(sets[21]), 21, 102.0) == []
    assert live.release(102.0 + 0.99 * IDLE_RELEASE_S) == []
    assert live.release(102.0 + 1.01 * IDLE_RELEASE_S) == [21]
    assert live.released_at_bound == 1
    out[21] = live.regressors(int(sets[21]), b[21])  # the last message's value, 50 ms old
    # no eddy rate while the window holds set 0, both sides
    assert all(out[i] is None for i in range(WINDOW_PERIODS))
    assert np.isnan(offline[:WINDOW_PERIODS]).any(axis=1).all()
    got = np.array([out[i] for i in range(WINDOW_PERIODS, 21)])
    np.testing.assert_allclose(got, offline[WINDOW_PERIODS:21], rtol=1e-12, atol=0)
    assert out[21] is not None and np.isfinite(out[21]).all()
