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

:class:`SigmaModel` holds both for one calibration as a quadratic form in ``(B_1', 1)``:
what a node evaluates per message and a bag pipeline per chunk (:func:`compensated_sigma`
is its one-call form).

With vehicle-effect terms (:mod:`.effects`) the form is in ``(B_1', 1, x)``, ``x`` the
terms' regressors (the design stays affine in them), the covariance is of
:meth:`~.model.InterferenceParameters.full_vector`, and a third source is added: the
**channels' noise** (a current or temperature reading's own noise, ``channel_noise`` of each
term) through the terms' coefficients, ``sum_j (W_j a^-1)^2 sigma_j^2`` per component.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._validate import as_vectors, frozen_array
from .design import CONSTRAINT_ROWS, affine_interference_design
from .geometry import TetraGeometry
from .model import InterferenceParameters
from .types import ArrayLike, FloatArray

__all__ = [
    'SigmaModel',
    'compensated_sigma',
    'constraint_bias_form',
    'noise_jacobian',
    'noise_sigma',
    'readings_sigma',
]


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


def terms_design(geometry: TetraGeometry, parameters: InterferenceParameters) -> FloatArray:
    """``M`` (4 + M, 9, 36 + 9 M) of ``D(x) = sum_c x_c M_c`` for ``x = (B_1', 1, z)``: the
    general design of eq. 18 and, for regressor ``j`` of the terms, ``dD[r, c] / dW[i, r, j]
    = a_inv[i, c]`` (coefficients in :meth:`InterferenceParameters.full_vector` order)."""
    m = parameters.n_term_regressors
    base = affine_interference_design(geometry, symmetric=False)  # (4, 9, 36)
    design = np.zeros((4 + m, 9, 36 + 9 * m))
    design[:4, :, :36] = base
    offset, start = 36, 0
    for term in parameters.terms:
        size = term.size
        for i in range(3):
            for r in range(3):
                for j in range(size):
                    column = offset + (i * 3 + r) * size + j
                    design[4 + start + j, 3 * r : 3 * r + 3, column] = geometry.a_inv[i]
        offset += 9 * size
        start += size
    return design


def channel_variance(geometry: TetraGeometry, parameters: InterferenceParameters) -> FloatArray:
    """Variance (9,) (T/m)^2 per component from the terms' channel noise (module docstring)."""
    variance = np.zeros(9)
    for term in parameters.terms:
        for j, noise in enumerate(term.channel_noise):
            # D[r, c] += sum_i W[i, r, j] z_j a_inv[i, c]
            per_unit = np.einsum('ir,ic->rc', term.coefficients[:, :, j], geometry.a_inv)
            variance += (per_unit.reshape(9) * noise) ** 2
    return variance


def check_covariance(covariance: ArrayLike) -> tuple[FloatArray, bool]:
    """A parameter covariance as a float array, and whether it is of the 27 symmetric
    parameters (else the 36 general ones).

    Raises
    ------
    InputError
        Not a finite (27, 27) or (36, 36) array.
    """
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape not in ((27, 27), (36, 36)) or not np.all(np.isfinite(covariance)):
        raise InputError(
            f'covariance must be a finite (27, 27) or (36, 36) array, got {covariance.shape}'
        )
    return covariance, covariance.shape == (27, 27)


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


def readings_sigma(jacobian: FloatArray, covariances_t2: ArrayLike) -> FloatArray:
    """Per-component 1-sigma (9,) T/m of a tensor from its readings' covariances: the square
    root of ``diag(J C J^T)``, ``C`` the (12, 12) block diagonal of the four sensors' (3, 3)
    covariances (independent sensors; correlated axes within one are kept).

    Parameters
    ----------
    jacobian : ndarray, shape (9, 12)
        :func:`noise_jacobian`, 1/m.
    covariances_t2 : array_like, shape (4, 9)
        Each sensor's covariance, row-major 3 x 3, T^2 (as ``sensor_msgs/MagneticField``).
    """
    blocks = np.asarray(covariances_t2, dtype=float).reshape(4, 3, 3)
    per_sensor = np.asarray(jacobian, dtype=float).reshape(9, 4, 3)
    variance = np.einsum('rsm,smn,rsn->r', per_sensor, blocks, per_sensor)
    return np.sqrt(np.maximum(variance, 0.0))


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

    Raises
    ------
    InputError
        ``covariance`` is not a finite (27, 27) or (36, 36) array, or ``b_reference`` is
        not a finite (N, 3) array.
    """
    return SigmaModel.build(geometry, sensor_noise_t, parameters, covariance)(b_reference)


@dataclass(frozen=True)
class SigmaModel:
    """:func:`compensated_sigma` of one calibration, with all that does not depend on the
    sample computed once: the variance of component ``q`` at ``x = (B_1', 1)`` is the
    quadratic form ``x^T F_q x`` (the design of eq. 18 is affine in ``B_1'``, so
    ``A_n C A_n^T`` is quadratic in ``x``; the constant noise variance sits in ``F_q[3, 3]``).
    Per sample it costs a (9, 16) product: a live node can afford it on every message, and
    a bag's chunk of 10^5 sets takes milliseconds instead of ``interference_design``'s
    (N, 9, P) and an (N, 9, P, P) contraction.

    Attributes
    ----------
    form : ndarray, shape (9, 4 + M, 4 + M)
        ``F``, row-major tensor component first; T^2/m^2 per unit ``x x^T`` (``B_1'`` in
        tesla, ``M`` term regressors in SI). Read-only.
    """

    form: FloatArray

    def __post_init__(self) -> None:
        size = np.shape(self.form)[-1]
        object.__setattr__(self, 'form', frozen_array(self.form, 'form', (9, size, size)))

    @property
    def n_regressors(self) -> int:
        """``M``: the term regressors the model expects."""
        return int(self.form.shape[-1]) - 4

    @classmethod
    def build(
        cls,
        geometry: TetraGeometry,
        sensor_noise_t: float,
        parameters: InterferenceParameters | None = None,
        covariance: np.ndarray | None = None,
    ) -> SigmaModel:
        """The model of :func:`compensated_sigma`'s arguments (all but ``b_reference``)."""
        if parameters is not None and parameters.terms:
            return cls._with_terms(geometry, sensor_noise_t, parameters, covariance)
        form = np.zeros((9, 4, 4))
        form[:, 3, 3] = (noise_sigma(geometry, sensor_noise_t, parameters) ** 2).reshape(9)
        if covariance is not None:
            covariance, symmetric = check_covariance(covariance)
            design = affine_interference_design(geometry, symmetric=symmetric)  # (4, 9, P)
            form += np.einsum('cqp,pr,dqr->qcd', design, covariance, design)
        return cls(form)

    @classmethod
    def _with_terms(
        cls,
        geometry: TetraGeometry,
        sensor_noise_t: float,
        parameters: InterferenceParameters,
        covariance: np.ndarray | None,
    ) -> SigmaModel:
        m = parameters.n_term_regressors
        form = np.zeros((9, 4 + m, 4 + m))
        noise = (noise_sigma(geometry, sensor_noise_t, parameters) ** 2).reshape(9)
        form[:, 3, 3] = noise + channel_variance(geometry, parameters)
        if covariance is not None:
            covariance = np.asarray(covariance, dtype=float)
            size = 36 + 9 * m
            if covariance.shape != (size, size) or not np.all(np.isfinite(covariance)):
                raise InputError(
                    f'covariance must be a finite ({size}, {size}) array for k, b and '
                    f'{m} term regressors, got {covariance.shape}'
                )
            design = terms_design(geometry, parameters)
            form += np.einsum('cqp,pr,dqr->qcd', design, covariance, design)
        return cls(form)

    def __call__(self, b_reference: ArrayLike, regressors: ArrayLike | None = None) -> FloatArray:
        """1-sigma per sample and component, shape (N, 3, 3), T/m, for ``b_reference``
        (N, 3) tesla and, with terms, their ``regressors`` (N, M) SI."""
        b_reference = as_vectors(b_reference, 'b_reference')
        blocks = [b_reference, np.ones((len(b_reference), 1))]
        if self.n_regressors:
            if regressors is None or np.shape(regressors) != (len(b_reference), self.n_regressors):
                raise InputError(
                    f"this sigma model needs the terms' {self.n_regressors} regressors per sample"
                )
            blocks.append(np.asarray(regressors, dtype=float))
        return self._sigma(np.concatenate(blocks, axis=1)).reshape(-1, 3, 3)

    def one(self, b_reference: np.ndarray, regressors: np.ndarray | None = None) -> FloatArray:
        """1-sigma (3, 3), T/m, of one sample ``b_reference`` (3,) tesla (and the terms'
        ``regressors`` (M,)), unchecked (the per-message path of a node that has checked
        the reading already)."""
        x = np.concatenate([b_reference, [1.0], [] if regressors is None else regressors])
        return self._sigma(x[None])[0].reshape(3, 3)

    def _sigma(self, x: FloatArray) -> FloatArray:
        """(N, 9) from ``x`` (N, 4 + M)."""
        size = x.shape[1]
        outer = (x[:, :, None] * x[:, None, :]).reshape(len(x), size * size)
        variance = outer @ self.form.reshape(9, size * size).T
        # A positive semi-definite form can round to -1e-30 where it is ~0: clip, never NaN.
        return np.sqrt(np.maximum(variance, 0.0))


def constraint_bias_form(geometry: TetraGeometry, covariance: np.ndarray | None) -> FloatArray:
    """The calibration error's variance in the four constraint quantities ``L vec(G)`` of a
    set (core/health), as a quadratic form: ``Q`` (4, 4) with
    ``trace(L A_n C A_n^T L^T) = x_n^T Q x_n``, ``x_n = (B_1', 1)``.

    ``L A_n`` is linear in ``x_n``: ``sum_c x_n[c] H_c``; ``Q[c, d] = trace(H_c C H_d^T)``.
    Zero without a covariance.
    """
    if covariance is None:
        return np.zeros((4, 4))
    covariance, symmetric = check_covariance(covariance)
    design = affine_interference_design(geometry, symmetric=symmetric)  # (4, 9, P)
    h = np.einsum('kq,cqp->ckp', CONSTRAINT_ROWS, design)  # H_x, H_y, H_z, H_1
    return np.einsum('ckp,pq,dkq->cd', h, covariance, h)
