"""The first-order recursive filter of the health monitor, in numpy.

Written here rather than taken from ``scipy.signal.lfilter``: importing ``scipy.signal``
costs ~1.5 s of CPU, three times what the monitor then spends on an hour of 100 Hz data,
and every compensation runs the monitor. The recursion is evaluated in blocks short enough
that ``lam**-k`` stays below 1e6 (about 10 digits kept); tested against a plain loop in
test/core/test_filters.py.
"""

from __future__ import annotations

import math

import numpy as np

#: ``lam**-k`` within a block stays below this.
MAX_GROWTH = 1e6


def exponential_filter(lam: float, inputs: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """``y[n] = inputs[n] + lam * y[n-1]`` along axis 0, ``y[-1]`` being ``initial / lam``
    (``initial`` has the shape of one row of ``inputs`` with a leading axis of 1 for 2-D
    ``inputs``, or (1,)); the shape of ``inputs``. ``0 < lam < 1``."""
    x = np.asarray(inputs, dtype=float)
    out = np.empty_like(x)
    carry = np.asarray(initial, dtype=float).reshape(x.shape[1:])  # lam * y[-1]
    block = max(1, int(math.log(MAX_GROWTH) / -math.log(lam))) if 0.0 < lam < 1.0 else 1
    for start in range(0, len(x), block):
        segment = x[start : start + block]
        k = np.arange(len(segment)).reshape((-1,) + (1,) * (x.ndim - 1))
        # y[i] = lam^i (carry + sum_{j <= i} lam^-j x[j]) within the block.
        y = (np.cumsum(segment * lam ** (-k), axis=0) + carry) * lam**k
        out[start : start + len(segment)] = y
        carry = lam * y[-1]
    return out
