"""What a calibration's misfit looks like: a field, or the vehicle?

A field that is not uniform over the window (a target passed, geology) leaves in the fit's
residual a true gradient: symmetric and traceless (eqs. 2-3). An interference the model
lacks (a current, a drift, an eddy term without its channel) leaves the difference of
sensor readings, ``P a^-1`` for a general ``P``: of a random such tensor 5/9 of the energy
falls in the symmetric traceless part and 4/9 in the rest (antisymmetric and trace). So the
share of the residual's energy *above the noise* that is symmetric and traceless tells the
two apart: ~1 for a field, ~0.56 for the vehicle. :func:`gradient_share` computes it with
the sensor noise's own share of each part taken out (``J J^T`` of
:func:`~..uncertainty.noise_jacobian` through each projector).
"""

from __future__ import annotations

import numpy as np

from ..geometry import TetraGeometry
from ..types import FloatArray

#: A misfit at least this much symmetric and traceless (above the noise) is a field's: a
#: field gives ~1 (1.00 for a dipole passed beside a trim); the vehicle ~0.56 on average, but
#: one current on few sensors reached 0.90 (two thrusters' currents left out of the fit).
FIELD_SHARE = 0.97


def _symmetric_traceless_projector() -> FloatArray:
    """(9, 9) orthogonal projector of row-major ``vec(G)`` onto symmetric traceless tensors."""
    sym = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            sym[3 * i + j, 3 * i + j] += 0.5
            sym[3 * i + j, 3 * j + i] += 0.5
    trace = np.zeros(9)
    trace[[0, 4, 8]] = 1.0
    return sym - np.outer(trace, trace) / 3.0


SYMMETRIC_TRACELESS = _symmetric_traceless_projector()


def gradient_share(
    residual: FloatArray, geometry: TetraGeometry, sensor_noise_t: float
) -> float | None:
    """The share of ``residual``'s (N, 3, 3) T/m energy above the noise that is symmetric
    and traceless (see the module); None when there is no energy above the noise.

    ``sensor_noise_t``: white noise per sensor axis, tesla (e.g. the window check's estimate).
    """
    from ..uncertainty import noise_jacobian

    flat = residual.reshape(len(residual), 9)
    flat = flat[np.all(np.isfinite(flat), axis=1)]
    if not len(flat):
        return None
    noise = sensor_noise_t**2 * noise_jacobian(geometry) @ noise_jacobian(geometry).T
    rest = np.eye(9) - SYMMETRIC_TRACELESS
    field_part = np.mean(np.sum((flat @ SYMMETRIC_TRACELESS) ** 2, axis=1))
    rest_part = np.mean(np.sum((flat @ rest) ** 2, axis=1))
    field_excess = max(field_part - np.trace(SYMMETRIC_TRACELESS @ noise), 0.0)
    rest_excess = max(rest_part - np.trace(rest @ noise), 0.0)
    total = field_excess + rest_excess
    if total <= 0.1 * np.trace(noise):
        return None
    return float(field_excess / total)
