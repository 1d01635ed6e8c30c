"""nodes/compensator.py as a process over real DDS: uncompensated pass-through on a corrupt
file, then the exact parameters from the latched topic give the true (zero) tensor."""
from __future__ import annotations

import time

import numpy as np
from ros_helpers import interference_set, ros_graph, wait_for, wait_matched

from tetra_gradiometer import core
from tetra_gradiometer.io.calibration import CalibrationFile

NT = 1e-9
T0 = 1_800_000_000 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)


def _diag(probe, name: str) -> dict:
    return probe.status(name)


def test_corrupt_calibration_file_runs_uncompensated_then_follows_the_latched_topic(tmp_path):
    calibration_file = tmp_path / 'calibration.yaml'
    calibration_file.write_text('tetra_gradiometer_calibration: 1\nmethod: known_gradient_lstsq\nk_soft: [[[0.1, ')
    rng = np.random.default_rng(5)
    g, b, exact = interference_set(20, rng, 'rich')
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
        # Implausible calibrations (k = 1e308 would put inf on gradient/norm; a NaN position
        # compares false and used to pass the array check) are refused; the current one is kept.
        huge = CalibrationFile(parameters=core.InterferenceParameters(np.full((3, 3, 3), 1e308), np.zeros((3, 3))),
                               method='test', symmetric_k=False, sensor_positions=GEOMETRY.to_flat())
        nan_positions = CalibrationFile(parameters=exact, method='test', symmetric_k=False,
                                        sensor_positions=[float('nan')] + GEOMETRY.to_flat()[1:])
        for document, reason in ((huge, 'k_soft[0, 0, 0] = 1e+308 is implausible'),
                                 (nan_positions, 'sensor_positions[0] = nan is not finite')):
            feeder.calibration.publish(String(data=document.to_yaml()))
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
