"""Fit a point dipole (position, moment, odom frame) plus a uniform background gradient per
pass to the tensor samples of one or more passes.

The model (:mod:`.forward`): eq. 7 applied to the dipole's field at the four sensors, so
exact at any range, plus a symmetric traceless background per pass (the regional gradient
and what the compensation left, constant along a straight pass). The residual is taken in
the odom frame on the five components of the symmetric traceless part, whitened by their
``sigma`` (:func:`.detection.detect`).

The tensor is linear in the moment and the backgrounds, so the fit is over the position
only (variable projection, Golub & Pereyra): for a trial position the linear parameters
are the least-squares solution. Initial position: the best of a grid of trial positions
around the pass's peak (distances 1.5 m .. 150 m, directions on a Fibonacci sphere: a
closed-form single-point estimate such as Euler deconvolution needs the anomaly's field,
which the array only has through the reference sensor and its interference). Then
``scipy.optimize.least_squares`` refines the position, and the covariance of all
parameters is ``s^2 (J^T J)^-1`` with ``J`` the whitened Jacobian at the solution and
``s^2`` the reduced chi-square (the residual's own scale).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ...errors import InputError
from ..geometry import TetraGeometry, to_world
from ..identification.lstsq import REGIONAL_BASIS
from ..types import FloatArray
from .forward import sensor_points, symmetric_components, unit_moment_tensors

#: Trial distances (m) of the initial grid, geometric.
GRID_DISTANCES_M = np.geomspace(1.5, 150.0, 12)
#: Trial directions of the initial grid.
GRID_DIRECTIONS = 64
#: At most this many samples per pass in the grid search (every k-th sample).
GRID_SAMPLES = 60


@dataclass(frozen=True)
class Pass:
    """Tensor samples of one pass: body origin ``positions`` (n, 3) m, ``rotations``
    (n, 3, 3) body -> odom, body-frame ``tensors`` (n, 3, 3) T/m, times ``t_s`` (n,) s."""

    positions: FloatArray
    rotations: FloatArray
    tensors: FloatArray
    t_s: FloatArray

    def thinned(self, at_most: int) -> Pass:
        step = max(1, len(self.t_s) // at_most)
        return Pass(
            self.positions[::step], self.rotations[::step], self.tensors[::step], self.t_s[::step]
        )


@dataclass(frozen=True)
class DipoleFit:
    """A fitted dipole: ``position`` (3,) m and ``moment`` (3,) A m^2 in the odom frame,
    their covariance ``covariance`` (6, 6) (position first; m^2, m A m^2, (A m^2)^2),
    the per-pass ``backgrounds`` (P, 3, 3) T/m, the RMS residual ``rms`` T/m (over the five
    symmetric traceless components, per component), the reduced chi-square, the misfit
    fraction (residual over signal, root of the sums of squares), and the number of
    samples."""

    position: FloatArray
    moment: FloatArray
    covariance: FloatArray
    backgrounds: FloatArray
    rms: float
    chi2_reduced: float
    misfit_fraction: float
    n_samples: int

    @property
    def position_sigma(self) -> FloatArray:
        return np.sqrt(np.diag(self.covariance)[:3])

    @property
    def moment_sigma(self) -> FloatArray:
        return np.sqrt(np.diag(self.covariance)[3:6])


class _Problem:
    """The whitened data and the linear design for trial positions."""

    def __init__(self, passes: list[Pass], geometry: TetraGeometry, sigma: FloatArray) -> None:
        self.passes = passes
        self.geometry = geometry
        self.weights = 1.0 / np.asarray(sigma, float)
        self.points = [sensor_points(p.positions, p.rotations, geometry) for p in passes]
        self.data = np.concatenate(
            [
                (symmetric_components(to_world(p.tensors, p.rotations)) * self.weights).ravel()
                for p in passes
            ]
        )
        # Background columns: constant per pass in the whitened five-component space.
        basis = symmetric_components(REGIONAL_BASIS) * self.weights  # (5 basis, 5 comps)
        blocks = []
        for i, p in enumerate(passes):
            block = np.zeros((len(p.t_s), 5, 5 * len(passes)))
            block[:, :, 5 * i : 5 * i + 5] = basis.T[None]
            blocks.append(block.reshape(-1, 5 * len(passes)))
        self.background_columns = np.concatenate(blocks)

    def moment_columns(self, source: FloatArray) -> FloatArray:
        columns = []
        for p, points in zip(self.passes, self.points, strict=True):
            unit = unit_moment_tensors(points, p.rotations, self.geometry, source)  # (3, n, 3, 3)
            world = np.stack([symmetric_components(to_world(u, p.rotations)) for u in unit])
            columns.append((world * self.weights).reshape(3, -1).T)
        return np.concatenate(columns)

    def design(self, source: FloatArray) -> FloatArray:
        return np.hstack([self.moment_columns(source), self.background_columns])

    def solve(self, source: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Linear parameters and whitened residual at a trial source position."""
        design = self.design(source)
        # Columns scaled to unit norm: moment columns (per A m^2) and background columns
        # (per T/m) differ by ~15 orders of magnitude, which lstsq's rcond would truncate.
        scale = np.linalg.norm(design, axis=0)
        scale[scale == 0.0] = 1.0
        scaled, *_ = np.linalg.lstsq(design / scale, self.data, rcond=None)
        linear = scaled / scale
        return linear, self.data - design @ linear


