"""Discrepancy workflow: find where the simulated (model-predicted) and the
measured sensor readings of a recorded run disagree, name the missing physical effect from
the candidates (every effect of the one registry,
:data:`tetra_gradiometer.core.effects.EFFECTS`, and the search's detectors of model
errors), add it, and show the held-out gap shrink to the noise floor.

``analyze(run, geometry, earth_field_enu=None)`` returns a :class:`Report`;
``tetra_gradiometer.reports.discrepancy.write_report(report, out_dir)`` writes ``report.json``,
``report.md`` and the plots.
The command line is ``python -m tetra_gradiometer discrepancy BAG --params FILE --out DIR``.
The core imports numpy and scipy only; the run comes in as a :class:`RecordedRun` (plain
arrays) or anything with the same attributes.
"""

from .analysis import analyze
from .candidate import Candidate
from .effects import CANDIDATES, LIBRARY, OPEN_WORLD
from .prepare import RecordedRun
from .result import BASE_MODEL, Report, Settings, Step, criterion_text

__all__ = [
    'BASE_MODEL',
    'CANDIDATES',
    'Candidate',
    'LIBRARY',
    'OPEN_WORLD',
    'RecordedRun',
    'Report',
    'Settings',
    'Step',
    'analyze',
    'criterion_text',
]
