"""nodes/calibrator.py: refusals with the reason, the exact parameters of a known vehicle,
the paper's objective satisfied (eqs. 21-22), files it must never write, the trim guidance,
the regional gradient from odom. Node logic in this process (test/ros/in_process.py: its
callbacks called, what it publishes captured); over real DDS, the solve off the executor
(cancel and the time budget answered while it runs) and the process's refusal at start."""
from __future__ import annotations

import re
import time

import numpy as np
from in_process import last_status, node_in_process
from ros_helpers import interference_set, ros_graph, set_parameter, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io.calibration import load_calibration

T0 = 1_700_000_000 * 10**9  # in the past: nodes refuse stamps ahead of their clock
GEOMETRY = core.TetraGeometry.regular(0.5)
CALIBRATION = 'tetra/calibrator: calibration'


def _calibrator(monkeypatch, calibration_file, **parameters):
    """``(node, published)`` of a calibrator in this process writing ``calibration_file``."""
    from tetra_gradiometer.nodes.calibrator import CalibratorNode

    return node_in_process(CalibratorNode, monkeypatch, calibration_file=str(calibration_file), **parameters)


def _trigger(handler):
    from std_srvs.srv import Trigger

    return handler(Trigger.Request(), Trigger.Response())


def _calibrate(node):
    from tetra_gradiometer_msgs.srv import Calibrate

    return node._on_calibrate(Calibrate.Request(), Calibrate.Response())


def _set(node, name, value):
    """The node's answer to setting one parameter."""
    from rclpy.parameter import Parameter

    return node.set_parameters([Parameter(name, value=value)])[0]


def _collect(node, stamps, g, b, q=None) -> None:
    """~/start, each set (with its odom when ``q``) through the callbacks, ~/stop; every set kept
    but the implausible ones."""
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt

    assert _trigger(node._on_start).success
    types = cv.rclpy_types()
    for i, stamp in enumerate(int(s) for s in stamps):
        if q is not None:
            node._on_odom(cv.odometry_msg(types, np.zeros(3), q[i], stamp))
        node._on_raw(gt.gradient_tensor_msg(types, gt.TensorSet(stamp, g[i], reference_field=b[i])))
    assert _trigger(node._on_stop).success


def _status(node, published) -> dict:
    """The calibrator's /diagnostics status published now: its values, ``message``, ``level``."""
    node._publish_diagnostics()
    return last_status(published, CALIBRATION)


def _stamps(n: int, first: int = 0) -> np.ndarray:
    """``n`` stamps 0.1 s apart from set ``first``, ns."""
    return T0 + (first + np.arange(n)) * 10**8


