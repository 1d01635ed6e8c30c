"""Sim time on replay, over real DDS: the replaying driver publishes ``/clock`` from the bag's
log times, and a tensor node with ``use_sim_time`` reports the bag's rates and staleness on
``/diagnostics`` whatever the playback speed (10x gives the same figures as 1x; on the wall
clock 10x would show 500 Hz). The statuses themselves come on the steady clock (sim
time cannot freeze them), so 10x gives a tenth as many."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from ros_helpers import ros_graph, uniform_gradient_fields, wait_for

from tetra_gradiometer import core
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter

NT = 1e-9
T0 = 1_800_000_000 * 10**9
RATE_HZ = 50.0
SECONDS = 6.0
PERIOD_S = 0.1  # diagnostics, steady clock
GEOMETRY = core.TetraGeometry.regular(0.5)
FIELDS = uniform_gradient_fields(GEOMETRY.positions, np.array([12e-6, -20e-6, 43e-6]),
                                 np.diag([100.0, -60.0, -40.0]) * NT)


def _replay(bag: str, rate: float) -> tuple[list[int], list[dict[str, float]]]:
    """Play ``bag`` at ``rate`` x real time to a tensor node with use_sim_time: the /clock
    values (ns) and the tensor node's mag1 diagnostics (rate_hz, staleness_s, received)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rosgraph_msgs.msg import Clock

    clocks: list[int] = []
    statuses: list[dict[str, float]] = []
    lock = threading.Lock()

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == 'tetra/tensor: mag1':
                values = {kv.key: float(kv.value) for kv in status.values if kv.key in
                          ('rate_hz', 'staleness_s', 'received')}
                with lock:
                    statuses.append(values)

    with ros_graph() as (graph, probe, _):
        probe.create_subscription(Clock, '/clock', lambda msg: clocks.append(cv.stamp_to_ns(msg.clock)), 1000)
        probe.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 1000)
        graph.start('tensor', use_sim_time=True, diagnostics_period_s=PERIOD_S)
        wait_for(lambda: probe.count_publishers('/tetra/gradient/raw') >= 2, 20, 'tensor node', graph)  # and the feeder
        graph.start('driver', mode='replay', bag=bag, rate=rate, min_subscribers=1, start_paused=True)
        for topic in ('mag1', 'mag2', 'mag3', 'mag4'):
            wait_for(lambda t=topic: probe.count_publishers(f'/tetra/{t}') >= 2, 30, f'the driver on {topic}', graph)
        wait_for(lambda: probe.count_publishers('/clock') >= 1, 30, 'the driver on /clock', graph)
        time.sleep(2.0)  # the tensor node's side of the discovery
        assert probe.call('driver/resume').success
        wait_for(lambda: probe.status('tetra/driver: playback').get('state') == 'finished',
                 SECONDS / rate + 30, 'the end of the replay', graph)
        time.sleep(0.5)
    with lock:
        return list(clocks), list(statuses)


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp('sim_time') / 'bag'
    n = int(RATE_HZ * SECONDS)
    with BagWriter(folder) as writer:
        writer.write_fields(T0 + np.arange(n, dtype=np.int64) * int(1e9 / RATE_HZ),
                            np.broadcast_to(FIELDS, (n, 4, 3)))
    return str(folder)


@pytest.mark.parametrize('rate', [1.0, 10.0])
def test_replay_publishes_clock_and_diagnostics_follow_the_bag_time(bag, rate):
    clocks, statuses = _replay(bag, rate)
    last = T0 + (int(RATE_HZ * SECONDS) - 1) * int(1e9 / RATE_HZ)
    # /clock: the bag's log times, never backwards, from the first sample to the last.
    assert clocks and clocks[0] == T0 and clocks[-1] == last
    assert np.all(np.diff(clocks) > 0)
    # Diagnostics every PERIOD_S of the steady clock: SECONDS / rate / PERIOD_S while playing
    # (the rates and staleness in them are on the bag's time). A loaded machine plays slower,
    # never faster (11 for 6 in a fresh-clone run): up to twice as many; on the bag's time
    # there would be SECONDS / PERIOD_S (60 at 10x).
    playing = [s for s in statuses if s.get('received', 0) > 0]
    expected = SECONDS / rate / PERIOD_S
    during = len([s for s in playing if s['received'] < RATE_HZ * SECONDS])
    assert expected - 3 <= during <= 2 * expected + 3
    middle = playing[1:-1]  # the first window starts before the data, the last may be partial
    # The rate is on the readings' own stamps: exactly the bag's in every window with new
    # readings, however late the executor runs (the node clock gave 29-142 Hz under load; the
    # wall clock would give 500 Hz at 10x).
    fresh = [b['rate_hz'] for a, b in zip(middle, middle[1:]) if b['received'] > a['received']]
    assert fresh and np.allclose(fresh, RATE_HZ, rtol=1e-6), fresh
    assert max(s['staleness_s'] for s in middle) < 0.2
