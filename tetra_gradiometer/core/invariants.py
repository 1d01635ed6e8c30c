"""Rotational invariants of the gradient tensor (Pedersen & Rasmussen 1990), the quantities
a survey map shows whatever the frame: the same value in the body, odom and world frames.

``I0 = trace(S)``, ``I1 = sum of the principal 2x2 minors of S``,
``I2 = det(S)``, with ``S`` the symmetric part of the tensor (a measured tensor is not
exactly symmetric; the field's gradient is, and its trace is zero, so ``I0`` is a check:
noise plus residual interference). For a field's tensor ``-I1 >= 0`` and
``(I2 / 2)^2 <= (-I1 / 3)^3``.
"""

from __future__ import annotations

import numpy as np

from .types import FloatArray

__all__ = ['INVARIANT_NAMES', 'tensor_invariants']

#: Column names of :func:`tensor_invariants`.
INVARIANT_NAMES = ('i0', 'i1', 'i2')


def tensor_invariants(tensors: FloatArray) -> FloatArray:
    """``I0``, ``I1``, ``I2`` (N, 3) of tensors (N, 3, 3) in T/m: units T/m, (T/m)^2,
    (T/m)^3 (scale a tensor by ``c`` and they scale by ``c``, ``c^2``, ``c^3``).

    >>> import numpy as np
    >>> tensor_invariants(np.diag([1.0, 2.0, -3.0])[None]).round(12).tolist()
    [[0.0, -7.0, -6.0]]
    """
    sym = 0.5 * (tensors + np.swapaxes(tensors, -1, -2))
    xx, yy, zz = sym[..., 0, 0], sym[..., 1, 1], sym[..., 2, 2]
    xy, xz, yz = sym[..., 0, 1], sym[..., 0, 2], sym[..., 1, 2]
    i0 = xx + yy + zz
    i1 = xx * yy + yy * zz + xx * zz - xy**2 - yz**2 - xz**2
    i2 = np.linalg.det(sym)
    return np.stack([i0, i1, i2], axis=-1)
