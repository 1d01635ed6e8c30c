"""Safe, atomic outputs: an output never destroys an input or anything it did not write.

Every file or folder a command writes goes through :func:`atomic_output`:

* **Refusal first, nothing touched.** The target is refused (:class:`OutputError`) when it
  is, contains or lies inside one of the command's inputs, when it lies inside a rosbag2
  folder (a folder holding ``metadata.yaml``), or when it exists and is not a previous
  output of the same :class:`OutputKind`. A previous output is replaced only with
  ``force=True`` (the CLI's ``--force``). An empty folder may be filled without ``force``.
* **How a previous output is recognized.** Files by their content: a tensor CSV by its
  header line ``stamp_s,gxx,...``, a calibration file by its first key
  ``tetra_gradiometer_calibration``, a simulated params file by its first line ``# Written
  by "python -m tetra_gradiometer simulate"``, a truth file by being a ``.npz`` with
  ``g_true`` and ``stamps_ns``. Folders (bags, reports, paper and demo outputs) by the
  marker file :data:`MARKER` this module writes into them, naming their kind.
* **Atomic and private.** Each run fills a path inside its own temporary folder beside the
  target (``tempfile.mkdtemp``: two runs never share it), fsyncs it, checks the target
  again and moves it into place with one ``os.replace``. A folder that replaces a previous
  output is first moved aside into that temporary folder, then deleted. On any error (or a
  kill) the target is as it was; a run killed by SIGKILL (or a power cut) leaves its
  ``.NAME.XXXXXXXX.partial`` folder, which the next run writing the same target as the same
  kind removes: the temporary folder holds :data:`OWNER` (the run's host, pid, process start
  time and output kind), and only a folder of a run that no longer exists on this host is
  removed (never a concurrent run's, never one with anything else in it but no owner). A
  kill between ``mkdtemp`` and the owner file (microseconds; seen on a machine at load 10)
  leaves an empty folder: removed once :data:`UNOWNED_EMPTY_AGE_S` old, when no live run
  can still be about to write its owner file.
* **Disk full** (``ENOSPC``, ``EDQUOT``, ``EFBIG`` past a file-size limit) and sqlite3's
  ``database or disk is full`` while filling the temporary path are an :class:`OutputError`
  (one line), the temporary folder removed.
* **Folders filled over time** (``batch``'s output folder): :func:`output_folder` refuses
  what :func:`check_output` refuses, continues a previous output of its kind (never replaces
  it) and marks a new one at once; each entry inside is its own atomic output.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import sqlite3
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..errors import OutputError

__all__ = [
    'BAG',
    'BATCH',
    'BATCH_BAG',
    'BATCH_SUMMARY',
    'CALIBRATION',
    'CSV',
    'DEMO',
    'MARKER',
    'OutputError',
    'OutputKind',
    'PAPER',
    'PARAMS',
    'REPORT',
    'SURVEY',
    'TARGETS',
    'TRUTH',
    'atomic_output',
    'atomic_write_text',
    'check_output',
    'output_folder',
    'remove_stale_temporaries',
]

#: Name of the marker file inside every folder this package writes (JSON: kind, command).
MARKER = '.tetra_gradiometer_output'
#: sqlite3's messages of a storage that cannot take more: a full disk or quota
#: (``SQLITE_FULL``), a write refused by the system (``SQLITE_IOERR``: ``EFBIG`` past
#: ``ulimit -f``, a failing disk).
SQLITE_STORAGE_ERRORS = ('database or disk is full', 'disk I/O error')
#: Name of the file in a run's temporary folder naming its owner (JSON: host, pid, start,
#: kind), beside the output being filled (never inside it).
OWNER = '.owner'
#: An empty temporary folder without a readable owner file, older than this (s, by its
#: mtime), is a run's killed before it wrote :data:`OWNER`: removed.
UNOWNED_EMPTY_AGE_S = 60.0


def _starts_with(prefix: bytes) -> Callable[[Path], bool]:
    def recognize(path: Path) -> bool:
        try:
            with open(path, 'rb') as handle:
                return handle.read(len(prefix)) == prefix
        except OSError:
            return False

    return recognize


def _truth_npz(path: Path) -> bool:
    try:
        with zipfile.ZipFile(path) as archive:
            return {'g_true.npy', 'stamps_ns.npy'} <= set(archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


@dataclass(frozen=True)
class OutputKind:
    """One kind of output: what it is called, whether it is a folder, how it is recognized.

    Attributes
    ----------
    name : str
        Used in messages and in a folder's marker file.
    folder : bool
        A folder (recognized by :data:`MARKER`) rather than a file.
    recognize : callable or None
        For files: ``recognize(path) -> bool``, True when ``path`` holds this kind.
    """

    name: str
    folder: bool = False
    recognize: Callable[[Path], bool] | None = None

    def holds(self, path: Path) -> bool:
        """True when ``path`` (which exists) is a previous output of this kind."""
        if path.is_symlink():
            return False
        if self.folder:
            return path.is_dir() and _marker_kind(path) == self.name
        return path.is_file() and self.recognize is not None and self.recognize(path)


CSV = OutputKind('tensor CSV', recognize=_starts_with(b'stamp_s,gxx,'))
CALIBRATION = OutputKind(
    'calibration file', recognize=_starts_with(b'tetra_gradiometer_calibration:')
)
PARAMS = OutputKind(
    'simulated params file',
    recognize=_starts_with(b'# Written by "python -m tetra_gradiometer simulate"'),
)
TRUTH = OutputKind('simulation truth file', recognize=_truth_npz)
BAG = OutputKind('rosbag2 folder', folder=True)
REPORT = OutputKind('discrepancy report folder', folder=True)
HEALTH_REPORT = OutputKind('health report folder', folder=True)
CALIBRATION_REPORT = OutputKind('calibration report folder', folder=True)
PAPER = OutputKind('paper reproduction folder', folder=True)
DEMO = OutputKind('demo folder', folder=True)
#: ``locate --out``: targets.json, the raw comparison, the map and report.md.
TARGETS = OutputKind('targets folder', folder=True)
#: ``survey --out``: grids (netCDF, GeoTIFF), targets and track (GeoJSON), report.html.
SURVEY = OutputKind('survey folder', folder=True)
#: ``batch --out``: the fleet's folder (``summary.csv`` and one :data:`BATCH_BAG` per bag).
BATCH = OutputKind('batch folder', folder=True)
#: ``batch``: one bag's outputs (calibration, CSV, report, ``row.json``), written as a whole.
BATCH_BAG = OutputKind('batch bag folder', folder=True)
BATCH_SUMMARY = OutputKind('batch summary CSV', recognize=_starts_with(b'bag,status,reason,'))


def _marker_text(kind: OutputKind, command: str) -> str:
    return json.dumps({'kind': kind.name, 'command': command}) + '\n'


def _marker_kind(folder: Path) -> str | None:
    try:
        return str(json.loads((folder / MARKER).read_text(encoding='utf-8'))['kind'])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _bag_folder_around(path: Path) -> Path | None:
    """The nearest folder at or above ``path``'s parent that is a rosbag2 folder."""
    for folder in path.parents:
        if (folder / 'metadata.yaml').is_file():
            return folder
    return None


