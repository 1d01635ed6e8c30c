"""Every command line the README, docs/offline.md and bags/README.md show is run as written
(issue 30): each ```sh block is marked, the line before it, as run by this test or not run
(with why); the run blocks are executed by bash, each in its own temporary folder holding
the repository's .venv and config and a copy of bags/, all at once (the README's block is
~25 s of CPU, batch's ~20 s; measured 163-246 s wall while other jobs held the shared
2-core machine at load 11-15)."""
import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = ('README.md', 'docs/offline.md', 'bags/README.md')
RUN = '<!-- commands: run as written by test/cli/test_docs_commands.py -->'
NOT_RUN = re.compile(r'<!-- commands: not run by the tests \(.+\) -->')
BLOCK = re.compile(r'^```sh\n(.*?)^```', re.S | re.M)


def _blocks() -> list[tuple[str, str, str]]:
    """(document, marker line, block text) of every ```sh block."""
    found = []
    for doc in DOCS:
        text = (REPO / doc).read_text(encoding='utf-8')
        for match in BLOCK.finditer(text):
            before = text[: match.start()].rstrip('\n').rsplit('\n', 1)[-1]
            found.append((doc, before, match.group(1)))
    return found


def test_every_command_block_is_marked_and_pasteable():
    blocks = _blocks()
    assert len(blocks) >= 5
    for doc, marker, text in blocks:
        assert marker == RUN or NOT_RUN.fullmatch(marker), (doc, marker, text)
        for line in text.splitlines():
            command = line.split('#', 1)[0]
            assert not re.search(r'\[--', command), f'{doc}: an optional flag in brackets: {line}'


def _run_blocks() -> dict[str, str]:
    """The distinct run blocks, each under a name saying where it is."""
    blocks = {}
    for doc, marker, text in _blocks():
        if marker == RUN and text not in blocks.values():
            blocks[f'{doc}:{len(blocks)}'] = text
    return blocks


@pytest.fixture(scope='module')
def ran(tmp_path_factory):
    """Start every run block at once; their (exit status, stdout, stderr, folder)."""
    processes = {}
    for name, text in _run_blocks().items():
        folder = tmp_path_factory.mktemp('docs')
        (folder / '.venv').symlink_to(REPO / '.venv')
        (folder / 'config').symlink_to(REPO / 'config')
        shutil.copytree(REPO / 'bags', folder / 'bags')
        processes[name] = (subprocess.Popen(
            ['bash', '-euo', 'pipefail', '-c', text], cwd=folder, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE), folder)
    results = {}
    for name, (process, folder) in processes.items():
        out, err = process.communicate(timeout=600)
        results[name] = (process.returncode, out, err, folder)
    return results


@pytest.mark.parametrize('name', sorted(_run_blocks()))
def test_the_command_block_runs_as_written(ran, name):
    code, out, err, folder = ran[name]
    assert code == 0, f'{name} exit {code}\n{out[-2000:]}\n{err[-2000:]}'
    assert 'Traceback' not in err and 'error:' not in err, err
    # Every output named after --out / --csv exists.
    text = _run_blocks()[name]
    for path in re.findall(r'--(?:out|csv) (\S+)', text):
        assert (folder / path).exists(), (name, path)
