"""Progress bars on stderr for long reads and writes (tqdm), shown only when useful."""

from __future__ import annotations

import sys
from typing import Any

__all__ = ['MIN_TOTAL', 'progress_bar']

#: Below this many items no bar is drawn (short runs finish before a bar helps).
MIN_TOTAL = 50_000


def progress_bar(
    total: int,
    enabled: bool | None,
    description: str,
    unit: str = 'msg',
    *,
    min_total: int = MIN_TOTAL,
) -> Any:
    """A tqdm bar of ``total`` items on stderr.

    Parameters
    ----------
    total : int
        Number of items the bar counts to.
    enabled : bool or None
        True or False to force the bar on or off; None shows it only when stderr is a
        terminal. Either way, no bar is drawn below ``min_total`` items.
    description : str
        Text shown before the bar.
    unit : str, optional
        Name of one item.
    min_total : int, optional
        Fewest items worth a bar (default :data:`MIN_TOTAL`; ``batch``: 1, one bag is long).
    """
    from tqdm import tqdm

    show = sys.stderr.isatty() if enabled is None else enabled
    return tqdm(
        total=total,
        desc=description,
        unit=unit,
        disable=not show or total < min_total,
        mininterval=0.5,
        file=sys.stderr,
    )
