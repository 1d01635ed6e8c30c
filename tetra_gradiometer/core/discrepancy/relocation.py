"""The targets refined again with what the search named: the detector's model, in which
:mod:`.dipoles` places them, has only the families global in time; a step, a line or a
term outside it that the search names afterwards was in the residual the positions were
fitted to.

Measured (test_dipoles_survey, seed 47): a 30-sigma step on sensor 3 at the end of a line
moved a target 37 m away by 0.09 m (the refinement's sigma ~0.002 m) and its moment by
2.7 %; the step and a 1.7 Hz line were then named, and with them a spurious 0.041 Hz line
that the misplaced target's field left. Refined once more with every named unit's columns
linear beside the moments (variable projection, as before), the search is run again on the
run with the refined targets: one more pass, only when the search named something outside
the detector's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .cv import lstsq_view
from .dipoles import Located, Track, model_targets, refine, target_columns
from .prepare import Prepared
from .search import SearchResult

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Relocated:
    """The targets refined with the search's model: ``located`` (its ``prep`` the run the
    search started from, with the refined targets' columns) and how far each moved, m."""

    located: Located
    moved_m: Array


def outside_detector(search: SearchResult) -> list[str]:
    """Names of the named families that the detector's model (where the targets were
    placed) does not have."""
    return sorted({f.candidate.name for f in search.active if not f.candidate.in_detector})


def relocate(
    search: SearchResult, start: Prepared, track: Track, located: Located
) -> Relocated | None:
    """The targets of ``located`` refined with the search's final model (its columns and
    fixed offsets linear beside the moments), placed in ``start`` (the run the search
    started from, whose targets are ``located``'s); None when the search named nothing
    outside the detector's model."""
    prep, fit = search.prep, search.fit
    if not outside_detector(search) or prep.target_cols is None:
        return None
    n_base = prep.base_cols.shape[-1]
    first = n_base - prep.target_cols.shape[-1]
    keep = np.r_[0:first, n_base : fit.cols.shape[-1]]
    other = fit.cols[..., keep]
    positions, position_sigma, moment_sigma = refine(
        prep, track, other, located.positions, offset=fit.offset
    )
    cols, _ = target_columns(track, positions)
    design = np.concatenate([other, cols], axis=-1)
    coef = lstsq_view(prep.sensors, design, prep.fields - prep.base_offset - fit.offset)
    moments = coef[-cols.shape[-1] :].reshape(-1, 3)
    moved = np.linalg.norm(positions - located.positions, axis=1)
    return Relocated(
        Located(
            model_targets(start, track, positions, moments),
            positions,
            position_sigma,
            moment_sigma,
            located.spans,
            moments,
        ),
        moved,
    )
