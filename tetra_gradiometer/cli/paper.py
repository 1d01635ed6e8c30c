"""``python -m tetra_gradiometer paper --out DIR``: reproduce section 6 of Yu et al. 2014.

The numbers are :mod:`tetra_gradiometer.core.paper` (the scenario, both readings, every
method); ``results.json``, the figures and the printed table are
:mod:`tetra_gradiometer.reports.paper`. Every choice the paper leaves open is written into
``results.json`` ("scenario") and docs/paper.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.identification.paper_ga import GENERATIONS
from ..core.paper import METHODS, Choices
from ..errors import InputError
from ..reports.paper import FIGURES, format_table, reproduce
from ._args import add_force_argument, int_range, seed_arg

#: ``--generations``: at least one, at most 100x the paper's 1000.
MAX_GENERATIONS = 100_000

__all__ = ['FIGURES', 'METHODS', 'add_arguments', 'run']


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        '--out', required=True, help='output folder (results.json and PNG figures)'
    )
    parser.add_argument(
        '--generations',
        type=int_range(1, MAX_GENERATIONS),
        default=GENERATIONS,
        help=f'GA generations for paper_ga, 1 to {MAX_GENERATIONS} (default {GENERATIONS})',
    )
    parser.add_argument(
        '--seed',
        type=seed_arg,
        default=Choices.seed,
        help=f'seed of every random draw, 0 <= n < 2^31 (default {Choices.seed})',
    )
    parser.add_argument('--no-plots', action='store_true', help='skip the PNG figures')
    add_force_argument(parser, 'a previous paper folder at --out')


def run(args: argparse.Namespace) -> int:
    if args.generations < 1:
        raise InputError(f'--generations must be >= 1, got {args.generations}')
    choices = Choices(seed=args.seed, generations=args.generations)
    results = reproduce(args.out, choices=choices, plots=not args.no_plots, force=args.force)
    print(format_table(results, 'Earth-field reading (dipole + 50 000 nT)'))
    print()
    print(format_table(results['scenarios']['dipole_only'], 'Dipole-only reading'))
    print(f'\nwrote {Path(args.out) / "results.json"}')
    return 0
