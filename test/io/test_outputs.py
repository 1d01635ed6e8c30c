"""Fault table, outputs: an output never destroys an input or anything it did not write.

One test per row. Each asserts the bytes of the data it protects (every file under it,
before and after), the exit status, the one ``error:`` line and the absence of a
traceback. Commands run in-process through ``__main__.main`` (the same code path as
``python -m tetra_gradiometer``); the concurrency rows run real processes.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tetra_gradiometer.core import InterferenceParameters, Scenario, TetraGeometry, TrimManoeuvre, random_interference, simulate
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration
from tetra_gradiometer.io.outputs import CALIBRATION, MARKER, OutputError, atomic_write_text
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag
from cli_helpers import assert_refused, run_cli, snapshot

REPO = Path(__file__).resolve().parents[2]
GEOMETRY = TetraGeometry.regular(0.5)
HEADER = 'stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz'


@pytest.fixture(scope='module')
def data(tmp_path_factory) -> Path:
    """A small bag of ours (``bag``), its params and a calibration, plus a foreign bag
    (``other_bag``, no marker: somebody else's recording) in one folder."""
    root = tmp_path_factory.mktemp('faults')
    rng = np.random.default_rng(1)
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=np.array([2e-5, 3e-6, -4.5e-5]),
                        interference=random_interference(rng, k_scale=0.01, b_scale_t=300e-9),
                        segments=(TrimManoeuvre(duration_s=30.0),), sample_rate_hz=10.0, noise_t=0.05e-9)
    mission = simulate(scenario, rng)
    write_mission_bag(root / 'bag', mission, command='test')
    write_mission_bag(root / 'other_bag', mission)
    (root / 'other_bag' / MARKER).unlink()
    (root / 'params.yaml').write_text(params_document({'sensor_positions': GEOMETRY.to_flat()}))
    return root


@pytest.fixture()
def work(data, tmp_path) -> Path:
    """A private copy of ``data`` for one test (tests may write beside it)."""
    import shutil
    target = tmp_path / 'data'
    shutil.copytree(data, target)
    return target


def calibrate(capsys, work: Path, out: Path, *extra) -> tuple[int, str, str]:
    return run_cli(capsys, 'calibrate', work / 'bag', '--params', work / 'params.yaml', '--out', out,
                   '--no-progress', *extra)


def compensate(capsys, work: Path, *extra) -> tuple[int, str, str]:
    return run_cli(capsys, 'compensate', work / 'bag', '--params', work / 'params.yaml', '--raw',
                   '--no-progress', *extra)


def test_csv_over_another_bag_is_refused_and_the_bag_kept(capsys, work):
    before = snapshot(work / 'other_bag')
    assert_refused(compensate(capsys, work, '--csv', work / 'other_bag'), 'not a tensor CSV', 'refusing')
    assert snapshot(work / 'other_bag') == before


def test_csv_over_another_bag_is_refused_even_with_force(capsys, work):
    before = snapshot(work / 'other_bag')
    assert_refused(compensate(capsys, work, '--csv', work / 'other_bag', '--force'), 'refusing')
    assert snapshot(work / 'other_bag') == before


def test_csv_over_the_input_bag_is_refused(capsys, work):
    before = snapshot(work)
    assert_refused(compensate(capsys, work, '--csv', work / 'bag', '--force'), 'is the input')
    assert snapshot(work) == before


def test_out_bag_at_the_parent_of_the_input_is_refused(capsys, work):
    before = snapshot(work)
    assert_refused(compensate(capsys, work, '--out-bag', work, '--force'), 'contains the input')
    assert snapshot(work) == before


def test_csv_at_dot_dot_is_refused(capsys, work, monkeypatch):
    (work / 'sub').mkdir()
    monkeypatch.chdir(work / 'sub')
    before = snapshot(work)
    assert_refused(compensate(capsys, work, '--csv', '..', '--force'), 'refusing')
    assert snapshot(work) == before


