"""The few distribution functions the on-vehicle code needs, from ``scipy.special``.

``scipy.stats`` costs about a second of import (1.3 s of the compensator node's 1.7 s on this
machine; more on a vehicle's ARM board); its chi-square and F tails are one special function
each. Tested against ``scipy.stats`` in test/core/test_distributions.py.
"""

from __future__ import annotations

import scipy  # submodules load on first use: see core/__init__.py


def chi2_isf(p: float, dof: float) -> float:
    """The chi-square upper quantile: ``x`` with ``P(X > x) = p``, ``X ~ chi2(dof)``."""
    return float(2.0 * scipy.special.gammainccinv(dof / 2.0, p))


def f_ppf(q: float, dfn: float, dfd: float) -> float:
    """The F quantile: ``x`` with ``P(X <= x) = q``, ``X ~ F(dfn, dfd)``."""
    b = float(scipy.special.betaincinv(dfn / 2.0, dfd / 2.0, q))
    return dfd * b / (dfn * (1.0 - b))


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """The F upper tail ``P(X > x)``, ``X ~ F(dfn, dfd)``."""
    if x <= 0.0:
        return 1.0
    return float(scipy.special.betainc(dfd / 2.0, dfn / 2.0, dfd / (dfd + dfn * x)))
