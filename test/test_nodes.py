"""Integration tests of the ROS 2 graph: nodes as separate processes over real DDS.

Truth is independent of the code under test: the simulator's ground truth (re-simulated
here from the same scenario and seed), exact linear fields whose eq. 7 tensor is known,
physical interference whose exact compensation parameters are known, and the offline
core path on the same bag.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ros_helpers import (REPO, child_env, ros_graph, uniform_gradient_fields, unique_domain, wait_for,
                         wait_matched)

from tetra_gradiometer import core
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.calibration import CalibrationFile, load_calibration
from tetra_gradiometer.io.scenario import load_scenario
from tetra_gradiometer.io.scenario import load_scenario_or_default

NT = 1e-9
T0 = 1_800_000_000 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)
B0 = np.array([12e-6, -20e-6, 43e-6])
G_KNOWN = np.array([[120.0, 35.0, -12.0], [35.0, -80.0, 22.0], [-12.0, 22.0, -40.0]]) * NT  # symmetric, traceless


def _diag(probe, name: str) -> dict:
    return probe.status(name)


def _wait_discovered(probe, graph) -> None:
    """The derived topics have all their subscribers (calibrator, compensator, probe), so
    nothing published from now on is lost to discovery."""
    wait_for(lambda: probe.count_subscribers('/tetra/gradient/raw') >= 3
             and probe.count_subscribers('/tetra/reference_field') >= 2
             and probe.count_publishers('/tetra/gradient/raw') >= 1, 30, 'discovery', graph)
    time.sleep(0.5)


def test_sim_graph_calibrates_on_trim_and_compensates_the_survey_against_simulator_truth(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    scenario, seed = load_scenario_or_default()
    mission = core.simulate(scenario, np.random.default_rng(seed))
    survey = mission.select(mission.segment == 1)
    exact = scenario.interference.effective_parameters()
    with ros_graph() as (graph, probe, _):
        graph.start('tensor')
        graph.start('calibrator', calibration_file=str(calibration_file))
        graph.start('compensator', calibration_file=str(calibration_file))
        graph.start('driver', rate=20.0, start_paused=True, hold_between_segments=True, min_subscribers=1)
        _wait_discovered(probe, graph)
        # A missing calibration file: the compensator runs, uncompensated, and says so.
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'False',
                 30, 'compensator diagnostics', graph)
        assert 'UNCOMPENSATED' in _diag(probe, 'tetra/compensator: compensation')['message']

        assert probe.call('calibrator/start').success
        assert probe.call('driver/resume').success
        wait_for(lambda: _diag(probe, 'tetra/driver: playback').get('state') == 'holding', 60, 'end of trim', graph)
        assert probe.call('calibrator/stop').success
        reply = probe.call('calibrator/calibrate', timeout_s=60)
        assert reply.success, reply.message
        saved = load_calibration(calibration_file)
        assert saved.diagnostics['n_samples'] >= 1100  # 1200 trim sets, a few may be lost in transit
        assert np.abs(saved.parameters.k_soft - exact.k_soft).max() < 2e-5      # |k| up to ~7e-3
        assert np.abs(saved.parameters.b_hard - exact.b_hard).max() < 1.0 * NT  # |b| up to ~200 nT
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'True',
                 10, 'the compensator to follow the latched calibration', graph)

        with probe.lock:
            probe.collecting = True
        assert probe.call('driver/resume').success
        wait_for(lambda: _diag(probe, 'tetra/driver: playback').get('state') == 'finished', 60, 'survey', graph)
        wait_for(lambda: len(probe.tensors['gradient/truth']) == len(survey), 10, 'all truth tensors', graph)
        time.sleep(1.0)
        stamps, g_raw, g_comp, g_true = probe.paired()
        percent = probe.percent
        tensor_status = _diag(probe, 'tetra/tensor: matching')

    # The driver's truth is the simulator's, sample for sample (stamps 0.1 s apart).
    truth_stamps = np.array(sorted(probe.tensors['gradient/truth']))
    np.testing.assert_allclose(np.diff(truth_stamps), 1e8, atol=2)
    np.testing.assert_allclose(np.array([probe.tensors['gradient/truth'][s] for s in truth_stamps]),
                               survey.g_true, rtol=0, atol=1e-18)
    assert len(stamps) >= 0.95 * len(survey), (len(stamps), tensor_status)
    assert core.rms_residual(g_raw, g_true) > 100 * NT               # the interference is large ...
    assert core.rms_residual(g_comp, g_true) < 0.5 * NT              # ... and removed to the noise floor
    assert core.compensated_percent(core.epsilon(g_raw, g_comp, g_true)) > 99.0
    assert percent > 99.0                                            # the node's running eq. 24


def test_replayed_bags_give_the_offline_core_tensors(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    trim_scenario, _ = load_scenario(REPO / 'bags' / 'trim.yaml')
    exact = trim_scenario.interference.effective_parameters()
    with ros_graph() as (graph, probe, _):
        graph.start('tensor')
        graph.start('calibrator', calibration_file=str(calibration_file))
        graph.start('compensator', calibration_file=str(calibration_file))
        graph.start('driver', mode='replay', bag=str(REPO / 'bags' / 'trim'), rate=0.0, start_paused=True,
                    min_subscribers=1)
        _wait_discovered(probe, graph)
        assert probe.call('calibrator/start').success
        assert probe.call('driver/resume').success
        wait_for(lambda: _diag(probe, 'tetra/driver: playback').get('state') == 'finished', 60, 'trim replay', graph)
        time.sleep(0.5)
        assert probe.call('calibrator/stop').success
        reply = probe.call('calibrator/calibrate', timeout_s=60)
        assert reply.success, reply.message
        assert '1200 samples' in reply.message                   # rate 0: nothing dropped
        saved = load_calibration(calibration_file)
        assert np.abs(saved.parameters.k_soft - exact.k_soft).max() < 2e-5
        assert np.abs(saved.parameters.b_hard - exact.b_hard).max() < 1.0 * NT
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'True',
                 10, 'compensator', graph)

        graph.stop('driver')
        with probe.lock:
            probe.collecting = True
        graph.start('driver', mode='replay', bag=str(REPO / 'bags' / 'survey'), rate=0.0, min_subscribers=1,
                    start_paused=True)
        # The new driver's truth publisher must be known to the compensator and the probe first.
        wait_for(lambda: probe.count_publishers('/tetra/gradient/truth') >= 1, 30, 'the new driver', graph)
        time.sleep(1.0)
        assert probe.call('driver/resume').success
        wait_for(lambda: len(probe.paired()[0]) == 1500, 60, 'all 1500 survey sets', graph)
        stamps, g_raw, g_comp, g_true = probe.paired()

    with MagneticBag(REPO / 'bags' / 'survey') as bag:
        bag_stamps, fields = bag.read_sets()
    np.testing.assert_array_equal(stamps, bag_stamps)
    offline_raw = core.difference_tensor(fields, GEOMETRY)
    offline_comp = core.compensate(offline_raw, fields[:, 0], saved.parameters, GEOMETRY)
    scale = np.abs(offline_raw).max()
    assert np.abs(g_raw - offline_raw).max() <= 1e-9 * scale
    assert np.abs(g_comp - offline_comp).max() <= 1e-9 * np.abs(offline_comp).max()
    assert core.rms_residual(g_comp, g_true) < 0.5 * NT  # against the recorded simulator truth


def _tensor_graph_feed(feeder, probe, graph, n: int, start: int, bad: dict[int, tuple[int, float]] | None = None,
                       skip: tuple[int, ...] = (), period_s: float = 0.004) -> None:
    """Publish ``n`` sets of the exact linear field from stamp index ``start``; ``bad`` maps a
    set index to (sensor, value) written into that sensor's x component."""
    fields = uniform_gradient_fields(GEOMETRY.positions, B0, G_KNOWN)
    for i in range(start, start + n):
        values = fields.copy()
        if bad and i in bad:
            sensor, value = bad[i]
            values[sensor, 0] = value
        feeder.publish_set(T0 + i * 10**8, values, skip=skip)
        time.sleep(period_s)


