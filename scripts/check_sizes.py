"""Size gate: no module over 600 lines, no function over 80 lines (docs/architecture.md).

``python scripts/check_sizes.py [ROOT]`` (default ``tetra_gradiometer``) prints every
violation and exits 1 if there is one. Function length is counted from the ``def`` line to
the last line of the body (decorators and docstrings included), as a reader sees it.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def violations(root: Path) -> list[str]:
    """Every module and function over its limit under ``root``, as ``path:line: text``."""
    found = []
    for path in sorted(root.rglob('*.py')):
        text = path.read_text(encoding='utf-8')
        n_lines = len(text.splitlines())
        if n_lines > MAX_MODULE_LINES:
            found.append(f'{path}:1: module has {n_lines} lines (max {MAX_MODULE_LINES})')
        for node in ast.walk(ast.parse(text, filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f'{path}:{node.lineno}: function {node.name} has {length} lines '
                                 f'(max {MAX_FUNCTION_LINES})')
    return found


def main(argv: list[str]) -> int:
    root = Path(argv[0] if argv else 'tetra_gradiometer')
    found = violations(root)
    for line in found:
        print(line)
    print(f'check_sizes: {len(found)} violation(s) under {root}')
    return 1 if found else 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
