"""Atomic file output: write a temporary file beside the target, fsync, then rename.

A reader (or a node restarted after a crash) sees the old file or the new one, never a
truncated one.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; creates parent folders. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        with os.fdopen(fd, 'w', encoding='utf-8') as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextmanager
def atomic_output_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling path to fill (a file or a folder, e.g. a rosbag2 directory);
    on success it replaces ``path``, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.partial')
    _remove(tmp)
    try:
        yield tmp
        if tmp.is_file():
            with open(tmp, 'rb+') as handle:
                os.fsync(handle.fileno())
        if path.is_dir() and not path.is_symlink():
            _remove(path)  # os.replace cannot put a folder over a folder; a file is replaced in one step
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def save_figure(figure: Any, path: str | os.PathLike, *, dpi: int = 110) -> Path:
    """Save a matplotlib figure as PNG atomically; returns the path."""
    with atomic_output_path(path) as tmp:
        figure.savefig(tmp, format='png', dpi=dpi)
    return Path(path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
