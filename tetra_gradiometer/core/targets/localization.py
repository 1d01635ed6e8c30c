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
import scipy  # submodules load on first use: see core/__init__.py

from ...errors import InputError
from ..geometry import TetraGeometry, to_world
from ..identification.lstsq import REGIONAL_BASIS
from ..types import FloatArray
from .forward import sensor_points, symmetric_components, unit_moment_tensors_odom

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
        self._background_basis = basis.T
        self._columns: dict[bytes, FloatArray] = {}
        self._data_demeaned = self._demeaned(self.data[:, None])[:, 0]

    def _demeaned(self, columns: FloatArray) -> FloatArray:
        """``columns`` (rows, c) less their mean per pass and component: the projection
        off the background columns (the basis spans all five components, so a background
        per pass is any constant five-vector)."""
        out = []
        start = 0
        for p in self.passes:
            block = columns[start : start + 5 * len(p.t_s)].reshape(len(p.t_s), 5, -1)
            out.append((block - block.mean(axis=0)).reshape(5 * len(p.t_s), -1))
            start += 5 * len(p.t_s)
        return np.concatenate(out)

    def moment_columns(self, source: FloatArray) -> FloatArray:
        columns = []
        for p, points in zip(self.passes, self.points, strict=True):
            unit = unit_moment_tensors_odom(points, p.rotations, self.geometry, source)
            world = symmetric_components(unit.reshape(-1, 3, 3)).reshape(3, len(points), 5)
            columns.append((world * self.weights).reshape(3, -1).T)
        return np.concatenate(columns)

    def moments_design(self, sources: FloatArray) -> FloatArray:
        """Whitened moment columns (rows, 3K) of each source (``sources`` (3K,) or (K, 3)
        m), in order."""
        positions = np.reshape(np.asarray(sources, float), (-1, 3))
        per_source = []
        for source in positions:
            # A finite-difference Jacobian moves one source at a time: the others' columns
            # are those of the last calls.
            key = source.tobytes()
            if key not in self._columns:
                self._columns[key] = self.moment_columns(source)
            per_source.append(self._columns[key])
        while len(self._columns) > 4 * len(positions) + 4:
            del self._columns[next(iter(self._columns))]
        return np.hstack(per_source)

    def design(self, sources: FloatArray) -> FloatArray:
        """Whitened columns: the moments of each source, then the backgrounds."""
        return np.hstack([self.moments_design(sources), self.background_columns])

    def solve(self, sources: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Linear parameters (moments, then backgrounds) and whitened residual at trial
        source positions (3K,) m. The backgrounds are projected out first (variable
        projection twice over): the solve is over the 3K moments only."""
        moments = self.moments_design(sources)
        demeaned = self._demeaned(moments)
        # Columns scaled to unit norm (per A m^2 they are ~1e-10), which lstsq's rcond
        # would otherwise truncate.
        scale = np.linalg.norm(demeaned, axis=0)
        scale[scale == 0.0] = 1.0
        scaled, *_ = np.linalg.lstsq(demeaned / scale, self._data_demeaned, rcond=None)
        moment = scaled / scale
        residual = self._data_demeaned - demeaned @ moment
        means = (self.data - moments @ moment) - residual  # per pass: its background
        backgrounds = []
        start = 0
        for p in self.passes:
            backgrounds.append(np.linalg.solve(self._background_basis, means[start : start + 5]))
            start += 5 * len(p.t_s)
        return np.concatenate([moment, *backgrounds]), residual


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
    if initial is None:
        initial = initial_position(passes, geometry, sigma, _strongest_point(passes, geometry))
    return fit_dipoles(passes, geometry, sigma, [initial])[0]


def fit_dipoles(
    passes: list[Pass],
    geometry: TetraGeometry,
    sigma: FloatArray,
    initials: list[FloatArray],
) -> list[DipoleFit]:
    """Fit K dipoles together (a cluster whose tensors overlap) to ``passes``, from the
    start positions ``initials`` (K of (3,) m). Each fit carries its own block of the joint
    covariance; the residual statistics (``rms``, ``chi2_reduced``, ``misfit_fraction``)
    and the backgrounds are the cluster's.

    Raises
    ------
    InputError
        Fewer samples than parameters.
    """
    problem = _Problem(passes, geometry, sigma)
    count = len(initials)
    n_linear = 3 * count + 5 * len(passes)
    if len(problem.data) <= n_linear + 3 * count:
        raise InputError(
            f'a fit of {count} dipole(s) needs more than {n_linear + 3 * count} values, '
            f'got {len(problem.data)}'
        )
    solution = scipy.optimize.least_squares(
        lambda s: problem.solve(s)[1], np.concatenate(initials), x_scale='jac', method='lm'
    )
    sources = solution.x.reshape(count, 3)
    linear, residual = problem.solve(sources)
    covariance = _covariance(problem, sources, linear, len(residual))
    signal = problem.data - problem.background_columns @ linear[3 * count :]
    dof = max(len(residual) - (n_linear + 3 * count), 1)
    chi2 = float(residual @ residual) / dof
    unwhitened = (residual.reshape(-1, 5) / problem.weights).ravel()
    backgrounds = np.einsum('pb,bij->pij', linear[3 * count :].reshape(-1, 5), REGIONAL_BASIS)
    rms = float(np.sqrt(np.mean(unwhitened**2)))
    misfit = float(np.sqrt(float(residual @ residual) / max(float(signal @ signal), 1e-300)))
    n_samples = int(sum(len(p.t_s) for p in passes))
    return [
        DipoleFit(
            sources[k],
            linear[3 * k : 3 * k + 3],
            covariance[k],
            backgrounds,
            rms,
            chi2,
            misfit,
            n_samples,
        )
        for k in range(count)
    ]


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


def _covariance(
    problem: _Problem, sources: FloatArray, linear: FloatArray, n: int
) -> list[FloatArray]:
    """Per source, the covariance (6, 6) of its position and moment: the blocks of
    ``s^2 (J^T J)^-1`` over all parameters (positions, moments, backgrounds)."""
    count = len(sources)
    closest = min(np.min(np.linalg.norm(p[:, :, None] - sources, axis=3)) for p in problem.points)
    step = 1e-4 * max(1.0, float(closest))
    design = problem.design(sources)
    model = design @ linear
    position_columns = []
    for k in range(3 * count):
        shifted = sources.ravel().copy()
        shifted[k] += step
        back = sources.ravel().copy()
        back[k] -= step
        moments = linear[: 3 * count]  # the backgrounds do not move with a source
        position_columns.append(
            (problem.moments_design(shifted) - problem.moments_design(back)) @ moments / (2 * step)
        )
    jacobian = np.column_stack([*position_columns, design])
    residual = problem.data - model
    dof = max(n - jacobian.shape[1], 1)
    scale = float(residual @ residual) / dof
    norms = np.linalg.norm(jacobian, axis=0)
    norms[norms == 0.0] = 1.0
    normalized = jacobian / norms
    full = scale * np.linalg.pinv(normalized.T @ normalized) / np.outer(norms, norms)
    out = []
    for k in range(count):
        index = np.r_[3 * k : 3 * k + 3, 3 * count + 3 * k : 3 * count + 3 * k + 3]
        out.append(full[np.ix_(index, index)])
    return out
