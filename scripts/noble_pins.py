"""Write the pins of the Noble test venv (make test-noble): the main pins with the deviations
of constraints-noble.txt substituted.

    python scripts/noble_pins.py OUTDIR

writes OUTDIR/requirements.txt (requirements.txt + requirements-dev.txt) and
OUTDIR/constraints.txt (constraints.txt), each pin of a package named in constraints-noble.txt
replaced by the Noble pin (pip refuses two different pins of one package, so the files cannot
simply be given together). Exits 1 when a Noble pin names a package the main pins do not
have (a typo would otherwise pass silently) or is not of the form name==version.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_NAME = re.compile(r'^\s*([A-Za-z0-9][A-Za-z0-9._-]*)(\[[^\]]*\])?\s*==')


def canonical(name: str) -> str:
    """PEP 503 normalised project name."""
    return re.sub(r'[-_.]+', '-', name).lower()


def parse(line: str) -> tuple[str, str] | None:
    """(canonical name, extras such as ``[distributed]`` or '') of a ``name==version`` pin."""
    match = _NAME.match(line.split('#', 1)[0])
    return (canonical(match.group(1)), match.group(2) or '') if match else None


def noble_pins(path: Path) -> dict[str, str]:
    pins: dict[str, str] = {}
    for number, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        parsed = parse(line)
        if parsed is None or parsed[1]:
            sys.exit(f'error: {path.name}:{number}: not a name==version pin: {raw!r}')
        pins[parsed[0]] = line
    return pins


def substitute(lines: list[str], pins: dict[str, str], used: set[str]) -> list[str]:
    out = []
    for line in lines:
        parsed = parse(line)
        if parsed is None or parsed[0] not in pins:
            out.append(line)
            continue
        name, extras = parsed
        used.add(name)
        pin = pins[name].replace('==', f'{extras}==', 1)  # keeps dask[distributed]'s extras
        out.append(f'{pin}  # Noble (constraints-noble.txt); main: {line.strip()}')
    return out


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        sys.exit(__doc__)
    outdir = Path(argv[0])
    outdir.mkdir(parents=True, exist_ok=True)
    pins = noble_pins(ROOT / 'constraints-noble.txt')
    used: set[str] = set()
    requirements = []
    for name in ('requirements.txt', 'requirements-dev.txt'):
        requirements += substitute((ROOT / name).read_text().splitlines(), pins, used)
    constraints = substitute((ROOT / 'constraints.txt').read_text().splitlines(), pins, used)
    unknown = sorted(set(pins) - used)
    if unknown:
        sys.exit(
            f'error: constraints-noble.txt pins {", ".join(unknown)}, '
            'which the main pins (requirements*.txt, constraints.txt) do not have'
        )
    (outdir / 'requirements.txt').write_text('\n'.join(requirements) + '\n')
    (outdir / 'constraints.txt').write_text('\n'.join(constraints) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
