"""The ROS commands end to end as a user runs them: ``demo`` and ``record``."""
from __future__ import annotations

import re
import subprocess
import sys

import numpy as np

from ros_helpers import REPO, child_env, unique_domain

from tetra_gradiometer import core
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.scenario import load_scenario_or_default


def _run(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env=child_env(unique_domain()))


def test_demo_calibrates_compensates_and_ends_with_one_result_line(tmp_path):
    result = _run('demo', '--out', str(tmp_path / 'demo'))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith('RESULT')]
    assert len(lines) == 1 and result.stdout.rstrip().splitlines()[-1] == lines[0]
    match = re.fullmatch(r'RESULT compensated_percent=(\S+) rms_residual_nT_per_m=(\S+) improvement_ratio=(\S+)',
                         lines[0])
    assert match, lines[0]
    percent, rms, ratio = map(float, match.groups())
    assert percent >= 99.0
    noise_floor_nt = core.noise_floor(0.1e-9, core.TetraGeometry.regular(0.5)) * 1e9  # 0.28 nT/m
    assert rms < 1.5 * noise_floor_nt
    assert ratio > 100
    assert 'calibrator/calibrate: known_gradient_lstsq' in result.stdout
    png = tmp_path / 'demo' / 'norms.png'
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 20_000


def test_record_writes_the_sim_driver_topics_as_simulated(tmp_path):
    bag_path = tmp_path / 'bag'
    result = _run('record', '--out', str(bag_path), '--duration', '5', '--rate', '10', '--storage', 'mcap')
    assert result.returncode == 0, result.stdout + result.stderr
    scenario, seed = load_scenario_or_default()
    mission = core.simulate(scenario, np.random.default_rng(seed))
    with MagneticBag(bag_path) as bag:
        stamps, fields = bag.read_sets()
        odom = bag.read_series('/odom')
        truth_topic = bag.has_topic('/tetra/gradient/truth')
    assert len(stamps) == 50
    np.testing.assert_allclose(np.diff(stamps), 1e8, atol=2)
    np.testing.assert_array_equal(fields, mission.fields_measured[:50])
    np.testing.assert_allclose(np.abs(np.sum(odom.values * mission.orientation_xyzw[:50], axis=1)), 1.0, atol=1e-12)
    assert truth_topic
    assert not list(tmp_path.glob('.*partial*'))
