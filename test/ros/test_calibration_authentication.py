"""Issue 34, a calibration adopted only from its author: over real DDS, the compensator takes
the topic only while the configured calibrator is its one publisher and, with a key, only a
calibration whose HMAC-SHA256 signature verifies; in this process (test/ros/in_process.py),
files at start verified too, and the calibrator signs what it writes and publishes. Every
refusal is a WARN naming the publishing node."""
from __future__ import annotations

import hashlib
import hmac
import json

import numpy as np
import pytest
import yaml
from ros_helpers import calibration_msg, interference_set, ros_graph, wait_for

from tetra_gradiometer import core
from tetra_gradiometer.io.calibration import CalibrationFile

T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
KEY = bytes(range(40, 80))
COMPENSATION = 'tetra/compensator: compensation'
INPUTS = 'tetra/compensator: inputs'


def _key_file(tmp_path, key: bytes = KEY):
    path = tmp_path / 'calibration.key'
    path.write_bytes(key)
    path.chmod(0o600)
    return path


def _signed(text: str, key: bytes = KEY) -> str:
    """Signed as the issue asks, written out here: HMAC-SHA256 of the canonical document."""
    document = yaml.safe_load(text)
    value = hmac.new(key, json.dumps(document, sort_keys=True, separators=(',', ':')).encode(),
                     hashlib.sha256).hexdigest()
    signature = {'algorithm': 'HMAC-SHA256', 'key_id': hashlib.sha256(key).hexdigest()[:16], 'value': value}
    return text + yaml.safe_dump({'signature': signature}, sort_keys=False)


def _calibration(parameters, created: str = '2026-11-26T09:00:00Z', noise: float | None = None,
                 notes: tuple[str, ...] = ()) -> str:
    return CalibrationFile(parameters=parameters, method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat(),
                           created_utc=created, sensor_noise_t=noise,
                           diagnostics={'notes': list(notes)} if notes else {}).to_yaml()


