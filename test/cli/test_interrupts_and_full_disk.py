"""No traceback, no litter: SIGTERM as SIGINT, a closed pipe, a full disk, a
file-size limit, and the temporaries of a killed run removed by the next run of the same
output. Each: the exit status, one line (or none), the bytes of the previous output, no
`.partial` folder left."""
import errno
import os
import resource
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tetra_gradiometer.io import bag as bag_module
from tetra_gradiometer.io.outputs import BAG, CSV, OWNER, remove_stale_temporaries
from tetra_gradiometer.pipelines import compensation

from test.io.cli_helpers import assert_refused, run_cli, snapshot

REPO = Path(__file__).resolve().parents[2]
SMALL = {
    'seed': 3, 'sample_rate_hz': 10, 'noise_nT': 0.05, 'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300}},
    'segments': [{'trim': {'duration_s': 60, 'center_m': [0.0, 0.0, -50.0]}}],
}
#: Long enough to be caught writing (~60 000 sets with /odom, temperature and battery).
LONG = {**SMALL, 'sample_rate_hz': 100,
        'segments': [{'trim': {'duration_s': 600, 'center_m': [0.0, 0.0, -50.0]}}]}


def _env() -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop('TETRA_DEBUG', None)
    return env


def _command(*args) -> list[str]:
    return [sys.executable, '-m', 'tetra_gradiometer', *map(str, args)]


def _partials(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith('.partial'))


@pytest.fixture(scope='module')
def scenarios(tmp_path_factory):
    root = tmp_path_factory.mktemp('interrupts')
    (root / 'small.yaml').write_text(yaml.safe_dump(SMALL))
    (root / 'long.yaml').write_text(yaml.safe_dump(LONG))
    return root


def _previous(out: Path, scenarios: Path, capsys) -> dict[str, bytes]:
    """A previous simulate output at ``out``, and its bytes."""
    assert run_cli(capsys, 'simulate', '--scenario', scenarios / 'small.yaml', '--out', out,
                   '--mag-only')[0] == 0
    return snapshot(out)


def test_sqlite_disk_full_is_one_line_and_keeps_the_previous_bag(scenarios, tmp_path, capsys,
                                                                    monkeypatch):
    root = tmp_path
    before = _previous(root / 'out', scenarios, capsys)
    calls = [0]
    original = bag_module.BagWriter.write_raw

    def full_after_100(self, *args):
        calls[0] += 1
        if calls[0] > 100:  # what rosbags' sqlite3 storage raises on a full disk
            raise sqlite3.OperationalError('database or disk is full')
        return original(self, *args)

    monkeypatch.setattr(bag_module.BagWriter, 'write_raw', full_after_100)
    result = run_cli(capsys, 'simulate', '--scenario', scenarios / 'small.yaml', '--out',
                     root / 'out', '--mag-only', '--force')
    assert_refused(result, f'database or disk is full while writing {root / "out"}',
                   'nothing was replaced')
    assert snapshot(root / 'out') == before
    assert _partials(root) == []


def test_enospc_writing_the_csv_is_one_line(scenarios, tmp_path, capsys, monkeypatch):
    (tmp_path / 'small.yaml').write_text(yaml.safe_dump(SMALL))
    assert run_cli(capsys, 'simulate', '--scenario', tmp_path / 'small.yaml', '--out',
                   tmp_path / 'bag', '--mag-only')[0] == 0
    csv = tmp_path / 'out.csv'
    assert run_cli(capsys, 'compensate', tmp_path / 'bag', '--params', tmp_path / 'bag.params.yaml',
                   '--raw', '--csv', csv)[0] == 0
    before = csv.read_bytes()

    class FullFile:
        def __init__(self, *args, **kwargs):
            self.handle = open(*args, **kwargs)

        def write(self, text):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

    monkeypatch.setattr(compensation, 'open', FullFile, raising=False)
    result = run_cli(capsys, 'compensate', tmp_path / 'bag', '--params',
                     tmp_path / 'bag.params.yaml', '--raw', '--csv', csv, '--force')
    assert_refused(result, f'cannot write {csv}: No space left on device (nothing was replaced)')
    assert csv.read_bytes() == before
    assert _partials(tmp_path) == []


