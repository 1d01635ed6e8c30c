"""The vehicle interference model and its compensation (Yu et al. 2014, eqs. 8-19).

Per sensor (eq. 10): ``B_i' = B_i + K_i B^b + B_i^h``. Differencing against sensor 1
(eqs. 11-13) leaves ``K_i1 = K_i - K_1`` and ``B_i1^h = B_i^h - B_1^h``. With the
paper's assumption ``B^b = B_1'`` the interference on the tensor is (eq. 18)
``D = (k B_1m + b) a^-1`` and the compensation is ``G = G_m - D`` (eq. 19).

Parameter vector layouts (``to_vector``/``from_vector``), SI units:

* symmetric (27, the paper's): ``K_21, K_31, K_41`` as their 6 unique entries
  ``(xx, xy, xz, yy, yz, zz)`` (dimensionless), then ``B_21^h, B_31^h, B_41^h`` (tesla);
* general (36): ``K_21, K_31, K_41`` as 9 entries each, row-major, then the same 9 offsets.

Vehicle effects (:mod:`.effects`: currents, eddy currents, thermal drift) extend eq. 18 as
terms ``W x(t)`` on the pair differences: ``D = (k B_1m + b + sum W x) a^-1``. Their
coefficients are :attr:`InterferenceParameters.terms`; :meth:`~InterferenceParameters.
full_vector` appends them (``[pair][axis][regressor]`` each) to the general layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ._validate import as_array, as_fields, as_tensors, as_vectors, frozen_array, same_length
from .effects import Term, pair_interference
from .geometry import TetraGeometry, difference_tensor
from .types import ArrayLike, FloatArray

#: Index pairs of the 6 unique entries of a symmetric 3x3 matrix, in vector order.
SYMMETRIC_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _symmetric_expansion() -> FloatArray:
    """(9, 6) matrix mapping the 6 unique entries to the row-major 9 entries."""
    expand = np.zeros((9, 6))
    for col, (r, c) in enumerate(SYMMETRIC_ENTRIES):
        expand[3 * r + c, col] = 1.0
        expand[3 * c + r, col] = 1.0
    return expand


SYMMETRIC_EXPANSION = _symmetric_expansion()


def n_parameters(*, symmetric: bool) -> int:
    """27 for symmetric ``K_i1`` (the paper), 36 for general 3x3 ``K_i1``."""
    return 27 if symmetric else 36


@dataclass(frozen=True)
class InterferenceParameters:
    """Compensation parameters ``k`` and ``b`` of eqs. 15-17.

    Parameters
    ----------
    k_soft : array_like, shape (3, 3, 3)
        ``k_soft[i] = K_(i+2)1``, soft-iron difference matrices, dimensionless.
    b_hard : array_like, shape (3, 3)
        ``b_hard[i] = B_(i+2)1^h``, hard-iron difference vectors, tesla.
    terms : sequence of Term
        Vehicle effects fitted with ``k``, ``b`` (:mod:`.effects`); () for the paper's model.
    """

    k_soft: np.ndarray
    b_hard: np.ndarray
    terms: tuple[Term, ...] = field(default=())

    def __post_init__(self) -> None:
        object.__setattr__(self, 'k_soft', frozen_array(self.k_soft, 'k_soft', (3, 3, 3)))
        object.__setattr__(self, 'b_hard', frozen_array(self.b_hard, 'b_hard', (3, 3)))
        object.__setattr__(self, 'terms', tuple(self.terms))

    @property
    def n_term_regressors(self) -> int:
        """``M``: the regressors of every term (the columns of ``regressors`` in
        :func:`interference_tensor`)."""
        return sum(term.size for term in self.terms)

    def full_vector(self) -> FloatArray:
        """The general (36) vector followed by every term's coefficients, SI (the layout of
        a calibration's covariance when it has terms)."""
        parts = [self.to_vector(symmetric=False)]
        parts += [term.coefficients.reshape(-1) for term in self.terms]
        return np.concatenate(parts)

    def without_terms(self) -> InterferenceParameters:
        """``k``, ``b`` alone."""
        return InterferenceParameters(self.k_soft, self.b_hard)

    @classmethod
    def zero(cls) -> InterferenceParameters:
        """No interference."""
        return cls(np.zeros((3, 3, 3)), np.zeros((3, 3)))

    @property
    def is_symmetric(self) -> bool:
        """True when every ``K_i1`` is symmetric (to 1e-12 relative)."""
        scale = max(float(np.abs(self.k_soft).max()), 1e-300)
        return bool(np.abs(self.k_soft - np.swapaxes(self.k_soft, 1, 2)).max() <= 1e-12 * scale)

    def to_vector(self, *, symmetric: bool) -> FloatArray:
        """Pack into the 27- or 36-element vector described in the module docstring.

        Raises
        ------
        ValueError
            If ``symmetric`` is asked for but a ``K_i1`` is not symmetric.
        """
        if symmetric:
            if not self.is_symmetric:
                raise InputError(
                    'k_soft is not symmetric: pack it with symmetric=False (36 parameters)'
                )
            k_part = np.concatenate([[k[r, c] for r, c in SYMMETRIC_ENTRIES] for k in self.k_soft])
        else:
            k_part = self.k_soft.reshape(-1)
        return np.concatenate([k_part, self.b_hard.reshape(-1)])

    @classmethod
    def from_vector(cls, theta: ArrayLike, *, symmetric: bool) -> InterferenceParameters:
        """Unpack a 27- (symmetric) or 36-element (general) vector, SI units."""
        size = n_parameters(symmetric=symmetric)
        theta = as_array(theta, 'parameter vector', (size,))
        n_k = size - 9
        if symmetric:
            k_soft = (SYMMETRIC_EXPANSION @ theta[:n_k].reshape(3, 6).T).T.reshape(3, 3, 3)
        else:
            k_soft = theta[:n_k].reshape(3, 3, 3)
        return cls(k_soft, theta[n_k:].reshape(3, 3))


