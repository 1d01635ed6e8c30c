"""nodes/tensor.py as a process over real DDS: exact linear fields whose eq. 7 tensor is known,
bad readings dropped and counted, a silent sensor reported, run-time parameter validation."""
from __future__ import annotations

import re
import time

import numpy as np
from ros_helpers import reconfigure, ros_graph, set_parameter, uniform_gradient_fields, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
B0 = np.array([12e-6, -20e-6, 43e-6])
G_KNOWN = np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT  # symmetric, traceless


def _diag(probe, name: str) -> dict:
    return probe.status(name)


def _tensor_graph_feed(feeder, probe, graph, n: int, start: int, bad: dict[int, tuple[int, float]] | None = None,
                       skip: tuple[int, ...] = (), period_s: float = 0.004) -> None:
    """Publish ``n`` sets of the exact linear field from stamp index ``start``; ``bad`` maps a
    set index to (sensor, value) written into that sensor's x component."""
    fields = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)
    for i in range(start, start + n):
        values = fields.copy()
        if bad and i in bad:
            sensor, value = bad[i]
            values[sensor, 0] = value
        feeder.publish_set(T0 + i * 10**8, values, skip=skip)
        time.sleep(period_s)


#: Set index -> (sensor, bad value of its x component).
BAD = {10: (1, float('nan')), 11: (2, float('inf')), 12: (3, 2e-3), 13: (0, -float('inf')),
       **{i: (1, float('nan')) for i in range(20, 30)}}


def _feed_bad_readings(graph, probe, feeder, **params):
    """Start the tensor node with ``params``, then feed 60 sets with the readings of BAD."""
    tensor = graph.start('tensor', warn_throttle_s=30.0, diagnostics_period_s=0.2, **params)
    for publisher in feeder.mags:
        wait_matched(publisher, 1)
    wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)  # the feeder's and the node's
    with probe.lock:
        probe.collecting = True
    _tensor_graph_feed(feeder, probe, graph, 60, 0, BAD)
    return tensor


def test_non_finite_and_implausible_readings_drop_the_set_and_nothing_non_finite_is_published():
    """Pairing stamps (sync nearest): a bad reading costs its set."""
    with ros_graph() as (graph, probe, feeder):
        tensor = _feed_bad_readings(graph, probe, feeder, sync='nearest')
        bad = BAD
        good = 60 - len(bad)
        wait_for(lambda: probe.counts['gradient/raw'] >= good, 10, f'the good tensors ({probe.counts})', graph)
        time.sleep(0.5)
        raw = probe.tensors['gradient/raw']
        matching = _diag(probe, 'tetra/tensor: matching')
        wait_for(lambda: _diag(probe, 'tetra/tensor: matching').get('sets_dropped_invalid') == str(len(bad)),
                 5, 'drop counters', graph)
        per_sensor = [int(_diag(probe, f'tetra/tensor: mag{s}')['dropped_invalid']) for s in range(1, 5)]
        log = tensor.output()
    assert probe.counts['gradient/raw'] == good
    assert sorted(raw) == [T0 + i * 10**8 for i in range(60) if i not in bad]
    tensors = np.array(list(raw.values()))
    assert np.all(np.isfinite(tensors))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-12 * 1e-6)
    assert matching['messages_dropped_unmatched'] == '0'
    assert per_sensor == [1, 11, 1, 1]
    assert 1 <= log.count('dropped a set') <= 2  # warned, and throttled