def check_output(
    path: str | os.PathLike,
    kind: OutputKind,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
) -> Path:
    """Raise :class:`OutputError` unless ``path`` may be written as ``kind``; return it.

    Parameters
    ----------
    path : path-like
        The output the command is asked to write.
    kind : OutputKind
        What it writes there.
    force : bool
        Allow replacing a previous output of the same kind.
    inputs : iterable of path-like
        Files and folders the command reads: the output may not be, contain or lie in one.
    """
    path = Path(path)
    resolved = path.resolve()
    for source in inputs:
        source_resolved = Path(source).resolve()
        if _inside(source_resolved, resolved):
            relation = 'is' if source_resolved == resolved else 'contains'
            raise OutputError(
                f'{path} {relation} the input {source}: refusing to write there '
                '(nothing was written)'
            )
        if _inside(resolved, source_resolved):
            raise OutputError(
                f'{path} lies inside the input {source}: refusing to write there '
                '(nothing was written)'
            )
    bag = _bag_folder_around(resolved)
    if bag is not None:
        raise OutputError(
            f'{path} lies inside the rosbag2 folder {bag}: refusing to write there '
            '(nothing was written)'
        )
    if not os.path.lexists(path):
        return path
    if kind.folder and path.is_dir() and not path.is_symlink() and not any(path.iterdir()):
        return path  # an empty folder: nothing to lose
    if not kind.holds(path):
        what = 'folder' if path.is_dir() else 'file'
        raise OutputError(
            f'{path} exists and is not a {kind.name} written by tetra_gradiometer '
            f'(an existing {what}): refusing to replace it (nothing was written)'
        )
    if not force:
        raise OutputError(
            f'{path} exists (a previous {kind.name}); --force replaces it (nothing was written)'
        )
    return path


