"""YAML in and out: a file read with errors that name the file and what it was meant to be,
and the one safe loader and dumper every module uses."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

#: libyaml's parser and emitter where PyYAML has them (the pinned wheel does), else PyYAML's
#: own: the same documents (a long non-ASCII string may fold at other columns), ~10x faster,
#: for the documents of thousands of floats (a calibration with its covariance, 42 kB: dumped
#: in 9 ms instead of 49, parsed in 7 instead of 87). Files a person writes (params) are read
#: by PyYAML's own parser (:func:`read_yaml`), whose error messages are the documented ones.
SAFE_LOADER: type[yaml.SafeLoader] = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
SAFE_DUMPER: type[yaml.SafeDumper] = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


#: libyaml's parser recurses in C: ~30 000 nested brackets (60 kB) overflow its stack and end
#: the process. Text whose brackets (counted in strings and comments too) may nest deeper than
#: this goes to PyYAML's own parser, which recurses in Python: it reads brackets in strings
#: as text, and a real nesting past Python's recursion limit (~1000) is refused. No document
#: of ours nests brackets; block nesting that deep would take gigabytes of indentation.
MAX_FLOW_DEPTH = 100


def loads(text: str) -> Any:
    """The document in ``text``, as ``yaml.safe_load``; brackets nested too deep for the
    parser are a ``yaml.YAMLError``."""
    if text.count('[') + text.count('{') > MAX_FLOW_DEPTH:  # else it cannot be that deep
        codes = np.frombuffer(text.encode(), np.uint8)
        opened = (codes == ord('[')) | (codes == ord('{'))
        closed = (codes == ord(']')) | (codes == ord('}'))
        if np.cumsum(opened.astype(np.int64) - closed).max() > MAX_FLOW_DEPTH:
            try:
                return yaml.load(text, Loader=yaml.SafeLoader)
            except RecursionError:
                raise yaml.YAMLError('brackets nested deeper than the parser can follow') from None
    return yaml.load(text, Loader=SAFE_LOADER)


def dumps(document: Any) -> str:
    """``document`` as YAML text, keys in their order, as ``yaml.safe_dump(sort_keys=False)``."""
    return yaml.dump(document, Dumper=SAFE_DUMPER, sort_keys=False)


def _yaml_problem(problem: yaml.YAMLError) -> str:
    """One line: the parser's problem and where (PyYAML's own text spans several lines)."""
    what = getattr(problem, 'problem', None) or getattr(problem, 'context', None)
    mark = getattr(problem, 'problem_mark', None) or getattr(problem, 'context_mark', None)
    text = str(what) if what else ' '.join(str(problem).split())
    if mark is not None:
        text += f' (line {mark.line + 1}, column {mark.column + 1})'
    return text


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing a mapping that repeats a key (PyYAML keeps the last
    silently: a second ``sensor_positions`` would win without a word)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                repeated = key in seen
            except TypeError:  # an unhashable key: SafeLoader's own error says so
                break
            if repeated:
                raise yaml.constructor.ConstructorError(
                    None, None, f'duplicate key {key!r}', key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(
    path: str | os.PathLike, what: str, error: type[ValueError], unique_keys: bool = False
) -> Any:
    """The parsed document at ``path``.

    Every failure is one ``error`` (e.g. ParamsError) whose one-line message names
    ``what`` (e.g. "params"), the file and the problem: not found, a directory, not
    readable (permission, I/O), not UTF-8 text, not valid YAML (with line and column),
    or empty (nothing but whitespace and comments); with ``unique_keys``, a mapping that
    repeats a key (with its line and column).
    """
    path = Path(path)
    label = f'{what} file {path}'
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise error(f'{what} file not found: {path}') from None
    except IsADirectoryError:
        raise error(f'{label} is a directory, not a file') from None
    except PermissionError:
        raise error(f'{label} cannot be read: permission denied') from None
    except UnicodeDecodeError as problem:
        raise error(
            f'{label} is not UTF-8 text: byte 0x{problem.object[problem.start]:02x} at '
            f'offset {problem.start} ({problem.reason})'
        ) from None
    except OSError as problem:
        raise error(f'{label} cannot be read: {problem.strerror or problem}') from None
    try:
        document = yaml.load(text, Loader=_UniqueKeyLoader if unique_keys else yaml.SafeLoader)
    except yaml.YAMLError as problem:
        raise error(f'{label} is not valid YAML: {_yaml_problem(problem)}') from None
    except RecursionError:
        raise error(f'{label} is not valid YAML: nested too deeply') from None
    if document is None:
        raise error(f'{label} is empty (no YAML document)')
    return document
