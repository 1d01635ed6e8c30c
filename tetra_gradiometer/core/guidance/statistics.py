"""Trim samples reduced to what the guidance needs: sufficient statistics and coverage.

The known-gradient solve (:func:`~..identification.known_gradient_lstsq`, whitened GLS) sees
its data only through the 4x4 Gram matrix of ``x_n = (B_1', 1)``, the 4x9 products of ``x_n``
with the whitened targets and their sum of squares (``identification._linear.reduce_affine``).
:class:`TrimStatistics` holds exactly these plus attitude coverage counts: O(1) memory, and
adding or removing samples is a sum (the calibrator node accumulates them while it collects).

Headings are compass headings (degrees clockwise from north; the simulator's yaw is
counter-clockwise from east: ``yaw = 90° - heading``). Coverage is counted in heading x roll x
pitch bins when the attitude is known (``/odom``); without it only the direction of ``B_1'``
in the body frame is known (azimuth x elevation bins), and :class:`Coverage` says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .._validate import as_array, as_tensors, as_vectors, same_length
from ..geometry import TetraGeometry
from ..identification.lstsq import noise_whitener
from ..types import ArrayLike, FloatArray, IntArray

__all__ = [
    'AZIMUTH_EDGES_DEG',
    'ELEVATION_EDGES_DEG',
    'HEADING_EDGES_DEG',
    'REGRESSOR_UNIT',
    'TILT_EDGES_DEG',
    'Coverage',
    'TrimStatistics',
    'attitude_rotation',
    'body_fields',
    'coverage_condition',
    'coverage_of',
    'heading_roll_pitch',
    'trim_statistics',
]

#: Coverage bins: compass heading, degrees ...
HEADING_EDGES_DEG = tuple(float(h) for h in range(0, 361, 30))
#: ... roll and pitch, degrees ...
TILT_EDGES_DEG = (-180.0, -15.0, -5.0, 5.0, 15.0, 180.0)
#: ... and, without attitude, the body-frame field direction: azimuth and elevation, degrees.
AZIMUTH_EDGES_DEG = tuple(float(a) for a in range(-180, 181, 30))
ELEVATION_EDGES_DEG = tuple(float(e) for e in range(-90, 91, 30))

#: ``B_1'`` enters the accumulated Gram matrix in this unit, T (its entries then ~1) ...
FIELD_UNIT_T = 5.0e-5
#: ... so the regressors accumulated are ``(B_1', 1) / REGRESSOR_UNIT``.
REGRESSOR_UNIT = np.array([FIELD_UNIT_T, FIELD_UNIT_T, FIELD_UNIT_T, 1.0])

# --------------------------------------------------------------------------- attitude


def attitude_rotation(
    heading_deg: ArrayLike, roll_deg: ArrayLike, pitch_deg: ArrayLike
) -> Rotation:
    """Body -> ENU rotation of compass headings, rolls and pitches (degrees, broadcast)."""
    h, r, p = np.broadcast_arrays(
        np.asarray(heading_deg, float), np.asarray(roll_deg, float), np.asarray(pitch_deg, float)
    )
    euler = np.column_stack([90.0 - h.ravel(), p.ravel(), r.ravel()])
    return Rotation.from_euler('ZYX', euler, degrees=True)


def heading_roll_pitch(orientation_xyzw: ArrayLike) -> FloatArray:
    """Compass heading in [0, 360), roll and pitch, degrees, shape (N, 3), from quaternions
    (N, 4) x, y, z, w rotating body vectors into ENU (``/odom``, the simulator)."""
    q = as_array(orientation_xyzw, 'orientation_xyzw', (None, 4))
    if not len(q):
        return np.zeros((0, 3))
    yaw, pitch, roll = Rotation.from_quat(q).as_euler('ZYX', degrees=True).T
    return np.column_stack([np.mod(90.0 - yaw, 360.0), roll, pitch])


def body_fields(rotation: Rotation, earth_field_enu: FloatArray) -> FloatArray:
    """The Earth field in the body frame, (N, 3) T: ``R^T B``."""
    return rotation.inv().apply(earth_field_enu).reshape(-1, 3)


# --------------------------------------------------------------------------- statistics


@dataclass(frozen=True)
class TrimStatistics:
    """What the known-gradient solve and the coverage need of a set of trim samples.

    Attributes
    ----------
    n : int
        Samples.
    gram : ndarray, shape (4, 4)
        ``sum x x^T`` with ``x = (B_1' / 5e-5 T, 1)``.
    cross : ndarray, shape (4, 9)
        ``sum x (t - reference)^T``, ``t`` the whitened target ``G_m @ W`` (9,), T/m.
    sum_sq : float
        ``sum |t - reference|^2``, (T/m)^2.
    reference : ndarray, shape (9,)
        Subtracted from every target (the first sample's): the offsets absorb a constant
        exactly, and the sums stay small against the residual they must resolve.
    attitude_counts : ndarray, shape (12, 5, 5), int
        Samples per heading x roll x pitch bin (``HEADING_EDGES_DEG``, ``TILT_EDGES_DEG``);
        samples without attitude are not counted here.
    direction_counts : ndarray, shape (12, 6), int
        Samples per azimuth x elevation bin of ``B_1'`` in the body frame.
    """

    n: int
    gram: FloatArray
    cross: FloatArray
    sum_sq: float
    reference: FloatArray
    attitude_counts: IntArray
    direction_counts: IntArray

    @classmethod
    def empty(cls) -> TrimStatistics:
        """No samples."""
        return cls(
            0,
            np.zeros((4, 4)),
            np.zeros((4, 9)),
            0.0,
            np.zeros(9),
            np.zeros((len(HEADING_EDGES_DEG) - 1, 5, 5), dtype=np.int64),
            np.zeros((len(AZIMUTH_EDGES_DEG) - 1, len(ELEVATION_EDGES_DEG) - 1), dtype=np.int64),
        )

    def _aligned(self, reference: FloatArray) -> TrimStatistics:
        """The same samples with targets taken relative to ``reference`` (exact)."""
        delta = self.reference - reference  # t - reference = (t - self.reference) + delta
        cross = self.cross + np.outer(self.gram[:, 3], delta)  # gram[:, 3] = sum x
        sum_sq = self.sum_sq + 2.0 * float(self.cross[3] @ delta) + self.n * float(delta @ delta)
        return TrimStatistics(
            self.n,
            self.gram,
            cross,
            sum_sq,
            reference,
            self.attitude_counts,
            self.direction_counts,
        )

    def plus(self, other: TrimStatistics) -> TrimStatistics:
        """These samples and ``other``'s."""
        if self.n == 0:
            return other
        o = other._aligned(self.reference)
        return TrimStatistics(
            self.n + o.n,
            self.gram + o.gram,
            self.cross + o.cross,
            self.sum_sq + o.sum_sq,
            self.reference,
            self.attitude_counts + o.attitude_counts,
            self.direction_counts + o.direction_counts,
        )

    def minus(self, other: TrimStatistics) -> TrimStatistics:
        """These samples without ``other``'s (which must be among them)."""
        if other.n >= self.n:
            return TrimStatistics.empty()
        o = other._aligned(self.reference)
        return TrimStatistics(
            self.n - o.n,
            self.gram - o.gram,
            self.cross - o.cross,
            max(self.sum_sq - o.sum_sq, 0.0),
            self.reference,
            np.maximum(self.attitude_counts - o.attitude_counts, 0),
            np.maximum(self.direction_counts - o.direction_counts, 0),
        )


def _attitude_counts(orientation_xyzw: FloatArray | None, n: int) -> IntArray:
    counts = TrimStatistics.empty().attitude_counts.copy()
    if orientation_xyzw is None:
        return counts
    q = np.asarray(orientation_xyzw, dtype=float).reshape(n, 4)
    known = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0)
    angles = heading_roll_pitch(q[known])
    h = np.clip(np.digitize(angles[:, 0], HEADING_EDGES_DEG) - 1, 0, counts.shape[0] - 1)
    r, p = (np.clip(np.digitize(a, TILT_EDGES_DEG) - 1, 0, 4) for a in angles[:, 1:].T)
    np.add.at(counts, (h, r, p), 1)
    return counts


def _direction_counts(b_reference: FloatArray) -> IntArray:
    counts = TrimStatistics.empty().direction_counts.copy()
    norm = np.linalg.norm(b_reference, axis=1)
    ok = norm > 0
    b = b_reference[ok] / norm[ok, None]
    azimuth = np.degrees(np.arctan2(b[:, 1], b[:, 0]))
    elevation = np.degrees(np.arcsin(np.clip(b[:, 2], -1.0, 1.0)))
    a = np.clip(np.digitize(azimuth, AZIMUTH_EDGES_DEG) - 1, 0, counts.shape[0] - 1)
    e = np.clip(np.digitize(elevation, ELEVATION_EDGES_DEG) - 1, 0, counts.shape[1] - 1)
    np.add.at(counts, (a, e), 1)
    return counts


def trim_statistics(
    b_reference: ArrayLike,
    g_measured: ArrayLike,
    geometry: TetraGeometry,
    *,
    orientation_xyzw: ArrayLike | None = None,
    reference: ArrayLike | None = None,
) -> TrimStatistics:
    """The :class:`TrimStatistics` of trim samples (true gradient taken as zero).

    Parameters
    ----------
    b_reference : array_like, shape (N, 3)
        ``B_1'``, tesla, body frame.
    g_measured : array_like, shape (N, 3, 3)
        ``G_m``, T/m.
    geometry : TetraGeometry
        The array (statistics of different arrays must not be combined).
    orientation_xyzw : array_like, shape (N, 4), optional
        Body -> ENU quaternions; rows with a NaN count as "attitude unknown".
    reference : array_like, shape (9,), optional
        Whitened target subtracted from all (default the first sample's); give the
        accumulator's own when adding to or removing from it.
    """
    b = as_vectors(b_reference, 'b_reference')
    g = as_tensors(g_measured, 'g_measured')
    n = same_length(b_reference=b, g_measured=g)
    if n == 0:
        return TrimStatistics.empty()
    targets = (g @ noise_whitener(geometry)).reshape(n, 9)
    ref = targets[0].copy() if reference is None else as_array(reference, 'reference', (9,))
    shifted = targets - ref
    x = np.column_stack([b, np.ones(n)]) / REGRESSOR_UNIT
    q = None if orientation_xyzw is None else np.asarray(orientation_xyzw, dtype=float)
    return TrimStatistics(
        n=n,
        gram=x.T @ x,
        cross=x.T @ shifted,
        sum_sq=float(np.sum(shifted**2)),
        reference=ref,
        attitude_counts=_attitude_counts(q, n),
        direction_counts=_direction_counts(b),
    )


def coverage_condition(statistics: TrimStatistics) -> float:
    """:func:`~.identification.attitude_coverage` from the Gram matrix: the condition number
    of ``[B_1' 1]`` with unit-norm columns (inf without samples or with a zero column)."""
    diagonal = np.diag(statistics.gram)
    if statistics.n == 0 or np.any(diagonal <= 0.0):
        return float('inf')
    normalized = statistics.gram / np.sqrt(np.outer(diagonal, diagonal))
    w = np.linalg.eigvalsh(normalized)
    return float('inf') if w[0] <= 0.0 else float(np.sqrt(w[-1] / w[0]))


# --------------------------------------------------------------------------- coverage


@dataclass(frozen=True)
class Coverage:
    """Which attitudes the samples cover.

    Attributes
    ----------
    source : str
        'attitude' (heading x roll x pitch from ``/odom``) or 'field direction' (no
        attitude: azimuth x elevation of ``B_1'`` in the body frame).
    counts : ndarray, int
        (12, 5, 5) samples per heading x roll x pitch bin, or (12, 6) per azimuth x
        elevation bin.
    edges_deg : tuple of tuples
        The bin edges of each axis, degrees.
    """

    source: str
    counts: IntArray
    edges_deg: tuple[tuple[float, ...], ...]

    @property
    def text(self) -> str:
        """One line, e.g. 'heading 7/12 sectors of 30°, roll -15…15°, pitch -5…5°'."""
        if self.source == 'field direction':
            seen = int(np.count_nonzero(self.counts))
            return (
                f'no attitude (no /odom): body-frame field directions cover {seen}/'
                f'{self.counts.size} bins of 30°x30°'
            )
        if not self.counts.any():
            return 'no samples'
        headings = int(np.count_nonzero(self.counts.sum(axis=(1, 2))))
        roll = _span(self.counts.sum(axis=(0, 2)))
        pitch = _span(self.counts.sum(axis=(0, 1)))
        return f'heading {headings}/12 sectors of 30°, roll {roll}, pitch {pitch}'

    def to_dict(self) -> dict[str, Any]:
        """Plain types for JSON: the source, the text, the axes, edges (deg) and counts."""
        axes = (
            ('heading', 'roll', 'pitch') if self.source == 'attitude' else ('azimuth', 'elevation')
        )
        return {
            'source': self.source,
            'text': self.text,
            'axes': list(axes),
            'edges_deg': [list(e) for e in self.edges_deg],
            'counts': self.counts.tolist(),
        }


def _span(counts: IntArray) -> str:
    """The tilt range of the occupied bins, e.g. '-15…15°' ('< -15' for the open ends)."""
    occupied = np.flatnonzero(counts)
    if not len(occupied):
        return 'none'
    lo, hi = TILT_EDGES_DEG[occupied[0]], TILT_EDGES_DEG[occupied[-1] + 1]
    low = f'< {TILT_EDGES_DEG[1]:g}' if lo == TILT_EDGES_DEG[0] else f'{lo:g}'
    high = f'> {TILT_EDGES_DEG[-2]:g}' if hi == TILT_EDGES_DEG[-1] else f'{hi:g}'
    return f'{low}…{high}°'


def coverage_of(statistics: TrimStatistics) -> Coverage:
    """By attitude when any sample had one, else by the body-frame field direction."""
    if statistics.attitude_counts.any():
        return Coverage(
            'attitude',
            statistics.attitude_counts,
            (HEADING_EDGES_DEG, TILT_EDGES_DEG, TILT_EDGES_DEG),
        )
    return Coverage(
        'field direction', statistics.direction_counts, (AZIMUTH_EDGES_DEG, ELEVATION_EDGES_DEG)
    )
