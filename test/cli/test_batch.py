"""``python -m tetra_gradiometer batch DIR --out OUT``: a fleet of seven
bags, one truncated, against a real Dask scheduler and two workers started from this
environment; every row against the single-bag commands run on the same bag; the rerun skip,
``--force`` and the default LocalCluster."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tetra_gradiometer import core
from tetra_gradiometer.__main__ import main
from tetra_gradiometer.cli import calibrate as calibrate_cli
from tetra_gradiometer.cli import compensate as compensate_cli
from tetra_gradiometer.cli import discrepancy as discrepancy_cli
from tetra_gradiometer.cli._args import timebase_from_args
from tetra_gradiometer.core.discrepancy import Settings
from tetra_gradiometer.core.timebase import DEFAULT_TIMEBASE
from tetra_gradiometer.cli import fleet
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag
from tetra_gradiometer.io.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
NT = 1e-9
EARTH = np.array([0.0, 20000.0, -45000.0]) * NT
WINDOW = '0:59'
#: The fleet: name -> expected status. Four simulated bags (sqlite3 and mcap, params with and
#: without the Earth field), the shipped sample bags with their scenario files beside them
#: (trim: calibrates; survey, a pass over a target: its window is refused), one truncated.
EXPECTED = {
    'sim1': 'ok',
    'sim2': 'ok',
    'sim3': 'ok',
    'sim4': 'ok',
    'trim': 'ok',
    'survey': 'refused',
    'truncated': 'failed',
}


def _simulated(root: Path, name: str, seed: int, *, storage: str, earth: bool) -> None:
    """A 60 s trim then a 20 s straight leg at 10 Hz (800 sets), its params beside it."""
    rng = np.random.default_rng(seed)
    geometry = core.TetraGeometry.regular(0.5)
    scenario = core.Scenario(
        geometry=geometry,
        earth_field_enu=EARTH,
        segments=(
            core.TrimManoeuvre(60.0, center=(0.0, 0.0, -50.0)),
            core.SurveyLine((-20.0, 20.0, -50.0), (20.0, 20.0, -50.0), 2.0),
        ),
        sample_rate_hz=10.0,
        interference=core.random_interference(rng, reference_clean=seed % 2 == 0),
        noise_t=0.1 * NT,
    )
    mission = core.simulate(scenario, rng)
    write_mission_bag(root / name, mission, storage=storage, progress=False)
    params = {'sensor_positions': geometry.to_flat()}
    if earth:
        params['earth_field_enu'] = [float(v) for v in EARTH]
    (root / f'{name}.yaml').write_text(params_document(params))


def _truncate(bag: Path) -> None:
    """Cut the bag's storage file to half its length (a copy that stopped half way)."""
    (storage,) = [p for p in bag.iterdir() if p.suffix in ('.db3', '.mcap')]
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])


@pytest.fixture(scope='module')
def fleet_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp('fleet')
    for seed, storage in zip((1, 2, 3, 4), ('sqlite3', 'mcap', 'sqlite3', 'mcap'), strict=True):
        _simulated(root, f'sim{seed}', seed, storage=storage, earth=seed != 3)
    for name in ('trim', 'survey'):
        shutil.copytree(REPO / 'bags' / name, root / name)
        shutil.copy(REPO / 'bags' / f'{name}.yaml', root / f'{name}.yaml')
    shutil.copytree(root / 'sim1', root / 'truncated')
    shutil.copy(root / 'sim1.yaml', root / 'truncated.yaml')
    _truncate(root / 'truncated')
    (root / 'README.txt').write_text('not a bag\n')
    (root / 'notes').mkdir()  # a folder without metadata.yaml or notes.yaml: not a bag
    return root


def _kill_group(process: subprocess.Popen) -> None:
    """End a process this test started, and its children (its own session)."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=20)


@pytest.fixture
def scheduler(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes of this environment on a free
    port (the scheduler picks it and writes it to its scheduler file). One test uses them:
    function scope ends them with it (idle, the three processes still spin: module scope kept
    them, and their CPU, through the rest of the module)."""
    from dask.distributed import Client

    work = tmp_path_factory.mktemp('dask')
    info = work / 'scheduler.json'
    processes = []

    def start(name, *args):
        log = open(work / f'{name}.log', 'w')  # noqa: SIM115 - closed with the process
        processes.append(
            subprocess.Popen([str(BIN / 'dask'), *args], cwd=work, stdout=log, stderr=log,
                             start_new_session=True)
        )

    try:
        start('scheduler', 'scheduler', '--host', '127.0.0.1', '--port', '0', '--no-dashboard',
              '--dashboard-address', '127.0.0.1:0', '--scheduler-file', str(info))
        deadline = time.monotonic() + 60
        while not info.exists() and time.monotonic() < deadline:  # polls the scheduler's file
            assert processes[0].poll() is None, (work / 'scheduler.log').read_text()
            time.sleep(0.1)
        address = json.loads(info.read_text())['address']
        for i in (1, 2):
            start(f'worker{i}', 'worker', address, '--host', '127.0.0.1', '--nthreads', '1',
                  '--no-dashboard', '--dashboard-address', '127.0.0.1:0',
                  '--name', f'worker{i}', '--local-directory', str(work / f'worker{i}'))
        with Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for process in reversed(processes):
            _kill_group(process)


