"""Shared by the fault tables under test/io: run a command in-process through
``__main__.main`` (the code path of ``python -m tetra_gradiometer``) and check a refusal."""
from __future__ import annotations

from pathlib import Path

from tetra_gradiometer.__main__ import main


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (or ``root`` itself) with its bytes."""
    if root.is_file():
        return {'.': root.read_bytes()}
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob('*')) if p.is_file()}


def run_cli(capsys, *args) -> tuple[int, str, str]:
    """(exit status, stdout, stderr); an exception other than TetraError propagates (a bug)."""
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_refused(result, *fragments) -> None:
    """Exit 1 with exactly one ``error:`` line holding every fragment, no traceback."""
    code, out, err = result
    assert code == 1, (code, out, err)
    assert err.startswith('error: ') and err.count('\n') == 1, err
    assert 'Traceback' not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
