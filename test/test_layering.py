"""The package's layers (docs/architecture.md) and what an on-vehicle node may load.

core < io (formats and messages) < pipelines < reports < cli; nodes use core, io and the
bag-free pipelines. A node must start on a rosdep-only install: without the pip-only
packages (rosbags, ppigrf, dask) and without matplotlib on its path.
"""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'tetra_gradiometer'

#: Layer -> the layers its modules may import (itself included). ``cli`` is the top.
ALLOWED = {
    'errors': set(),
    '_optional': {'errors'},
    'core': {'core', 'errors'},
    'io': {'core', 'io', 'errors', '_optional'},
    'pipelines': {'core', 'io', 'pipelines', 'errors', '_optional'},
    # _optional: the survey report's pyproj
    'reports': {'core', 'io', 'pipelines', 'reports', 'errors', '_optional'},
    'nodes': {'core', 'io', 'pipelines', 'nodes', 'errors', '_optional'},
    'cli': {'core', 'io', 'pipelines', 'reports', 'nodes', 'cli', 'errors', '_optional'},
    '__main__': {'cli', 'errors'},
    '__init__': set(),
}
NODES = ('driver', 'tensor', 'calibrator', 'compensator', 'target')
#: Packages a rosdep install of package.xml does not have, and one no node should load.
OFFLINE_ONLY = (
    'rosbags', 'ppigrf', 'dask', 'distributed', 'matplotlib',
    'verde', 'xarray', 'h5netcdf', 'rioxarray', 'rasterio', 'pyproj',
)


def _layer(module: str) -> str:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else '__init__'


def _module(path: Path) -> str:
    return '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts)


def _imports(path: Path, module: str) -> list[tuple[int, str]]:
    """Every ``tetra_gradiometer`` module that the file ``path``, module ``module``, imports
    (module level, in functions, under TYPE_CHECKING alike), absolute, with its line."""
    package = module.split('.')[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ''
            names = [target] if node.module or not node.level else []
            # ``from . import x``: each name is a module of that package.
            names += [f'{target}.{alias.name}' for alias in node.names] if not node.module else []
            out += [(node.lineno, name) for name in names]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
    return sorted((line, name) for line, name in out if name.startswith('tetra_gradiometer.'))


def test_the_layers_import_only_downwards():
    assert set(ALLOWED) >= {_layer('tetra_gradiometer.' + p.name) for p in PACKAGE.iterdir()
                            if p.suffix == '.py' or (p / '__init__.py').exists()} - {'__init__'}
    bad = []
    for path in sorted(PACKAGE.rglob('*.py')):
        own = _module(path)
        for line, target in _imports(path, own):
            if _layer(target) not in ALLOWED[_layer(own)]:
                bad.append(f'{path.relative_to(PACKAGE.parent)}:{line} imports {target}')
    assert bad == []


def test_the_checker_sees_a_violation(tmp_path):
    """The import scan reads relative, nested and ``from . import`` forms (so that the test
    above can fail)."""
    probe = tmp_path / 'probe.py'
    probe.write_text(
        'from . import window_check\n'
        'def f():\n    from ..reports import calibration\n    from ..cli.fleet import x\n'
    )
    found = [target for _, target in _imports(probe, 'tetra_gradiometer.pipelines.probe')]
    assert found == [
        'tetra_gradiometer.pipelines.window_check',
        'tetra_gradiometer.reports',
        'tetra_gradiometer.cli.fleet',
    ]
    assert [_layer(name) for name in found if _layer(name) not in ALLOWED['pipelines']] == [
        'reports',
        'cli',
    ]


BLOCK = (
    'import importlib, sys\n'
    f'BLOCKED = {OFFLINE_ONLY!r}\n'
    'class Block:\n'
    '    def find_spec(self, name, path=None, target=None):\n'
    '        if name.split(".")[0] in BLOCKED:\n'
    '            raise ModuleNotFoundError(f"No module named {name!r}", name=name)\n'
    'sys.meta_path.insert(0, Block())\n'
)


@pytest.mark.parametrize('node', NODES)
def test_a_node_imports_without_the_offline_only_packages(node):
    code = BLOCK + (
        f'importlib.import_module("tetra_gradiometer.nodes.{node}")\n'
        f'print(sorted({{m.split(".")[0] for m in sys.modules}} & set(BLOCKED)))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '[]'


def test_a_replay_without_rosbags_is_one_clear_error(tmp_path):
    """The driver's replay imports rosbags only when it opens a bag, and then says what to
    install instead of a ModuleNotFoundError."""
    code = BLOCK + (
        'from tetra_gradiometer.errors import DependencyError\n'
        'from tetra_gradiometer.nodes import replay\n'
        'try:\n'
        f'    replay.describe_bag({str(tmp_path)!r})\n'
        'except DependencyError as error:\n'
        '    print(error)\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "'rosbags'" in out.stdout and 'pip install "rosbags==' in out.stdout
