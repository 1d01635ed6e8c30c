"""nodes/compensator.py: uncompensated pass-through without a calibration file, then the
exact parameters from the calibration topic give the true (zero) tensor, each GradientTensor
saying its state and calibration; refusals of calibrations that do not fit; its sigma; the
health alarm. Node logic in this process (test/ros/in_process.py: its callbacks called with
serialized tensors, what it publishes captured, the graph naming the configured publisher:
who publishes is test_calibration_authentication.py's, over real DDS); as a process, a
corrupt file refuses the start (the lifecycle refusal: test_lifecycle.py)."""
from __future__ import annotations

import numpy as np
from in_process import compensator_in_process, deserialized, last_status
from ros_helpers import calibration_msg, interference_set, ros_graph

from tetra_gradiometer import core
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.io.calibration import CalibrationFile

NT = 1e-9
T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
COMPENSATION = 'tetra/compensator: compensation'


def _compensator(monkeypatch, calibration_file, **parameters):
    return compensator_in_process(monkeypatch, calibration_file=str(calibration_file), **parameters)


def _raw(node, i, g, b, g_sigma=None) -> None:
    """Set ``i`` (stamp T0 + i * 0.1 s) on gradient/raw, serialized by rclpy."""
    from rclpy.serialization import serialize_message

    from tetra_gradiometer.io import conversions as cv

    sigma = gt.UNKNOWN_SIGMA.reshape(3, 3) if g_sigma is None else g_sigma
    tensor = gt.TensorSet(T0 + i * 10**8, g, sigma, b)
    node._on_raw(serialize_message(gt.gradient_tensor_msg(cv.rclpy_types(), tensor)))


def _compensated(published) -> dict[int, gt.TensorSet]:
    """``{stamp: TensorSet}`` published on gradient/compensated."""
    return {t.stamp_ns: t for t in (gt.tensor_set_from_msg(m) for m in
                                    deserialized(published, '/tetra/gradient/compensated', gt.rclpy_class()))}


def _status(node, published, name=COMPENSATION) -> dict:
    node._publish_diagnostics()
    return last_status(published, name)


