"""``bringup --bag`` as a user runs it: the shipped survey bag replayed through the four
nodes with a calibration from the shipped trim; it ends by itself once the bag is played and
the chain has drained, with a summary. With ``--loop`` it plays the bag again until Ctrl-C.

Truth: the bag's own count of sets (1500 at 10 Hz); the process's exit status."""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
from ros_helpers import REPO, child_env, unique_domain

PARAMS = REPO / 'config' / 'tetra_gradiometer.yaml'


@pytest.fixture(scope='module')
def calibration(tmp_path_factory):
    """The shipped trim's calibration, as a user makes it."""
    path = tmp_path_factory.mktemp('bringup') / 'calibration.yaml'
    subprocess.run([sys.executable, '-m', 'tetra_gradiometer', 'calibrate', 'bags/trim', '--params',
                    str(PARAMS), '--out', str(path)], cwd=REPO, check=True, capture_output=True)
    return path


def _bringup(calibration, *options: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, '-m', 'tetra_gradiometer', 'bringup', '--bag', 'bags/survey', '--rate', '0',
         '--params', str(PARAMS), '--calibration-file', str(calibration), *options],
        cwd=REPO, env=child_env(unique_domain()), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.mark.slow
def test_bringup_of_a_bag_ends_once_played_with_a_summary(calibration):
    process = _bringup(calibration)
    try:
        output, _ = process.communicate(timeout=240)
    finally:
        process.kill()
    assert process.returncode == 0, output
    assert 'bringup: played 1500 sets; tensor node: 1500 tensors, 0 invalid;' in output, output
    line = next(line for line in output.splitlines() if line.startswith('compensator: '))
    compensated = int(line.split()[1])
    assert compensated >= 1485 and '0 passed through uncompensated' in line, line  # rate 0: paced, none lost
    assert 'Traceback' not in output


@pytest.mark.slow
def test_bringup_with_loop_plays_the_bag_again_until_ctrl_c(calibration):
    process = _bringup(calibration, '--loop')
    lines: list[str] = []
    deadline = time.monotonic() + 240
    assert process.stdout is not None
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        lines.append(line)
        if 'loop: pass 2' in line or not line:
            break
    assert any('loop: pass 2' in line for line in lines), ''.join(lines)
    process.send_signal(signal.SIGINT)  # while it plays as fast as the chain takes it
    try:
        output, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 0, ''.join(lines) + output
    assert 'bringup: played' not in ''.join(lines) + output  # stopped, not played through
