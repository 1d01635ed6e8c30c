"""nodes/compensator.py as a process over real DDS: uncompensated pass-through without a
calibration file, then the exact parameters from the latched topic give the true (zero)
tensor, each GradientTensor saying its state and calibration; a corrupt file refuses the start
(the lifecycle refusal: test_lifecycle.py)."""
from __future__ import annotations

import numpy as np
from ros_helpers import calibration_msg, interference_set, ros_graph, wait_connected, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.io.calibration import CalibrationFile

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)


def _diag(probe, name: str) -> dict:
    return probe.status(name)


def test_corrupt_calibration_file_refuses_the_start_with_the_reason(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text('tetra_gradiometer_calibration: 1\nmethod: known_gradient_lstsq\nk_soft: [[[0.1, ')
    with ros_graph() as (graph, _, _):
        code, log = graph.start('compensator', calibration_file=str(calibration_file)).refusal()
    assert code == 1
    assert 'cannot start' in log and str(calibration_file) in log and 'not valid YAML' in log
    assert 'Traceback' not in log


def test_missing_calibration_file_runs_uncompensated_then_follows_the_latched_topic(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'  # not written yet
    rng = np.random.default_rng(5)
    g, b, exact = interference_set(20, rng, 'rich')
    with ros_graph() as (graph, probe, feeder):
        compensator = graph.start('compensator', calibration_publisher='test_feeder', calibration_file=str(calibration_file), diagnostics_period_s=0.2)
        sets = _compensated_subscription(probe)
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'False',
                 30, 'compensator diagnostics', graph)
        status = _diag(probe, 'tetra/compensator: compensation')
        assert status['level'] == 1 and 'UNCOMPENSATED' in status['message'] and 'no calibration file' in status['message']
        from std_msgs.msg import Float64
        norms: list[float] = []
        probe.create_subscription(Float64, 'gradient/norm', lambda msg: norms.append(msg.data), 100)
        wait_matched(feeder.raw, 2)  # compensator and probe
        wait_connected(probe, graph, 'compensator', '/tetra/gradient/norm', 1)
        with probe.lock:
            probe.collecting = True
        for i in range(10):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(sets) == 10 and len(norms) == 10, 10, 'pass-through tensors', graph)
        for i in range(10):
            passed = sets[T0 + i * 10**8]
            np.testing.assert_array_equal(passed.g, g[i])
            np.testing.assert_array_equal(passed.reference_field, b[i])  # B_1' travels with it
            assert (passed.state, passed.calibration_id) == (gt.UNCOMPENSATED, '')
        np.testing.assert_allclose(norms, [np.sqrt(np.sum(g[i] ** 2)) / NT for i in range(10)], rtol=1e-12)

        # A calibration with the exact parameters, on the latched topic: the true tensor (zero) comes out.
        exact_document = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                         sensor_positions=GEOMETRY.to_flat(), created_utc='2026-11-28T09:30:00Z')
        feeder.calibration.publish(calibration_msg(exact_document.to_yaml()))
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'True',
                 10, 'the latched calibration', graph)
        for i in range(10, 20):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(probe.tensors['gradient/compensated']) == 20 and len(sets) == 20, 10,
                 'compensated tensors', graph)
        compensated = np.array([probe.tensors['gradient/compensated'][T0 + i * 10**8] for i in range(10, 20)])
        assert np.abs(g[10:]).max() > 50 * NT
        assert np.abs(compensated).max() < 1e-6 * NT
        assert {(sets[T0 + i * 10**8].state, sets[T0 + i * 10**8].calibration_id) for i in range(10, 20)} == {
            (gt.COMPENSATED, '2026-11-28T09:30:00Z')}
        # A calibration for another array is refused; the current one is kept.
        other = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                sensor_positions=core.TetraGeometry.regular(0.3).to_flat())
        feeder.calibration.publish(calibration_msg(other.to_yaml()))
        wait_for(lambda: 'other sensor positions' in _diag(probe, 'tetra/compensator: compensation')['message'],
                 10, 'the refusal', graph)
        assert _diag(probe, 'tetra/compensator: compensation')['compensating'] == 'True'
        # A message whose summary disagrees with the document it carries is refused too.
        altered = calibration_msg(exact_document.to_yaml())
        altered.parameters[0] += 1e-3
        feeder.calibration.publish(altered)
        wait_for(lambda: 'the field parameters disagrees with the document'
                 in _diag(probe, 'tetra/compensator: compensation')['message'], 10, 'the refusal', graph)
        assert _diag(probe, 'tetra/compensator: compensation')['compensating'] == 'True'
        # Implausible calibrations (k = 1e308 would put inf on gradient/norm; a NaN position
        # compares false and used to pass the array check) are refused; the current one is kept.
        huge = CalibrationFile(parameters=core.InterferenceParameters(np.full((3, 3, 3), 1e308), np.zeros((3, 3))),
                               method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat())
        nan_positions = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                        sensor_positions=[float('nan')] + GEOMETRY.to_flat()[1:])
        # The implausible k has no summary (no publisher of ours writes one): the exact one's.
        for document, summarized, reason in (
                (huge, exact_document, 'k_soft[0, 0, 0] = 1e+308 is implausible'),
                (nan_positions, nan_positions, 'sensor_positions[0] = nan is not finite')):
            message = calibration_msg(summarized.to_yaml())
            message.document = document.to_yaml()
            feeder.calibration.publish(message)
            wait_for(lambda reason=reason: reason in _diag(probe, 'tetra/compensator: compensation')['message'],
                     10, 'the refusal', graph)
            assert _diag(probe, 'tetra/compensator: compensation')['compensating'] == 'True'
        # A reference reading of 1 T is dropped and counted, never compensated.
        feeder.publish_raw(T0 + 20 * 10**8, g[0], np.array([1.0, 0.0, 0.0]))
        feeder.publish_raw(T0 + 21 * 10**8, g[1], b[1])
        wait_for(lambda: len(probe.tensors['gradient/compensated']) == 21, 10, 'the next tensor', graph)
        assert T0 + 20 * 10**8 not in probe.tensors['gradient/compensated']
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('dropped_non_finite') == '1',
                 10, 'the drop counted', graph)
        assert all(np.isfinite(norms)) and len(norms) == 21
        assert compensator.alive()


