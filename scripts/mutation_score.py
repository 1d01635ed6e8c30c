"""The mutation score per mutated file, from the results `make mutation` leaves in mutants/.

mutmut 3 keeps each file's verdicts in ``mutants/<path>.meta`` (JSON: ``exit_code_by_key``,
one exit code per mutant) and prints only a run-wide total and the survivors' names; this
tallies them per file with mutmut's own reading of the exit codes (``mutmut.stats``).

Usage: ``.venv/bin/python scripts/mutation_score.py [mutants]``
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

from mutmut.stats import status_by_exit_code

COLUMNS = ('killed', 'survived', 'no tests', 'timeout', 'not checked')


def tally(root: Path) -> dict[str, Counter[str]]:
    """Counts of each status per source file (path as mutated, e.g. tetra_gradiometer/...)."""
    found: dict[str, Counter[str]] = {}
    for meta in sorted(root.rglob('*.py.meta')):
        codes = json.loads(meta.read_text(encoding='utf-8')).get('exit_code_by_key', {})
        if codes:
            name = meta.relative_to(root).as_posix().removesuffix('.meta')
            found[name] = Counter(status_by_exit_code[code] for code in codes.values())
    return found


def main(argv: list[str]) -> int:
    root = Path(argv[0] if argv else 'mutants')
    if not root.is_dir():
        print(f'error: no {root}/ here: run `make mutation` first', file=sys.stderr)
        return 1
    table = tally(root)
    total: Counter[str] = Counter()
    print(f'{"file":60s} ' + ' '.join(f'{c:>11s}' for c in COLUMNS) + '  killed/reached')
    for name, counts in table.items():
        total.update(counts)
        reached = counts['killed'] + counts['survived'] + counts['timeout']
        score = f'{100 * (counts["killed"] + counts["timeout"]) / reached:.1f} %' if reached else '-'
        print(f'{name:60s} ' + ' '.join(f'{counts[c]:11d}' for c in COLUMNS) + f'  {score}')
    reached = total['killed'] + total['survived'] + total['timeout']
    print(f'{"all":60s} ' + ' '.join(f'{total[c]:11d}' for c in COLUMNS)
          + f'  {100 * (total["killed"] + total["timeout"]) / max(reached, 1):.1f} %')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