def test_calibrate_refuses_no_data_and_a_single_field_direction_with_the_condition_number(monkeypatch, tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(3)
    with _calibrator(monkeypatch, calibration_file) as (node, published):
        reply = _calibrate(node)
        assert not reply.success and 'too few' in reply.message

        g, b, _ = interference_set(300, rng, 'one')
        _collect(node, _stamps(300), g, b)
        reply = _calibrate(node)
        assert not reply.success
        assert 'too few directions' in reply.message and 'condition number' in reply.message
        assert not calibration_file.exists()

        # Rich directions: the calibration is exact (no noise), written and latched. One
        # reference reading of 1 T among them is dropped and counted, never fitted.
        g, b, exact = interference_set(300, rng, 'rich')
        b_faulty = b.copy()
        b_faulty[10] = [1.0, 0.0, 0.0]
        _collect(node, _stamps(300, first=1000), g, b_faulty)
        status = _status(node, published)
        assert (status['samples'], status['dropped_implausible']) == ('299', '1'), status
        reply = _calibrate(node)
        assert reply.success, reply.message
        saved = load_calibration(calibration_file)
        np.testing.assert_allclose(saved.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)
        np.testing.assert_allclose(saved.parameters.b_hard, exact.b_hard, rtol=0, atol=1e-15)
        result = _set(node, 'method', 'constraint_lstsq')
        assert not result.successful and 'read-only while calibrator is configured' in result.reason

    # The paper's objective on the same samples: the compensated training tensors become
    # symmetric and traceless, as eqs. 21-22 ask. The method decides what is written.
    with _calibrator(monkeypatch, calibration_file, method='constraint_lstsq') as (node, _):
        _collect(node, _stamps(300, first=2000), g, b_faulty)
        reply = _calibrate(node)
        assert reply.success and reply.message.startswith('constraint_lstsq'), reply.message
    paper = load_calibration(calibration_file)
    compensated = core.compensate(g, b, paper.parameters, GEOMETRY)
    assert np.abs(compensated - np.swapaxes(compensated, 1, 2)).max() < 1e-6 * np.abs(g).max()
    assert np.abs(np.trace(compensated, axis1=1, axis2=2)).max() < 1e-6 * np.abs(g).max()


def test_calibrate_before_the_guidance_ticks_judges_the_excitation_of_every_sample(monkeypatch, tmp_path):
    """The guidance's timer folds the samples once a second: a ~/calibrate right after the last
    samples is judged on all of them, not on those of its last tick. Truth: the trim's first
    30 samples share nearly one field direction (too few, as the tick says), all 300 are rich
    and give the exact parameters."""
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io import gradient_tensor as gt

    calibration_file = tmp_path / 'calibration.yaml'
    g, b, exact = interference_set(300, np.random.default_rng(11), 'rich')
    unit = b / np.linalg.norm(b, axis=1, keepdims=True)
    order = np.argsort(-(unit @ unit[0]))  # the directions nearest the first one first
    g, b = g[order], b[order]
    types = cv.rclpy_types()
    with _calibrator(monkeypatch, calibration_file) as (node, published):
        assert _trigger(node._on_start).success
        for i, stamp in enumerate(int(s) for s in _stamps(300)):
            node._on_raw(gt.gradient_tensor_msg(types, gt.TensorSet(stamp, g[i], reference_field=b[i])))
            if i == 29:
                node._publish_guidance()  # the timer's tick after the first 30
                assert _status(node, published)['guidance'] == 'not enough'
        assert _trigger(node._on_stop).success
        reply = _calibrate(node)
        assert reply.success, reply.message
    saved = load_calibration(calibration_file)
    np.testing.assert_allclose(saved.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)


def test_calibrator_never_overwrites_a_file_that_is_not_a_calibration_and_its_path_is_read_only(monkeypatch, tmp_path):
    """Fault table rows: nobody on the ROS domain can turn ~/calibrate into a file writer."""
    precious = tmp_path / 'vehicle.conf'
    precious.write_bytes(b'rudder_gain: 3\n')
    rng = np.random.default_rng(4)
    with _calibrator(monkeypatch, precious) as (node, _):
        result = _set(node, 'calibration_file', str(tmp_path / 'elsewhere.yaml'))
        assert not result.successful and 'read-only' in result.reason.lower(), result.reason
        g, b, _ = interference_set(200, rng, 'rich')
        _collect(node, _stamps(200), g, b)
        reply = _calibrate(node)
        assert not reply.success and 'not a calibration file' in reply.message, reply.message
    assert precious.read_bytes() == b'rudder_gain: 3\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['vehicle.conf']


def _feed_and_stop(probe, feeder, graph, g, b, first=0, kept=None) -> None:
    """Publish the sets ``(g, b)`` (stamps 0.1 s apart from set ``first``), then ``~/stop``
    once the calibrator holds ``kept`` (default all) of them (its /diagnostics ``samples``: a
    ``~/stop`` served before the last queued messages would end the collection without them)."""
    kept = len(g) if kept is None else kept
    wait_for(lambda: probe.status(CALIBRATION).get('samples') == '0', 10, 'samples 0 after ~/start', graph)
    for i in range(len(g)):
        feeder.publish_raw(T0 + (first + i) * 10**8, g[i], b[i])
        time.sleep(0.002)
    wait_for(lambda: probe.status(CALIBRATION).get('samples') == str(kept), 15, f'{kept} samples', graph)
    reply = probe.call('calibrator/stop')
    assert f'{kept} samples' in reply.message, reply.message



def test_a_long_ga_solve_runs_off_the_executor_is_cancellable_and_bounded_by_max_solve_s(tmp_path):
    """Fault table rows: a 20 000-generation paper_ga solve (about 4 s) does not stop
    /diagnostics, a second ~/calibrate is answered at once, ~/cancel ends it within ~1 s
    (nothing written), and max_solve_s ends it with the best individual so far. max_solve_s
    is 1.5 s, not less: its clock starts with the ~/calibrate call, and on a loaded machine
    the work before the first generation took all of a 0.5 s budget (0 generations run)."""
    from tetra_gradiometer_msgs.srv import Calibrate
    calibration_file = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(5)
    with ros_graph() as (graph, probe, feeder):
        graph.start('calibrator', calibration_file=str(calibration_file), method='paper_ga',
                    ga_generations=20000, diagnostics_period_s=0.1)
        wait_matched(feeder.raw, 1)
        assert probe.call('calibrator/start').success
        g, b, _ = interference_set(300, rng, 'rich')
        _feed_and_stop(probe, feeder, graph, g, b)
        assert not probe.call('calibrator/cancel').success  # nothing to cancel yet

        client = probe.create_client(Calibrate, 'calibrator/calibrate')
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(Calibrate.Request())
        elapsed: set[str] = set()

        def solving() -> bool:
            s = probe.status(CALIBRATION)
            if s.get('state') == 'solving':
                elapsed.add(s['solve_elapsed_s'])
            return len(elapsed) >= 3
        wait_for(solving, 10, 'three /diagnostics reports while solving', graph)
        assert not future.done()
        second = probe.call('calibrator/calibrate', timeout_s=2.0)
        assert not second.success and second.message == 'a solve is already running'

        cancelled_at = time.monotonic()
        assert probe.call('calibrator/cancel', timeout_s=2.0).success
        wait_for(future.done, 5, 'the cancelled ~/calibrate reply', graph)
        assert time.monotonic() - cancelled_at < 1.5
        reply = future.result()
        assert not reply.success and reply.message.startswith('cancelled'), reply.message
        assert 'of 20000 generations' in reply.message and not calibration_file.exists()
        wait_for(lambda: probe.status(CALIBRATION).get('state') == 'stopped', 5, 'state back to stopped', graph)

        result = set_parameter(probe, graph, 'calibrator', 'max_solve_s', 1.5)
        assert result.successful, result.reason
        started = time.monotonic()
        reply = probe.call('calibrator/calibrate')
        took = time.monotonic() - started
        assert reply.success, reply.message
        match = re.search(r'stopped at max_solve_s 1.5 s after (\d+) of 20000 generations', reply.message)
        assert match and 0 < int(match.group(1)) < 20000, reply.message
        assert took < 3.0, took
        saved = load_calibration(calibration_file)
        assert np.all(np.isfinite(saved.parameters.to_vector(symmetric=True)))


def test_while_collecting_the_calibrator_publishes_trim_guidance_with_attitude_from_odom(monkeypatch, tmp_path):
    """~/guidance (latched JSON, from its timer) and the key figures on /diagnostics: one field
    direction, the vehicle level on heading north (its odom), is not enough and gets advice;
    after ~/start, rich directions are enough. Truth: the attitudes and directions fed."""
    import json

    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(6)
    with _calibrator(monkeypatch, tmp_path / 'calibration.yaml') as (node, published):
        def guidance() -> dict:
            node._publish_guidance()
            return json.loads([m for t, m in published if t == '/tetra/calibrator/guidance'][-1].data)

        north = Rotation.from_euler('ZYX', [90.0, 0.0, 0.0], degrees=True).as_quat()  # yaw 90° from east
        g, b, _ = interference_set(200, rng, 'one')
        _collect(node, _stamps(200), g, b, q=np.tile(north, (200, 1)))
        document = guidance()
        assert document['samples'] == 200
        assert document['enough'] is False and document['ratio'] > 10, document['text']
        assert document['advice']['kind'] in ('roll', 'pitch', 'level turn') and 'next: ' in document['text']
        counts = np.array(document['coverage']['counts'])
        assert document['coverage']['source'] == 'attitude'
        assert counts[0, 2, 2] == 200 and counts.sum() == 200  # heading 0-30°, level
        status = _status(node, published)
        assert status['next_manoeuvre'] == document['advice']['text'] and status['guidance'] == 'not enough'

        # The site's field is checked like the offline tools' (|B| <= 1e-3 T) at run time too.
        refused = _set(node, 'earth_field_enu', [1.0, 0.0, 0.0])
        assert not refused.successful and 'earth_field_enu' in refused.reason and '0.001 T' in refused.reason

        g, b, _ = interference_set(300, rng, 'rich')
        _collect(node, _stamps(300, first=1000), g, b)  # ~/start forgets the sums too
        document = guidance()
        assert document['samples'] == 300
        assert document['enough'] is True and document['advice'] is None, document['text']
        assert document['coverage']['source'] == 'field direction'  # the last odom is too old


def test_an_implausible_earth_field_is_refused_at_start_with_the_reason():
    from ros_helpers import NodeProcess, unique_domain

    code, output = NodeProcess('calibrator', unique_domain(), {'earth_field_enu': [0.0, 2e-5, -4.5e-2]}).refusal()
    assert code == 1 and 'Traceback' not in output, output
    line = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(line) == 1 and "'earth_field_enu'" in line[0] and '|B| <= 0.001 T' in line[0], output


def _trim(seed, dipoles=()):
    """A 60 s trim at 10 Hz in a 4 nT/m regional gradient (world frame), simulated: the
    samples (stamps, G_m, B_1'), the attitudes, and the gradient's truth, T/m."""
    g_world = np.array([[2.5, 1.0, -0.8], [1.0, -1.5, 1.4], [-0.8, 1.4, -1.0]])
    g_world *= 4e-9 / np.linalg.norm(g_world)
    rng = np.random.default_rng(seed)
    scenario = core.Scenario(
        geometry=GEOMETRY, earth_field_enu=np.array([0.0, 2e-5, -4.5e-5]),
        segments=(core.TrimManoeuvre(60.0),), sample_rate_hz=10.0,
        interference=core.random_interference(rng, reference_clean=True), noise_t=0.1e-9,
        regional_gradient_enu=g_world, dipoles=dipoles)
    mission = core.simulate(scenario, rng)
    stamps = T0 + np.round(mission.t * 1e9).astype(np.int64)
    fields = mission.fields_measured
    return stamps, core.difference_tensor(fields, GEOMETRY), fields[:, 0], mission.orientation_xyzw, g_world


def test_calibrate_fits_a_regional_gradient_with_odom_and_refuses_samples_over_a_target(monkeypatch, tmp_path):
    """~/calibrate as `calibrate` does: with the vehicle's odom, the simulator's 4 nT/m
    regional gradient is recovered within 3 sigma and stored; a trim over a magnetic target
    (its gradient changes along the circle) is refused with the figures and nothing written,
    and written with the warning only with force:=true (read-only while configured)."""
    import yaml

    calibration_file = tmp_path / 'calibration.yaml'
    with _calibrator(monkeypatch, calibration_file) as (node, _):
        stamps, g, b, q, g_world = _trim(8)
        _collect(node, stamps, g, b, q)
        reply = _calibrate(node)
        assert reply.success and 'regional gradient (ENU, nT/m) gxx' in reply.message, reply.message
        diagnostics = yaml.safe_load(calibration_file.read_text())['diagnostics']
        fitted = np.array(diagnostics['regional_gradient_enu_nT_per_m'])
        sigma = np.array(diagnostics['regional_gradient_sigma_nT_per_m'])
        assert np.all(np.abs(fitted - g_world * 1e9) <= 3 * sigma + 1e-6), (fitted - g_world * 1e9) / sigma
        assert diagnostics['window_check']['passed'] is True
        assert 'estimated jointly' in diagnostics['notes'][0]
        calibration_file.unlink()

        target = core.Dipole([0.0, 0.0, -65.0], [2e3, 1e3, -3e3])
        stamps, g, b, q, _ = _trim(9, dipoles=(target,))
        _collect(node, stamps, g, b, q)
        reply = _calibrate(node)
        assert not reply.success, reply.message
        assert re.search(r'does not fit the model \(.*\): .*x the noise.*force:=true', reply.message), \
            reply.message
        assert not calibration_file.exists()
        refused = _set(node, 'force', True)
        assert not refused.successful and 'read-only while calibrator is configured' in refused.reason

    with _calibrator(monkeypatch, calibration_file, force=True) as (node, published):
        _collect(node, stamps, g, b, q)
        reply = _calibrate(node)
        assert reply.success and 'WARNING (force:=true)' in reply.message, reply.message
        # A forced calibration keeps the calibrator at WARN, saying so.
        status = _status(node, published)
        assert 'forced' in status['message'] and status['level'] == 1, status
    diagnostics = yaml.safe_load(calibration_file.read_text())['diagnostics']
    assert diagnostics['window_check']['passed'] is False
    assert any(note.startswith('WARNING (force:=true)') for note in diagnostics['notes'])


def test_unfilled_and_unnormalized_odom_orientations_are_dropped_counted_and_named(monkeypatch, tmp_path):
    """Among a trim's odom, three unfilled orientations (all zeros) and one scaled by 3: the
    calibrator drops and counts the first, normalizes the second, says so at WARN on
    /diagnostics, and ~/calibrate fits the regional gradient as with a clean odom (within
    3 sigma of the simulator's)."""
    import yaml

    calibration_file = tmp_path / 'calibration.yaml'
    with _calibrator(monkeypatch, calibration_file) as (node, published):
        stamps, g, b, q, g_world = _trim(8)
        fed = q.copy()
        fed[200:203] = 0.0
        fed[400] *= 3.0
        _collect(node, stamps, g, b, fed)
        reply = _calibrate(node)
        assert reply.success and 'regional gradient (ENU, nT/m) gxx' in reply.message, reply.message
        status = _status(node, published)
    diagnostics = yaml.safe_load(calibration_file.read_text())['diagnostics']
    fitted = np.array(diagnostics['regional_gradient_enu_nT_per_m'])
    sigma = np.array(diagnostics['regional_gradient_sigma_nT_per_m'])
    assert np.all(np.abs(fitted - g_world * 1e9) <= 3 * sigma + 1e-6), (fitted - g_world * 1e9) / sigma
    assert (status['odom_dropped_zero_norm'], status['odom_normalized']) == ('3', '1'), status
    # Said at WARN in the report after they came (the one ~/calibrate publishes).
    warnings = [s.message for topic, m in published if topic == '/diagnostics' for s in m.status
                if s.name == CALIBRATION and s.level == bytes([1])]
    assert any('with a zero-norm or non-finite orientation dropped' in w and '3 in all' in w for w in warnings), \
        warnings
    assert any('1 odometry orientation not of unit norm (norm 3) normalized' in w for w in warnings), warnings
