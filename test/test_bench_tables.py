"""The README's benchmark tables are what bench/results/ holds (bench/tables.py writes them),
each naming the machine its figures came from."""
import importlib.util
import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / 'bench' / 'results'


def _tables():
    spec = importlib.util.spec_from_file_location('bench_tables', REPO / 'bench' / 'tables.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_tables_are_the_data():
    tables = _tables()
    readme = (REPO / 'README.md').read_text(encoding='utf-8')
    machines = json.loads((RESULTS / 'machines.json').read_text(encoding='utf-8'))
    assert tables.rewrite(readme, machines) == readme, 'run bench/tables.py'
    marked = re.findall(r'<!-- bench:(\w+) -->', readme)
    assert sorted(marked) == sorted(tables.TABLES), 'a table missing from the README'
    for name in marked:
        assert (RESULTS / f'{name}.json').is_file(), name


def test_a_table_is_rewritten_from_its_file_and_names_the_machine():
    tables = _tables()
    rows = json.loads((RESULTS / 'accuracy.json').read_text(encoding='utf-8'))
    general = next(r for r in rows if r['scenario'] == 'reference clean'
                   and r['method'] == 'known_gradient_lstsq_general')
    text = ('before\n<!-- bench:accuracy -->\nstale\n| old |\n<!-- /bench:accuracy -->\n'
            'after <!-- bench:elsewhere -->\n')
    new = tables.rewrite(text, {'accuracy.json': 'a test machine'})
    assert new.startswith('before\n') and new.endswith(
        '<!-- /bench:accuracy -->\nafter <!-- bench:elsewhere -->\n')
    assert 'stale' not in new and '| old |' not in new
    caption = new.splitlines()[1]
    assert caption.endswith('measured on a test machine. <!-- bench:accuracy -->')
    line = next(row for row in new.splitlines()
                if row.startswith('| `known_gradient_lstsq_general`'))
    assert f'{general["rms_nT_per_m"]:.4g}' in line
    assert f'{round(general["improvement_ratio"])}' in line
    assert tables.rewrite(new, {'accuracy.json': 'a test machine'}) == new
