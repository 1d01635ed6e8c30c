"""The first-order recursive filter of the health monitor, from ``scipy.signal``, imported at
the first call: ``scipy.signal`` is ~0.3 s of a compensator node's or ``compensate``'s start
(0.92 -> 0.61 s CPU of its imports), and most runs never monitor (no calibration noise, no
``--report``). Tested against a plain loop in test/core/test_filters.py.
"""

from __future__ import annotations

import numpy as np


def exponential_filter(lam: float, inputs: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """``y[n] = inputs[n] + lam * y[n-1]`` along axis 0, ``y[-1]`` being ``initial / lam``
    (``scipy.signal.lfilter``'s ``zi``: ``initial`` has the shape of one row of ``inputs``
    with a leading axis of 1 for 2-D ``inputs``, or (1,)); the shape of ``inputs``."""
    from scipy.signal import lfilter

    return lfilter([1.0], [1.0, -lam], inputs, axis=0, zi=initial)[0]