def test_non_finite_and_implausible_readings_drop_the_set_and_nothing_non_finite_is_published():
    with ros_graph() as (graph, probe, feeder):
        tensor = graph.start('tensor', warn_throttle_s=30.0, diagnostics_period_s=0.2)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_for(lambda: probe.count_publishers('/tetra/gradient/raw') >= 1, 20, 'tensor node', graph)
        time.sleep(0.5)
        with probe.lock:
            probe.collecting = True
        bad = {10: (1, float('nan')), 11: (2, float('inf')), 12: (3, 2e-3), 13: (0, -float('inf')),
               **{i: (1, float('nan')) for i in range(20, 30)}}
        _tensor_graph_feed(feeder, probe, graph, 60, 0, bad)
        good = 60 - len(bad)
        wait_for(lambda: probe.counts['gradient/raw'] >= good, 10, f'the good tensors ({probe.counts})', graph)
        time.sleep(0.5)
        raw = probe.tensors['gradient/raw']
        matching = _diag(probe, 'tetra/tensor: matching')
        wait_for(lambda: _diag(probe, 'tetra/tensor: matching').get('sets_dropped_invalid') == str(len(bad)),
                 5, 'drop counters', graph)
        per_sensor = [int(_diag(probe, f'tetra/tensor: mag{s}')['dropped_invalid']) for s in range(1, 5)]
        log = tensor.output()
    assert probe.counts['gradient/raw'] == good
    assert sorted(raw) == [T0 + i * 10**8 for i in range(60) if i not in bad]
    tensors = np.array(list(raw.values()))
    assert np.all(np.isfinite(tensors))
    np.testing.assert_allclose(tensors, np.broadcast_to(G_KNOWN, tensors.shape), rtol=0, atol=1e-12 * 1e-6)
    assert matching['messages_dropped_unmatched'] == '0'
    assert per_sensor == [1, 11, 1, 1]
    assert 1 <= log.count('dropped a set') <= 2  # warned, and throttled


