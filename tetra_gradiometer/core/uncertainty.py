"""Standard uncertainty (1-sigma) of the raw and compensated tensor, per component.

Two independent sources, added in quadrature:

* **sensor noise**: white, independent, ``sigma`` tesla per axis of every sensor. The
  compensated tensor (eqs. 7 and 19) is linear in the twelve readings,
  ``G[i, j] = sum_k a_inv[k, j] (B_(k+2),i - B_1,i - (K_(k+2)1 B_1)_i - b_(k+2),i)``, so its
  covariance is exactly ``sigma^2 J J^T`` with ``J`` the (9, 12) Jacobian: for sensor
  ``k+2``, ``dG[i, j]/dB[m] = delta(i, m) a_inv[k, j]``; for sensor 1,
  ``-sum_k a_inv[k, j] (delta(i, m) + K_(k+2)1[i, m])``. It does not depend on the sample.
* **calibration parameters**: the fit's covariance ``C`` (P, P) propagated through the
  design of eq. 18, ``diag(A_n C A_n^T)`` with ``A_n = interference_design(B_1',n)``; it
  grows with the field ``B_1'`` and is independent of the survey's own noise (the
  calibration came from other data).

Both are *first-order* (exact for the noise, which enters linearly; the parameter term
neglects the product of parameter error and reference-field noise, smaller by
``sigma / |B|`` ~ 1e-6).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._validate import as_vectors
from .design import interference_design
from .geometry import TetraGeometry
from .model import InterferenceParameters
from .types import ArrayLike, FloatArray

__all__ = ['compensated_sigma', 'noise_jacobian', 'noise_sigma']


def noise_jacobian(
    geometry: TetraGeometry, parameters: InterferenceParameters | None = None
) -> FloatArray:
    """Jacobian of the (compensated) tensor's row-major ``vec`` against the twelve readings,
    shape (9, 12), 1/m: ``dG[i, j] / dB[s, m]`` at column ``3 s + m`` (sensor ``s`` 0-based).

    Parameters
    ----------
    geometry : TetraGeometry
    parameters : InterferenceParameters, optional
        ``k``, ``b`` of the compensation (eq. 19); None for the raw tensor (eq. 7).
    """
    a_inv = geometry.a_inv
    k_soft = np.zeros((3, 3, 3)) if parameters is None else parameters.k_soft
    eye = np.eye(3)
    jacobian = np.zeros((3, 3, 4, 3))  # (i, j, sensor, m)
    # Sensors 2-4: dG[i, j]/dB_(k+2)[m] = delta(i, m) a_inv[k, j].
    jacobian[:, :, 1:, :] = np.einsum('im,kj->ijkm', eye, a_inv)
    # Sensor 1: dG[i, j]/dB_1[m] = -sum_k a_inv[k, j] (delta(i, m) + K_k[i, m]).
    jacobian[:, :, 0, :] = -np.einsum('kj,kim->ijm', a_inv, eye[None] + k_soft)
    return jacobian.reshape(9, 12)


def noise_sigma(
    geometry: TetraGeometry,
    sensor_noise_t: float,
    parameters: InterferenceParameters | None = None,
) -> FloatArray:
    """Per-component 1-sigma of the tensor from sensor noise, shape (3, 3), T/m.

    Parameters
    ----------
    geometry : TetraGeometry
    sensor_noise_t : float
        White noise per axis of each sensor, tesla RMS.
    parameters : InterferenceParameters, optional
        ``k``, ``b`` of the compensation (eq. 19); None for the raw tensor (eq. 7).
    """
    jacobian = noise_jacobian(geometry, parameters)
    return float(sensor_noise_t) * np.sqrt(np.sum(jacobian**2, axis=1)).reshape(3, 3)


def compensated_sigma(
    b_reference: ArrayLike,
    geometry: TetraGeometry,
    sensor_noise_t: float,
    parameters: InterferenceParameters | None = None,
    covariance: np.ndarray | None = None,
) -> FloatArray:
    """Per-sample, per-component 1-sigma of the (compensated) tensor, shape (N, 3, 3), T/m.

    Parameters
    ----------
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla.
    geometry : TetraGeometry
    sensor_noise_t : float
        White noise per axis of each sensor, tesla RMS.
    parameters : InterferenceParameters, optional
        None for the raw tensor (then ``covariance`` must be None too).
    covariance : ndarray, shape (P, P), optional
        Covariance of the parameter vector (27 symmetric or 36 general entries, SI units of
        ``InterferenceParameters.to_vector``); None leaves out the calibration term.
    """
    b_reference = as_vectors(b_reference, 'b_reference')
    variance = np.broadcast_to(
        noise_sigma(geometry, sensor_noise_t, parameters) ** 2, (len(b_reference), 3, 3)
    )
    if covariance is not None:
        covariance = np.asarray(covariance, dtype=float)
        if covariance.shape not in ((27, 27), (36, 36)) or not np.all(np.isfinite(covariance)):
            raise InputError(
                f'covariance must be a finite (27, 27) or (36, 36) array, got {covariance.shape}'
            )
        symmetric = covariance.shape == (27, 27)
        design = interference_design(b_reference, geometry, symmetric=symmetric)
        parameter_variance = np.einsum('nqp,pr,nqr->nq', design, covariance, design)
        variance = variance + parameter_variance.reshape(-1, 3, 3)
    return np.sqrt(variance)
