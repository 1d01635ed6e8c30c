"""Every command line the README, docs/offline.md and bags/README.md show is run as written:
each ```sh block is marked, the line before it, as run by this test or not run (with why);
the run blocks are executed by bash, each in its own temporary folder holding the
repository's .venv and config and a copy of bags/, all at once (the README's walk-through is
~15 s of CPU, docs/offline.md's mission ~25 s, batch's ~20 s). A block that is the first
lines of another (bags/README.md's is the README's walk-through without its last three
commands) is checked by that block's run, not run twice."""
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


def _runner(name: str, blocks: dict[str, str]) -> str:
    """The block whose run checks block ``name``: the longest run block that begins with
    every line of it (bags/README.md's block is the README's walk-through without its last
    commands: the README's run executes those commands as written, in that order, in one
    folder), else the block itself. Each such run is ~15-25 s of CPU: once, not twice."""
    lines = blocks[name].splitlines()
    covering = [other for other, text in blocks.items() if text.splitlines()[: len(lines)] == lines]
    return max(covering, key=lambda other: len(blocks[other]))


def test_a_block_is_run_within_a_block_beginning_with_its_lines_or_on_its_own():
    blocks = {'short': 'a\nb\n', 'long': 'a\nb\nc\n', 'other': 'a\nB\n', 'partial': 'a\nb c\n'}
    assert {name: _runner(name, blocks) for name in blocks} == {
        'short': 'long', 'long': 'long', 'other': 'other', 'partial': 'partial'}
    assert _runner('bags/README.md:3', _run_blocks()) == 'README.md:0'  # the case it is for


@pytest.fixture(scope='module')
def ran(tmp_path_factory):
    """Start every run block that covers the others at once; their (exit status, stdout,
    stderr, folder), the covered blocks sharing their runner's."""
    processes = {}
    blocks = _run_blocks()
    for name, text in blocks.items():
        if _runner(name, blocks) != name:
            continue
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
    for name in blocks:
        results.setdefault(name, results[_runner(name, blocks)])
    return results


@pytest.mark.parametrize('name', sorted(_run_blocks()))
@pytest.mark.slow
def test_the_command_block_runs_as_written(ran, name):
    code, out, err, folder = ran[name]
    assert code == 0, f'{name} exit {code}\n{out[-2000:]}\n{err[-2000:]}'
    assert 'Traceback' not in err and 'error:' not in err, err
    # Every output named after --out / --csv exists.
    text = _run_blocks()[name]
    for path in re.findall(r'--(?:out|csv) (\S+)', text):
        assert (folder / path).exists(), (name, path)


#: A commit hash (hex with a digit and a letter: not a decimal number, not a word), an issue
#: number or a load average: history, which git holds, not what the docs say is true now.
HISTORY = re.compile(
    r'\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b|issue\s+[0-9]+|load\s+average')


def test_the_history_pattern_finds_history_only():
    assert HISTORY.findall('at 94ead96, see issue 31; load\n  average 2.4') == [
        '94ead96', 'issue 31', 'load\n  average']
    assert HISTORY.findall('seed 20140611 at 1767225600.100000000, a deadbeef, 0.14142') == []


def test_the_readme_is_a_guide_and_the_docs_carry_no_history():
    readme = (REPO / 'README.md').read_text(encoding='utf-8')
    assert len(readme.splitlines()) <= 300
    documents = [REPO / 'README.md', REPO / 'bags' / 'README.md', *(REPO / 'docs').glob('*.md'),
                 *(REPO / 'tetra_gradiometer').rglob('*.py')]
    for path in sorted(documents):
        found = HISTORY.findall(path.read_text(encoding='utf-8'))
        assert found == [], (path.name, found)
    for path in sorted((REPO / 'test').rglob('test_*.py')):  # keys in hex are test data
        if path != Path(__file__).resolve():  # its own examples of history
            found = re.findall(r'issue\s+[0-9]+|load\s+average', path.read_text(encoding='utf-8'))
            assert found == [], (path.name, found)


def test_the_vehicle_walk_through_names_what_the_nodes_offer():
    """The README's `ros2 service call`s and `ros2 topic echo`s (not run here: they need a ROS
    install) name services and topics the suite's security policy grants, which
    test/ros/test_security_policy.py holds to the live graph; each service is of the type its
    node's source serves it with (a Calibrate for the calibrator's calibrate, else a Trigger)."""
    readme = (REPO / 'README.md').read_text(encoding='utf-8')
    policy = (REPO / 'security' / 'policy.xml').read_text(encoding='utf-8')
    calls = re.findall(r'ros2 service call (\S+) (\S+)', readme)
    assert len(calls) >= 3
    for name, kind in calls:
        assert f'<service>{name}</service>' in policy, name
        namespace, node, service = name.strip('/').split('/')
        source = (REPO / 'tetra_gradiometer' / 'nodes' / f'{node}.py').read_text(encoding='utf-8')
        served = 'Calibrate' if service == 'calibrate' else 'Trigger'
        package = 'tetra_gradiometer_msgs' if served == 'Calibrate' else 'std_srvs'
        assert namespace == 'tetra' and kind == f'{package}/srv/{served}', name
        assert re.search(rf"create_service\(\s*{served}, '~/{service}'", source), name
    topics = re.findall(r'ros2 topic echo [^\n]*?(/\S+)', readme)
    assert topics
    for topic in topics:
        assert f'<topic>{topic}</topic>' in policy, topic