def test_a_silent_sensor_is_an_error_on_diagnostics_and_no_tensor_is_published_until_it_returns():
    with ros_graph() as (graph, probe, feeder):
        graph.start('tensor', stale_timeout_s=0.3, diagnostics_period_s=0.1)
        for publisher in feeder.mags:
            wait_matched(publisher, 1)
        wait_for(lambda: probe.count_publishers('/tetra/gradient/raw') >= 1, 20, 'tensor node', graph)
        time.sleep(0.5)
        _tensor_graph_feed(feeder, probe, graph, 50, 0, period_s=0.01)
        wait_for(lambda: probe.counts['gradient/raw'] == 50, 5, '50 tensors', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('level') == 0, 5, 'mag3 OK', graph)

        _tensor_graph_feed(feeder, probe, graph, 100, 50, skip=(2,), period_s=0.01)  # mag3 silent ~1 s
        mag3 = _diag(probe, 'tetra/tensor: mag3')
        matching = _diag(probe, 'tetra/tensor: matching')
        assert mag3['level'] == 2 and 'stale' in mag3['message'], mag3
        assert float(mag3['staleness_s']) > 0.3
        assert matching['level'] == 2 and 'mag3' in matching['message']
        assert _diag(probe, 'tetra/tensor: mag1')['level'] == 0
        assert probe.counts['gradient/raw'] == 50

        _tensor_graph_feed(feeder, probe, graph, 50, 150, period_s=0.01)  # back
        wait_for(lambda: probe.counts['gradient/raw'] >= 95, 5, 'tensors again', graph)
        wait_for(lambda: _diag(probe, 'tetra/tensor: mag3').get('level') == 0, 5, 'mag3 OK again', graph)


def _interference_set(n: int, rng, directions: str) -> tuple[np.ndarray, np.ndarray, core.InterferenceParameters]:
    """Raw tensors and ``B_1'`` from a clean-reference vehicle in a uniform field, with the exact parameters."""
    k = rng.uniform(-3e-3, 3e-3, (4, 3, 3))
    k[0] = 0.0
    h = rng.uniform(-100e-9, 100e-9, (4, 3))
    h[0] = 0.0
    vehicle = core.SensorInterference(k, h)
    if directions == 'one':
        b = np.tile([0.0, 2e-5, -4.5e-5], (n, 1))
    else:
        b = rng.normal(size=(n, 3))
        b *= 5e-5 / np.linalg.norm(b, axis=1, keepdims=True)
    fields = vehicle.apply(np.repeat(b[:, None, :], 4, axis=1), b)
    return core.difference_tensor(fields, GEOMETRY), fields[:, 0], vehicle.pair_parameters()


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
        g, b, _ = _interference_set(300, rng, 'one')
        for i in range(len(g)):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
            time.sleep(0.002)
        wait_for(lambda: '300 samples' in probe.call('calibrator/stop').message, 10, '300 samples', graph)
        reply = probe.call('calibrator/calibrate')
        assert not reply.success
        assert 'too few directions' in reply.message and 'condition number' in reply.message
        assert not calibration_file.exists()

        # Rich directions: the calibration is exact (no noise), written and latched.
        assert probe.call('calibrator/start').success
        g, b, exact = _interference_set(300, rng, 'rich')
        for i in range(len(g)):
            feeder.publish_raw(T0 + (1000 + i) * 10**8, g[i], b[i])
            time.sleep(0.002)
        wait_for(lambda: '300 samples' in probe.call('calibrator/stop').message, 10, '300 samples', graph)
        reply = probe.call('calibrator/calibrate')
        assert reply.success, reply.message
        saved = load_calibration(calibration_file)
        np.testing.assert_allclose(saved.parameters.k_soft, exact.k_soft, rtol=0, atol=1e-9)
        np.testing.assert_allclose(saved.parameters.b_hard, exact.b_hard, rtol=0, atol=1e-15)

        # The paper's objective on the same samples (method changed at run time): the
        # compensated training tensors become symmetric and traceless, as eqs. 21-22 ask.
        _set_string(probe, graph, 'calibrator', 'method', 'constraint_lstsq')
        reply = probe.call('calibrator/calibrate')
        assert reply.success and reply.message.startswith('constraint_lstsq'), reply.message
        paper = load_calibration(calibration_file)
        compensated = core.compensate(g, b, paper.parameters, GEOMETRY)
        assert np.abs(compensated - np.swapaxes(compensated, 1, 2)).max() < 1e-6 * np.abs(g).max()
        assert np.abs(np.trace(compensated, axis1=1, axis2=2)).max() < 1e-6 * np.abs(g).max()


