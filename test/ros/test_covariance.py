"""``MagneticField.magnetic_field_covariance`` through the nodes (REP 145), in this process: the
tensor node's ``gradient/raw`` carries the covariance of its set's own ``mag1`` message as
``reference_field_covariance`` (a non-finite or all-zero one as unknown, 0) and the four
readings' covariances through the geometry as ``g_sigma`` (NaN unless all four are known); the
driver replaying a bag recorded without covariance fills ``diag(sensor_noise_t^2)``, and the
tensor node passes it on."""
from __future__ import annotations

import numpy as np
from in_process import deserialized, node_in_process
from ros_helpers import uniform_gradient_fields

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


def _tensor_node(monkeypatch):
    from tetra_gradiometer.nodes.tensor import TensorNode

    return node_in_process(TensorNode, monkeypatch)


def _raw(published) -> dict[int, gt.TensorSet]:
    """``{stamp: TensorSet}`` published on gradient/raw."""
    return {t.stamp_ns: t for t in (gt.tensor_set_from_msg(m) for m in
                                    deserialized(published, '/tetra/gradient/raw', gt.rclpy_class()))}


def test_gradient_raw_carries_the_covariances_of_its_own_set(monkeypatch):
    from rclpy.serialization import serialize_message

    types = cv.rclpy_types()
    with _tensor_node(monkeypatch) as (node, published):
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
                node._on_mag(s, serialize_message(cv.magnetic_field_msg(types, FIELDS[s], stamp, cv.MAG_FRAMES[s],
                                                                        covariance)))
        raw = _raw(published)
    assert len(raw) == 12
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


def test_driver_replay_fills_a_missing_covariance_from_sensor_noise_t(monkeypatch, tmp_path):
    """The driver's magnetometer messages of a bag recorded without covariance, handed to
    the tensor node as they were published."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    from tetra_gradiometer.nodes.driver import DriverNode

    with BagWriter(tmp_path / 'bag') as writer:  # the fast CDR writer: covariance all zero
        writer.write_fields(T0 + np.arange(20, dtype=np.int64) * 10**8, np.broadcast_to(FIELDS, (20, 4, 3)))
    noise = 0.2 * NT
    expected = np.diag([noise**2] * 3).reshape(9)
    with node_in_process(DriverNode, monkeypatch, mode='replay', bag=str(tmp_path / 'bag'), rate=0.0,
                         sensor_noise_t=noise) as (driver, played):
        for _ in range(10):  # no tensor comes back: a window at a time, past the ack timeout
            driver._tick()
            driver._last_progress -= 1.0
    mags = [deserialized(played, f'/tetra/{topic}', MagneticField) for topic in ('mag1', 'mag2', 'mag3', 'mag4')]
    assert [len(m) for m in mags] == [20] * 4
    with _tensor_node(monkeypatch) as (node, published):
        for i in range(20):
            for s in range(4):
                node._on_mag(s, serialize_message(mags[s][i]))
        raw = _raw(published)
    assert sorted(raw) == [T0 + i * 10**8 for i in range(20)]
    for covariance in [*(cv.magnetic_field_covariance(m) for m in mags[0]), *(t.reference_covariance for t in raw.values())]:
        np.testing.assert_allclose(covariance, expected, rtol=1e-12, atol=0)
    for tensor in raw.values():  # the four sensors' noise through eq. 7 (Monte-Carlo tested)
        np.testing.assert_allclose(tensor.g_sigma, noise_sigma(GEOMETRY, noise), rtol=1e-9)
