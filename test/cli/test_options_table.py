"""docs/offline.md's options table is the parsers': every numeric option of every
command is a row naming that command, and the row's range is the one its ``type=`` refuses
outside of (read from the type's own error message)."""
import argparse
import importlib
import re
from pathlib import Path

import pytest

from tetra_gradiometer.__main__ import COMMANDS

REPO = Path(__file__).resolve().parents[2]


def _table() -> dict[tuple[str, str], str]:
    """(option, command) -> the allowed column."""
    text = (REPO / 'docs/offline.md').read_text(encoding='utf-8')
    body = text[text.index('| option | commands | allowed | why |'):].split('\n\n', 1)[0]
    rows = {}
    for line in body.splitlines()[2:]:
        cells = [cell.strip() for cell in line.strip('|').split('|')]
        option = cells[0].strip('`').split()[0]
        for command in cells[1].split(','):
            rows[(option, command.strip())] = cells[2]
    return rows


def _numeric_options() -> dict[tuple[str, str], str]:
    """(option, command) -> the range its type= states, e.g. '0 < x <= 1000'."""
    found = {}
    for command, (module_name, _) in COMMANDS.items():
        parser = argparse.ArgumentParser()
        importlib.import_module(module_name).add_arguments(parser)
        for action in parser._actions:
            name = getattr(action.type, '__name__', '')
            if name not in ('number', 'integer'):
                continue
            with pytest.raises(argparse.ArgumentTypeError) as error:
                action.type('not a number')
            stated = re.search(r'with (.*?)(?: [a-z/]+)*, got', str(error.value)).group(1)
            found[(action.option_strings[-1], command)] = stated
    return found


def _bounds(text: str) -> tuple[float, bool, float, bool]:
    """(low, low included, high, high included) from '0 < x <= 1000' or '1 – 256' or the
    table's '0 ≤ n ≤ 2³¹−1'."""
    text = text.replace('2³¹−1', str(2**31 - 1)).replace('−', '-').replace('≤', '<=')
    text = re.sub(r'(?<=\d) (?=\d{3}\b)', '', text)
    numbers = re.findall(r'-?\d+(?:\.\d+)?(?:e\+?\d+)?', text)
    low, high = float(numbers[0]), float(numbers[1])
    if '–' in text:
        return low, True, high, True
    relations = re.findall(r'<=|<', text)
    return low, relations[0] == '<=', high, relations[1] == '<='


def test_every_numeric_option_is_in_the_table_with_its_range():
    table, options = _table(), _numeric_options()
    assert len(options) >= 20
    missing = sorted(key for key in options if key not in table)
    assert not missing, f'options missing from docs/offline.md\'s table: {missing}'
    for key, stated in options.items():
        assert _bounds(table[key]) == _bounds(stated), (key, table[key], stated)


def test_every_row_names_options_the_commands_have():
    options = {option for option, _ in _numeric_options()}
    for option, command in _table():
        parser = argparse.ArgumentParser()
        importlib.import_module(COMMANDS[command][0]).add_arguments(parser)
        names = {name for action in parser._actions for name in action.option_strings}
        assert option in names, (option, command)
    assert options <= {option for option, _ in _table()}