def _fibonacci_sphere(n: int) -> FloatArray:
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]
    )


def _too_close(source: FloatArray, problem: _Problem, clearance: float = 1.0) -> bool:
    return any(
        np.min(np.linalg.norm(points - source, axis=2)) < clearance for points in problem.points
    )


def initial_position(
    passes: list[Pass], geometry: TetraGeometry, sigma: FloatArray, center: FloatArray
) -> FloatArray:
    """The best trial position of the grid around ``center`` (3,) m (see the module
    docstring), each trial scored by the residual of its linear solve."""
    problem = _Problem([p.thinned(GRID_SAMPLES) for p in passes], geometry, sigma)
    best, best_cost = center, np.inf
    for direction in _fibonacci_sphere(GRID_DIRECTIONS):
        for distance in GRID_DISTANCES_M:
            source = center + distance * direction
            if _too_close(source, problem):
                continue
            _, residual = problem.solve(source)
            cost = float(residual @ residual)
            if cost < best_cost:
                best, best_cost = source, cost
    return best


def fit_dipole(
    passes: list[Pass],
    geometry: TetraGeometry,
    sigma: FloatArray,
    initial: FloatArray | None = None,
) -> DipoleFit:
    """Fit one dipole to ``passes`` (each with its own background), whitened by ``sigma``
    (5,) T/m (the symmetric traceless components' 1-sigma). ``initial`` (3,) m: a start
    position; None: the grid around the strongest sample's tensor point.

    Raises
    ------
    InputError
        Fewer samples than parameters.
    """
    problem = _Problem(passes, geometry, sigma)
    n_linear = 3 + 5 * len(passes)
    if len(problem.data) <= n_linear + 3:
        raise InputError(
            f'a dipole fit needs more than {n_linear + 3} values, got {len(problem.data)}'
        )
    if initial is None:
        initial = initial_position(passes, geometry, sigma, _strongest_point(passes, geometry))
    solution = optimize.least_squares(
        lambda s: problem.solve(s)[1], initial, x_scale='jac', method='lm'
    )
    source = solution.x
    linear, residual = problem.solve(source)
    covariance = _covariance(problem, source, linear, len(residual))
    signal = problem.data - problem.background_columns @ linear[3:]
    dof = max(len(residual) - (n_linear + 3), 1)
    chi2 = float(residual @ residual) / dof
    unwhitened = (residual.reshape(-1, 5) / problem.weights).ravel()
    backgrounds = np.einsum('pb,bij->pij', linear[3:].reshape(-1, 5), REGIONAL_BASIS)
    return DipoleFit(
        source,
        linear[:3],
        covariance,
        backgrounds,
        float(np.sqrt(np.mean(unwhitened**2))),
        chi2,
        float(np.sqrt(float(residual @ residual) / max(float(signal @ signal), 1e-300))),
        int(sum(len(p.t_s) for p in passes)),
    )


def _strongest_point(passes: list[Pass], geometry: TetraGeometry) -> FloatArray:
    best, best_norm = passes[0].positions[0], -1.0
    for p in passes:
        world = symmetric_components(to_world(p.tensors, p.rotations))
        anomaly = np.linalg.norm(world - np.median(world, axis=0), axis=1)
        i = int(np.argmax(anomaly))
        if anomaly[i] > best_norm:
            best_norm = float(anomaly[i])
            best = p.positions[i] + p.rotations[i] @ geometry.centroid
    return best


def _covariance(problem: _Problem, source: FloatArray, linear: FloatArray, n: int) -> FloatArray:
    """Covariance (6, 6) of position and moment: ``s^2 (J^T J)^-1`` over all parameters."""
    step = 1e-4 * max(
        1.0, float(np.min([np.min(np.linalg.norm(p - source, axis=2)) for p in problem.points]))
    )
    design = problem.design(source)
    model = design @ linear
    position_columns = []
    for k in range(3):
        shifted = source.copy()
        shifted[k] += step
        back = source.copy()
        back[k] -= step
        position_columns.append(
            (problem.design(shifted) @ linear - problem.design(back) @ linear) / (2 * step)
        )
    jacobian = np.column_stack([*position_columns, design])
    residual = problem.data - model
    dof = max(n - jacobian.shape[1], 1)
    scale = float(residual @ residual) / dof
    norms = np.linalg.norm(jacobian, axis=0)
    norms[norms == 0.0] = 1.0
    normalized = jacobian / norms
    full = scale * np.linalg.pinv(normalized.T @ normalized) / np.outer(norms, norms)
    return full[:6, :6]
