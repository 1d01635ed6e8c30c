"""The selection maths calibration's term selection (:mod:`.terms`) and the discrepancy
search (:mod:`tetra_gradiometer.core.discrepancy`) share: the pair differences' noise
whitener, the contiguous blocks of held-out validation, and the held-out F test."""

from __future__ import annotations

import numpy as np

from .._distributions import f_sf
from ..types import FloatArray

#: Whitening of the pair differences' noise: per axis the three pairs ``n_i - n_1`` have
#: covariance ``sigma^2 (I + 1 1^T)``; right-multiplying by ``(I + 1 1^T)^(-1/2) =
#: I - 1 1^T / 6`` makes it ``sigma^2 I``.
PAIR_WHITENER = np.eye(3) - np.ones((3, 3)) / 6.0


def held_out_blocks(t: FloatArray, block_s: float, n_folds: int) -> list[tuple[int, int, int]]:
    """The contiguous blocks of held-out validation: ``(start, stop, fold)`` per block.

    The samples at times ``t`` (N,) (increasing, any unit) are cut every ``block_s`` from
    ``t[0]`` into contiguous blocks, dealt to ``n_folds`` folds in turn (at least 2 folds,
    at most one per block). A contiguous block holds out the slow drifts a random split
    would leak. Equal sample counts are ``t = arange(N)``, ``block_s = N / n_folds``.
    """
    n = len(t)
    edges = np.searchsorted(t, np.arange(t[0], t[-1] + block_s, block_s)[1:], side='left')
    bounds = np.unique(np.concatenate([[0], edges[edges < n], [n]]))
    n_blocks = len(bounds) - 1
    n_folds = max(2, min(n_folds, n_blocks))
    return [(int(bounds[b]), int(bounds[b + 1]), b % n_folds) for b in range(n_blocks)]


def held_out_f_test(
    rss_without: float, rss_with: float, n_parameters: int, dof: float
) -> tuple[float, float]:
    """The F statistic ``((RSS_0 - RSS_1) / p) / (RSS_1 / dof)`` of ``n_parameters`` (``p``)
    that take the held-out residual sum of squares from ``rss_without`` to ``rss_with``
    (any unit, the same for both), and its p-value. No parameter or no reduction: (0, 1);
    an exact fit (``RSS_1 = 0``) of a reduction: (inf, 0)."""
    gain = rss_without - rss_with
    if n_parameters <= 0 or gain <= 0.0:
        return 0.0, 1.0
    if rss_with <= 0.0:
        return float('inf'), 0.0
    f_stat = (gain / n_parameters) / (rss_with / dof)
    return float(f_stat), f_sf(f_stat, n_parameters, dof)
