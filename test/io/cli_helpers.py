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


def rewrite_bag(bag: Path, out: Path, topic: str, change) -> Path:
    """A copy of ``bag`` with each message of ``topic`` replaced by ``change(msg, t_s)`` (the
    deserialized message, seconds from the bag's start -> a message to write, or None to keep
    the original); every other message byte for byte."""
    from rosbags.highlevel import AnyReader

    from tetra_gradiometer.io.bag import BagWriter, typestore

    with AnyReader([bag], default_typestore=typestore()) as reader, BagWriter(out) as writer:
        start = reader.start_time
        for connection, t, raw in reader.messages():
            new = None
            if connection.topic == topic:
                new = change(reader.deserialize(raw, connection.msgtype), (t - start) * 1e-9)
            if new is None:
                writer.write_raw(connection.topic, connection.msgtype, raw, t)
            else:
                writer.write(connection.topic, new, t)
    return out
