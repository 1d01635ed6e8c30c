"""No message advises an option that does not exist (``calibrate`` advised "fit
without orientation_xyzw"): every ``--option`` written in a string of the package (messages,
notes, help texts, docstrings) is an option of one of the commands, or one of ROS 2's own
command-line arguments (``ros2 run ... --ros-args --params-file FILE``)."""
from __future__ import annotations

import argparse
import ast
import importlib
import re
from pathlib import Path

from tetra_gradiometer.__main__ import COMMANDS

PACKAGE = Path(__file__).resolve().parents[1] / 'tetra_gradiometer'
#: ROS 2's arguments (rcl), which the nodes' messages name: not ours to define.
ROS_ARGUMENTS = {'--ros-args', '--params-file', '--param', '--remap', '--log-level'}
OPTION = re.compile(r'(?<![\w-])--[a-z][a-z0-9-]*')


def _command_options() -> set[str]:
    options = {'--help'}
    for module, _ in COMMANDS.values():
        parser = argparse.ArgumentParser()
        importlib.import_module(module).add_arguments(parser)
        for action in parser._actions:
            options.update(action.option_strings)
    return options


def test_every_option_a_string_names_exists():
    known = _command_options() | ROS_ARGUMENTS
    unknown = []
    for path in sorted(PACKAGE.rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                unknown += [f'{path.relative_to(PACKAGE)}:{node.lineno}: {option}'
                            for option in OPTION.findall(node.value) if option not in known]
    assert not unknown, unknown


def test_the_guard_can_fail():
    assert OPTION.findall('roll more, or run again with --no-such-option') == ['--no-such-option']
    assert '--no-such-option' not in _command_options()
