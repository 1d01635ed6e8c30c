"""The core must not pull in ROS: it runs ashore, in notebooks, anywhere numpy runs."""
import subprocess
import sys

import pytest


@pytest.mark.parametrize('module', [
    'tetra_gradiometer.core',
    'tetra_gradiometer.core.discrepancy',
    'tetra_gradiometer.core.discrepancy.synthetic',
    'tetra_gradiometer.core.paper',
])
def test_core_import_loads_no_ros_and_nothing_beyond_numpy_scipy_and_the_core(module):
    code = (
        f'import sys, {module}\n'
        'bad = sorted({m.split(".")[0] for m in sys.modules} & '
        '{"rclpy", "rosbags", "yaml", "matplotlib", "ppigrf", "pandas", "tqdm"})\n'
        'bad += sorted(m for m in sys.modules if m.startswith("tetra_gradiometer.") and '
        'not m.startswith(("tetra_gradiometer.core", "tetra_gradiometer.errors")))\n'
        'print(",".join(bad))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ''
