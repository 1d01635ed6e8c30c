"""The simulator's effects beyond the paper's model: the one table :data:`EFFECT_SPECS`,
the switches and magnitudes :class:`Effects`, and each sensor's 3x3 response.

Two kinds, one table:

* the operational effects of the registry (:data:`~tetra_gradiometer.core.effects.EFFECTS`:
  ``vehicle_current``, ``eddy_current``, ``thermal_drift``): their :class:`EffectSpec` and
  their physics (:meth:`~tetra_gradiometer.core.effects.Effect.simulate`) are the registry's,
  read here, so that calibration, compensation and the simulator share one definition;
* the simulator's own, which the base model absorbs or which are properties of the
  recording, not terms of the model: ``time_skew`` (a sensor's delay), and the sensor's
  3x3 response ``M_s = S_s N_s R_s`` applied to its reading (``scale_factor``
  ``S_s = diag(1 + s)``, ``non_orthogonality`` ``N_s``, ``sensor_misalignment`` ``R_s``;
  :func:`sensor_matrices`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from .effects import EFFECTS
from .effects.simulation import EffectSpec
from .types import FloatArray
from .units import PPM

_DEG = float(np.pi / 180.0)

#: The simulator's effects, each spelled once, by name: the registry's (their spec from
#: ``Effect.simulation``) and the simulator's own. :class:`Effects`, its validation and
#: ``active()``, and the scenario format (``io/scenario.py``) all read this table.
EFFECT_SPECS: dict[str, EffectSpec] = dict(
    sorted(
        {
            **{
                name: effect.simulation
                for name, effect in EFFECTS.items()
                if effect.simulation is not None
            },
            'non_orthogonality': EffectSpec((4, 3), 'rad', 'angles_deg', _DEG),
            'scale_factor': EffectSpec((4, 3), '1', 'error_ppm', PPM),
            'sensor_misalignment': EffectSpec((4, 3), 'rad', 'rotation_deg', _DEG),
            'time_skew': EffectSpec((4,), 's', 'delay_s'),
        }.items()
    )
)

#: The effects added to the readings through the registry (in :data:`EFFECT_SPECS`' order).
ADDITIVE = tuple(name for name in EFFECT_SPECS if name in EFFECTS)


@dataclass(frozen=True)
class Effects:
    """Physical effects beyond the paper's model, each off (None) or with its magnitude
    (shapes and units in :data:`EFFECT_SPECS`).

    Attributes
    ----------
    eddy_current : (4, 3, 3) seconds
        ``B_i += E_i dB^b/dt`` (body-frame rate of the background field).
    non_orthogonality : (4, 3) rad
        Each sensor's axes out of square, ``(alpha, beta, gamma)``: y tilted towards x by
        ``alpha``, z towards x by ``beta`` and towards y by ``gamma`` (:func:`axes_matrix`).
    scale_factor : (4, 3) dimensionless
        Each axis reads ``1 + s`` times the field along it.
    sensor_misalignment : (4, 3) rad
        Rotation vector of each sensor's axes against the array frame.
    thermal_drift : (4, 3) T/degC
        Offset per degree away from the profile's mean temperature.
    time_skew : (4,) s
        Each sensor's constant delay: its reading stamped ``t`` is the field at ``t - skew``.
    vehicle_current : (4, 3, m) T/A, or (4, 3) for the battery's channel alone
        Field per ampere of each current channel (the battery's first, then each thruster's
        of the scenario's ``CurrentProfile``).
    """

    eddy_current: FloatArray | None = None
    non_orthogonality: FloatArray | None = None
    scale_factor: FloatArray | None = None
    sensor_misalignment: FloatArray | None = None
    thermal_drift: FloatArray | None = None
    time_skew: FloatArray | None = None
    vehicle_current: FloatArray | None = None

    def __post_init__(self) -> None:
        for name, spec in EFFECT_SPECS.items():
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, spec.check(value, name))
        if self.scale_factor is not None and np.any(self.scale_factor <= -1.0):
            raise InputError('scale_factor must be > -1 (an axis reads 1 + s times the field)')
        if self.non_orthogonality is not None:
            sines = np.sin(self.non_orthogonality)
            if np.any(np.abs(self.non_orthogonality) >= np.pi / 4) or np.any(
                sines[:, 1] ** 2 + sines[:, 2] ** 2 >= 0.5
            ):
                raise InputError('non_orthogonality angles must be within 45 deg of square')

    def active(self) -> list[str]:
        """Names of the effects that are switched on."""
        return [name for name in EFFECT_SPECS if getattr(self, name) is not None]


def axes_matrix(angles: np.ndarray) -> FloatArray:
    """The non-orthogonal axes (3, 3) of one sensor, one unit row per axis in the frame of
    its (orthogonal, misaligned) x axis and xy plane, from ``(alpha, beta, gamma)`` rad::

        x = (1, 0, 0)
        y = (sin alpha, cos alpha, 0)
        z = (sin beta, sin gamma, sqrt(1 - sin^2 beta - sin^2 gamma))

    Three angles are every way a triad can be out of square; its orientation is the
    misalignment's."""
    alpha, beta, gamma = np.sin(np.asarray(angles, dtype=float))
    return np.array(
        [
            [1.0, 0.0, 0.0],
            [alpha, np.sqrt(1.0 - alpha**2), 0.0],
            [beta, gamma, np.sqrt(1.0 - beta**2 - gamma**2)],
        ]
    )


def sensor_matrices(effects: Effects) -> FloatArray | None:
    """Each sensor's response (4, 3, 3) ``M_s = S_s N_s R_s`` (reading = ``M_s`` times the
    field at the sensor with its interference), or None when no such effect is on. Only the
    factors that are on are multiplied (the misalignment alone is exactly ``R_s``)."""
    matrix = None
    if effects.sensor_misalignment is not None:
        # A writable copy: scipy's Cython Rotation refuses read-only buffers.
        matrix = Rotation.from_rotvec(np.array(effects.sensor_misalignment)).as_matrix()
    if effects.non_orthogonality is not None:
        axes = np.stack([axes_matrix(angles) for angles in effects.non_orthogonality])
        matrix = axes if matrix is None else axes @ matrix
    if effects.scale_factor is not None:
        scale = 1.0 + np.asarray(effects.scale_factor)
        matrix = (
            np.stack([np.diag(s) for s in scale]) if matrix is None else scale[:, :, None] * matrix
        )
    return matrix
