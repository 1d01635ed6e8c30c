"""What every identification returns: parameters (or maps) plus diagnostics."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from .._validate import as_fields
from ..geometry import TetraGeometry, difference_tensor
from ..model import InterferenceParameters, compensate_fields
from ..types import ArrayLike, FloatArray
from ..units import NT_PER_T


@dataclass(frozen=True)
class Calibration(ABC):
    """Diagnostics common to every method.

    Attributes
    ----------
    method : str
    n_samples : int
    n_parameters : int
    rank : int
        Numerical rank of the (column-scaled) design.
    condition_number : float
        Ratio of the largest to the smallest retained singular value of the scaled design.
    residual_rms : float
        RMS of the fitted equations' residual, T/m (tesla for per-sensor fits).
    details : dict
        Method-specific, JSON-serialisable extras.
    """

    method: str
    n_samples: int
    n_parameters: int
    rank: int
    condition_number: float
    residual_rms: float
    details: dict = field(default_factory=dict)

    #: Name (with unit) of ``residual_rms`` in :meth:`summary`.
    residual_key = 'residual_rms_nT_per_m'

    @property
    def null_space_dim(self) -> int:
        """Parameter directions the data cannot see."""
        return self.n_parameters - self.rank

    @abstractmethod
    def compensate_fields(self, fields_measured: ArrayLike, geometry: TetraGeometry) -> FloatArray:
        """Compensated tensor from raw readings, (N, 4, 3) tesla -> (N, 3, 3) T/m."""

    def summary(self) -> dict:
        """Diagnostics as plain types (residual in nT/m)."""
        return {
            'method': self.method,
            'n_samples': self.n_samples,
            'n_parameters': self.n_parameters,
            'rank': self.rank,
            'null_space_dim': self.null_space_dim,
            'condition_number': float(self.condition_number),
            self.residual_key: float(self.residual_rms * NT_PER_T),
            **self.details,
        }


@dataclass(frozen=True)
class TensorCalibration(Calibration):
    """A calibration in the paper's form: ``k``, ``b`` applied by eq. 19.

    Attributes
    ----------
    parameters : InterferenceParameters
    symmetric : bool
        The paper's symmetric ``K_i1`` (27 parameters) or general ones (36).
    covariance : ndarray, shape (P, P), or None
        Covariance of ``parameters.to_vector`` in its SI units (the marginal of the
        interference parameters when a regional gradient was fitted jointly), or None where
        the method gives none.
    regional_gradient_enu : ndarray, shape (3, 3), or None
        The constant regional (world-frame, ENU) gradient fitted jointly with ``k``, ``b``
        (symmetric, traceless), T/m; None when none was fitted. It is signal: compensation
        leaves it in the tensor.
    regional_gradient_sigma : ndarray, shape (3, 3), or None
        1-sigma of each component of ``regional_gradient_enu``, T/m (from the joint
        covariance).
    """

    parameters: InterferenceParameters = field(default_factory=InterferenceParameters.zero)
    symmetric: bool = True
    covariance: np.ndarray | None = None
    regional_gradient_enu: np.ndarray | None = None
    regional_gradient_sigma: np.ndarray | None = None

    def compensate_fields(self, fields_measured: ArrayLike, geometry: TetraGeometry) -> FloatArray:
        return compensate_fields(fields_measured, self.parameters, geometry)

    def summary(self) -> dict:
        """Diagnostics as plain types; with a regional gradient also
        ``regional_gradient_enu_nT_per_m`` and ``regional_gradient_sigma_nT_per_m`` (3x3
        nested lists, ENU) and the scalar ``regional_gradient_norm_nT_per_m`` (Frobenius)."""
        summary = super().summary()
        if self.regional_gradient_enu is not None:
            g_world = np.asarray(self.regional_gradient_enu, dtype=float) * NT_PER_T
            summary['regional_gradient_enu_nT_per_m'] = g_world.tolist()
            if self.regional_gradient_sigma is not None:
                sigma = np.asarray(self.regional_gradient_sigma, dtype=float) * NT_PER_T
                summary['regional_gradient_sigma_nT_per_m'] = sigma.tolist()
            summary['regional_gradient_norm_nT_per_m'] = float(np.linalg.norm(g_world))
        return summary

    @property
    def standard_errors(self) -> np.ndarray | None:
        """Square roots of the covariance diagonal, SI units of the parameter vector."""
        return None if self.covariance is None else np.sqrt(np.diag(self.covariance))


@dataclass(frozen=True)
class ReferenceSensorCalibration(Calibration):
    """Per-sensor maps onto the reference sensor (Pei & Yeo 2009): ``B_i,c = M_i B_i' + o_i``.

    ``matrices`` (3, 3, 3): ``M_2..M_4``, dimensionless; ``offsets`` (3, 3): ``o_2..o_4``, tesla.
    """

    residual_key = 'residual_rms_nT'  # a per-sensor field residual, not a tensor one
    matrices: np.ndarray = field(default_factory=lambda: np.tile(np.eye(3), (3, 1, 1)))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def corrected_fields(self, fields_measured: ArrayLike) -> FloatArray:
        """Sensors 2-4 mapped onto sensor 1, shape (N, 4, 3), tesla."""
        fields = as_fields(fields_measured, 'fields_measured').copy()
        fields[:, 1:] = (
            np.einsum('sij,nsj->nsi', self.matrices, fields[:, 1:]) + self.offsets[None]
        )
        return fields

    def compensate_fields(self, fields_measured: ArrayLike, geometry: TetraGeometry) -> FloatArray:
        return difference_tensor(self.corrected_fields(fields_measured), geometry)