@dataclass(frozen=True)
class SensorInterference:
    """The physical per-sensor interference of eq. 10 (what a simulator applies).

    Parameters
    ----------
    k_soft : array_like, shape (4, 3, 3)
        ``K_1 .. K_4``, soft-iron matrices, dimensionless (symmetric in the paper).
    b_hard : array_like, shape (4, 3)
        ``B_1^h .. B_4^h``, hard-iron fields, tesla, body frame.
    """

    k_soft: np.ndarray
    b_hard: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, 'k_soft', frozen_array(self.k_soft, 'k_soft', (4, 3, 3)))
        object.__setattr__(self, 'b_hard', frozen_array(self.b_hard, 'b_hard', (4, 3)))

    @classmethod
    def zero(cls) -> SensorInterference:
        """A clean vehicle."""
        return cls(np.zeros((4, 3, 3)), np.zeros((4, 3)))

    def apply(self, fields_true: ArrayLike, b_background: ArrayLike) -> FloatArray:
        """Measured fields ``B_i' = B_i + K_i B^b + B_i^h`` (eq. 10).

        Parameters
        ----------
        fields_true : array_like, shape (N, 4, 3)
            Fields the sensors would read on a clean vehicle, tesla, body frame.
        b_background : array_like, shape (N, 3)
            Background field that magnetises the vehicle, tesla, body frame.

        Returns
        -------
        ndarray, shape (N, 4, 3)
            Tesla.
        """
        fields_true = as_fields(fields_true, 'fields_true')
        b_background = as_vectors(b_background, 'b_background')
        same_length(fields_true=fields_true, b_background=b_background)
        induced = np.einsum('sij,nj->nsi', self.k_soft, b_background)
        return fields_true + induced + self.b_hard[None]

    def pair_parameters(self) -> InterferenceParameters:
        """``K_i1 = K_i - K_1``, ``B_i1^h = B_i^h - B_1^h`` (eq. 11): exact when sensor 1 is
        clean."""
        return InterferenceParameters(
            self.k_soft[1:] - self.k_soft[0], self.b_hard[1:] - self.b_hard[0]
        )

    def effective_parameters(self) -> InterferenceParameters:
        """Exact compensation parameters for the model ``B^b = B_1'`` (eq. 14).

        With sensor 1 not clean, ``B^b = (I + K_1)^-1 (B_1' - B_1^h)``, so the exact
        parameters are ``K_i1 (I + K_1)^-1`` (not symmetric in general) and
        ``B_i1^h - K_i1 (I + K_1)^-1 B_1^h``. Equal to :meth:`pair_parameters` when
        ``K_1 = 0`` and ``B_1^h = 0``.
        """
        pairs = self.pair_parameters()
        to_background = np.linalg.inv(np.eye(3) + self.k_soft[0])
        k_effective = pairs.k_soft @ to_background
        b_effective = pairs.b_hard - k_effective @ self.b_hard[0]
        return InterferenceParameters(k_effective, b_effective)