def _batch(capsys, *args):
    code = main(['batch', *map(str, args)])
    captured = capsys.readouterr()
    assert code == 0, (captured.out, captured.err)
    return captured.out


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with open(out / 'summary.csv', newline='') as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == list(fleet.COLUMNS)
    return {row['bag']: row for row in rows}


def _cli(capsys, *args):
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _params_for(fleet_dir: Path, name: str, tmp_path: Path) -> Path:
    """The params file of a bag for the single-bag commands (the scenario's, as simulate
    writes it, for the shipped bags)."""
    sidecar = fleet_dir / f'{name}.yaml'
    if 'segments' not in yaml.safe_load(sidecar.read_text()):
        return sidecar
    scenario, _ = load_scenario(sidecar)
    path = tmp_path / f'{name}.params.yaml'
    path.write_text(params_document({
        'sensor_positions': scenario.geometry.to_flat(),
        'earth_field_enu': [float(v) for v in scenario.earth_field_enu],
    }))
    return path


def _calibration(path: Path) -> dict:
    document = yaml.safe_load(path.read_text())
    document.pop('created_utc')
    return document


def _single_bag_reference(capsys, fleet_dir, name, tmp_path):
    """Calibrate, compensate and discrepancy on one bag through the single-bag commands."""
    bag, params = fleet_dir / name, _params_for(fleet_dir, name, tmp_path)
    ref = tmp_path / name
    ref.mkdir()
    calibrated = _cli(capsys, 'calibrate', bag, '--params', params, '--window', WINDOW,
                      '--out', ref / 'calib.yaml', '--no-progress')
    compensated = None
    if calibrated[0] == 0:
        compensated = _cli(capsys, 'compensate', bag, '--params', params, '--calibration',
                           ref / 'calib.yaml', '--csv', ref / 'out.csv', '--no-progress')
        assert compensated[0] == 0, compensated
    analysed = _cli(capsys, 'discrepancy', bag, '--params', params, '--out', ref / 'report',
                    '--no-plots')
    return ref, calibrated, compensated, analysed


#: The single-bag commands run here in-process with this process's multi-threaded BLAS, the
#: workers single-threaded (the nanny sets OPENBLAS_NUM_THREADS=1): the same computation up
#: to summation order, so floats agree to ~1e-15 and are compared at 1e-9 (bitwise with one
#: BLAS thread: _assert_bitwise_with_one_blas_thread).
REL = 1e-9


def _close(value: str, reference: float) -> bool:
    return float(value) == pytest.approx(reference, rel=REL, abs=0.0)


