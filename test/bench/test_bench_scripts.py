"""The benchmark scripts are not run in CI (they take minutes), but they must keep up with the
package: each one's module body (imports, constants) loads without running its main()."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / 'bench'


@pytest.mark.parametrize('script', sorted(p.name for p in BENCH.glob('bench_*.py')))
def test_benchmark_script_loads(script):
    spec = importlib.util.spec_from_file_location(f'bench_{script[:-3]}', BENCH / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # __name__ is not '__main__': main() does not run
    assert callable(module.main)