@pytest.mark.parametrize('storage, message', [
    ('sqlite3', 'disk I/O error while writing'),  # sqlite3's report of EFBIG
    ('mcap', 'File too large (nothing was replaced)'),
])
def test_a_real_file_size_limit_is_one_line(scenarios, tmp_path, storage, message):
    """RLIMIT_FSIZE of 256 kB in the child: the kernel refuses the write (EFBIG; SIGXFSZ is
    ignored by the command, so it is not killed)."""
    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))

    done = subprocess.run(_command('simulate', '--scenario', scenarios / 'small.yaml', '--out',
                                   tmp_path / 'out', '--storage', storage),
                          preexec_fn=limit, capture_output=True, text=True, env=_env(),
                          timeout=120)
    assert done.returncode == 1, done.stderr
    assert done.stderr.startswith('error: ') and done.stderr.count('\n') == 1, done.stderr
    assert message in done.stderr and 'Traceback' not in done.stderr
    assert not (tmp_path / 'out').exists() and _partials(tmp_path) == []


def test_a_closed_pipe_ends_quietly(tmp_path):
    """`calibrate ... | head -0`: the reader is gone before the first line."""
    (tmp_path / 's.yaml').write_text(yaml.safe_dump(SMALL))
    assert subprocess.run(_command('simulate', '--scenario', tmp_path / 's.yaml', '--out',
                                   tmp_path / 'bag'), env=_env(), capture_output=True).returncode == 0
    read, write = os.pipe()
    os.close(read)
    done = subprocess.run(_command('calibrate', tmp_path / 'bag', '--params',
                                   tmp_path / 'bag.params.yaml', '--out', tmp_path / 'c.yaml'),
                          stdout=write, stderr=subprocess.PIPE, text=True, env=_env(), timeout=120)
    os.close(write)
    assert (done.returncode, done.stderr) == (141, '')
    assert (tmp_path / 'c.yaml').read_text().startswith('tetra_gradiometer_calibration:')


@pytest.mark.parametrize('args, status', [
    (('--help',), 141),
    (('calibrate', '--help'), 0),  # argparse writes its help itself and swallows the OSError
])
def test_help_into_a_closed_pipe_ends_quietly(args, status):
    read, write = os.pipe()
    os.close(read)
    done = subprocess.run(_command(*args), stdout=write, stderr=subprocess.PIPE, text=True,
                          env=_env(), timeout=120)
    os.close(write)
    assert (done.returncode, done.stderr) == (status, '')