def test_corrupt_calibration_file_refuses_the_start_with_the_reason(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text('tetra_gradiometer_calibration: 1\nmethod: known_gradient_lstsq\nk_soft: [[[0.1, ')
    with ros_graph() as (graph, _, _):
        code, log = graph.start('compensator', calibration_file=str(calibration_file)).refusal()
    assert code == 1
    assert 'cannot start' in log and str(calibration_file) in log and 'not valid YAML' in log
    assert 'Traceback' not in log


def test_missing_calibration_file_runs_uncompensated_then_follows_the_latched_topic(monkeypatch, tmp_path):
    from std_msgs.msg import Float64

    rng = np.random.default_rng(5)
    g, b, exact = interference_set(20, rng, 'rich')
    with _compensator(monkeypatch, tmp_path / 'calibration.yaml') as (node, published):  # not written
        status = _status(node, published)
        assert status['compensating'] == 'False'
        assert status['level'] == 1 and 'UNCOMPENSATED' in status['message'] and 'no calibration file' in status['message']
        for i in range(10):
            _raw(node, i, g[i], b[i])
        sets = _compensated(published)
        assert sorted(sets) == [T0 + i * 10**8 for i in range(10)]
        for i in range(10):
            passed = sets[T0 + i * 10**8]
            np.testing.assert_array_equal(passed.g, g[i])
            np.testing.assert_array_equal(passed.reference_field, b[i])  # B_1' travels with it
            assert (passed.state, passed.calibration_id) == (gt.UNCOMPENSATED, '')
        norms = [m.data for m in deserialized(published, '/tetra/gradient/norm', Float64)]
        np.testing.assert_allclose(norms, [np.sqrt(np.sum(g[i] ** 2)) / NT for i in range(10)], rtol=1e-12)

        # A calibration with the exact parameters, on the topic: the true tensor (zero) comes out.
        exact_document = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                         sensor_positions=GEOMETRY.to_flat(), created_utc='2026-11-28T09:30:00Z')
        node._on_calibration(calibration_msg(exact_document.to_yaml()))
        assert _status(node, published)['compensating'] == 'True'
        for i in range(10, 20):
            _raw(node, i, g[i], b[i])
        sets = _compensated(published)
        compensated = np.array([sets[T0 + i * 10**8].g for i in range(10, 20)])
        assert np.abs(g[10:]).max() > 50 * NT
        assert np.abs(compensated).max() < 1e-6 * NT
        assert {(sets[T0 + i * 10**8].state, sets[T0 + i * 10**8].calibration_id) for i in range(10, 20)} == {
            (gt.COMPENSATED, '2026-11-28T09:30:00Z')}

        def refused(message, reason: str) -> None:  # said on /diagnostics; the current one kept
            node._on_calibration(message)
            status = _status(node, published)
            assert reason in status['message'] and status['compensating'] == 'True', status

        # A calibration for another array is refused.
        other = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                sensor_positions=core.TetraGeometry.regular(0.3).to_flat())
        refused(calibration_msg(other.to_yaml()), 'other sensor positions')
        # A message whose summary disagrees with the document it carries is refused too.
        altered = calibration_msg(exact_document.to_yaml())
        altered.parameters[0] += 1e-3
        refused(altered, 'the field parameters disagrees with the document')
        # Implausible calibrations (k = 1e308 would put inf on gradient/norm; a NaN position
        # compares false with the array's) are refused.
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
            refused(message, reason)
        # A reference reading of 1 T is dropped and counted, never compensated.
        _raw(node, 20, g[0], np.array([1.0, 0.0, 0.0]))
        _raw(node, 21, g[1], b[1])
        sets = _compensated(published)
        assert len(sets) == 21 and T0 + 20 * 10**8 not in sets and T0 + 21 * 10**8 in sets
        assert _status(node, published)['dropped_non_finite'] == '1'
        norms = [m.data for m in deserialized(published, '/tetra/gradient/norm', Float64)]
        assert all(np.isfinite(norms)) and len(norms) == 21


def _covariance(rng, n_parameters=36):
    """A full parameter covariance (K entries ~1e-5, offsets ~0.1 nT): its term is not small."""
    root = rng.normal(size=(n_parameters, n_parameters))
    scale = np.r_[np.full(n_parameters - 9, 1e-5), np.full(9, 0.1 * NT)]
    return root @ root.T / n_parameters * np.outer(scale, scale)


def test_g_sigma_follows_the_calibration_and_is_nan_while_the_noise_is_unknown(monkeypatch, tmp_path):
    from tetra_gradiometer.core.uncertainty import compensated_sigma

    rng = np.random.default_rng(8)
    g, b, exact = interference_set(20, rng, 'rich')
    noise, covariance = 0.1 * NT, _covariance(rng)
    # The calibration's own sigma model: frozen (tracking adds its state's variance).
    with _compensator(monkeypatch, tmp_path / 'missing.yaml', track_calibration=False) as (node, published):
        assert _status(node, published)['sigma'].startswith('none: sensor noise unknown')
        raw_sigma = np.arange(1.0, 10.0).reshape(3, 3) * 0.01 * NT
        for i in range(5):  # uncompensated, noise unknown: the raw tensor's own sigma, as it came
            _raw(node, i, g[i], b[i], raw_sigma)
        sets = _compensated(published)
        for i in range(5):
            np.testing.assert_array_equal(sets[T0 + i * 10**8].g_sigma, raw_sigma)

        document = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                   sensor_positions=GEOMETRY.to_flat(), sensor_noise_t=noise, covariance=covariance)
        node._on_calibration(calibration_msg(document.to_yaml()))
        assert 'parameter covariance' in _status(node, published)['sigma']
        for i in range(5, 15):
            _raw(node, i, g[i], b[i])
        sets = _compensated(published)
        stamps = [T0 + i * 10**8 for i in range(5, 15)]
        expected = compensated_sigma(b[5:15], GEOMETRY, noise, exact, covariance)  # Monte-Carlo tested
        np.testing.assert_allclose([sets[s].g_sigma for s in stamps], expected, rtol=1e-9)
        without_term = compensated_sigma(b[5:15], GEOMETRY, noise, exact)
        assert np.max(expected / without_term) > 1.05  # the covariance term is really there

        # A calibration without a noise estimate (and sensor_noise_t 0): sigma unknown, NaN.
        node._on_calibration(calibration_msg(CalibrationFile(
            parameters=exact, method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat()).to_yaml()))
        assert 'no estimate in the calibration' in _status(node, published)['sigma']
        for i in range(15, 20):
            _raw(node, i, g[i], b[i], raw_sigma)
        sets = _compensated(published)
        assert all(np.isnan(sets[T0 + i * 10**8].g_sigma).all() for i in range(15, 20))
        assert {sets[T0 + i * 10**8].state for i in range(15, 20)} == {gt.COMPENSATED}


