"""Tetrahedron geometry and the difference algorithm (Yu et al. 2014, eqs. 4-7).

Convention (eq. 1): ``G[i, j] = dB_i / dx_j``. Sensor 1 (index 0) is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ..errors import GeometryError
from ._validate import as_fields, frozen_array
from .plausibility import check_geometry
from .types import ArrayLike, FloatArray
from .units import S_PER_NS

#: Largest condition number of ``a`` accepted by default. A regular tetrahedron has 2;
#: noise on the tensor grows with cond(a), and past ~1e3 the array is nearly flat.
MAX_CONDITION = 1.0e3


@dataclass(frozen=True)
class TetraGeometry:
    """Positions of the four magnetometers in the body frame.

    Parameters
    ----------
    positions : array_like, shape (4, 3)
        Sensor positions, metres, body frame (x forward, y left, z up); row 0 is sensor 1,
        the reference.
    max_condition : float, optional
        Refuse geometries whose baseline matrix ``a`` has a larger 2-norm condition number.

    Raises
    ------
    GeometryError
        If the positions are (nearly) coplanar (the message names cond(a)), or an edge or a
        coordinate lies outside the physical bounds of :mod:`.plausibility`.
    """

    positions: np.ndarray
    max_condition: float = MAX_CONDITION
    a: np.ndarray = field(init=False, repr=False)
    a_inv: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        positions = frozen_array(self.positions, 'sensor positions', (4, 3))
        check_geometry(positions)
        a = (positions[1:] - positions[0]).T  # eq. 6: columns r_21, r_31, r_41
        condition = np.linalg.cond(a)
        if not np.isfinite(condition) or condition > self.max_condition:
            raise GeometryError(
                f'sensor positions are degenerate: condition number of a (eq. 6) is '
                f'{condition:.3g} > {self.max_condition:.3g}; '
                'the four sensors must not be coplanar'
            )
        a_inv = np.linalg.inv(a)
        a.setflags(write=False)
        a_inv.setflags(write=False)
        object.__setattr__(self, 'positions', positions)
        object.__setattr__(self, 'a', a)
        object.__setattr__(self, 'a_inv', a_inv)

    @classmethod
    def regular(cls, edge: float = 0.5) -> TetraGeometry:
        """Regular tetrahedron of ``edge`` metres, sensor 1 at the origin, base in the x-y
        plane."""
        if not edge > 0:
            raise GeometryError(f'edge must be positive, got {edge}')
        unit = np.array(
            [
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.5, np.sqrt(3) / 2, 0.0],
                [0.5, np.sqrt(3) / 6, np.sqrt(2.0 / 3.0)],
            ]
        )
        return cls(unit * edge)

    @classmethod
    def from_flat(cls, values: npt.ArrayLike) -> TetraGeometry:
        """From the 12-float ``sensor_positions`` parameter (x1 y1 z1 x2 ... z4, metres).

        The one check of ``sensor_positions``: the parameter file reader and the nodes call it
        and only relabel its error.

        Raises
        ------
        GeometryError
            Not 12 numbers, or (nearly) coplanar positions.
        InputError
            A non-finite value (the message names its index).
        """
        try:
            flat = np.asarray(values, dtype=float).ravel()
        except (TypeError, ValueError):
            raise GeometryError(f'sensor_positions must be 12 numbers, got {values!r}') from None
        if flat.size != 12:
            raise GeometryError(
                f'sensor_positions must be 12 finite floats, got {flat.size} values '
                '(4 sensors x 3 = 12 floats, metres)'
            )
        return cls(flat.reshape(4, 3))

    @property
    def condition_number(self) -> float:
        """2-norm condition number of ``a``."""
        return float(np.linalg.cond(self.a))

    @property
    def centroid(self) -> FloatArray:
        """Centre of the four sensors, shape (3,), metres."""
        return self.positions.mean(axis=0)

    def to_flat(self) -> list[float]:
        """The 12-float ``sensor_positions`` list, metres."""
        return [float(v) for v in self.positions.ravel()]


def sensor_differences(fields: np.ndarray) -> FloatArray:
    """``(B_21 B_31 B_41)`` as matrices with those columns (eq. 5).

    Parameters
    ----------
    fields : ndarray, shape (N, 4, 3)
        Sensor fields, tesla.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        ``out[n, :, i-2] = B_i - B_1``, tesla.
    """
    return np.swapaxes(fields[:, 1:, :] - fields[:, :1, :], 1, 2)


def difference_tensor(fields: ArrayLike, geometry: TetraGeometry) -> FloatArray:
    """Gradient tensor by differencing (eq. 7): ``G = (B_21 B_31 B_41) a^-1``.

    Parameters
    ----------
    fields : array_like, shape (N, 4, 3)
        Sensor fields, tesla, body frame.
    geometry : TetraGeometry

    Returns
    -------
    ndarray, shape (N, 3, 3)
        ``G[n, i, j] = dB_i/dx_j``, T/m.
    """
    return sensor_differences(as_fields(fields)) @ geometry.a_inv


def to_world(tensors: FloatArray, rotations: FloatArray) -> FloatArray:
    """Body-frame tensors (N, 3, 3) into the odom frame: ``R G R^T``.

    ``rotations`` (N, 3, 3) rotate body vectors into the odom frame (the ``/odom``
    orientation as a matrix). Units are kept (T/m in, T/m out).
    """
    return np.einsum('nij,njk,nlk->nil', rotations, tensors, rotations)


def to_body(tensors: FloatArray, rotations: FloatArray) -> FloatArray:
    """Odom-frame tensors (N, 3, 3) into the body frame: ``R^T G R`` (inverse of
    :func:`to_world`)."""
    return np.einsum('nji,njk,nkl->nil', rotations, tensors, rotations)


def interp_orientation(
    series_stamps: np.ndarray, quats: np.ndarray, stamps: np.ndarray
) -> np.ndarray:
    """Quaternions ``quats`` (m, 4) at ``series_stamps`` (m,) ns slerped onto ``stamps`` (n,)
    ns, held at the ends: (n, 4)."""
    # scipy.spatial is imported here, not with the module: only the attitude paths need it,
    # and it costs an on-vehicle node that never reads /odom a noticeable start-up.
    from scipy.spatial.transform import Rotation, Slerp

    if len(series_stamps) == 1:
        return np.repeat(quats, len(stamps), axis=0)
    t0 = series_stamps[0]
    slerp = Slerp((series_stamps - t0) * S_PER_NS, Rotation.from_quat(quats))
    clipped = np.clip((stamps - t0) * S_PER_NS, 0.0, (series_stamps[-1] - t0) * S_PER_NS)
    return slerp(clipped).as_quat()
