"""The calibrator's ~/calibrate (tetra_gradiometer_msgs/Calibrate) in this process: the
request's window fits only the samples stamped inside it, its force keeps a calibration that
fails the window check for that call only, its effects replace the node's parameter for that
call; the response carries the figures, and what is published on ``calibration`` is the file
written, field for field. Truth: the stamps fed, the exact parameters of the simulated
vehicle, the file on disk."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from in_process import node_in_process
from ros_helpers import interference_set

T0_S = 1_700_000_000  # in the past: nodes refuse stamps ahead of their clock
NS = 10**9
NT = 1e-9


def _calibrator(monkeypatch, tmp_path, **parameters):
    from tetra_gradiometer.nodes.calibrator import CalibratorNode

    return node_in_process(CalibratorNode, monkeypatch, calibration_file=str(tmp_path / 'calibration.yaml'),
                           **parameters)


def _collect(node, g, b) -> np.ndarray:
    """~/start, then the sets on gradient/raw at 10 Hz from T0_S; their stamps, ns."""
    from std_srvs.srv import Trigger

    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt

    assert node._on_start(Trigger.Request(), Trigger.Response()).success
    stamps = T0_S * NS + np.arange(len(g)) * NS // 10
    types = cv.rclpy_types()
    for stamp, g_i, b_i in zip(stamps, g, b, strict=True):
        node._on_raw(gt.gradient_tensor_msg(types, gt.TensorSet(int(stamp), g_i, reference_field=b_i)))
    assert node.n_samples == len(g)
    return stamps


def _call(node, window_s=(0.0, 0.0), force=False, effects=''):
    from tetra_gradiometer_msgs.srv import Calibrate

    request = Calibrate.Request(window_s=list(window_s), force=force, effects=effects)
    return node._on_calibrate(request, Calibrate.Response())


def _published(published: list) -> list:
    return [message for topic, message in published if topic == '/tetra/calibration']


def test_the_window_fits_only_the_samples_stamped_inside_it_and_the_message_is_the_file(monkeypatch, tmp_path):
    from tetra_gradiometer.io.calibration_message import calibration_from_message

    g, b, exact = interference_set(300, np.random.default_rng(31), 'rich')
    g[200:] += np.diag([3.0, -1.0, -2.0]) * NT  # a stretch the model cannot explain, left out
    with _calibrator(monkeypatch, tmp_path) as (node, published):
        stamps = _collect(node, g, b)
        first, last = stamps[50] / NS, stamps[179] / NS  # samples 50..179
        reply = _call(node, window_s=(first, last))
        assert reply.success, reply.message
        assert reply.samples == 130 and '130 samples' in reply.message
        assert reply.rank == 36 and reply.residual_t_per_m < 1e-6 * NT
        assert np.isfinite(reply.residual_over_floor)
        path = tmp_path / 'calibration.yaml'
        assert reply.calibration_file == str(path)
        text = path.read_text()
        written = yaml.safe_load(text)
        np.testing.assert_allclose(written['k_soft'], exact.k_soft, rtol=0, atol=1e-9)
        assert written['diagnostics']['n_samples'] == 130
        assert written['diagnostics']['samples_window_s'] == [stamps[50] / NS, stamps[179] / NS]
        assert written['diagnostics']['source'] == '/tetra/calibrator'
        (message,) = _published(published)
        assert message.document == text and message.header.frame_id == 'tetra_array'
        assert message.rank == 36 and message.source == '/tetra/calibrator'
        np.testing.assert_array_equal(message.window_s, [stamps[50] / NS, stamps[179] / NS])
        loaded = calibration_from_message(message, 'the published calibration')
        np.testing.assert_array_equal(loaded.parameters.k_soft, written['k_soft'])

        # [0, 0]: every sample collected (the stretch after 20 s included: it does not fit).
        reply = _call(node)
        assert not reply.success and 'the 300 samples since ~/start' in reply.message, reply.message
        assert reply.samples == 300 and np.isnan(reply.residual_t_per_m) and reply.calibration_file == ''
        assert len(_published(published)) == 1


@pytest.mark.parametrize('window, reason', [
    ((T0_S + 100.0, T0_S + 200.0), 'the 0 samples stamped'),
    ((T0_S + 10.0, T0_S + 5.0), 'with 0 <= first <= last'),
    ((float('nan'), T0_S + 5.0), 'with 0 <= first <= last'),
])
def test_a_window_without_enough_samples_or_backwards_is_refused_and_nothing_written(monkeypatch, tmp_path, window,
                                                                                      reason):
    g, b, _ = interference_set(200, np.random.default_rng(32), 'rich')
    with _calibrator(monkeypatch, tmp_path) as (node, published):
        _collect(node, g, b)
        reply = _call(node, window_s=window)
        assert not reply.success and reason in reply.message, reply.message
        assert reply.samples == 0 and not (tmp_path / 'calibration.yaml').exists() and not _published(published)


def test_force_keeps_a_failing_calibration_for_that_call_only(monkeypatch, tmp_path):
    rng = np.random.default_rng(33)
    g, b, _ = interference_set(400, rng, 'rich')
    g = g + rng.normal(0.0, 0.05 * NT, g.shape)
    g[200:] += np.diag([3.0, -1.0, -2.0]) * NT
    path = tmp_path / 'calibration.yaml'
    with _calibrator(monkeypatch, tmp_path) as (node, published):
        _collect(node, g, b)
        refused = _call(node)
        assert not refused.success and 'force:=true' in refused.message, refused.message
        assert refused.samples == 400 and not path.exists()
        forced = _call(node, force=True)
        assert forced.success and 'WARNING (force:=true)' in forced.message, forced.message
        assert forced.residual_over_floor > 2.0 and forced.samples == 400
        notes = yaml.safe_load(path.read_text())['diagnostics']['notes']
        assert any(note.startswith('WARNING (force:=true)') for note in notes)
        assert node.get_parameter('force').value is False
        again = _call(node)  # the parameter, false, again
        assert not again.success and 'force:=true' in again.message
        assert len(_published(published)) == 1


def test_the_requests_effects_replace_the_parameter_for_that_call(monkeypatch, tmp_path):
    g, b, _ = interference_set(300, np.random.default_rng(34), 'rich')
    path = tmp_path / 'calibration.yaml'
    with _calibrator(monkeypatch, tmp_path, effects='none') as (node, _):
        _collect(node, g, b)
        reply = _call(node)  # the parameter: none
        assert reply.success and "effects: none (the paper's k, b only)" in reply.message, reply.message
        reply = _call(node, effects='auto')  # the channels of the current and temperature are silent
        assert reply.success and 'effects (auto): none selected; cannot fit: vehicle_current' in reply.message
        assert yaml.safe_load(path.read_text())['diagnostics']['effects']['lacking'].keys() == {
            'vehicle_current', 'thermal_drift'}
        reply = _call(node, effects='vehicle_current')  # its current has no message here
        assert not reply.success and 'vehicle_current' in reply.message, reply.message
        reply = _call(node, effects='bogus')
        assert not reply.success and "effects 'bogus': unknown bogus" in reply.message, reply.message
        assert node.get_parameter('effects').value == 'none'
