"""Compensation metrics.

``epsilon`` is the paper's (eq. 24); it compares Frobenius norms only, so direction errors
cancel. Beside it: the RMS of the component residual and the improvement ratio.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._validate import as_tensors, same_length
from .geometry import TetraGeometry
from .types import ArrayLike, FloatArray
from .units import NT_PER_T


def _checked(**tensors: ArrayLike) -> dict[str, FloatArray]:
    arrays = {name: as_tensors(value, name) for name, value in tensors.items()}
    same_length(**arrays)
    return arrays


def epsilon_terms(g_before: ArrayLike, g_after: ArrayLike, g_true: ArrayLike) -> FloatArray:
    """Per-sample terms of eq. 24, ``|(|G_a|_F - |G_l|_F) / (|G_b|_F - |G_l|_F)|``, shape (N,);
    NaN where ``|G_b|_F == |G_l|_F`` (undefined).

    Parameters
    ----------
    g_before, g_after, g_true : array_like, shape (N, 3, 3)
        Uncompensated, compensated and true tensors, T/m.
    """
    t = _checked(g_before=g_before, g_after=g_after, g_true=g_true)
    norm = {name: np.linalg.norm(value, axis=(1, 2)) for name, value in t.items()}
    denominator = norm['g_before'] - norm['g_true']
    with np.errstate(divide='ignore', invalid='ignore'):
        terms = np.abs((norm['g_after'] - norm['g_true']) / denominator)
    return np.where(denominator == 0.0, np.nan, terms)


def epsilon(g_before: ArrayLike, g_after: ArrayLike, g_true: ArrayLike) -> float:
    """Eq. 24: the mean of :func:`epsilon_terms` (dimensionless).

    Raises
    ------
    ValueError
        If a sample's uncompensated norm equals the true norm (the ratio is undefined).
    """
    terms = epsilon_terms(g_before, g_after, g_true)
    if np.any(np.isnan(terms)):
        raise InputError('epsilon is undefined: a sample has |G_before|_F == |G_true|_F')
    return float(np.mean(terms))


def compensated_percent(eps: float) -> float:
    """``100 (1 - epsilon)``, percent."""
    return 100.0 * (1.0 - eps)


def rms_residual(g: ArrayLike, g_true: ArrayLike) -> float:
    """RMS over samples and all 9 components of ``g - g_true``, T/m."""
    t = _checked(g=g, g_true=g_true)
    return float(np.sqrt(np.mean((t['g'] - t['g_true']) ** 2)))


def improvement_ratio(g_before: ArrayLike, g_after: ArrayLike, g_true: ArrayLike) -> float:
    """``rms_residual(g_before) / rms_residual(g_after)`` (dimensionless)."""
    after = rms_residual(g_after, g_true)
    return float('inf') if after == 0.0 else rms_residual(g_before, g_true) / after


def noise_floor(sigma: float, geometry: TetraGeometry) -> float:
    """RMS over components of the tensor noise from i.i.d. sensor noise, T/m.

    Column ``j`` of every tensor row is ``sum_i (n_(i+1) - n_1) a^-1[i, j]``, variance
    ``sigma^2 (sum_i a^-1[i, j]^2 + (sum_i a^-1[i, j])^2)``; about ``1.42 sigma / d`` for a
    regular tetrahedron of edge ``d``.

    Parameters
    ----------
    sigma : float
        Per-axis sensor noise, tesla RMS.
    geometry : TetraGeometry
    """
    a_inv = geometry.a_inv
    variance = (a_inv**2).sum(axis=0) + a_inv.sum(axis=0) ** 2
    return float(sigma * np.sqrt(variance.mean()))


def summarize(g_before: ArrayLike, g_after: ArrayLike, g_true: ArrayLike) -> dict[str, float]:
    """All four metrics, residuals in nT/m, as the reports print them."""
    eps = epsilon(g_before, g_after, g_true)
    return {
        'epsilon': eps,
        'compensated_percent': compensated_percent(eps),
        'rms_residual_nT_per_m': rms_residual(g_after, g_true) * NT_PER_T,
        'improvement_ratio': improvement_ratio(g_before, g_after, g_true),
    }
