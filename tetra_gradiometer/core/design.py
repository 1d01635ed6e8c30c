"""Design matrices: the interference ``D`` (eq. 18) is linear in the parameter vector.

``vec(D_n) = A_n theta`` with ``vec`` row-major over ``(i, j)`` of ``D[i, j]``; ``theta``
is laid out as in :mod:`tetra_gradiometer.core.model`. Solvers in
:mod:`tetra_gradiometer.core.identification` take these matrices; nothing here solves.
"""

from __future__ import annotations

import numpy as np

from ._validate import as_vectors
from .geometry import TetraGeometry
from .model import SYMMETRIC_EXPANSION
from .types import ArrayLike, FloatArray

#: Rows of the symmetry/trace conditions of eq. 20 on a row-major vec of a 3x3 tensor:
#: ``G12 - G21``, ``G13 - G31``, ``G23 - G32``, ``G11 + G22 + G33``.
CONSTRAINT_ROWS = np.zeros((4, 9))
for _row, (_i, _j) in enumerate(((0, 1), (0, 2), (1, 2))):
    CONSTRAINT_ROWS[_row, 3 * _i + _j] = 1.0
    CONSTRAINT_ROWS[_row, 3 * _j + _i] = -1.0
CONSTRAINT_ROWS[3, [0, 4, 8]] = 1.0
del _row, _i, _j


def interference_design(
    b_reference: ArrayLike, geometry: TetraGeometry, *, symmetric: bool
) -> FloatArray:
    """Per-sample design ``A_n`` with ``vec(D_n) = A_n theta`` (eq. 18).

    Parameters
    ----------
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    symmetric : bool
        27 parameters (symmetric ``K_i1``) or 36 (general).

    Returns
    -------
    ndarray, shape (N, 9, P)
        Columns for ``K`` entries in 1/m (times tesla of ``B_1'``: T/m per unit ``K``),
        columns for offsets in 1/m (T/m per tesla).
    """
    b_reference = as_vectors(b_reference, 'b_reference')
    n = len(b_reference)
    a_inv = geometry.a_inv
    eye = np.eye(3)
    # d D[R, j] / d K_i[r, c] = delta(R, r) B[c] a_inv[i, j]
    k_columns = np.einsum('Rr,nc,ij->nRjirc', eye, b_reference, a_inv).reshape(n, 9, 3, 9)
    if symmetric:
        k_columns = k_columns @ SYMMETRIC_EXPANSION
    k_columns = k_columns.reshape(n, 9, -1)
    # d D[R, j] / d b_i[r] = delta(R, r) a_inv[i, j]
    b_columns = np.einsum('Rr,ij->Rjir', eye, a_inv).reshape(9, 9)
    return np.concatenate([k_columns, np.broadcast_to(b_columns, (n, 9, 9))], axis=2)


def affine_interference_design(geometry: TetraGeometry, *, symmetric: bool) -> FloatArray:
    """``M`` (4, 9, P) with ``A(B_1') = sum_c B_1',c M_c + M_3``: eq. 18's design is affine in
    ``B_1'``, so its value at the unit vectors and at zero gives the ``M_c`` exactly."""
    basis = np.vstack([np.eye(3), np.zeros(3)])
    design = interference_design(basis, geometry, symmetric=symmetric).copy()
    design[:3] -= design[3]
    return design


def constraint_residual(g: np.ndarray) -> FloatArray:
    """The four eq. 20 quantities of each tensor, shape (N, 4), T/m (zero for a true gradient)."""
    return g.reshape(len(g), 9) @ CONSTRAINT_ROWS.T


def constraint_design(
    b_reference: ArrayLike, geometry: TetraGeometry, *, symmetric: bool
) -> FloatArray:
    """Design of eq. 21: ``L vec(D_n)``, shape (N, 4, P); the target is ``L vec(G_m,n)``."""
    return np.einsum(
        'kq,nqp->nkp',
        CONSTRAINT_ROWS,
        interference_design(b_reference, geometry, symmetric=symmetric),
    )