def _set_string(probe, graph, node: str, name: str, value: str) -> None:
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    client = probe.create_client(SetParameters, f'{node}/set_parameters')
    assert client.wait_for_service(timeout_sec=30)
    parameter = Parameter(name=name, value=ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value))
    future = client.call_async(SetParameters.Request(parameters=[parameter]))
    wait_for(future.done, 10, 'set_parameters', graph)
    assert future.result().results[0].successful, future.result().results[0].reason


def test_corrupt_calibration_file_runs_uncompensated_then_follows_the_latched_topic(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text('tetra_gradiometer_calibration: 1\nmethod: known_gradient_lstsq\nk_soft: [[[0.1, ')
    rng = np.random.default_rng(5)
    g, b, exact = _interference_set(20, rng, 'rich')
    with ros_graph() as (graph, probe, feeder):
        compensator = graph.start('compensator', calibration_file=str(calibration_file), diagnostics_period_s=0.2)
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'False',
                 30, 'compensator diagnostics', graph)
        status = _diag(probe, 'tetra/compensator: compensation')
        assert status['level'] == 1 and 'UNCOMPENSATED' in status['message'] and 'not valid YAML' in status['message']
        from std_msgs.msg import Float64, String
        norms: list[float] = []
        probe.create_subscription(Float64, 'gradient/norm', lambda msg: norms.append(msg.data), 100)
        wait_matched(feeder.raw, 2)  # compensator and probe
        wait_for(lambda: probe.count_publishers('/tetra/gradient/norm') >= 1, 10, 'norm publisher', graph)
        time.sleep(0.5)
        with probe.lock:
            probe.collecting = True
        for i in range(10):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(probe.tensors['gradient/compensated']) == 10 and len(norms) == 10, 10,
                 'pass-through tensors', graph)
        for i in range(10):
            np.testing.assert_array_equal(probe.tensors['gradient/compensated'][T0 + i * 10**8], g[i])
        np.testing.assert_allclose(norms, [np.sqrt(np.sum(g[i] ** 2)) / NT for i in range(10)], rtol=1e-12)

        # A calibration with the exact parameters, on the latched topic: the true tensor (zero) comes out.
        document = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                   sensor_positions=GEOMETRY.to_flat())
        feeder.calibration.publish(String(data=document.to_yaml()))
        wait_for(lambda: _diag(probe, 'tetra/compensator: compensation').get('compensating') == 'True',
                 10, 'the latched calibration', graph)
        for i in range(10, 20):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
        wait_for(lambda: len(probe.tensors['gradient/compensated']) == 20, 10, 'compensated tensors', graph)
        compensated = np.array([probe.tensors['gradient/compensated'][T0 + i * 10**8] for i in range(10, 20)])
        assert np.abs(g[10:]).max() > 50 * NT
        assert np.abs(compensated).max() < 1e-6 * NT
        # A calibration for another array is refused; the current one is kept.
        other = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                sensor_positions=core.TetraGeometry.regular(0.3).to_flat())
        feeder.calibration.publish(String(data=other.to_yaml()))
        wait_for(lambda: 'other sensor positions' in _diag(probe, 'tetra/compensator: compensation')['message'],
                 10, 'the refusal', graph)
        assert _diag(probe, 'tetra/compensator: compensation')['compensating'] == 'True'
        assert compensator.alive()


