"""Reference [8] of the paper (Pei & Yeo 2009) as the paper describes it.

Sensors 2-4 are each compensated individually against reference sensor 1, then the
tensor is formed by differencing (eq. 7); no tensor constraint is used. Our reading of
"compensate against the reference": a per-sensor linear map ``B_i,c = M_i B_i' + o_i``
(3x3 + offset, the usual single-magnetometer calibration form) fitted by least squares
so that ``B_i,c - B_1'`` matches the known true difference (zero in a uniform field).
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from .._validate import as_fields, as_tensors, same_length
from ..geometry import TetraGeometry
from ..types import ArrayLike
from ._linear import solve_scaled
from .lstsq import _check_samples
from .result import ReferenceSensorCalibration


def pei_yeo_2009(
    fields_measured: ArrayLike,
    *,
    geometry: TetraGeometry | None = None,
    g_true: ArrayLike | None = None,
) -> ReferenceSensorCalibration:
    """Fit ``M_i``, ``o_i`` for sensors 2-4 against sensor 1.

    Parameters
    ----------
    fields_measured : array_like, shape (N, 4, 3)
        Raw readings, tesla, body frame.
    geometry : TetraGeometry, optional
        Needed only with ``g_true``.
    g_true : array_like, shape (N, 3, 3), optional
        Known true tensor, T/m: the target difference is ``G r_i1``. Zero when omitted.

    Returns
    -------
    ReferenceSensorCalibration
        ``rank`` and ``condition_number`` are those of the worst sensor's regression;
        ``residual_rms`` is in tesla.
    """
    fields = as_fields(fields_measured, 'fields_measured')
    n = len(fields)
    _check_samples(n, 'pei_yeo_2009')
    targets = np.repeat(fields[:, :1, :], 3, axis=1)
    if g_true is not None:
        if geometry is None:
            raise InputError('pei_yeo_2009: g_true needs the geometry')
        g_true = as_tensors(g_true, 'g_true')
        same_length(fields_measured=fields, g_true=g_true)
        targets = targets + np.einsum('nij,js->nsi', g_true, geometry.a)
    matrices, offsets, ranks, conditions, residuals = [], [], [], [], []
    for sensor in range(1, 4):
        regressors = np.column_stack([fields[:, sensor, :], np.ones(n)])
        solutions = [solve_scaled(regressors, targets[:, sensor - 1, axis]) for axis in range(3)]
        coefficients = np.array([s.theta for s in solutions])  # (3 axes, 4)
        matrices.append(coefficients[:, :3])
        offsets.append(coefficients[:, 3])
        ranks.append(solutions[0].rank)
        conditions.append(solutions[0].condition_number)
        residuals.append(np.concatenate([s.residual for s in solutions]))
    return ReferenceSensorCalibration(
        # 4 coefficients per axis, 3 axes, 3 sensors: the rank counts all 36.
        method='pei_yeo_2009',
        n_samples=n,
        n_parameters=36,
        rank=3 * sum(ranks),
        condition_number=max(conditions),
        residual_rms=float(np.sqrt(np.mean(np.concatenate(residuals) ** 2))),
        matrices=np.array(matrices),
        offsets=np.array(offsets),
    )