def test_a_new_file_inside_a_bag_folder_is_refused(capsys, work):
    before = snapshot(work / 'other_bag')
    assert_refused(compensate(capsys, work, '--csv', work / 'other_bag' / 'g.csv'), 'inside the rosbag2 folder')
    assert snapshot(work / 'other_bag') == before


def test_calibration_over_a_bags_metadata_is_refused(capsys, work):
    before = snapshot(work / 'bag')
    assert_refused(calibrate(capsys, work, work / 'bag' / 'metadata.yaml', '--force'), 'refusing')
    assert snapshot(work / 'bag') == before


def test_calibration_over_the_params_input_is_refused(capsys, work):
    before = snapshot(work / 'params.yaml')
    assert_refused(calibrate(capsys, work, work / 'params.yaml', '--force'), 'is the input')
    assert snapshot(work / 'params.yaml') == before


def test_simulate_into_a_folder_that_is_not_a_bag_of_ours_is_refused(capsys, work, tmp_path):
    folder = tmp_path / 'notes'
    folder.mkdir()
    (folder / 'keep.txt').write_text('field notes\n')
    scenario = REPO / 'config' / 'scenarios' / 'igrf_trim_and_pass.yaml'
    assert_refused(run_cli(capsys, 'simulate', '--scenario', scenario, '--out', folder, '--force', '--no-progress'),
                   'not a rosbag2 folder written by tetra_gradiometer')
    assert snapshot(folder) == {'keep.txt': b'field notes\n'}
    assert sorted(p.name for p in tmp_path.iterdir()) == ['data', 'notes']  # no sidecar, no temporary


def test_a_previous_output_is_kept_without_force_and_replaced_with_it(capsys, work):
    csv = work / 'g.csv'
    assert compensate(capsys, work, '--csv', csv)[0] == 0
    first = csv.read_bytes()
    assert first.startswith(HEADER.encode()) and first.count(b'\n') == 301
    csv.write_bytes(first[:200])  # so that a replacement shows
    assert_refused(compensate(capsys, work, '--csv', csv), 'exists (a previous tensor CSV)', '--force')
    assert csv.read_bytes() == first[:200]
    assert compensate(capsys, work, '--csv', csv, '--force')[0] == 0
    assert csv.read_bytes() == first


def test_a_previous_bag_of_ours_is_replaced_with_force(capsys, work):
    out = work / 'tensor_bag'
    assert compensate(capsys, work, '--out-bag', out)[0] == 0
    assert_refused(compensate(capsys, work, '--out-bag', out), 'exists (a previous rosbag2 folder)')
    assert compensate(capsys, work, '--out-bag', out, '--force')[0] == 0
    assert (out / 'metadata.yaml').is_file() and (out / MARKER).is_file()
    assert sorted(p.name for p in work.iterdir() if p.name.startswith('.')) == []


def test_an_empty_folder_may_receive_a_folder_output(capsys, work):
    (work / 'empty').mkdir()
    assert compensate(capsys, work, '--out-bag', work / 'empty')[0] == 0
    assert (work / 'empty' / 'metadata.yaml').is_file()


def test_a_symlink_at_the_output_is_refused_and_its_target_kept(capsys, work):
    target = work / 'precious.txt'
    target.write_text('precious\n')
    (work / 'link.csv').symlink_to(target)
    assert_refused(compensate(capsys, work, '--csv', work / 'link.csv', '--force'), 'refusing')
    assert target.read_text() == 'precious\n' and (work / 'link.csv').is_symlink()


def test_discrepancy_into_a_foreign_folder_is_refused_before_the_analysis(capsys, work):
    before = snapshot(work / 'other_bag')
    result = run_cli(capsys, 'discrepancy', work / 'bag', '--params', work / 'params.yaml', '--out',
                     work / 'other_bag', '--force')
    assert_refused(result, 'not a discrepancy report folder')
    assert snapshot(work / 'other_bag') == before