def _start_and_catch_writing(args, folder: Path) -> subprocess.Popen:
    """Start the command and return once its temporary folder exists (it is writing; a kill
    may land before its owner file is written)."""
    process = subprocess.Popen(_command(*args), env=_env(), stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not _partials(folder):
        assert process.poll() is None, f'finished before it could be caught: {process.stderr.read()}'
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return process


@pytest.fixture(scope='module')
def long_bag(scenarios):
    """The long mission, simulated once (the input of the compensate cases)."""
    done = subprocess.run(_command('simulate', '--scenario', scenarios / 'long.yaml', '--out',
                                   scenarios / 'long_bag', '--mag-only'), env=_env(),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return scenarios / 'long_bag'


@pytest.mark.parametrize('command', [pytest.param('simulate', marks=pytest.mark.slow), 'compensate'])
def test_sigterm_removes_the_temporaries_and_keeps_the_previous_output(
        scenarios, long_bag, tmp_path, capsys, command):
    out = tmp_path / 'out'
    if command == 'simulate':
        before = _previous(out, scenarios, capsys)
        args = ('simulate', '--scenario', scenarios / 'long.yaml', '--out', out, '--force')
    else:
        params = f'{long_bag}.params.yaml'
        assert run_cli(capsys, 'compensate', long_bag, '--params', params, '--raw',
                       '--out-bag', out)[0] == 0
        before = snapshot(out)
        args = ('compensate', long_bag, '--params', params, '--raw', '--out-bag', out, '--force')
    sidecars = [tmp_path / f'out.{end}' for end in ('params.yaml', 'truth.npz')]
    sidecars_before = [p.read_bytes() if p.exists() else None for p in sidecars]
    process = _start_and_catch_writing(args, tmp_path)
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=60) == 143
    assert process.stderr.read() == ''
    assert _partials(tmp_path) == []
    assert snapshot(out) == before  # simulate: the bag and its sidecars, all previous
    assert [p.read_bytes() if p.exists() else None for p in sidecars] == sidecars_before


def test_the_next_run_removes_a_killed_runs_temporaries(scenarios, tmp_path):
    out = tmp_path / 'out'
    args = ('simulate', '--scenario', scenarios / 'long.yaml', '--out', out, '--mag-only')
    process = _start_and_catch_writing(args, tmp_path)
    process.kill()  # SIGKILL: nothing of the run can clean up
    process.wait(timeout=30)
    left = _partials(tmp_path)
    assert left and not out.exists()  # the sidecars' and maybe the bag's
    (tmp_path / 'small.yaml').write_text(yaml.safe_dump(SMALL))
    done = subprocess.run(_command('simulate', '--scenario', tmp_path / 'small.yaml', '--out',
                                   out, '--mag-only'), env=_env(), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert _partials(tmp_path) == [] and (out / 'metadata.yaml').is_file()


def test_only_a_dead_runs_own_temporaries_are_removed(tmp_path):
    """remove_stale_temporaries: a live run's (this process), another kind's, one without an
    owner file but with something in it, an empty one made less than a minute ago (a run
    about to write its owner file), an empty one named by a live run, another output's stay;
    a dead run's of the same kind and output goes, and an empty one without an owner (or
    with a cut-short one) named by a dead run or older than a minute (a run killed before it
    owned it)."""
    dead = subprocess.run([sys.executable, '-c', 'import os; print(os.getpid())'],
                          capture_output=True, text=True).stdout.strip()
    import json
    import socket

    def partial(name, owner):
        folder = tmp_path / name
        (folder / 'out').mkdir(parents=True)
        if owner is not None:
            (folder / OWNER).write_text(json.dumps(owner))
        return folder

    host = socket.gethostname()
    gone = partial('.out.abcd1234.partial', {'host': host, 'pid': int(dead), 'kind': BAG.name})
    kept = [
        partial('.out.live0000.partial', {'host': host, 'pid': os.getpid(), 'kind': BAG.name}),
        partial('.out.kind0000.partial', {'host': host, 'pid': int(dead), 'kind': CSV.name}),
        partial('.out.host0000.partial', {'host': 'elsewhere', 'pid': int(dead), 'kind': BAG.name}),
        partial('.out.none0000.partial', None),
        partial('.out2.abcd1234.partial', {'host': host, 'pid': int(dead), 'kind': BAG.name}),
    ]
    old = time.time() - 120.0
    unowned_empty = tmp_path / '.out.empt0000.partial'
    unowned_empty.mkdir()
    cut_short = tmp_path / '.out.half0000.partial'
    cut_short.mkdir()
    (cut_short / OWNER).write_text('{"host": "')
    for folder in (unowned_empty, cut_short, kept[3]):
        os.utime(folder, (old, old))
    fresh_empty = tmp_path / '.out.new00000.partial'
    fresh_empty.mkdir()
    kept.append(fresh_empty)
    start = (Path(f'/proc/{os.getpid()}/stat').read_text().rsplit(')', 1)[1].split()[19])
    named_live = tmp_path / f'.out.live1111.{os.getpid()}-{start}.partial'
    named_dead = tmp_path / f'.out.dead1111.{dead}-1.partial'
    named_reused = tmp_path / f'.out.reus1111.{os.getpid()}-1.partial'  # this pid, another start
    for folder in (named_live, named_dead, named_reused):
        folder.mkdir()
    kept.append(named_live)
    removed = remove_stale_temporaries(tmp_path / 'out', BAG)
    assert sorted(removed) == sorted([gone, unowned_empty, cut_short, named_dead, named_reused])
    assert not any(folder.exists() for folder in removed) and all(folder.is_dir() for folder in kept)
