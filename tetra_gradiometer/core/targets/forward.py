"""What the array measures of a target: the differenced tensor of a point dipole (and of a
uniform background gradient) along a track, and tensors between the body and odom frames.

The tensor's reference point. Eq. 7 is exact for a uniform gradient and otherwise refers
to no single point: ``B_i - B_1`` is, to second order, the derivative along ``r_i - r_1``
at the midpoint of the pair. The package takes the array's centroid as the tensor's point
(:func:`reference_points`, the ``tetra_array`` frame's origin); at distance ``R`` from a
dipole the eq. 7 tensor differs from the gradient there by terms of order ``d/R`` (``d``
the array size: 2.5 % of the tensor at 20 m for a 0.5 m array). The localizer therefore
never compares the measurement with the dipole's gradient at a point: it compares it
with eq. 7 applied to the dipole's field at the four sensors (:func:`array_tensor`), which
is exact at any distance (the finite-size correction is the model itself).
"""

from __future__ import annotations

import numpy as np

from ..fields import MU0_OVER_4PI
from ..geometry import TetraGeometry, to_body
from ..types import FloatArray


def symmetric_components(tensors: FloatArray) -> FloatArray:
    """The five independent components (N, 5) of the symmetric traceless part, scaled so
    their sum of squares is the squared Frobenius norm of that part (xx, yy and zz are not
    independent: an orthonormal basis of the traceless diagonal is used)."""
    sym = 0.5 * (tensors + np.swapaxes(tensors, 1, 2))
    xx, yy, zz = sym[:, 0, 0], sym[:, 1, 1], sym[:, 2, 2]
    root2 = np.sqrt(2.0)
    return np.column_stack(
        [
            (xx - yy) / root2,
            (xx + yy - 2.0 * zz) / np.sqrt(6.0),
            root2 * sym[:, 0, 1],
            root2 * sym[:, 0, 2],
            root2 * sym[:, 1, 2],
        ]
    )


def reference_points(
    positions: FloatArray, rotations: FloatArray, geometry: TetraGeometry
) -> FloatArray:
    """The tensor's point (the array's centroid) in the odom frame, (N, 3) m, from the body
    origin's ``positions`` (N, 3) m and ``rotations`` (N, 3, 3) body -> odom."""
    return positions + rotations @ geometry.centroid


def sensor_points(
    positions: FloatArray, rotations: FloatArray, geometry: TetraGeometry
) -> FloatArray:
    """The four sensors in the odom frame, (N, 4, 3) m."""
    return positions[:, None, :] + np.einsum('nij,sj->nsi', rotations, geometry.positions)


def _unit_moment_tensors(points: FloatArray, source: FloatArray, maps: FloatArray) -> FloatArray:
    """``(B_21 B_31 B_41) maps`` (3, N, 3, 3) for a dipole at ``source`` (3,) m with unit
    moments along the odom axes x, y, z (``out[k]`` for ``e_k``), the fields in the odom frame
    at the sensors ``points`` (N, 4, 3) m; ``maps`` (N or 1, 3, 3): ``a^-1``, or
    ``a^-1 R^T`` for the tensor in the odom frame."""
    r = points - source  # (N, 4, 3)
    distance2 = np.einsum('nsi,nsi->ns', r, r)
    inv3 = distance2**-1.5
    # B_i(r) for m = e_k: mu0/4pi (3 r_k r_i / r^5 - delta_ki / r^3), one (k, i) per sensor:
    # symmetric in k and i.
    fields = (r * (3.0 * inv3 / distance2)[..., None])[..., :, None] * r[..., None, :]
    diagonal = np.arange(3)
    fields[..., diagonal, diagonal] -= inv3[..., None]
    differences = (fields[:, 1:] - fields[:, :1]) * MU0_OVER_4PI  # (N, sensor 2-4, k, i)
    # (N, 9 (k, i), 3 sensors) @ (N, 3 sensors, 3): one small matmul per sample
    out = np.swapaxes(differences.reshape(len(r), 3, 9), 1, 2) @ maps
    return out.reshape(len(r), 3, 3, 3).transpose(1, 0, 2, 3)


def unit_moment_tensors(
    points: FloatArray, rotations: FloatArray, geometry: TetraGeometry, source: FloatArray
) -> FloatArray:
    """Eq. 7 tensors, body frame, of a dipole at ``source`` (3,) m with unit moments along
    the odom axes x, y, z: (3, N, 3, 3) T/m per A m^2. The tensor is linear in the moment,
    so ``np.tensordot(moment, out, 1)`` is the tensor of ``moment``.

    ``points`` (N, 4, 3) are the sensors in the odom frame (:func:`sensor_points`), and
    ``rotations`` (N, 3, 3) the attitudes (body -> odom).
    Raises nothing; a sensor on the source gives inf (the caller keeps sources away).
    """
    # The body-frame differences are R^T (B_i - B_1).
    return np.swapaxes(rotations, 1, 2) @ _unit_moment_tensors(points, source, geometry.a_inv)


def unit_moment_tensors_odom(
    points: FloatArray, rotations: FloatArray, geometry: TetraGeometry, source: FloatArray
) -> FloatArray:
    """:func:`unit_moment_tensors` in the odom frame, ``R G R^T``: (3, N, 3, 3) T/m per
    A m^2. With the body tensor ``R^T dB a^-1`` that is ``dB a^-1 R^T``: one rotation, not
    three (the localizer's inner loop)."""
    return _unit_moment_tensors(points, source, geometry.a_inv @ np.swapaxes(rotations, 1, 2))


def array_tensor(
    positions: FloatArray,
    rotations: FloatArray,
    geometry: TetraGeometry,
    source: FloatArray,
    moment: FloatArray,
    background: FloatArray | None = None,
) -> FloatArray:
    """The eq. 7 tensor (N, 3, 3) T/m, body frame, that the array measures of a point dipole
    at ``source`` (3,) m with ``moment`` (3,) A m^2 (both odom frame), plus a uniform
    ``background`` gradient (3, 3) T/m in the odom frame (exact under differencing), with
    the body origin at ``positions`` (N, 3) m and attitudes ``rotations`` (N, 3, 3)."""
    points = sensor_points(positions, rotations, geometry)
    out = np.tensordot(
        np.asarray(moment, float),
        unit_moment_tensors(points, rotations, geometry, np.asarray(source, float)),
        1,
    )
    if background is not None:
        out += to_body(np.broadcast_to(background, out.shape), rotations)
    return out


def normalized_source_strength(tensors: FloatArray) -> FloatArray:
    """Normalized source strength (N,) T/m of tensors (N, 3, 3): ``sqrt(-l2^2 - l1 l3)`` of
    the symmetric part's eigenvalues ``l1 >= l2 >= l3`` (Beiki et al. 2012). For a point
    dipole it is ``3 mu0/4pi |m| / R^4`` whatever the moment's direction: one smooth peak
    per target along a track, where the Frobenius norm has lobes."""
    eigenvalues = np.linalg.eigvalsh(0.5 * (tensors + np.swapaxes(tensors, 1, 2)))
    l3, l2, l1 = eigenvalues[:, 0], eigenvalues[:, 1], eigenvalues[:, 2]
    return np.sqrt(np.maximum(-(l2**2) - l1 * l3, 0.0))
