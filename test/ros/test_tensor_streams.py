"""nodes/tensor.py, stream faults live (core/streams.LiveStreamCheck) over real DDS: a sensor
stamped in another epoch, zero stamps, and a sensor in Gauss are named per sensor on
/diagnostics, their readings dropped and counted; the node keeps publishing the exact tensor
of the good sets and never crashes."""
from __future__ import annotations

import time

import numpy as np
from ros_helpers import ros_graph, uniform_gradient_fields, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io import conversions as cv

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: stamps ahead of the clock are refused (max_stamp_ahead_s)
GPS_UNIX_NS = 315_964_800 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)
B0 = np.array([12e-6, -20e-6, 43e-6])
G_KNOWN = np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT


def test_stamps_off_the_other_sensors_and_zero_stamps_are_dropped_and_named():
    fields = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor', sync='nearest', diagnostics_period_s=0.2, warn_throttle_s=30.0)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)
        with probe.lock:
            probe.collecting = True
        for i in range(40):
            stamp = T0 + i * 10**8
            for s in range(4):
                sensor_stamp = stamp
                if s == 2 and 10 <= i < 20:
                    sensor_stamp = stamp - GPS_UNIX_NS  # sensor 3 on GPS time for 1 s
                if s == 1 and i in (25, 26):
                    sensor_stamp = 0  # an unfilled header on sensor 2
                feeder.mags[s].publish(cv.magnetic_field_msg(feeder.types, fields[s], sensor_stamp, cv.MAG_FRAMES[s]))
            time.sleep(0.01)
        wait_for(lambda: probe.counts['gradient/raw'] >= 28, 10, f'the good tensors ({probe.counts})', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('dropped_other_clock') == '10', 5, 'mag3 count', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag2').get('dropped_zero_stamp') == '2', 5, 'mag2 count', graph)
        mag3, mag2 = _diag(probe, 'tetra/tensor: mag3'), _diag(probe, 'tetra/tensor: mag2')
        raw = dict(probe.tensors['gradient/raw'])
    assert mag3['level'] == 1 and "10 stamped off the other sensors' clock" in mag3['message'], mag3
    assert mag2['level'] == 1 and '2 with header stamp 0' in mag2['message'], mag2
    assert sorted(raw) == [T0 + i * 10**8 for i in range(40) if not (10 <= i < 20 or i in (25, 26))]
    tensors = np.array(list(raw.values()))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-12 * 1e-6)


def test_a_sensor_in_gauss_is_named_on_diagnostics():
    fields = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor', diagnostics_period_s=0.2)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)
        gauss = fields.copy()
        gauss[3] *= 1e4  # 0.5 G written as 0.5 T: beyond max_field_t, every set dropped
        for i in range(30):
            feeder.publish_set(T0 + i * 10**8, gauss)
            time.sleep(0.01)
        wait_for(lambda: 'Gauss written as tesla' in _diag(probe, 'tetra/tensor: mag4').get('message', ''), 5,
                 'mag4 named', graph)
        assert probe.counts['gradient/raw'] == 0


def _diag(probe, name: str) -> dict:
    return probe.status(name)
