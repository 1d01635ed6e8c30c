"""``MagneticField.magnetic_field_covariance`` through the graph (REP 145), over real DDS: the
tensor node's ``gradient/raw`` carries the covariance of its set's own ``mag1`` message as
``reference_field_covariance`` (a non-finite or all-zero one as unknown, 0) and the four
readings' covariances through the geometry as ``g_sigma`` (NaN unless all four are known); the
driver replaying a bag recorded without covariance fills ``diag(sensor_noise_t^2)``, and the
tensor node passes it on."""
from __future__ import annotations

import time

import numpy as np
from ros_helpers import ros_graph, uniform_gradient_fields, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.core.uncertainty import noise_jacobian, noise_sigma, readings_sigma
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.io.bag import BagWriter

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
FIELDS = uniform_gradient_fields(GEOMETRY.positions, np.array([12e-6, -20e-6, 43e-6]),
                                 np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT)


def _collect(probe, topic: str, qos) -> dict[int, np.ndarray]:
    """``{stamp: covariance (9,)}`` of a MagneticField topic, filled by the probe's thread."""
    from sensor_msgs.msg import MagneticField

    found: dict[int, np.ndarray] = {}
    probe.create_subscription(
        MagneticField, topic,
        lambda msg: found.__setitem__(cv.stamp_to_ns(msg.header.stamp), cv.magnetic_field_covariance(msg)), qos)
    return found


def _collect_raw(probe) -> dict[int, gt.TensorSet]:
    """``{stamp: TensorSet}`` of ``gradient/raw`` from the tensor node, filled by the probe's thread."""
    from tetra_gradiometer.nodes.common import derived_qos

    found: dict[int, gt.TensorSet] = {}

    def keep(msg) -> None:
        tensor = gt.tensor_set_from_msg(msg)
        found[tensor.stamp_ns] = tensor

    probe.create_subscription(gt.rclpy_class(), 'gradient/raw', keep, derived_qos())
    return found


def test_gradient_raw_carries_the_covariances_of_its_own_set():
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor')
        raw = _collect_raw(probe)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_connected(probe, graph, 'tensor', '/tetra/gradient/raw', 2)  # the feeder's and the node's
        sent, all_sent = {}, {}
        for i in range(12):
            stamp = T0 + i * 10**8
            for s in range(4):  # each sensor and each sample its own covariance: no mix-up passes
                covariance = np.diag([1.0, 2.0, 3.0]).reshape(9) * (s + 1 + 10 * i) * 1e-22
                if i == 11 and s == 0:
                    covariance = np.full(9, np.nan)  # never published: unknown (-1 first) instead
                if i == 10 and s == 0:
                    covariance = np.zeros(9)  # the old unknown: published as REP 145's
                if s == 0:
                    sent[stamp] = covariance
                all_sent.setdefault(stamp, []).append(covariance)
                feeder.mags[s].publish(cv.magnetic_field_msg(feeder.types, FIELDS[s], stamp, cv.MAG_FRAMES[s],
                                                             covariance))
            time.sleep(0.004)
        wait_for(lambda: len(raw) == 12, 10, 'the raw tensors', graph)
    jacobian = noise_jacobian(GEOMETRY)
    for i in range(10):
        stamp = T0 + i * 10**8
        np.testing.assert_array_equal(raw[stamp].reference_covariance, sent[stamp])
        np.testing.assert_array_equal(raw[stamp].reference_field, FIELDS[0])
        # Sensor s's covariance scaled by (s + 1 + 10 i): a mix-up of sensors or sets shows.
        np.testing.assert_allclose(raw[stamp].g_sigma.reshape(9), readings_sigma(jacobian, all_sent[stamp]),
                                   rtol=1e-12)
    for i in (10, 11):  # mag1's covariance unknown: the reference's is 0, the tensor's sigma NaN
        np.testing.assert_array_equal(raw[T0 + i * 10**8].reference_covariance, np.zeros(9))
        assert np.isnan(raw[T0 + i * 10**8].g_sigma).all()


def test_driver_replay_fills_a_missing_covariance_from_sensor_noise_t(tmp_path):
    from tetra_gradiometer.nodes.common import sensor_qos

    with BagWriter(tmp_path / 'bag') as writer:  # the fast CDR writer: covariance all zero
        writer.write_fields(T0 + np.arange(20, dtype=np.int64) * 10**8, np.broadcast_to(FIELDS, (20, 4, 3)))
    noise = 0.2 * NT
    expected = np.diag([noise**2] * 3).reshape(9)
    with ros_graph() as (graph, probe, feeder):
        mag1 = _collect(probe, 'mag1', sensor_qos(100))
        mag2_reliable = _collect(probe, 'mag2', 10)  # REP 2003: a plain reliable subscriber
        raw = _collect_raw(probe)
        graph.start('tensor')
        # Discovery first: the driver waits for the tensor node, not for this probe.
        wait_for(lambda: probe.count_publishers('/tetra/gradient/raw') >= 2, 20, 'tensor node', graph)  # and the feeder
        time.sleep(1.0)
        graph.start('driver', mode='replay', bag=str(tmp_path / 'bag'), rate=0.0, min_subscribers=1,
                    sensor_noise_t=noise, start_paused=True)
        # The driver's publishers known to the tensor node before it plays (volatile topics: a
        # set sent before a reader matched them is not for it, and 20 sets take 0.7 s at rate
        # 0). Discovery on a loaded machine can lag the probe's view: a margin, and the check
        # below needs half of the sets, not all.
        for topic in ('mag1', 'mag2', 'mag3', 'mag4'):
            wait_for(lambda t=topic: probe.count_publishers(f'/tetra/{t}') >= 2, 30, f'the driver on {topic}', graph)
        time.sleep(2.0)
        assert probe.call('driver/resume').success
        wait_for(lambda: len(raw) >= 10 and len(mag2_reliable) >= 10, 30, 'the replayed sets', graph)
        time.sleep(0.5)  # the rest of the replay, if it comes
    assert len(mag1) >= 15  # best effort: a few may be lost, none has another covariance
    for covariance in [*mag1.values(), *(t.reference_covariance for t in raw.values())]:
        np.testing.assert_allclose(covariance, expected, rtol=1e-12, atol=0)
    for tensor in raw.values():  # the four sensors' noise through eq. 7 (Monte-Carlo tested)
        np.testing.assert_allclose(tensor.g_sigma, noise_sigma(GEOMETRY, noise), rtol=1e-9)