def test_resampling_drops_a_bad_reading_with_its_own_set_and_never_interpolates_it():
    """Resampling (the default): a bad reading costs its own set (dropped and counted, as
    when pairing) and is never interpolated into its neighbours, also ten in a row."""
    with ros_graph() as (graph, probe, feeder):
        _feed_bad_readings(graph, probe, feeder)
        # The streams share their stamps: every other instant is an exact sample of each sensor.
        expected = [T0 + i * 10**8 for i in range(60) if i not in BAD]
        wait_for(lambda: probe.counts['gradient/raw'] >= len(expected), 10, f'tensors ({probe.counts})', graph)
        time.sleep(0.5)
        raw = dict(probe.tensors['gradient/raw'])
        wait_for(lambda: [_diag(probe, f'tetra/tensor: mag{s}').get('dropped_invalid') for s in range(1, 5)]
                 == ['1', '11', '1', '1'], 5, 'per-sensor refusals', graph)
        matching = _diag(probe, 'tetra/tensor: matching')
    assert sorted(raw) == expected
    tensors = np.array(list(raw.values()))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-10 * NT)
    assert matching['sets_dropped_invalid'] == '14' and matching['sets_skipped_gap'] == '0'
    assert matching['sets_matched'] == '60'


def test_a_silent_sensor_is_an_error_on_diagnostics_and_no_tensor_is_published_until_it_returns():
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor', stale_timeout_s=0.3, diagnostics_period_s=0.1)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)  # the feeder's and the node's
        _tensor_graph_feed(feeder, probe, graph, 50, 0, period_s=0.01)
        wait_for(lambda: probe.counts['gradient/raw'] == 50, 5, '50 tensors', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('level') == 0, 5, 'mag3 OK', graph)

        _tensor_graph_feed(feeder, probe, graph, 100, 50, skip=(2,), period_s=0.01)  # mag3 silent ~1 s
        mag3 = _diag(probe, 'tetra/tensor: mag3')
        matching = _diag(probe, 'tetra/tensor: matching')
        assert mag3['level'] == 2 and 'stale' in mag3['message'], mag3
        assert float(mag3['staleness_s']) > 0.3
        assert matching['level'] == 2 and 'mag3' in matching['message']
        assert _diag(probe, 'tetra/tensor: mag1')['level'] == 0
        assert probe.counts['gradient/raw'] == 50

        _tensor_graph_feed(feeder, probe, graph, 50, 150, period_s=0.01)  # back
        wait_for(lambda: probe.counts['gradient/raw'] >= 95, 5, 'tensors again', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('level') == 0, 5, 'mag3 OK again', graph)


def test_a_bad_value_set_at_run_time_is_refused():
    with ros_graph() as (graph, probe, _):
        graph.start('tensor')
        result = set_parameter(probe, graph, 'tensor', 'stale_timeout_s', -0.5)
        assert not result.successful and 'stale_timeout_s' in result.reason
        # How data is judged is read-only while configured: only after cleanup.
        result = set_parameter(probe, graph, 'tensor', 'stale_timeout_s', 2.0)
        assert not result.successful and 'read-only while tensor is configured' in result.reason
        for name, value in (('max_field_t', 5e-4), ('use_sim_time', True)):
            assert not set_parameter(probe, graph, 'tensor', name, value).successful, name
        reconfigure(probe, graph, 'tensor', stale_timeout_s=2.0)  # asserts each step
        output = graph.processes['tensor'].output()  # each change logged at WARN
        assert re.search(r'WARN.*parameter stale_timeout_s set to 2\.0 \(unconfigured\)', output), output
        assert re.search(r'WARN.*cleanup: inactive -> unconfigured', output)


def test_a_remap_to_a_topic_nobody_publishes_is_named_with_its_resolved_name():
    """mag3 remapped to /auv1/mag3, where nothing publishes: its ERROR names the resolved
    topic and its publishers (0); mag1's names its own, where the feeder publishes."""
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor', remaps={'mag3': '/auv1/mag3'}, diagnostics_period_s=0.2)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('message') ==
                 'no data received on /auv1/mag3 (0 publishers)', 30, 'the remapped topic named', graph)
        assert _diag(probe, 'tetra/tensor: mag3')['level'] == 2
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag1').get('message') ==
                 'no data received on /tetra/mag1 (1 publishers)', 30, 'mag1 with the feeder publishing', graph)