def test_forged_calibrations_on_the_topic_are_refused_naming_the_publisher(tmp_path):
    import rclpy
    from tetra_gradiometer_msgs.msg import Calibration

    from tetra_gradiometer.nodes.common import latched_qos

    rng = np.random.default_rng(11)
    _, _, exact = interference_set(10, rng, 'rich')
    forged = core.InterferenceParameters(exact.k_soft * 1.5, exact.b_hard + 20e-9)
    with ros_graph() as (graph, probe, feeder):
        process = graph.start('compensator', calibration_file=str(tmp_path / 'missing.yaml'),
                              calibration_key_file=str(_key_file(tmp_path)), diagnostics_period_s=0.2)
        wait_for(lambda: probe.status(COMPENSATION).get('compensating') == 'False', 30, 'diagnostics', graph)
        assert probe.status(COMPENSATION)['authentication'].startswith('HMAC-SHA256, key id ')

        # Row 1: another node publishes its own calibration (even a correctly signed one).
        feeder.calibration.publish(calibration_msg(_signed(_calibration(forged))))
        wait_for(lambda: '/tetra/test_feeder' in probe.status(COMPENSATION).get('message', ''), 10,
                 'the refusal', graph)
        assert probe.status(COMPENSATION)['compensating'] == 'False'
        assert 'calibration refused' in process.output() and '/tetra/test_feeder' in process.output()
        wait_for(lambda: probe.status(INPUTS).get('level') == 1, 10, 'the inputs WARN', graph)
        assert 'unexpected publisher on /tetra/calibration: /tetra/test_feeder' in probe.status(INPUTS)['message']
        feeder.destroy_publisher(feeder.calibration)

        # Row 2: a node that names itself /tetra/calibrator: unsigned, then with another key,
        # refused; signed with the key, adopted; an older signed one (a replay) refused.
        spoof = rclpy.create_node('calibrator', namespace='/tetra', context=probe.context)
        try:
            publisher = spoof.create_publisher(Calibration, 'calibration', latched_qos())
            wait_for(lambda: probe.status(INPUTS).get('level') == 0, 10, 'one publisher left', graph)
            cases = ((_calibration(forged, noise=1e-6), 'is not signed'),
                     (_signed(_calibration(forged), b'y' * 32), 'signed with another key'))
            for text, reason in cases:
                publisher.publish(calibration_msg(text))
                wait_for(lambda r=reason: r in probe.status(COMPENSATION).get('message', ''), 10, reason, graph)
                assert probe.status(COMPENSATION)['compensating'] == 'False'
            # Signed, but a summary field disagrees with the signed document: refused.
            altered = calibration_msg(_signed(_calibration(exact)))
            altered.method = 'forged'
            publisher.publish(altered)
            wait_for(lambda: 'the field method disagrees' in probe.status(COMPENSATION).get('message', ''), 10,
                     'the altered summary refused', graph)
            assert probe.status(COMPENSATION)['compensating'] == 'False'
            publisher.publish(calibration_msg(_signed(_calibration(exact))))
            wait_for(lambda: probe.status(COMPENSATION).get('compensating') == 'True', 10, 'adopted', graph)
            assert 'topic calibration from /tetra/calibrator' in probe.status(COMPENSATION)['message']
            assert probe.status(COMPENSATION)['level'] == 0
            # A calibration written with force:=true: adopted (signed), but the status stays WARN.
            forced_note = 'WARNING (force:=true): the samples do not fit the model'
            publisher.publish(calibration_msg(_signed(_calibration(exact, created='2026-11-26T09:30:00Z',
                                                               notes=(forced_note,)))))
            wait_for(lambda: 'the calibration was forced' in probe.status(COMPENSATION).get('message', ''), 10,
                     'forced', graph)
            assert probe.status(COMPENSATION)['level'] == 1 and forced_note in probe.status(COMPENSATION)['message']
            publisher.publish(calibration_msg(_signed(_calibration(forged, created='2026-11-25T09:00:00Z'))))
            wait_for(lambda: 'a replay' in probe.status(COMPENSATION).get('message', ''), 10, 'replay', graph)
            assert probe.status(COMPENSATION)['level'] == 1
            assert '2026-11-26T09:30:00Z' in probe.status(COMPENSATION)['message']  # kept the one in use
        finally:
            spoof.destroy_node()
        assert process.alive()


def test_the_file_at_start_is_verified_with_a_key_and_said_unauthenticated_without(monkeypatch, tmp_path):
    """In this process (test/ros/in_process.py): the compensator's configuration refuses an
    unsigned file or a key others may read; a signed file is adopted; without a key it says
    calibrations are unauthenticated."""
    from in_process import compensator_in_process, last_status

    from tetra_gradiometer.errors import TetraError

    rng = np.random.default_rng(12)
    _, _, exact = interference_set(10, rng, 'rich')
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text(_calibration(exact))  # unsigned
    key_file = _key_file(tmp_path)
    parameters = {'calibration_file': str(calibration_file), 'calibration_key_file': str(key_file)}
    with pytest.raises(TetraError, match='is not signed'):
        compensator_in_process(monkeypatch, **parameters).__enter__()
    key_file.chmod(0o644)
    with pytest.raises(TetraError, match='chmod 600'):
        compensator_in_process(monkeypatch, **parameters).__enter__()
    key_file.chmod(0o600)
    calibration_file.write_text(_signed(_calibration(exact)))
    with compensator_in_process(monkeypatch, **parameters) as (node, published):
        node._publish_diagnostics()
        status = last_status(published, COMPENSATION)
        assert status['compensating'] == 'True' and 'unauthenticated' not in status['message'], status
    with compensator_in_process(monkeypatch, calibration_file=str(calibration_file)) as (node, published):  # no key
        node._publish_diagnostics()
        status = last_status(published, COMPENSATION)
        assert 'unauthenticated (no calibration_key_file)' in status['message'], status
        assert status['authentication'].startswith('none')