def _compensated_subscription(probe) -> dict[int, gt.TensorSet]:
    """``{stamp: TensorSet}`` of ``gradient/compensated``, filled by the probe's thread."""
    from tetra_gradiometer.nodes.common import derived_qos

    sets: dict[int, gt.TensorSet] = {}

    def keep(msg) -> None:
        tensor = gt.tensor_set_from_msg(msg)
        sets[tensor.stamp_ns] = tensor

    probe.create_subscription(gt.rclpy_class(), 'gradient/compensated', keep, derived_qos())
    return sets


def _covariance(rng, n_parameters=36):
    """A full parameter covariance (K entries ~1e-5, offsets ~0.1 nT): its term is not small."""
    root = rng.normal(size=(n_parameters, n_parameters))
    scale = np.r_[np.full(n_parameters - 9, 1e-5), np.full(9, 0.1 * NT)]
    return root @ root.T / n_parameters * np.outer(scale, scale)


def test_g_sigma_follows_the_calibration_and_is_nan_while_the_noise_is_unknown(tmp_path):
    from tetra_gradiometer.core.uncertainty import compensated_sigma

    rng = np.random.default_rng(8)
    g, b, exact = interference_set(20, rng, 'rich')
    noise, covariance = 0.1 * NT, _covariance(rng)
    status = 'tetra/compensator: compensation'
    with ros_graph() as (graph, probe, feeder):
        # The calibration's own sigma model: frozen (tracking adds its state's variance).
        graph.start('compensator', calibration_publisher='test_feeder', calibration_file=str(tmp_path / 'missing.yaml'),
                    diagnostics_period_s=0.2, track_calibration=False)
        sets = _compensated_subscription(probe)
        wait_for(lambda: _diag(probe, status).get('sigma', '').startswith('none: sensor noise unknown'),
                 30, 'compensator diagnostics', graph)
        wait_matched(feeder.raw, 2)
        wait_connected(probe, graph, 'compensator', '/tetra/gradient/compensated', 1)
        raw_sigma = np.arange(1.0, 10.0).reshape(3, 3) * 0.01 * NT
        for i in range(5):  # uncompensated, noise unknown: the raw tensor's own sigma, as it came
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i], raw_sigma)
        wait_for(lambda: len(sets) == 5, 10, 'pass-through tensors', graph)
        for i in range(5):
            np.testing.assert_array_equal(sets[T0 + i * 10**8].g_sigma, raw_sigma)

        document = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                   sensor_positions=GEOMETRY.to_flat(), sensor_noise_t=noise, covariance=covariance)
        feeder.calibration.publish(calibration_msg(document.to_yaml()))
        wait_for(lambda: 'parameter covariance' in _diag(probe, status).get('sigma', ''), 10, 'the calibration', graph)
        for i in range(5, 15):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(sets) == 15, 10, 'the compensated tensors', graph)
        stamps = [T0 + i * 10**8 for i in range(5, 15)]
        expected = compensated_sigma(b[5:15], GEOMETRY, noise, exact, covariance)  # Monte-Carlo tested
        np.testing.assert_allclose([sets[s].g_sigma for s in stamps], expected, rtol=1e-9)
        without_term = compensated_sigma(b[5:15], GEOMETRY, noise, exact)
        assert np.max(expected / without_term) > 1.05  # the covariance term is really there

        # A calibration without a noise estimate (and sensor_noise_t 0): sigma unknown, NaN.
        feeder.calibration.publish(calibration_msg(CalibrationFile(
            parameters=exact, method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat()).to_yaml()))
        wait_for(lambda: 'no estimate in the calibration' in _diag(probe, status).get('sigma', ''), 10,
                 'the second calibration', graph)
        for i in range(15, 20):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i], raw_sigma)
        wait_for(lambda: len(sets) == 20, 10, 'compensated tensors', graph)
        assert all(np.isnan(sets[T0 + i * 10**8].g_sigma).all() for i in range(15, 20))
        assert {sets[T0 + i * 10**8].state for i in range(15, 20)} == {gt.COMPENSATED}


