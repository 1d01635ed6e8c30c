"""The few distribution functions the on-vehicle code needs, from ``scipy.special`` (the
chi-square quantile of an even degree of freedom closed, in floats).

``scipy.stats`` costs about a second of import (1.3 s of the compensator node's 1.7 s on this
machine; more on a vehicle's ARM board; 0.6 s of every ``discrepancy``); its chi-square and
F tails are one special function each. Tested against ``scipy.stats`` in
test/core/test_distributions.py.
"""

from __future__ import annotations

import math

import scipy  # submodules load on first use: see core/__init__.py


def chi2_isf(p: float, dof: float) -> float:
    """The chi-square upper quantile: ``x`` with ``P(X > x) = p``, ``X ~ chi2(dof)``.

    For an even ``dof`` up to 8 (the health monitor's 4) the tail is closed, ``exp(-z)
    sum_{j<dof/2} z^j / j!`` at ``z = x / 2``, solved by Newton's method in floats: no
    ``scipy.special`` import (~0.4 s of every compensation's CPU)."""
    if dof in (2, 4, 6, 8) and 0.0 < p < 1.0:
        terms = int(dof) // 2
        target = math.log(p)
        z = max(1.0, -target)
        for _ in range(100):
            series = [z**j / math.factorial(j) for j in range(terms)]
            log_tail = -z + math.log(sum(series))
            slope = -series[-1] / sum(series)  # d log(tail) / dz = -z^(k-1) / (k-1)! / sum
            step = (log_tail - target) / slope
            z = max(z - step, z / 10.0)
            if abs(step) < 1e-13 * max(1.0, z):
                break
        return 2.0 * z
    return float(2.0 * scipy.special.gammainccinv(dof / 2.0, p))


def f_isf(p: float, dfn: float, dfd: float) -> float:
    """The F upper quantile: ``x`` with ``P(X > x) = p``, ``X ~ F(dfn, dfd)`` (from the
    upper tail's own incomplete beta, so a small ``p`` keeps its digits)."""
    y = float(scipy.special.betaincinv(dfd / 2.0, dfn / 2.0, p))
    return dfd * (1.0 - y) / (dfn * y)


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """The F upper tail ``P(X > x)``, ``X ~ F(dfn, dfd)``."""
    if x <= 0.0:
        return 1.0
    return float(scipy.special.betainc(dfd / 2.0, dfn / 2.0, dfd / (dfd + dfn * x)))