def _assert_row_is_the_single_bag_result(row, out, ref, calibrated, analysed, status):
    code, stdout, stderr = calibrated
    if status == 'failed':
        assert code == 1 and row['reason'] == 'calibrate: ' + stderr.removeprefix('error: ').strip()
        return
    report = json.loads((ref / 'report' / 'report.json').read_text())
    assert row['effects'] == (';'.join(report['named_effects']) or 'none')
    assert _close(row['gap_initial_nT'], report['gap_initial_nT'])
    assert _close(row['gap_final_nT'], report['gap_final_nT'])
    assert _close(row['discrepancy_noise_floor_nT'], report['noise_floor_nT'])
    assert row['adequate'] == ('yes' if report['adequate'] else 'no')
    named = ', '.join(report['named_effects']) or 'none'
    if report['unresolved_effects']:  # fitted, not named
        named += f" (unresolved, not named: {', '.join(report['unresolved_effects'])})"
    assert analysed[0] == 0 and f'named effects: {named};' in analysed[1]
    if status == 'refused':
        assert code == 1 and row['reason'] == 'calibrate: ' + stderr.removeprefix('error: ').strip()
        assert not (out / 'calibration.yaml').exists() and not (out / 'compensated.csv').exists()
        assert row['residual_nT_per_m'] == row['sets_compensated'] == ''
        return
    assert code == 0 and row['reason'] == ''
    diagnostics = _calibration(ref / 'calib.yaml')['diagnostics']
    assert _close(row['residual_nT_per_m'], diagnostics['residual_rms_nT_per_m'])
    assert f'residual RMS {float(row["residual_nT_per_m"]):.4g} nT/m' in stdout
    assert _close(row['sensor_noise_nT'], diagnostics['sensor_noise_nT'])
    assert int(row['sets_in_window']) == diagnostics['sets_in_window']
    assert _close(row['coverage_condition'], diagnostics['attitude_coverage_condition'])
    assert _close(row['window_check_ratio'], diagnostics['window_check']['ratio'])
    # The noise floor is the window check's own noise estimate, as calibrate prints it.
    assert _close(row['noise_floor_nT_per_m'], diagnostics['window_check']['noise_rms_nT_per_m'])
    floor = re.search(r'window check passes: .* the noise ([0-9.]+) nT/m', stdout).group(1)
    assert f'{float(row["noise_floor_nT_per_m"]):.3g}' == floor
    ours = np.loadtxt(out / 'compensated.csv', delimiter=',', skiprows=1)
    theirs = np.loadtxt(ref / 'out.csv', delimiter=',', skiprows=1)
    assert ours.shape == theirs.shape and np.array_equal(ours[:, 0], theirs[:, 0])
    np.testing.assert_allclose(ours[:, 1:], theirs[:, 1:], rtol=0, atol=2e-6)  # 6 decimals
    g = theirs[:, 1:10]
    assert int(row['sets_compensated']) == len(g)
    assert float(row['compensated_rms_nT_per_m']) == pytest.approx(np.sqrt(np.mean(g**2)), abs=1e-6)
    assert float(row['raw_rms_nT_per_m']) > 100 * float(row['compensated_rms_nT_per_m'])


@pytest.mark.slow
def test_seven_bags_on_a_scheduler_and_two_workers(fleet_dir, scheduler, tmp_path, capsys):
    out = tmp_path / 'out'
    started = time.perf_counter()
    text = _batch(capsys, fleet_dir, '--out', out, '--window', WINDOW, '--scheduler', scheduler,
                  '--no-plots')
    wall = time.perf_counter() - started
    rows = _summary(out)
    assert {name: row['status'] for name, row in rows.items()} == EXPECTED
    assert f'running on the scheduler {scheduler} (2 workers)' in text
    assert 'batch: 7 bags: 5 ok, 1 refused, 1 failed' in text
    assert len(re.findall(r'^\[\d/7\] ', text, re.M)) == 7  # one line as each bag completes
    workers = {row['worker'] for row in rows.values()}
    assert len(workers) == 2 and f':{os.getpid()}' not in ''.join(workers)
    truncated = rows['truncated']
    assert truncated['reason'].startswith('calibrate: cannot open bag ')
    assert 'database disk image is malformed' in truncated['reason']
    assert rows['survey']['reason'].startswith(
        'calibrate: the window (0:59 s) does not fit the model (a target or a spatially varying field'
    )
    assert rows['trim']['params'] == str(out / 'trim' / 'params.yaml')
    for name, status in EXPECTED.items():
        ref, calibrated, _, analysed = _single_bag_reference(capsys, fleet_dir, name, tmp_path)
        _assert_row_is_the_single_bag_result(rows[name], out / name, ref, calibrated, analysed,
                                             status)
    with capsys.disabled():
        runtimes = sorted(float(r['runtime_s']) for r in rows.values())
        print(f'\nbatch of 7 bags on 2 workers: {wall:.1f} s wall; task runtimes {runtimes} s')

    # A rerun skips the bags done (ok, refused) and retries the failed one.
    before = {name: (out / name / 'row.json').read_bytes() for name in EXPECTED}
    text = _batch(capsys, fleet_dir, '--out', out, '--window', WINDOW, '--scheduler', scheduler,
                  '--no-plots')
    assert 'batch: 7 bags in' in text and '6 done before, skipped' in text and '1 to run' in text
    assert re.findall(r'^\[1/1\] failed\s+truncated; ', text, re.M)
    again = _summary(out)
    for name in EXPECTED:
        if name != 'truncated':
            assert again[name] == rows[name]
            assert (out / name / 'row.json').read_bytes() == before[name]
    assert again['truncated']['reason'] == truncated['reason']

    # A changed input is redone: the params file of sim2 (same values, new bytes).
    params = fleet_dir / 'sim2.yaml'
    params.write_text(params.read_text() + '# edited\n')
    text = _batch(capsys, fleet_dir, '--out', out, '--window', WINDOW, '--scheduler', scheduler,
                  '--no-plots')
    assert '5 done before, skipped' in text and '2 to run' in text
    redone = _summary(out)
    assert re.findall(r'^\[\d/2\] ok\s+sim2; ', text, re.M)
    assert (out / 'sim2' / 'row.json').read_bytes() != before['sim2']
    for column in ('residual_nT_per_m', 'noise_floor_nT_per_m', 'effects', 'gap_final_nT'):
        assert redone['sim2'][column] == rows['sim2'][column]


