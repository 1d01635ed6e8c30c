"""The core must not pull in ROS: it runs ashore, in notebooks, anywhere numpy runs."""
import subprocess
import sys


def test_core_import_loads_no_ros_and_nothing_beyond_numpy_scipy():
    code = (
        'import sys, tetra_gradiometer.core\n'
        'bad = sorted({m.split(".")[0] for m in sys.modules} & '
        '{"rclpy", "rosbags", "yaml", "matplotlib", "ppigrf", "pandas", "tqdm"})\n'
        'print(",".join(bad))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ''
