"""cli/record.py end to end: the sim driver's topics in a bag, as the simulator simulates them
(the true tensor as tetra_gradiometer_msgs/GradientTensor)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
from ros_helpers import REPO, child_env, unique_domain

from tetra_gradiometer import core
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io import gradient_tensor as gt
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.scenario import load_scenario_or_default


def _run(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env=child_env(unique_domain()))


def test_record_writes_the_sim_driver_topics_as_simulated(tmp_path):
    bag_path = tmp_path / 'bag'
    result = _run('record', '--out', str(bag_path), '--duration', '5', '--rate', '10', '--storage', 'mcap')
    assert result.returncode == 0, result.stdout + result.stderr
    scenario, seed = load_scenario_or_default()
    mission = core.simulate(scenario, np.random.default_rng(seed))
    with MagneticBag(bag_path) as bag:
        stamps, fields = bag.read_sets()
        odom = bag.read_series('/odom')
        (truth_connection,) = [c for c in bag.reader.connections if c.topic == '/tetra/gradient/truth']
        truth = [gt.tensor_set_from_msg(bag.reader.deserialize(raw, truth_connection.msgtype))
                 for _, _, raw in bag.reader.messages(connections=[truth_connection])]
    assert len(stamps) == 50
    np.testing.assert_allclose(np.diff(stamps), 1e8, atol=2)
    np.testing.assert_array_equal(fields, mission.fields_measured[:50])
    np.testing.assert_allclose(np.abs(np.sum(odom.values[:, cv.POSE_ORIENTATION] * mission.orientation_xyzw[:50], axis=1)),
                               1.0, atol=1e-12)
    np.testing.assert_allclose(odom.values[:, cv.POSE_POSITION], mission.position_enu[:50], atol=1e-9)
    assert truth_connection.msgtype == gt.GRADIENT_TENSOR
    assert [t.stamp_ns for t in truth] == stamps.tolist()
    np.testing.assert_array_equal([t.g for t in truth], mission.g_true[:50])
    assert not list(tmp_path.glob('.*partial*'))