def _assert_bitwise_with_one_blas_thread(bag: Path, params: Path, out: Path, ref: Path) -> None:
    """With one BLAS thread, as the workers run, the single-bag commands write the very bytes
    batch wrote (the calibration but for its creation time, the report but for its runtime)."""
    env = {**os.environ, 'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1', 'MKL_NUM_THREADS': '1'}
    for args in (('calibrate', bag, '--params', params, '--out', ref / 'c.yaml'),
                 ('compensate', bag, '--params', params, '--calibration', ref / 'c.yaml', '--csv',
                  ref / 'out.csv'),
                 ('discrepancy', bag, '--params', params, '--out', ref / 'report', '--no-plots')):
        subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)], env=env,
                       check=True, capture_output=True)
    assert _calibration(out / 'calibration.yaml') == _calibration(ref / 'c.yaml')
    assert (out / 'compensated.csv').read_bytes() == (ref / 'out.csv').read_bytes()
    ours, theirs = (json.loads((p / 'report.json').read_text())
                    for p in (out / 'discrepancy', ref / 'report'))
    ours.pop('runtime_s'), theirs.pop('runtime_s')
    assert ours == theirs


@pytest.mark.slow
def test_default_local_cluster_and_force(fleet_dir, tmp_path, capsys):
    small = tmp_path / 'small'
    small.mkdir()
    for name in ('sim3', 'truncated'):
        shutil.copytree(fleet_dir / name, small / name)
        shutil.copy(fleet_dir / f'{name}.yaml', small / f'{name}.yaml')
    out = tmp_path / 'out'
    text = _batch(capsys, small, '--out', out, '--no-progress')
    assert 'running on a LocalCluster of 2 workers' in text
    rows = _summary(out)
    assert {n: r['status'] for n, r in rows.items()} == {'sim3': 'ok', 'truncated': 'failed'}
    # Without --window the trim is found: the simulated 60 s manoeuvre at 10 Hz (sets 0-59.9 s),
    # not the 20 s line after it.
    assert rows['sim3']['window'] == '0:59.9 s'
    assert (out / 'sim3' / 'discrepancy' / 'gap.png').exists()  # plots by default
    _assert_bitwise_with_one_blas_thread(small / 'sim3', small / 'sim3.yaml', out / 'sim3',
                                         tmp_path / 'ref')
    row_json = (out / 'sim3' / 'row.json').read_bytes()

    text = _batch(capsys, small, '--out', out, '--force')
    assert '2 to run' in text and 'skipped' not in text.splitlines()[0]
    assert (out / 'sim3' / 'row.json').read_bytes() != row_json
    forced = _summary(out)
    for column in ('residual_nT_per_m', 'compensated_rms_nT_per_m', 'effects', 'gap_final_nT'):
        assert forced['sim3'][column] == rows['sim3'][column]
    assert forced['truncated']['status'] == 'failed'


def test_outputs_that_are_not_a_batch_folder_are_refused(fleet_dir, tmp_path, capsys):
    foreign = tmp_path / 'foreign'
    foreign.mkdir()
    (foreign / 'keep.txt').write_text('mine')
    for out, fragment in ((foreign, 'is not a batch folder'), (fleet_dir, 'contains the input')):
        assert main(['batch', str(fleet_dir), '--out', str(out)]) == 1
        err = capsys.readouterr().err
        assert err.startswith('error: ') and fragment in err, err
    assert sorted(p.name for p in foreign.iterdir()) == ['keep.txt']
    assert not (fleet_dir / 'summary.csv').exists()
    assert main(['batch', str(fleet_dir / 'sim1'), '--out', str(tmp_path / 'x')]) == 1
    assert 'is a rosbag2 folder' in capsys.readouterr().err
    assert main(['batch', str(tmp_path / 'x'), '--out', str(tmp_path / 'y')]) == 1
    assert 'is not a folder' in capsys.readouterr().err