def test_sensor_noise_t_gives_the_raw_tensor_its_sigma_and_overrides_the_calibration_estimate(tmp_path):
    from tetra_gradiometer.core.uncertainty import compensated_sigma

    rng = np.random.default_rng(9)
    g, b, exact = interference_set(6, rng, 'rich')
    noise = 0.2 * NT
    status = 'tetra/compensator: compensation'
    with ros_graph() as (graph, probe, feeder):
        graph.start('compensator', calibration_publisher='test_feeder', calibration_file=str(tmp_path / 'missing.yaml'), sensor_noise_t=noise,
                    diagnostics_period_s=0.2)
        sets = _compensated_subscription(probe)
        wait_for(lambda: 'raw tensor' in _diag(probe, status).get('sigma', ''), 30, 'compensator diagnostics', graph)
        wait_matched(feeder.raw, 2)
        wait_connected(probe, graph, 'compensator', '/tetra/gradient/compensated', 1)
        for i in range(3):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(sets) == 3, 10, 'sigma of the raw tensors', graph)
        # Independent truth: the spread of eq. 7 over noise draws on the four readings.
        draws = rng.normal(0.0, noise, (20_000, 4, 3)) + rng.normal(0, 5e-5, 3)
        spread = core.difference_tensor(draws, GEOMETRY).std(axis=0)
        for tensor in list(sets.values()):
            np.testing.assert_allclose(tensor.g_sigma, spread, rtol=0.03)  # 20 000 draws: 0.5 % per std

        # The parameter beats the calibration's own estimate (0.3 nT here).
        feeder.calibration.publish(calibration_msg(CalibrationFile(
            parameters=exact, method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat(),
            sensor_noise_t=0.3 * NT).to_yaml()))
        wait_for(lambda: 'from sensor_noise_t' in _diag(probe, status).get('sigma', '')
                 and _diag(probe, status).get('compensating') == 'True', 10, 'the calibration', graph)
        for i in range(3, 6):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(sets) == 6, 10, 'sigma of the compensated tensors', graph)
        np.testing.assert_allclose([sets[T0 + i * 10**8].g_sigma for i in range(3, 6)],
                                   compensated_sigma(b[3:6], GEOMETRY, noise, exact), rtol=1e-9)


def test_health_alarm_names_the_jumped_sensor_within_5s_and_diagnostics_turn_error(tmp_path):
    """10 Hz sets of a vehicle turning in a uniform field (true gradient zero), 0.05 nT noise,
    compensated with its exact parameters; sensor 2's offset jumps by 2 nT at sample 250."""
    import json

    from std_msgs.msg import String

    rng = np.random.default_rng(12)
    n, jump_at, noise = 400, 250, 0.05 * NT
    interference = core.random_interference(rng, k_scale=3e-3, b_scale_t=200 * NT)
    directions = rng.normal(size=(n, 3))
    b_true = 50_000 * NT * directions / np.linalg.norm(directions, axis=1)[:, None]
    fields = interference.apply(np.repeat(b_true[:, None, :], 4, axis=1), b_true)
    fields += rng.normal(0.0, noise, fields.shape)
    fields[jump_at:, 1] += [1.2 * NT, 0.0, -1.6 * NT]
    g = core.difference_tensor(fields, GEOMETRY)
    document = CalibrationFile(parameters=interference.pair_parameters(), method='test', symmetric_k=True,
                               sensor_positions=GEOMETRY.to_flat(), sensor_noise_t=noise)
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text(document.to_yaml())
    alarms: list[dict] = []
    with ros_graph() as (graph, probe, feeder):
        graph.start('compensator', calibration_file=str(calibration_file), diagnostics_period_s=0.2)
        probe.create_subscription(String, 'health/alarm', lambda msg: alarms.append(json.loads(msg.data)), 10)
        wait_for(lambda: _diag(probe, 'tetra/compensator: health').get('message') == 'watching', 30,
                 'the health monitor', graph)
        wait_matched(feeder.raw, 1)
        for i in range(n):
            feeder.publish_raw(T0 + i * 10**8, g[i], fields[i, 0])
        wait_for(lambda: alarms, 20, 'a health alarm', graph)
        t_jump = (T0 + jump_at * 10**8) / 1e9
        assert t_jump <= alarms[0]['t_s'] <= t_jump + 5.0
        assert 2 in alarms[0]['sensors'] and alarms[0]['statistic'] > alarms[0]['threshold']
        wait_for(lambda: _diag(probe, 'tetra/compensator: health').get('level') == 2, 10, 'ERROR', graph)
        assert 'the vehicle changed during the run; recalibrate' in _diag(probe, 'tetra/compensator: health')['message']
