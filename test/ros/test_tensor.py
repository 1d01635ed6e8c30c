"""nodes/tensor.py: exact linear fields whose eq. 7 tensor is known, bad readings dropped and
counted, a silent sensor reported (in this process: test/ros/in_process.py, its sim time set
through its /clock callback); over real DDS, run-time parameter validation and the
resolved name of a remapped topic nobody publishes."""
from __future__ import annotations

import re

import numpy as np
import pytest
from in_process import deserialized, last_status, node_in_process, set_sim_time
from ros_helpers import reconfigure, ros_graph, set_parameter, uniform_gradient_fields, wait_for

from tetra_gradiometer import core

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
B0 = np.array([12e-6, -20e-6, 43e-6])
G_KNOWN = np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT  # symmetric, traceless


def _diag(probe, name: str) -> dict:
    return probe.status(name)


FIELDS = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)
#: Set index -> (sensor, bad value of its x component).
BAD = {10: (1, float('nan')), 11: (2, float('inf')), 12: (3, 2e-3), 13: (0, -float('inf')),
       **{i: (1, float('nan')) for i in range(20, 30)}}


def _tensor_node(monkeypatch, **params):
    """``(node, published)`` of a tensor node in this process (test/ros/in_process.py)."""
    from tetra_gradiometer.nodes.tensor import TensorNode

    return node_in_process(TensorNode, monkeypatch, **params)


def _feed(node, n: int, start: int, bad: dict[int, tuple[int, float]] | None = None, skip: tuple[int, ...] = (),
          clock_ns: int | None = None) -> None:
    """Hand the node ``n`` sets of the exact linear field from stamp index ``start``, serialized;
    ``bad`` maps a set index to (sensor, value) written into that sensor's x component;
    sensors in ``skip`` stay silent. ``clock_ns``: its sim time follows the stamps, from there."""
    from rclpy.serialization import serialize_message

    from tetra_gradiometer.io import conversions as cv

    types = cv.rclpy_types()
    for i in range(start, start + n):
        if clock_ns is not None:
            set_sim_time(node, clock_ns + i * 10**8)
        values = FIELDS.copy()
        if bad and i in bad:
            sensor, value = bad[i]
            values[sensor, 0] = value
        for s in range(4):
            if s not in skip:
                node._on_mag(s, serialize_message(cv.magnetic_field_msg(types, values[s], T0 + i * 10**8, cv.MAG_FRAMES[s])))


def _raw(published) -> dict[int, np.ndarray]:
    """``{stamp: g (3, 3)}`` published on gradient/raw."""
    from tetra_gradiometer.io import gradient_tensor as gt

    return {t.stamp_ns: t.g for t in map(gt.tensor_set_from_msg,
                                         deserialized(published, '/tetra/gradient/raw', gt.rclpy_class()))}


def _status(node, published, name: str) -> dict:
    node._publish_diagnostics()
    return last_status(published, name)


def test_non_finite_and_implausible_readings_drop_the_set_and_nothing_non_finite_is_published(monkeypatch, capfd):
    """Pairing stamps (sync nearest): a bad reading costs its set."""
    with _tensor_node(monkeypatch, sync='nearest', warn_throttle_s=30.0) as (node, published):
        _feed(node, 60, 0, BAD)
        raw = _raw(published)
        matching = _status(node, published, 'tetra/tensor: matching')
        per_sensor = [int(last_status(published, f'tetra/tensor: mag{s}')['dropped_invalid']) for s in range(1, 5)]
    log = capfd.readouterr().err
    assert sorted(raw) == [T0 + i * 10**8 for i in range(60) if i not in BAD]
    tensors = np.array(list(raw.values()))
    assert np.all(np.isfinite(tensors))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-12 * 1e-6)
    assert matching['sets_dropped_invalid'] == str(len(BAD))
    assert matching['messages_dropped_unmatched'] == '0'
    assert per_sensor == [1, 11, 1, 1]
    assert 1 <= log.count('dropped a set') <= 2  # warned, and throttled


def test_resampling_drops_a_bad_reading_with_its_own_set_and_never_interpolates_it(monkeypatch):
    """Resampling (the default): a bad reading costs its own set (dropped and counted, as
    when pairing) and is never interpolated into its neighbours, also ten in a row."""
    with _tensor_node(monkeypatch, warn_throttle_s=30.0) as (node, published):
        _feed(node, 60, 0, BAD)
        raw = _raw(published)
        matching = _status(node, published, 'tetra/tensor: matching')
        per_sensor = [last_status(published, f'tetra/tensor: mag{s}')['dropped_invalid'] for s in range(1, 5)]
    # The streams share their stamps: every other instant is an exact sample of each sensor.
    assert sorted(raw) == [T0 + i * 10**8 for i in range(60) if i not in BAD]
    tensors = np.array(list(raw.values()))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-10 * NT)
    assert per_sensor == ['1', '11', '1', '1']
    assert matching['sets_dropped_invalid'] == '14' and matching['sets_skipped_gap'] == '0'
    assert matching['sets_matched'] == '60'


def test_a_silent_sensor_is_an_error_on_diagnostics_and_no_tensor_is_published_until_it_returns(monkeypatch):
    """Its sim time follows the sets (10 Hz) from 1000 s: mag3 silent for 10 s of it."""
    clock_ns = 1000 * 10**9
    with _tensor_node(monkeypatch, stale_timeout_s=0.3, use_sim_time=True) as (node, published):
        _feed(node, 50, 0, clock_ns=clock_ns)
        assert len(_raw(published)) == 50
        assert _status(node, published, 'tetra/tensor: mag3')['level'] == 0

        _feed(node, 100, 50, skip=(2,), clock_ns=clock_ns)  # mag3 silent
        mag3 = _status(node, published, 'tetra/tensor: mag3')
        matching = last_status(published, 'tetra/tensor: matching')
        assert mag3['level'] == 2 and 'stale' in mag3['message'], mag3
        assert float(mag3['staleness_s']) == pytest.approx(10.0)  # its last reading at set 49, now set 149
        assert matching['level'] == 2 and 'mag3' in matching['message']
        assert last_status(published, 'tetra/tensor: mag1')['level'] == 0
        assert len(_raw(published)) == 50

        _feed(node, 50, 150, clock_ns=clock_ns)  # back
        assert len(_raw(published)) >= 95
        assert _status(node, published, 'tetra/tensor: mag3')['level'] == 0


def test_a_stall_of_the_node_between_the_readings_of_a_set_costs_no_set(monkeypatch):
    """The node's clock jumps 2 s (> stale_timeout_s 1 s) between mag2's and mag3's readings
    of one set, as when its process stalls on a loaded machine with the readings queued:
    every set is still published, exact. Truth: the linear field's tensor G_KNOWN."""
    from rclpy.serialization import serialize_message

    from tetra_gradiometer.io import conversions as cv

    types = cv.rclpy_types()
    clock_ns = 1000 * 10**9
    with _tensor_node(monkeypatch, stale_timeout_s=1.0, use_sim_time=True) as (node, published):
        for i in range(30):
            for s in range(4):
                clock_ns += 2 * 10**9 if (i, s) == (15, 2) else 10**7
                set_sim_time(node, clock_ns)
                node._on_mag(s, serialize_message(cv.magnetic_field_msg(types, FIELDS[s], T0 + i * 10**8, cv.MAG_FRAMES[s])))
        raw = _raw(published)
    assert sorted(raw) == [T0 + i * 10**8 for i in range(30)]
    tensors = np.array(list(raw.values()))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-10 * NT)


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
