"""nodes/calibrator.py as a process over real DDS: refusals with the reason, the exact
parameters of a known vehicle, the paper's objective satisfied (eqs. 21-22), and files it
must never write."""
from __future__ import annotations

import re
import time

import numpy as np
from ros_helpers import interference_set, ros_graph, set_parameter, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io.calibration import load_calibration

T0 = 1_800_000_000 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)
CALIBRATION = 'tetra/calibrator: calibration'


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


def test_calibrate_refuses_no_data_and_a_single_field_direction_with_the_condition_number(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(3)
    with ros_graph() as (graph, probe, feeder):
        graph.start('calibrator', calibration_file=str(calibration_file))
        reply = probe.call('calibrator/calibrate')
        assert not reply.success and 'too few' in reply.message

        wait_matched(feeder.raw, 1)
        wait_matched(feeder.reference, 1)
        assert probe.call('calibrator/start').success
        g, b, _ = interference_set(300, rng, 'one')
        _feed_and_stop(probe, feeder, graph, g, b)
        reply = probe.call('calibrator/calibrate')
        assert not reply.success
        assert 'too few directions' in reply.message and 'condition number' in reply.message
        assert not calibration_file.exists()

        # Rich directions: the calibration is exact (no noise), written and latched. One
        # reference reading of 1 T among them is dropped and counted, never fitted.
        assert probe.call('calibrator/start').success
        g, b, exact = interference_set(300, rng, 'rich')
        b_faulty = b.copy()
        b_faulty[10] = [1.0, 0.0, 0.0]
        _feed_and_stop(probe, feeder, graph, g, b_faulty, first=1000, kept=299)
        assert probe.status(CALIBRATION).get('dropped_implausible') == '1'
        reply = probe.call('calibrator/calibrate')
        assert reply.success, reply.message
        saved = load_calibration(calibration_file)
        np.testing.assert_allclose(saved.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)
        np.testing.assert_allclose(saved.parameters.b_hard, exact.b_hard, rtol=0, atol=1e-15)

        # The paper's objective on the same samples (method changed at run time): the
        # compensated training tensors become symmetric and traceless, as eqs. 21-22 ask.
        result = set_parameter(probe, graph, 'calibrator', 'method', 'constraint_lstsq')
        assert result.successful, result.reason
        reply = probe.call('calibrator/calibrate')
        assert reply.success and reply.message.startswith('constraint_lstsq'), reply.message
        paper = load_calibration(calibration_file)
        compensated = core.compensate(g, b, paper.parameters, GEOMETRY)
        assert np.abs(compensated - np.swapaxes(compensated, 1, 2)).max() < 1e-6 * np.abs(g).max()
        assert np.abs(np.trace(compensated, axis1=1, axis2=2)).max() < 1e-6 * np.abs(g).max()


def test_calibrator_never_overwrites_a_file_that_is_not_a_calibration_and_its_path_is_read_only(tmp_path):
    """Fault table rows: nobody on the ROS domain can turn ~/calibrate into a file writer."""
    precious = tmp_path / 'vehicle.conf'
    precious.write_bytes(b'rudder_gain: 3\n')
    rng = np.random.default_rng(4)
    with ros_graph() as (graph, probe, feeder):
        graph.start('calibrator', calibration_file=str(precious))
        result = set_parameter(probe, graph, 'calibrator', 'calibration_file', str(tmp_path / 'elsewhere.yaml'))
        assert not result.successful and 'read-only' in result.reason.lower(), result.reason

        wait_matched(feeder.raw, 1)
        wait_matched(feeder.reference, 1)
        assert probe.call('calibrator/start').success
        g, b, _ = interference_set(200, rng, 'rich')
        _feed_and_stop(probe, feeder, graph, g, b)
        reply = probe.call('calibrator/calibrate')
        assert not reply.success and 'not a calibration file' in reply.message, reply.message
    assert precious.read_bytes() == b'rudder_gain: 3\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['vehicle.conf']


def test_a_long_ga_solve_runs_off_the_executor_is_cancellable_and_bounded_by_max_solve_s(tmp_path):
    """Fault table rows: a 20 000-generation paper_ga solve (about 4 s) does not stop
    /diagnostics, a second ~/calibrate is answered at once, ~/cancel ends it within ~1 s
    (nothing written), and max_solve_s ends it with the best individual so far."""
    from std_srvs.srv import Trigger
    calibration_file = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(5)
    with ros_graph() as (graph, probe, feeder):
        graph.start('calibrator', calibration_file=str(calibration_file), method='paper_ga',
                    ga_generations=20000, diagnostics_period_s=0.1)
        wait_matched(feeder.raw, 1)
        wait_matched(feeder.reference, 1)
        assert probe.call('calibrator/start').success
        g, b, _ = interference_set(300, rng, 'rich')
        _feed_and_stop(probe, feeder, graph, g, b)
        assert not probe.call('calibrator/cancel').success  # nothing to cancel yet

        client = probe.create_client(Trigger, 'calibrator/calibrate')
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(Trigger.Request())
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

        result = set_parameter(probe, graph, 'calibrator', 'max_solve_s', 0.5)
        assert result.successful, result.reason
        started = time.monotonic()
        reply = probe.call('calibrator/calibrate')
        took = time.monotonic() - started
        assert reply.success, reply.message
        match = re.search(r'stopped at max_solve_s 0.5 s after (\d+) of 20000 generations', reply.message)
        assert match and 0 < int(match.group(1)) < 20000, reply.message
        assert took < 2.0, took
        saved = load_calibration(calibration_file)
        assert np.all(np.isfinite(saved.parameters.to_vector(symmetric=True)))