def _check_regressors(
    parameters: InterferenceParameters, regressors: ArrayLike | None, n: int
) -> FloatArray:
    """The terms' regressors (N, M) for ``parameters``; refuse them missing (a term is never
    taken as zero) or of the wrong shape."""
    m = parameters.n_term_regressors
    if regressors is None:
        if m:
            names = ', '.join(term.effect for term in parameters.terms)
            raise InputError(
                f'the calibration has terms ({names}): their regressors (the channels they '
                'read, effects.term_regressors) must be given'
            )
        return np.zeros((n, 0))
    regressors = np.asarray(regressors, dtype=float)
    if regressors.shape != (n, m):
        raise InputError(f'regressors must be ({n}, {m}) for these terms, got {regressors.shape}')
    return regressors


def interference_tensor(
    b_reference: ArrayLike,
    parameters: InterferenceParameters,
    geometry: TetraGeometry,
    regressors: ArrayLike | None = None,
) -> FloatArray:
    """Interference on the tensor, ``D = (k B_1m + b + sum W x) a^-1`` (eq. 18 and the
    vehicle effects' terms).

    Parameters
    ----------
    b_reference : array_like, shape (N, 3)
        Reference-sensor reading ``B_1'``, tesla, body frame (taken as ``B^b``).
    parameters : InterferenceParameters
    geometry : TetraGeometry
    regressors : array_like, shape (N, M), optional
        The terms' regressors on the samples (``effects.term_regressors`` offline,
        ``effects.LiveTerms`` live), SI; required when ``parameters`` has terms. A NaN
        regressor (an unknown channel) gives a NaN tensor: callers drop such samples.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        T/m.
    """
    b_reference = as_vectors(b_reference, 'b_reference')
    x = _check_regressors(parameters, regressors, len(b_reference))
    # Column i of (k B_1m + b) is K_(i+2)1 B_1' + B_(i+2)1^h.
    columns = np.einsum('irc,nc->nri', parameters.k_soft, b_reference) + parameters.b_hard.T[None]
    if parameters.terms:
        columns = columns + pair_interference(parameters.terms, x)
    return columns @ geometry.a_inv


def compensate(
    g_measured: ArrayLike,
    b_reference: ArrayLike,
    parameters: InterferenceParameters,
    geometry: TetraGeometry,
    regressors: ArrayLike | None = None,
) -> FloatArray:
    """Compensated tensor ``G = G_m - D`` (eq. 19).

    Parameters
    ----------
    g_measured : array_like, shape (N, 3, 3)
        Measured tensor ``G_m`` (eq. 7 on the raw readings), T/m.
    b_reference : array_like, shape (N, 3)
        Reference-sensor reading ``B_1'``, tesla.
    parameters : InterferenceParameters
    geometry : TetraGeometry
    regressors : array_like, shape (N, M), optional
        The terms' regressors (see :func:`interference_tensor`); required with terms.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        T/m.
    """
    g_measured = as_tensors(g_measured, 'g_measured')
    b_reference = as_vectors(b_reference, 'b_reference')
    same_length(g_measured=g_measured, b_reference=b_reference)
    return g_measured - interference_tensor(b_reference, parameters, geometry, regressors)


def compensate_fields(
    fields_measured: ArrayLike,
    parameters: InterferenceParameters,
    geometry: TetraGeometry,
    regressors: ArrayLike | None = None,
) -> FloatArray:
    """Eq. 7 then eq. 19 on raw readings, shape (N, 4, 3) tesla -> (N, 3, 3) T/m
    (``regressors`` (N, M): the terms', see :func:`interference_tensor`)."""
    fields_measured = as_fields(fields_measured, 'fields_measured')
    g_measured = difference_tensor(fields_measured, geometry)
    return compensate(g_measured, fields_measured[:, 0, :], parameters, geometry, regressors)