KILL_WRITER = '''
import sys
import numpy as np
from tetra_gradiometer.core import InterferenceParameters, TetraGeometry
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration
geometry = TetraGeometry.regular(0.5)
big = {f"entry_{i}": float(i) for i in range(20000)}  # a large file: each write takes a while
i = 0
while True:
    i += 1
    params = InterferenceParameters(np.full((3, 3, 3), 1e-3 * i), np.full((3, 3), 1e-9 * i))
    save_calibration(sys.argv[1], CalibrationFile(params, "test", False, geometry.to_flat(), big), force=True)
    print(i, flush=True)
'''


def test_a_writer_killed_mid_write_never_leaves_a_truncated_calibration_file(tmp_path):
    target = tmp_path / 'calibration.yaml'
    rng = np.random.default_rng(11)
    for _ in range(5):
        process = subprocess.Popen([sys.executable, '-c', KILL_WRITER, str(target)], cwd=REPO,
                                   env=child_env(unique_domain()), stdout=subprocess.PIPE, text=True)
        try:
            process.stdout.readline()                  # at least one complete write
            time.sleep(rng.uniform(0.0, 0.3))
            process.send_signal(signal.SIGKILL)        # mid-write, most likely
            process.wait(timeout=10)
        finally:
            if process.poll() is None:
                process.kill()
        loaded = load_calibration(target)                # complete, parseable ...
        i = round(loaded.parameters.k_soft[0, 0, 0] / 1e-3)
        np.testing.assert_allclose(loaded.parameters.b_hard, 1e-9 * i)  # ... and self-consistent
        assert len(loaded.diagnostics) == 20000


@pytest.mark.parametrize('name, params, expected', [
    ('tensor', {'sensor_positions': [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0]}, 'coplanar'),
    ('tensor', {'stamp_tolerance_s': -1.0}, 'stamp_tolerance_s'),
    ('calibrator', {'method': 'simplex'}, 'must be one of'),
    ('driver', {'mode': 'replay', 'bag': '/nonexistent/bag'}, 'bag not found'),
])
def test_bad_parameters_are_refused_at_start_with_the_reason(name, params, expected):
    from ros_helpers import NodeProcess
    process = NodeProcess(name, unique_domain(), params)
    try:
        code = process.process.wait(timeout=30)
        output = process.output()
    finally:
        process.stop()
    assert code == 1, output
    assert expected in output


def test_a_bad_value_set_at_run_time_is_refused():
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    with ros_graph() as (graph, probe, _):
        graph.start('tensor')
        client = probe.create_client(SetParameters, 'tensor/set_parameters')
        assert client.wait_for_service(timeout_sec=30)
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=-0.5)
        future = client.call_async(SetParameters.Request(parameters=[Parameter(name='stale_timeout_s', value=value)]))
        wait_for(future.done, 10, 'set_parameters', graph)
        result = future.result().results[0]
        assert not result.successful and 'stale_timeout_s' in result.reason
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=2.0)
        future = client.call_async(SetParameters.Request(parameters=[Parameter(name='stale_timeout_s', value=value)]))
        wait_for(future.done, 10, 'set_parameters', graph)
        assert future.result().results[0].successful


def test_calibrator_never_overwrites_a_file_that_is_not_a_calibration_and_its_path_is_read_only(tmp_path):
    """Fault table rows: nobody on the ROS domain can turn ~/calibrate into a file writer."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    precious = tmp_path / 'vehicle.conf'
    precious.write_bytes(b'rudder_gain: 3\n')
    rng = np.random.default_rng(4)
    with ros_graph() as (graph, probe, feeder):
        graph.start('calibrator', calibration_file=str(precious))
        client = probe.create_client(SetParameters, 'calibrator/set_parameters')
        assert client.wait_for_service(timeout_sec=30)
        value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=str(tmp_path / 'elsewhere.yaml'))
        future = client.call_async(SetParameters.Request(parameters=[Parameter(name='calibration_file', value=value)]))
        wait_for(future.done, 10, 'set_parameters', graph)
        result = future.result().results[0]
        assert not result.successful and 'read-only' in result.reason.lower(), result.reason

        wait_matched(feeder.raw, 1)
        wait_matched(feeder.reference, 1)
        assert probe.call('calibrator/start').success
        g, b, _ = _interference_set(200, rng, 'rich')
        for i in range(len(g)):
            feeder.publish_raw(T0 + i * 10**8, g[i], b[i])
            time.sleep(0.002)
        wait_for(lambda: '200 samples' in probe.call('calibrator/stop').message, 10, '200 samples', graph)
        reply = probe.call('calibrator/calibrate')
        assert not reply.success and 'not a calibration file' in reply.message, reply.message
    assert precious.read_bytes() == b'rudder_gain: 3\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['vehicle.conf']