def test_the_calibrator_signs_what_it_writes_and_publishes_and_the_compensator_adopts_it(monkeypatch, tmp_path, capfd):
    """In this process: the calibrator fed, ~/calibrate; its published calibration handed to
    a compensator with the same key, the graph naming the calibrator as its publisher."""
    from std_srvs.srv import Trigger
    from tetra_gradiometer_msgs.srv import Calibrate

    from in_process import compensator_in_process, last_status, node_in_process, served
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.nodes.calibrator import CalibratorNode

    rng = np.random.default_rng(13)
    key_file = _key_file(tmp_path)
    calibration_file = tmp_path / 'calibration.yaml'
    g, b, exact = interference_set(300, rng, 'rich')
    types = cv.rclpy_types()
    with node_in_process(CalibratorNode, monkeypatch, calibration_file=str(calibration_file),
                         calibration_key_file=str(key_file)) as (calibrator, from_calibrator), \
            compensator_in_process(monkeypatch, calibration_file=str(tmp_path / 'compensator.yaml'),
                                   calibration_key_file=str(key_file)) as (compensator, published):
        assert served(calibrator, 'start')(Trigger.Request(), Trigger.Response()).success
        for i in range(len(g)):
            calibrator._on_raw(gt.gradient_tensor_msg(types, gt.TensorSet(T0 + i * 10**8, g[i], reference_field=b[i])))
        assert served(calibrator, 'stop')(Trigger.Request(), Trigger.Response()).success
        reply = served(calibrator, 'calibrate')(Calibrate.Request(), Calibrate.Response())
        assert reply.success, reply.message
        (message,) = [m for t, m in from_calibrator if t == '/tetra/calibration']
        compensator._on_calibration(message)
        compensator._publish_diagnostics()
        status = last_status(published, COMPENSATION)
        assert status['compensating'] == 'True', status
        assert 'topic calibration from /tetra/calibrator' in status['message']
    output = capfd.readouterr().err  # state-changing calls logged at WARN
    for line in ('~/start called: done: collecting (0 earlier samples discarded)',
                 '~/stop called: done: stopped with 300 samples', '~/calibrate called: done: '):
        assert any('WARN' in row and line in row for row in output.splitlines()), line
    text = calibration_file.read_text()
    body, _, _ = text.partition('signature:\n')
    assert yaml.safe_load(text)['signature'] == yaml.safe_load(_signed(body))['signature']
    assert message.document == text
    saved = CalibrationFile.from_yaml(text)
    np.testing.assert_allclose(saved.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)


def test_without_a_key_a_second_node_under_the_calibrators_name_is_refused(tmp_path):
    """Row 2 without a key: the forger names itself /tetra/calibrator beside the real one."""
    import rclpy
    from tetra_gradiometer_msgs.msg import Calibration

    from tetra_gradiometer.nodes.common import latched_qos

    rng = np.random.default_rng(14)
    _, _, exact = interference_set(10, rng, 'rich')
    forged = core.InterferenceParameters(exact.k_soft * 1.5, exact.b_hard + 20e-9)
    with ros_graph() as (graph, probe, _):
        process = graph.start('compensator', calibration_file=str(tmp_path / 'missing.yaml'), diagnostics_period_s=0.2)
        wait_for(lambda: probe.status(COMPENSATION).get('compensating') == 'False', 30, 'diagnostics', graph)
        real = rclpy.create_node('calibrator', namespace='/tetra', context=probe.context)
        forger = rclpy.create_node('calibrator', namespace='/tetra', context=probe.context)
        try:
            real.create_publisher(Calibration, 'calibration', latched_qos())
            publisher = forger.create_publisher(Calibration, 'calibration', latched_qos())
            wait_for(lambda: 'a second node of that name' in probe.status(INPUTS).get('message', ''), 10,
                     'the inputs WARN', graph)
            publisher.publish(calibration_msg(_calibration(forged, noise=1e-6)))
            wait_for(lambda: '2 nodes named /tetra/calibrator' in probe.status(COMPENSATION).get('message', ''), 10,
                     'the refusal', graph)
            assert probe.status(COMPENSATION)['compensating'] == 'False'
            assert 'unauthenticated' not in probe.status(COMPENSATION)['message']  # UNCOMPENSATED: the reason
        finally:
            forger.destroy_node()
            real.destroy_node()
        assert 'calibration refused' in process.output()