def test_sensor_noise_t_gives_the_raw_tensor_its_sigma_and_overrides_the_calibration_estimate(monkeypatch, tmp_path):
    from tetra_gradiometer.core.uncertainty import compensated_sigma

    rng = np.random.default_rng(9)
    g, b, exact = interference_set(6, rng, 'rich')
    noise = 0.2 * NT
    with _compensator(monkeypatch, tmp_path / 'missing.yaml', sensor_noise_t=noise) as (node, published):
        assert 'raw tensor' in _status(node, published)['sigma']
        for i in range(3):
            _raw(node, i, g[i], b[i])
        sets = _compensated(published)
        # Independent truth: the spread of eq. 7 over noise draws on the four readings.
        draws = rng.normal(0.0, noise, (20_000, 4, 3)) + rng.normal(0, 5e-5, 3)
        spread = core.difference_tensor(draws, GEOMETRY).std(axis=0)
        assert len(sets) == 3
        for tensor in sets.values():
            np.testing.assert_allclose(tensor.g_sigma, spread, rtol=0.03)  # 20 000 draws: 0.5 % per std

        # The parameter beats the calibration's own estimate (0.3 nT here).
        node._on_calibration(calibration_msg(CalibrationFile(
            parameters=exact, method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat(),
            sensor_noise_t=0.3 * NT).to_yaml()))
        status = _status(node, published)
        assert 'from sensor_noise_t' in status['sigma'] and status['compensating'] == 'True', status
        for i in range(3, 6):
            _raw(node, i, g[i], b[i])
        sets = _compensated(published)
        np.testing.assert_allclose([sets[T0 + i * 10**8].g_sigma for i in range(3, 6)],
                                   compensated_sigma(b[3:6], GEOMETRY, noise, exact), rtol=1e-9)


def test_health_alarm_names_the_jumped_sensor_within_5s_and_diagnostics_turn_error(monkeypatch, tmp_path):
    """10 Hz sets of a vehicle turning in a uniform field (true gradient zero), 0.05 nT noise,
    compensated with its exact parameters; sensor 2's offset jumps by 2 nT at sample 250."""
    import json

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
    health = 'tetra/compensator: health'
    with _compensator(monkeypatch, calibration_file) as (node, published):
        assert _status(node, published, health)['message'] == 'watching'
        for i in range(n):
            _raw(node, i, g[i], fields[i, 0])
            if i % 10 == 9:
                node._feed_health()  # its timer: about once a second of these sets
        alarms = [json.loads(m.data) for t, m in published if t == '/tetra/health/alarm']
        assert alarms, 'no health alarm'
        t_jump = (T0 + jump_at * 10**8) / 1e9
        assert t_jump <= alarms[0]['t_s'] <= t_jump + 5.0
        assert 2 in alarms[0]['sensors'] and alarms[0]['statistic'] > alarms[0]['threshold']
        status = _status(node, published, health)
        assert status['level'] == 2 and 'the vehicle changed during the run; recalibrate' in status['message'], status