def test_paper_into_a_foreign_folder_is_refused_before_the_work(capsys, tmp_path):
    (tmp_path / 'thesis.tex').write_text('chapter 1\n')
    assert_refused(run_cli(capsys, 'paper', '--out', tmp_path, '--force'), 'not a paper reproduction folder')
    assert snapshot(tmp_path) == {'thesis.tex': b'chapter 1\n'}


def test_save_calibration_never_replaces_a_file_that_is_not_a_calibration(tmp_path):
    target = tmp_path / 'vehicle.conf'
    target.write_bytes(b'rudder_gain: 3\n')
    calibration = CalibrationFile(InterferenceParameters(np.zeros((3, 3, 3)), np.zeros((3, 3))), 'test', False,
                                  GEOMETRY.to_flat())
    with pytest.raises(OutputError, match='not a calibration file'):
        save_calibration(target, calibration, force=True)
    assert target.read_bytes() == b'rudder_gain: 3\n'


def test_a_failed_write_leaves_the_previous_output_and_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / 'c.yaml'
    atomic_write_text(target, 'tetra_gradiometer_calibration: 1\n', CALIBRATION)

    def disk_full(*args):
        raise OSError('disk full')
    monkeypatch.setattr(os, 'replace', disk_full)
    with pytest.raises(OutputError, match='disk full'):
        atomic_write_text(target, 'tetra_gradiometer_calibration: 2\n', CALIBRATION, force=True)
    assert target.read_text() == 'tetra_gradiometer_calibration: 1\n'
    assert [p.name for p in tmp_path.iterdir()] == ['c.yaml']


def test_two_runs_writing_one_csv_each_leave_a_whole_file(data, tmp_path):
    """Temporary names are private to a run: both exit 0 and the CSV is complete."""
    csv = tmp_path / 'g.csv'
    command = [sys.executable, '-m', 'tetra_gradiometer', 'compensate', str(data / 'bag'), '--params',
               str(data / 'params.yaml'), '--raw', '--no-progress', '--csv', str(csv), '--force']
    env = dict(os.environ, PYTHONPATH=str(REPO))
    runs = [subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for _ in range(2)]
    results = [(run.wait(timeout=120), run.stderr.read()) for run in runs]
    for code, err in results:
        assert code == 0 or ('exists (a previous tensor CSV)' in err and 'Traceback' not in err), err
    assert any(code == 0 for code, _ in results)
    lines = csv.read_text().splitlines()
    assert lines[0] == HEADER and len(lines) == 301
    assert [p.name for p in tmp_path.iterdir()] == ['g.csv']


def test_a_refusal_from_a_real_process_is_one_line_without_traceback(data, tmp_path):
    command = [sys.executable, '-m', 'tetra_gradiometer', 'compensate', str(data / 'bag'), '--params',
               str(data / 'params.yaml'), '--raw', '--csv', str(data / 'other_bag'), '--force']
    result = subprocess.run(command, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 1
    assert result.stderr.startswith('error: ') and result.stderr.count('\n') == 1, result.stderr
    assert (data / 'other_bag' / 'metadata.yaml').is_file()


def test_an_interrupt_while_the_temporary_folder_is_made_leaves_no_folder(tmp_path, monkeypatch):
    """SIGTERM (raised as KeyboardInterrupt, as __main__ does) delivered just after mkdtemp,
    while the folder's owner file is written: it used to escape before the try that removes
    the folder, leaving a .partial behind (a real signal to this process, not a mock raise)."""
    import signal

    from tetra_gradiometer.io import outputs

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    real_owner = outputs._owner

    def owner_and_signal(kind):
        os.kill(os.getpid(), signal.SIGTERM)
        return real_owner(kind)

    previous = signal.signal(signal.SIGTERM, interrupt)
    monkeypatch.setattr(outputs, '_owner', owner_and_signal)
    try:
        with pytest.raises(KeyboardInterrupt):
            with outputs.atomic_output(tmp_path / 'out.csv', outputs.CSV) as tmp:
                tmp.write_text('stamp_s,gxx\n', encoding='utf-8')
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == set()  # nothing left held
