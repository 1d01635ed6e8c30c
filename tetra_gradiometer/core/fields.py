"""Source fields: point magnetic dipole (field and exact gradient) and a uniform field."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._validate import as_array, as_vectors
from .types import ArrayLike, FloatArray

#: mu_0 / (4 pi), T m / A.
MU0_OVER_4PI = 1.0e-7


def _relative(points: ArrayLike, source: ArrayLike) -> tuple[FloatArray, FloatArray]:
    points = as_vectors(points, 'points')
    source = as_array(source, 'dipole position', (3,))
    r = points - source
    distance = np.linalg.norm(r, axis=1)
    if np.any(distance == 0.0):
        raise InputError(f'a point coincides with the dipole at {source.tolist()} m')
    return r, distance


def dipole_field(points: ArrayLike, moment: ArrayLike, source: ArrayLike) -> FloatArray:
    """Field of a point dipole, ``B = mu0/4pi (3 r (m.r) / r^5 - m / r^3)``.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Where to evaluate, metres.
    moment : array_like, shape (3,)
        Dipole moment, A m^2, same frame as ``points``.
    source : array_like, shape (3,)
        Dipole position, metres.

    Returns
    -------
    ndarray, shape (N, 3)
        Field, tesla.
    """
    moment = as_array(moment, 'dipole moment', (3,))
    r, distance = _relative(points, source)
    m_dot_r = r @ moment
    return MU0_OVER_4PI * (
        3.0 * r * (m_dot_r / distance**5)[:, None] - moment[None, :] / (distance**3)[:, None]
    )


def dipole_gradient(points: ArrayLike, moment: ArrayLike, source: ArrayLike) -> FloatArray:
    """Exact gradient tensor of a point dipole, ``G[n, i, j] = dB_i/dx_j``.

    ``dB_i/dx_j = mu0/4pi [3 (delta_ij (m.r) + r_i m_j + m_i r_j) / r^5
    - 15 r_i r_j (m.r) / r^7]``: symmetric and traceless.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Metres.
    moment : array_like, shape (3,)
        A m^2.
    source : array_like, shape (3,)
        Metres.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        T/m.
    """
    moment = as_array(moment, 'dipole moment', (3,))
    r, distance = _relative(points, source)
    m_dot_r = r @ moment
    inv5 = 1.0 / distance**5
    outer_rm = r[:, :, None] * moment[None, None, :]
    gradient = (
        3.0
        * inv5[:, None, None]
        * (m_dot_r[:, None, None] * np.eye(3)[None] + outer_rm + np.swapaxes(outer_rm, 1, 2))
    )
    gradient -= (15.0 * m_dot_r / distance**7)[:, None, None] * (r[:, :, None] * r[:, None, :])
    return MU0_OVER_4PI * gradient


def uniform_field(n_samples: int, field: ArrayLike) -> FloatArray:
    """A uniform field repeated for ``n_samples`` points, shape (N, 3), tesla."""
    field = as_array(field, 'uniform field', (3,))
    return np.broadcast_to(field, (n_samples, 3)).copy()