def test_a_bug_is_a_failed_row_with_its_traceback(fleet_dir, tmp_path, monkeypatch):
    """In process: an exception that is not a TetraError fails the bag, not the batch."""

    def broken(*args, **kwargs):
        raise ZeroDivisionError('simulated bug')

    monkeypatch.setattr(fleet, 'analyze_bag', broken)
    job = fleet.make_job(fleet.FleetBag('sim4', fleet_dir / 'sim4', fleet_dir / 'sim4.yaml'),
                         tmp_path / 'out', (0.0, 59.0))
    row = fleet.process_bag(job)
    folder = tmp_path / 'out' / 'sim4'
    assert row['status'] == 'failed'
    assert row['reason'] == ('bug in discrepancy: ZeroDivisionError: simulated bug '
                             f'(traceback in {folder / "error.txt"})')
    assert 'Traceback' in (folder / 'error.txt').read_text()
    assert (folder / 'calibration.yaml').exists() and (folder / 'compensated.csv').exists()
    assert row['residual_nT_per_m'] is not None and 'effects' not in row
    assert fleet.done_row(job) is None  # failed: a rerun retries it
    lost = fleet.task_error_row(job, RuntimeError('worker gone'))
    assert lost['status'] == 'failed'
    assert lost['reason'] == 'the task did not complete on the cluster: RuntimeError: worker gone'


def test_a_bag_without_its_params_file_is_a_failed_row(fleet_dir, tmp_path):
    bag = fleet.FleetBag('sim1', fleet_dir / 'sim1', tmp_path / 'missing.yaml')
    row = fleet.process_bag(fleet.make_job(bag, tmp_path / 'out', None))
    assert row['status'] == 'failed'
    assert row['reason'] == f'params: params file not found: {tmp_path / "missing.yaml"}'
    assert json.loads((tmp_path / 'out' / 'sim1' / 'row.json').read_text())['row'] == row


def test_the_batch_uses_the_single_bag_commands_defaults():
    """The figures are the same only if the defaults are: calibrate, compensate and
    discrepancy with no options form sets and search effects as batch does."""
    import argparse

    for module, extra in ((calibrate_cli, ['--out', 'x.yaml']), (compensate_cli, []),
                          (discrepancy_cli, ['--out', 'x'])):
        parser = argparse.ArgumentParser()
        module.add_arguments(parser)
        args = parser.parse_args(['bag', '--params', 'p.yaml', *extra])
        assert timebase_from_args(args) == DEFAULT_TIMEBASE
        if module is discrepancy_cli:
            assert discrepancy_cli.settings_from_args(args) == Settings()
        if module is calibrate_cli:
            import inspect

            from tetra_gradiometer.pipelines.calibration import calibrate_bag
            defaults = {k: p.default for k, p in inspect.signature(calibrate_bag).parameters.items()}
            for name in ('method', 'seed', 'generations', 'wide_bounds', 'max_coverage_condition',
                         'max_sets', 'force'):
                assert getattr(args, name) == defaults[name], name
        if module is compensate_cli:
            assert args.sensor_noise_nt is None and not args.generic_reader



def test_only_the_command_imports_dask():
    """The per-bag task and everything below it run without Dask (core/, io/)."""
    code = ('import sys, tetra_gradiometer.cli.fleet, tetra_gradiometer.core; '
            'print(sorted(m for m in sys.modules if m.split(".")[0] in ("dask", "distributed")))')
    result = subprocess.run([sys.executable, '-c', code], check=True, capture_output=True, text=True)
    assert result.stdout.strip() == '[]'


def test_the_batch_folder_is_continued_never_replaced(tmp_path):
    from tetra_gradiometer.io.outputs import BATCH, MARKER, OutputError, output_folder

    empty = tmp_path / 'empty'
    empty.mkdir()
    assert output_folder(empty, BATCH, command='batch') == empty
    assert json.loads((empty / MARKER).read_text()) == {'kind': 'batch folder', 'command': 'batch'}
    (empty / 'sim1').mkdir()  # a previous run's content stays
    assert output_folder(empty, BATCH) == empty and (empty / 'sim1').is_dir()
    assert output_folder(tmp_path / 'new' / 'out', BATCH).is_dir()
    (tmp_path / 'file').write_text('x')
    with pytest.raises(OutputError, match='is not a batch folder'):
        output_folder(tmp_path / 'file', BATCH)
