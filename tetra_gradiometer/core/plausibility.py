"""Plausibility: the one set of physical bounds on inputs, used live (the nodes) and offline
(the bag tools), so a reading the tensor node drops is also dropped by ``calibrate`` and
``compensate``, and a calibration the compensator refuses is also refused on disk.

Readings (:func:`plausible_readings`, :func:`plausible_sets`): every component finite and
every sensor's ``|B|`` at most :data:`MAX_FIELD_T`. An implausible reading is dropped with
its whole set and counted by reason (:class:`DroppedSets`), never fitted. Geometry
(:func:`check_geometry`, called by :class:`~tetra_gradiometer.core.geometry.TetraGeometry`):
every edge within
[:data:`MIN_EDGE_M`, :data:`MAX_EDGE_M`], coordinates within :data:`MAX_COORDINATE_M`.
Calibration parameters (:func:`check_parameters`): finite, ``|k| <=`` :data:`MAX_K`,
``|b| <=`` :data:`MAX_B_T`; their sensor positions finite and within
:data:`POSITION_MATCH_M` of this array's (:func:`check_positions_match`).

Stamp sanity lives where the stamps are read: each sensor's stamps must increase (the
matcher drops and counts the rest) and ``nanosec`` must lie in [0, 1e9) (the bag reader skips
such a message as malformed). Negative and pre-1970 stamps are legal and kept exactly as
integer nanoseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import GeometryError, InputError
from .types import ArrayLike, FloatArray

__all__ = [
    'MAX_B_T',
    'MAX_COORDINATE_M',
    'MAX_EDGE_M',
    'MAX_FIELD_T',
    'MAX_K',
    'MIN_EDGE_M',
    'POSITION_MATCH_M',
    'DroppedSets',
    'check_geometry',
    'check_parameters',
    'check_positions_match',
    'plausible_reading',
    'plausible_readings',
    'plausible_sets',
]

#: Largest plausible magnetometer reading, tesla: the Earth's field is below 7e-5 T and the
#: vehicle's own field at a sensor a few times that; 1e-3 T means a fault (saturation, a
#: corrupt value), and one such reading in a fit can move ``k`` by orders of magnitude.
MAX_FIELD_T = 1.0e-3
#: Edge bounds of the tetrahedron, metres: below 1 cm the difference tensor is all noise,
#: beyond 10 m no vehicle carries it (and the linear-gradient model of eq. 7 fails).
MIN_EDGE_M, MAX_EDGE_M = 0.01, 10.0
#: Largest coordinate of a sensor in the body frame, metres.
MAX_COORDINATE_M = 100.0
#: Largest element of a soft-iron difference matrix ``K_i1`` (dimensionless): beyond 1 the
#: vehicle's induced field would exceed the Earth's field it is induced by.
MAX_K = 1.0
#: Largest element of a hard-iron difference ``B_i1^h``, tesla (1e5 nT, twice the Earth's
#: field): a larger permanent field saturates the sensors' useful range.
MAX_B_T = 1.0e-4
#: A calibration belongs to an array whose sensor positions agree with its own to this, m.
POSITION_MATCH_M = 1.0e-3


@dataclass
class DroppedSets:
    """Sample sets dropped as implausible, by reason (a set counts once, first reason wins).

    Attributes
    ----------
    non_finite : int
        A NaN or inf component in one of the four readings.
    field_magnitude : int
        A finite reading with ``|B| > MAX_FIELD_T``.
    """

    non_finite: int = 0
    field_magnitude: int = 0

    @property
    def total(self) -> int:
        return self.non_finite + self.field_magnitude

    def add(self, other: DroppedSets) -> None:
        """Accumulate ``other`` (chunks of one run)."""
        self.non_finite += other.non_finite
        self.field_magnitude += other.field_magnitude

    def as_dict(self) -> dict[str, int]:
        """For summaries, calibration files and reports."""
        return {
            'sets_dropped_non_finite': self.non_finite,
            'sets_dropped_field_magnitude': self.field_magnitude,
        }

    def text(self) -> str:
        """``'none'`` or e.g. ``'3 non-finite, 10 with |B| > 1e-3 T'``."""
        parts = []
        if self.non_finite:
            parts.append(f'{self.non_finite} non-finite')
        if self.field_magnitude:
            parts.append(f'{self.field_magnitude} with |B| > {MAX_FIELD_T:g} T')
        return ', '.join(parts) or 'none'


def _reading_checks(array: np.ndarray, max_field_t: float) -> tuple[np.ndarray, np.ndarray]:
    """Per reading (shape ``array.shape[:-1]``): all components finite; and finite with
    ``|B| <= min(max_field_t, MAX_FIELD_T)``."""
    finite_components = np.isfinite(array)
    finite = finite_components.all(axis=-1)
    # Non-finite components become 0 so the magnitude test sees only the finite readings.
    magnitude = np.linalg.norm(np.where(finite_components, array, 0.0), axis=-1)
    return finite, finite & (magnitude <= min(max_field_t, MAX_FIELD_T))


def plausible_readings(fields: ArrayLike, max_field_t: float = MAX_FIELD_T) -> np.ndarray:
    """Per reading: every component finite and ``|B| <= max_field_t``.

    Parameters
    ----------
    fields : array_like, shape (..., 3)
        Readings, tesla (e.g. (N, 4, 3) sets, (4, 3) one set).
    max_field_t : float
        Bound on ``|B|``, tesla; at most :data:`MAX_FIELD_T` (a node may be stricter).

    Returns
    -------
    ndarray of bool, shape (...)
    """
    return _reading_checks(np.asarray(fields, dtype=float), max_field_t)[1]


def plausible_reading(x: float, y: float, z: float, max_field_t: float = MAX_FIELD_T) -> bool:
    """:func:`plausible_readings` of one reading given as three floats (tesla), in Python
    scalars: the live path (one message at a time), where numpy's per-call overhead is most of
    the cost. Same rule, same result."""
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    return math.sqrt(x * x + y * y + z * z) <= min(max_field_t, MAX_FIELD_T)


def plausible_sets(fields: ArrayLike) -> tuple[np.ndarray, DroppedSets]:
    """Which sets to keep (all four readings plausible), and the others' count by reason.

    Parameters
    ----------
    fields : array_like, shape (N, 4, 3)
        Sensor fields, tesla.

    Returns
    -------
    keep : ndarray of bool, shape (N,)
    dropped : DroppedSets
    """
    finite, plausible = _reading_checks(np.asarray(fields, dtype=float), MAX_FIELD_T)
    keep, finite_set = plausible.all(axis=-1), finite.all(axis=-1)
    dropped = DroppedSets(
        non_finite=int(np.sum(~finite_set)),
        field_magnitude=int(np.sum(finite_set & ~keep)),
    )
    return np.asarray(keep), dropped


def check_geometry(positions: FloatArray) -> None:
    """Raise :class:`GeometryError` unless every edge of the tetrahedron ``positions``
    (4, 3) m lies in [MIN_EDGE_M, MAX_EDGE_M] and every coordinate within MAX_COORDINATE_M."""
    far = float(np.abs(positions).max())
    if far > MAX_COORDINATE_M:
        raise GeometryError(
            f'sensor positions reach {far:.3g} m from the body origin; a sensor must lie '
            f'within {MAX_COORDINATE_M:g} m of it'
        )
    for i in range(4):
        for j in range(i + 1, 4):
            edge = float(np.linalg.norm(positions[j] - positions[i]))
            if not MIN_EDGE_M <= edge <= MAX_EDGE_M:
                raise GeometryError(
                    f'sensors {i + 1} and {j + 1} are {edge:.3g} m apart; every edge must lie '
                    f'within {MIN_EDGE_M:g} to {MAX_EDGE_M:g} m (positions are in metres)'
                )


def check_parameters(k_soft: ArrayLike, b_hard: ArrayLike, source: str = 'calibration') -> None:
    """Raise :class:`InputError` naming the first element of ``k_soft`` (3, 3, 3) or
    ``b_hard`` (3, 3) T that is not finite or exceeds :data:`MAX_K` / :data:`MAX_B_T`."""
    for name, value, bound, unit in (
        ('k_soft', k_soft, MAX_K, ''),
        ('b_hard', b_hard, MAX_B_T, ' T'),
    ):
        array = np.asarray(value, dtype=float)
        bad = ~np.isfinite(array) | (np.abs(np.nan_to_num(array, nan=np.inf)) > bound)
        if bad.any():
            index = tuple(int(i) for i in np.argwhere(bad)[0])
            raise InputError(
                f'{source}: {name}{list(index)} = {array[index]:.6g}{unit} is implausible '
                f'(every element must be finite with |{name}| <= {bound:g}{unit})'
            )


def check_positions_match(
    sensor_positions: ArrayLike,
    positions: FloatArray,
    *,
    source: str = 'calibration',
    target: str = 'this array',
) -> None:
    """Raise :class:`InputError` unless ``sensor_positions`` (12 floats, m) are finite and
    agree with ``positions`` (4, 3) m to :data:`POSITION_MATCH_M`."""
    flat = np.asarray(sensor_positions, dtype=float).ravel()
    if flat.shape != (12,):
        raise InputError(f'{source}: sensor_positions must hold 12 floats, got {flat.size}')
    if not np.all(np.isfinite(flat)):
        index = int(np.argwhere(~np.isfinite(flat))[0][0])
        raise InputError(f'{source}: sensor_positions[{index}] = {flat[index]} is not finite')
    offset = float(np.abs(flat - np.asarray(positions, dtype=float).ravel()).max())
    if offset > POSITION_MATCH_M:
        raise InputError(
            f'{source} was made for other sensor positions than {target} '
            f'(they differ by up to {offset:.3g} m; at most {POSITION_MATCH_M:g} m allowed)'
        )