#: The signals held while an output's temporary folder is made (see :func:`atomic_output`).
_INTERRUPTS = frozenset({signal.SIGINT, signal.SIGTERM})


@contextmanager
def atomic_output(
    path: str | os.PathLike,
    kind: OutputKind,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    command: str = '',
) -> Iterator[Path]:
    """Yield a private temporary path to fill as ``kind``; on success it becomes ``path``.

    The yielded path does not exist yet: create the file, or the folder (``mkdir`` or a
    writer that creates it). On success a folder gets the :data:`MARKER` file (naming
    ``kind`` and ``command``), everything is fsynced, ``path`` is checked again and the
    temporary path moved into place. On error nothing at ``path`` changes.
    """
    inputs = tuple(inputs)
    path = check_output(path, kind, force=force, inputs=inputs)
    # Ctrl-C and SIGTERM are held while the temporary folder is made and owned: delivered
    # between mkdtemp's return and the try below, they left a folder no one removed (seen
    # once in a fresh-clone run of test_interrupts_and_full_disk). They land inside the try.
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _INTERRUPTS)
    work: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path, kind)
        work = Path(tempfile.mkdtemp(prefix=f'.{path.name}.', suffix='.partial', dir=path.parent))
        (work / OWNER).write_text(json.dumps(_owner(kind)), encoding='utf-8')
    except BaseException as error:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        if isinstance(error, OSError):
            raise OutputError(f'cannot write {path}: {error.strerror or error}') from error
        raise
    try:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)  # a held interrupt is raised here
        tmp = work / path.name
        yield tmp
        if kind.folder:
            if not tmp.is_dir():
                raise OutputError(f'{path}: nothing was written')
            (tmp / MARKER).write_text(_marker_text(kind, command), encoding='utf-8')
        _fsync_tree(tmp)
        check_output(path, kind, force=force, inputs=inputs)  # it may have appeared meanwhile
        _move_into_place(tmp, path, work)
    except OSError as error:  # disk full, permissions: the user's problem, said in one line
        raise OutputError(
            f'cannot write {path}: {error.strerror or error} (nothing was replaced)'
        ) from error
    except sqlite3.OperationalError as error:  # rosbags' sqlite3 storage
        if str(error) not in SQLITE_STORAGE_ERRORS:
            raise  # not the storage failing (a locked or malformed input bag): its own error
        raise OutputError(f'{error} while writing {path} (nothing was replaced)') from error
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` (Linux ``/proc``: clock ticks since boot), telling
    a reused pid from the run that wrote an owner file; None where unknown."""
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii', errors='replace') as handle:
            return handle.read().rsplit(')', 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _owner(kind: OutputKind) -> dict[str, object]:
    pid = os.getpid()
    return {
        'host': socket.gethostname(),
        'pid': pid,
        'start': _process_start(pid),
        'kind': kind.name,
    }


def _alive(pid: int, start: object) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return start is None or _process_start(pid) in (None, start)


def remove_stale_temporaries(path: str | os.PathLike, kind: OutputKind) -> list[Path]:
    """Remove the temporary folders an earlier, killed run left beside ``path`` while
    writing it as ``kind`` (see the module); return them. A folder is removed only when its
    :data:`OWNER` file names this host, ``kind`` and a process that no longer runs."""
    path = Path(path)
    pattern = re.compile(rf'\.{re.escape(path.name)}\.[A-Za-z0-9_]{{8}}\.partial')
    removed: list[Path] = []
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return removed
    host = socket.gethostname()
    for entry in entries:
        if not pattern.fullmatch(entry.name) or entry.is_symlink() or not entry.is_dir():
            continue
        try:
            owner = json.loads((entry / OWNER).read_text(encoding='utf-8'))
            mine = owner['host'] == host and owner['kind'] == kind.name
            stale = mine and not _alive(int(owner['pid']), owner.get('start'))
        except (OSError, ValueError, KeyError, TypeError):
            stale = _unowned_and_empty(entry)  # else an older run's, or not ours: left alone
        if stale:
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


def _unowned_and_empty(folder: Path) -> bool:
    """True for a temporary folder holding nothing but (maybe) a cut-short owner file, last
    changed over :data:`UNOWNED_EMPTY_AGE_S` ago: a run killed before it owned it."""
    try:
        names = [entry.name for entry in folder.iterdir()]
        age_s = time.time() - folder.stat().st_mtime
    except OSError:
        return False
    return set(names) <= {OWNER} and age_s > UNOWNED_EMPTY_AGE_S


def output_folder(
    path: str | os.PathLike,
    kind: OutputKind,
    *,
    inputs: Iterable[str | os.PathLike] = (),
    command: str = '',
) -> Path:
    """The folder ``path`` of ``kind``, to be filled over time: created (with its marker)
    when absent or empty, continued when it is a previous output of ``kind``.

    Entries are written into it one by one, each through :func:`atomic_output`; the folder
    itself is never replaced. Refused (:class:`OutputError`, nothing touched) as by
    :func:`check_output`: an input, inside a rosbag2 folder, or anything else already there.
    """
    path = check_output(path, kind, force=True, inputs=inputs)
    try:
        path.mkdir(parents=True, exist_ok=True)
        if _marker_kind(path) != kind.name:
            tmp = path / f'{MARKER}.partial'
            tmp.write_text(_marker_text(kind, command), encoding='utf-8')
            os.replace(tmp, path / MARKER)
    except OSError as error:
        raise OutputError(f'cannot write {path}: {error.strerror or error}') from error
    return path


def atomic_write_text(
    path: str | os.PathLike,
    text: str,
    kind: OutputKind,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
) -> Path:
    """Write ``text`` (UTF-8) to ``path`` as ``kind`` through :func:`atomic_output`."""
    with atomic_output(path, kind, force=force, inputs=inputs) as tmp:
        tmp.write_text(text, encoding='utf-8')
    return Path(path)


def _fsync_tree(root: Path) -> None:
    files = [root] if root.is_file() else [p for p in root.rglob('*') if p.is_file()]
    for file in files:
        with open(file, 'rb') as handle:
            os.fsync(handle.fileno())


def _move_into_place(tmp: Path, path: Path, work: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        # os.replace cannot put a folder over a non-empty folder: move the old one aside first
        # (into this run's own temporary folder, deleted afterwards), then put the new one in.
        aside = work / '.previous'
        os.replace(path, aside)
        try:
            os.replace(tmp, path)
        except BaseException:
            os.replace(aside, path)
            raise
    else:
        os.replace(tmp, path)
