"""Targets in the model: magnetic objects passed by the track, fitted as point dipoles with
the base model instead of cut out of the run.

A dipole of 4.5e4 A m^2 gives ~330 nT at 30 m and still ~0.05 nT (a typical noise) at
~550 m: on a survey line a target's field is present almost everywhere, so excluding the
passes leaves their tails, which the step and line scans then read as steps and lines. With
the track (``/odom``: attitude and position) the field of a dipole at ``s`` with moment
``m`` (odom frame) at sensor ``i`` is ``R^T B(p_i - s) m`` (body frame), linear in ``m``:
at fixed positions the moments are three more columns of the base model, fitted jointly
with it and with every effect the search names.

The positions are the nonlinear part, fitted once before the search (the choice, against
an alternation of model fit and localization on the residual: one joint problem, no
convergence loop):

1. **Where**: the detector of :mod:`.targets` (the base model plus every global candidate,
   robust start) marks the spans a localized field dominates.
2. **Greedy start**: on the residual of that model fitted outside the spans, the strongest
   remaining peak inside a span gets a start position from a grid (distances 3-200 m from
   the track at the peak, 96 directions) fitted to the stretch around the peak (moments and
   a constant per channel linear); the dipole joins the model and the residual is
   recomputed; repeated while a peak reaches the detector's threshold and the new dipole
   explains at least half of its stretch.
3. **Joint refinement** (variable projection, Golub & Pereyra): over every position at
   once, on the whole run (every k-th sample, at most :data:`FIT_SAMPLES`), with the
   moments and the columns of the base model plus every global candidate linear (projected
   out by a QR factorization). Position and moment sigmas from the projected Jacobian,
   ``s^2 (J^T J)^-1``, scaled to all samples (white noise: information grows with the
   count). Done twice: the second time with the first fit's target field at sensor 1 in
   ``B^b`` (the soft iron is magnetised by it too, ``K_i B^b``).

What no dipole explains stays for the detector (run again with the dipoles in the model)
to exclude, with its evidence. The same point-dipole physics as :mod:`..targets` (which
fits the tensor of a compensated survey); here the fields of all four sensors are the data
(the view is absolute), so the moments come with the base model's offsets.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy  # submodules load on first use: see core/__init__.py
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

from ..fields import MU0_OVER_4PI
from ..geometry import TetraGeometry
from ..targets.forward import sensor_points
from ..units import NT_PER_T
from .cv import flat, lstsq_view, noise_floor, solve_fast
from .prepare import Prepared, with_targets
from .result import Settings
from .targets import detector_columns, full_model_residual, robust_start, settle

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]

#: At most this many samples in the joint refinement of the positions.
FIT_SAMPLES = 3000
#: At most this many targets.
MAX_TARGETS = 8
#: Grid of start positions: distances (m) from the track at the peak, and directions.
GRID_DISTANCES_M = np.geomspace(3.0, 200.0, 16)
GRID_DIRECTIONS = 96
#: Samples of the stretch around a peak used by the grid.
GRID_SAMPLES = 150


@dataclass(frozen=True)
class Target:
    """A target fitted as a point dipole (odom frame, ENU).

    Attributes
    ----------
    position_m, position_sigma_m : (3,) m
    moment_Am2, moment_sigma_Am2 : (3,) A m^2
    closest_m : closest approach of the track, m
    passes : stretches of the track where its field exceeds 10 x the noise
    field_rms_nT : RMS of its fitted field over the run, every sensor and axis
    peak_time_s : time of the closest approach, s
    """

    position_m: Array
    position_sigma_m: Array
    moment_Am2: Array
    moment_sigma_Am2: Array
    closest_m: float
    passes: int
    field_rms_nT: float
    peak_time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {
            'position_m': [float(v) for v in self.position_m],
            'position_sigma_m': [float(v) for v in self.position_sigma_m],
            'moment_Am2': [float(v) for v in self.moment_Am2],
            'moment_sigma_Am2': [float(v) for v in self.moment_sigma_Am2],
            'moment_magnitude_Am2': float(np.linalg.norm(self.moment_Am2)),
            'closest_approach_m': self.closest_m,
            'passes': self.passes,
            'field_rms_nT': self.field_rms_nT,
            'closest_approach_time_s': self.peak_time_s,
        }


@dataclass(frozen=True)
class TargetModel:
    """The targets fitted into the model: the prepared data with their columns, the targets
    and notes (what could not be done, and why)."""

    prep: Prepared
    targets: list[Target] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Track:
    """The body origin ``position`` (N, 3) m and attitude ``rotation`` (N, 3, 3) body ->
    odom, with the array's ``geometry``."""

    position: Array
    rotation: Array
    geometry: TetraGeometry
    #: The sensors' positions (N, 4, 3) m, odom frame: computed once (the fits evaluate
    #: thousands of trial sources on one track).
    points: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        points = sensor_points(self.position, self.rotation, self.geometry)
        object.__setattr__(self, 'points', points)

    def at(self, idx: NDArray[np.int_]) -> Track:
        return Track(self.position[idx], self.rotation[idx], self.geometry)


def track_of(prep: Prepared, geometry: TetraGeometry | None) -> Track | None:
    """The track of the run, or None without /odom's position or the array's geometry."""
    if prep.position is None or prep.rotation is None or geometry is None:
        return None
    return Track(prep.position, prep.rotation, geometry)


def unit_fields(track: Track, source: Array) -> Array:
    """Field (N, 4, 3) body frame, nT per A m^2, of unit moments along the odom axes of a
    dipole at ``source`` (3,) m: (N, 4, 3, 3), the last axis the moment's axis."""
    r = track.points - source
    d2 = np.einsum('nsi,nsi->ns', r, r)
    inv3 = d2**-1.5
    inv5 = inv3 / d2
    world = 3.0 * r[..., :, None] * (r * inv5[..., None])[..., None, :]  # (N,4,i,k)
    world -= np.eye(3)[None, None] * inv3[..., None, None]
    # R^T W per sample and sensor as a batched matmul (einsum's generic loop: ~3x slower).
    body: Array = np.matmul(np.swapaxes(track.rotation, 1, 2)[:, None], world)
    return body * (MU0_OVER_4PI * NT_PER_T)


def target_columns(track: Track, sources: Array) -> tuple[Array, list[tuple[int, str]]]:
    """Columns (N, 4, 3, 3K) nT per A m^2 of the dipoles at ``sources`` (K, 3) m, labels."""
    cols = [unit_fields(track, s) for s in sources]
    labels = [
        (-1, f'target{k + 1}_m_{"enu"[a]}_Am2') for k in range(len(sources)) for a in range(3)
    ]
    return np.concatenate(cols, axis=-1), labels


def _strength(prep: Prepared, residual: Array, sigma: Array, width: int) -> Array:
    """Mean square of ``residual`` in noise sigmas over the channels, averaged over ``width``
    samples within each continuous piece (N,)."""
    q = np.mean((flat(residual, prep.sensors) / sigma) ** 2, axis=1)
    z = np.empty_like(q)
    for p in np.unique(prep.piece):
        idx = np.flatnonzero(prep.piece == p)
        z[idx] = uniform_filter1d(q[idx], min(width, len(idx)), mode='nearest')
    return z


def _fibonacci(n: int) -> Array:
    k = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * k / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * k
    return np.column_stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]
    )


def _stretch(
    z: Array, peak: int, piece: NDArray[np.int_], fraction: float = 0.05
) -> NDArray[np.int_]:
    """Indices around ``peak`` (same piece) where ``z`` stays above ``fraction`` of it."""
    above = (z > fraction * z[peak]) & (piece == piece[peak])
    lo = peak
    while lo > 0 and above[lo - 1]:
        lo -= 1
    hi = peak
    while hi < len(z) - 1 and above[hi + 1]:
        hi += 1
    return np.arange(lo, hi + 1)


def _grid_start(
    prep: Prepared, track: Track, residual: Array, idx: NDArray[np.int_], peak: int
) -> tuple[Array, float]:
    """Start position (3,) m for a dipole explaining ``residual`` on samples ``idx``: the
    best of a grid around the track at ``peak``, refined on the stretch (moment and a
    constant per channel linear); and the share of the stretch's sum of squares (about its
    mean per channel) it explains."""
    idx = idx[:: max(1, len(idx) // GRID_SAMPLES)]
    sub = track.at(idx)
    y = flat(residual[idx], prep.sensors)
    y = (y - y.mean(axis=0)).reshape(-1)
    total = float(y @ y)

    def misfit(source: Array) -> Array:
        cols = flat(unit_fields(sub, source), prep.sensors)
        cols = (cols - cols.mean(axis=0)).reshape(-1, 3)
        result: Array = y - cols @ _normal_solve(cols, y)
        return result

    centre = track.position[peak]
    directions = _fibonacci(GRID_DIRECTIONS)
    # One shell of the grid at a time, all its directions at once (a Python loop over the
    # 1,536 sources cost ~1 s per peak); the first of equal costs wins, as in a scan.
    grid = np.concatenate([centre + d * directions for d in GRID_DISTANCES_M])
    costs = np.concatenate(
        [_grid_costs(sub, prep.sensors, y, centre + d * directions) for d in GRID_DISTANCES_M]
    )
    best = grid[int(np.argmin(costs))] if np.isfinite(costs).any() else centre
    solution = scipy.optimize.least_squares(misfit, best, method='lm', x_scale=1.0)
    cost = float(np.sum(solution.fun**2))
    return solution.x, 1.0 - cost / max(total, 1e-300)


def _grid_costs(track: Track, sensors: tuple[int, ...], y: Array, sources: Array) -> Array:
    """Sum of squares (S,) of ``y`` (L,) nT (centred per channel) left by a dipole at each
    of ``sources`` (S, 3) m, its moment and a constant per channel linear: the batched form
    of :func:`_normal_solve` (normalised normal equations, the same tiny ridge)."""
    r = track.points[None] - sources[:, None, None, :]  # (S, N, 4, 3)
    d2 = np.einsum('qnsi,qnsi->qns', r, r)
    inv3 = d2**-1.5
    inv5 = inv3 / d2
    world = 3.0 * r[..., :, None] * (r * inv5[..., None])[..., None, :]
    world -= np.eye(3) * inv3[..., None, None]
    body = np.matmul(np.swapaxes(track.rotation, 1, 2)[None, :, None], world)
    body *= MU0_OVER_4PI * NT_PER_T  # (S, N, 4, 3, 3)
    cols = flat(np.moveaxis(body, 0, -1), sensors)  # (N, m, 3, S)
    cols = cols - cols.mean(axis=0)
    cols = np.moveaxis(cols.reshape(-1, 3, len(sources)), -1, 0)  # (S, L, 3)
    norm = np.linalg.norm(cols, axis=1)
    norm[norm == 0] = 1.0
    an = cols / norm[:, None, :]
    gram = np.matmul(np.swapaxes(an, 1, 2), an)
    ridge = 1e-10 * np.maximum(np.trace(gram, axis1=1, axis2=2) / 3.0, 1e-300)
    gram += ridge[:, None, None] * np.eye(3)
    coef = np.linalg.solve(gram, np.matmul(np.swapaxes(an, 1, 2), y)[..., None])[..., 0]
    left = y - np.matmul(cols, (coef / norm)[..., None])[..., 0]
    out: Array = np.sum(left**2, axis=1)
    return out


@dataclass(frozen=True)
class _Projected:
    """The thinned data with the base model plus global candidates projected out."""

    idx: NDArray[np.int_]
    q: Array
    y: Array
    scale: float  # sqrt(thinned / all samples): sigmas to all samples

    def perp(self, a: Array) -> Array:
        result: Array = a - self.q @ (self.q.T @ a)
        return result


def _projection(prep: Prepared, other: Array, offset: Array | None) -> _Projected:
    n = len(prep.t)
    idx = np.arange(0, n, max(1, int(np.ceil(n / FIT_SAMPLES))))
    a = flat(other[idx], prep.sensors).reshape(-1, other.shape[-1])
    norm = np.linalg.norm(a, axis=0)
    a = a[:, norm > 0] / norm[norm > 0]
    q, r, _ = scipy.linalg.qr(a, mode='economic', pivoting=True)
    diag = np.abs(np.diag(r))
    q = q[:, diag > 1e-9 * max(float(diag[0]), 1e-300)] if len(diag) else q
    y = prep.fields - prep.base_offset - (0.0 if offset is None else offset)
    y = flat(y[idx], prep.sensors).reshape(-1)
    proj = _Projected(idx, q, np.zeros(0), float(np.sqrt(len(idx) / n)))
    return _Projected(idx, q, proj.perp(y), proj.scale)


def _normal_solve(a: Array, y: Array) -> Array:
    """Least squares by the normal equations on normalised columns (a few columns)."""
    norm = np.linalg.norm(a, axis=0)
    norm[norm == 0] = 1.0
    an = a / norm
    result: Array = solve_fast(an.T @ an, an.T @ y) / norm
    return result


def refine(
    prep: Prepared, track: Track, other: Array, starts: Array, offset: Array | None = None
) -> tuple[Array, Array, Array]:
    """Positions (K, 3) m of the dipoles starting at ``starts``, fitted on the whole run with
    their moments and the columns ``other`` (N, 4, 3, p) linear (variable projection; the
    fixed part ``offset`` (N, 4, 3) nT of the other terms taken out first); and the sigmas
    (K, 3) m of the positions and (K, 3) A m^2 of the moments."""
    proj = _projection(prep, other, offset)
    sub = track.at(proj.idx)
    k = len(starts)

    def design(x: Array) -> Array:
        cols = target_columns(sub, x.reshape(k, 3))[0]
        return proj.perp(flat(cols, prep.sensors).reshape(-1, 3 * k))

    def residual(x: Array) -> Array:
        a = design(x)
        result: Array = proj.y - a @ _normal_solve(a, proj.y)
        return result

    # Tolerances 1e-6 (relative): ~0.1 mm on positions ~100 m from the odom origin, against
    # sigmas of ~1 mm; the default 1e-8 took twice the evaluations (0.1 s each on 3000 sets).
    solution = scipy.optimize.least_squares(
        residual, starts.ravel(), method='lm', x_scale=1.0, ftol=1e-6, xtol=1e-6
    )
    x = solution.x
    a = design(x)
    moments = _normal_solve(a, proj.y)
    # Jacobian of the projected model in positions and moments (Schur complement of the
    # linear base columns: the projection), by central differences in the positions.
    jac = [a]
    for j in range(3 * k):
        step = np.zeros_like(x)
        step[j] = 1e-3
        jac.append(((design(x + step) - design(x - step)) @ moments / 2e-3)[:, None])
    full = np.concatenate(jac[1:] + jac[:1], axis=1)
    rss = float(np.sum((proj.y - a @ moments) ** 2))
    dof = max(len(proj.y) - proj.q.shape[1] - 6 * k, 1)
    norms = np.linalg.norm(full, axis=0)
    norms[norms == 0] = 1.0
    cov = np.linalg.pinv((full / norms).T @ (full / norms)) / np.outer(norms, norms)
    sigma = np.sqrt(np.maximum(np.diag(cov), 0.0) * rss / dof) * proj.scale
    return x.reshape(k, 3), sigma[: 3 * k].reshape(k, 3), sigma[3 * k :].reshape(k, 3)


def greedy_starts(
    prep: Prepared,
    track: Track,
    residual_of: Any,
    spans: Mask,
    high: float,
    width: int,
) -> list[Array]:
    """Start positions, one dipole at a time: the strongest peak of the residual inside
    ``spans`` while it reaches ``high`` (mean square in sigmas over ``width`` samples, over
    the median outside the spans) and the new dipole explains at least half of its stretch.
    ``residual_of(sources)`` is the model's residual (N, 4, 3) nT with those dipoles in."""
    starts: list[Array] = []
    residual = residual_of(np.zeros((0, 3)))
    _, sigma = noise_floor(flat(residual, prep.sensors)[~spans])
    sigma = np.maximum(sigma, 1e-12)
    tried: list[int] = []
    while len(starts) < MAX_TARGETS:
        z = _strength(prep, residual, sigma, width)
        level = max(float(np.median(z[~spans])), 1.0)
        zin = np.where(spans, z, 0.0)
        for t in tried:  # a peak a dipole could not explain is not tried again
            zin[max(0, t - 5 * width) : t + 5 * width] = 0.0
        peak = int(np.argmax(zin))
        if zin[peak] < high * level:
            break
        idx = _stretch(z, peak, prep.piece)
        source, share = _grid_start(prep, track, residual, idx, peak)
        if share < 0.5:
            tried.append(peak)
            if len(tried) > 2:
                break
            continue
        starts.append(source)
        residual = residual_of(np.array(starts))
    return starts


def describe(
    prep: Prepared,
    track: Track,
    positions: Array,
    position_sigma: Array,
    moments: Array,
    moment_sigma: Array,
    noise_nT: float,
) -> list[Target]:
    """The targets' records: closest approach, passes (stretches where the field exceeds
    10 x ``noise_nT``), the RMS of the field over the run."""
    out = []
    for k, source in enumerate(positions):
        fields = np.einsum('nsak,k->nsa', unit_fields(track, source), moments[k])
        strong = np.sqrt(np.mean(fields**2, axis=(1, 2))) > 10.0 * max(noise_nT, 1e-12)
        distance = np.linalg.norm(track.position - source, axis=1)
        closest = int(np.argmin(distance))
        edges = np.diff(np.concatenate([[0], strong.astype(int), [0]]))
        starts = np.flatnonzero(edges == 1)
        # A pass is a stretch of strong field; one split by a jump between segments is one.
        passes = int(len(starts))
        out.append(
            Target(
                position_m=np.asarray(source, float),
                position_sigma_m=position_sigma[k],
                moment_Am2=moments[k],
                moment_sigma_Am2=moment_sigma[k],
                closest_m=float(distance[closest]),
                passes=passes,
                field_rms_nT=float(np.sqrt(np.mean(fields**2))),
                peak_time_s=float(prep.t[closest]),
            )
        )
    return out


def model_targets(
    prep: Prepared, track: Track, sources: Array, moments: Array | None = None
) -> Prepared:
    """``prep`` with the dipoles at ``sources`` (K, 3) m in its base model (``track``: the
    run's, sample for sample); with their ``moments`` (K, 3) A m^2, their field at sensor 1
    joins ``B^b``."""
    if not len(sources):
        return with_targets(prep, None, [])
    cols, labels = target_columns(track, sources)
    background = None
    if moments is not None:
        background = np.einsum('nap,p->na', cols[:, 0], np.asarray(moments).ravel())
    return with_targets(prep, cols, labels, background)


def _moments(
    prep: Prepared,
    track: Track,
    names: frozenset[str],
    settings: Settings,
    positions: Array,
    prior: Array | None = None,
) -> Array:
    """Moments (K, 3) A m^2 of the dipoles at ``positions`` in the full model on all samples
    (with the ``prior`` moments' field at sensor 1 in ``B^b``)."""
    modelled = model_targets(prep, track, positions, prior)
    cols = detector_columns(modelled, names, np.ones(len(prep.t), dtype=bool), settings)
    y = modelled.fields - modelled.base_offset
    coef = lstsq_view(prep.sensors, cols, y)
    start = prep.base_cols.shape[-1] - len(prep.target_labels)
    return coef[start : start + 3 * len(positions)].reshape(-1, 3)


@dataclass(frozen=True)
class Located:
    """Dipoles fitted into a run: ``prep`` with their columns (the run as given, ``B^b`` as
    the detector left it), their positions (K, 3) m with sigmas, their moment sigmas (K, 3)
    A m^2, the detector's spans (bool, N) they were sought in, and the moments (K, 3) A m^2
    of the full model (their field at sensor 1 is part of ``B^b``)."""

    prep: Prepared
    positions: Array
    position_sigma: Array
    moment_sigma: Array
    spans: Mask
    moments: Array

    def fixed(self) -> Prepared:
        """``prep`` with the dipoles' fitted field (their full-model moments) taken out of
        the data and their columns out of the model (their field stays in ``B^b``): what the
        detector looks at for what no dipole explains. With free moments, a detector fit
        that leaves a pass out (its robust start keeps half the run) has nothing to pin
        them to, and their extrapolated field reads as a target of its own."""
        cols = self.prep.target_cols
        if cols is None:
            return self.prep
        field = cols @ self.moments.ravel()
        background = self.prep.target_background
        fixed = with_targets(self.prep, None, [], background)
        return replace(fixed, fields=self.prep.fields - field)


def locate_targets(
    prep: Prepared, track: Track, names: frozenset[str], settings: Settings
) -> Located | None | bool:
    """Detect the localized fields of the run (the detector of :mod:`.targets`) and fit them
    as dipoles (greedy starts, joint refinement); None when no dipole explains what is
    localized, False when nothing is."""
    dt = float(np.median(np.diff(prep.t)))
    width = max(5, int(round(2.0 / dt)))
    include = robust_start(prep, names, settings, width)
    settled = settle(prep, names, settings, width, include)
    if not settled.mask.any():
        return False
    base = settled.prep
    outside = ~settled.mask

    def residual_of(sources: Array) -> Array:
        # Without dipoles the model is fitted outside the spans (a target pulls a fit);
        # with them, on every sample (their tails reach the whole run).
        modelled = model_targets(base, track, sources)
        rows = outside if not len(sources) else np.ones(len(prep.t), dtype=bool)
        return full_model_residual(modelled, names, rows, settings)[1]

    starts = greedy_starts(base, track, residual_of, settled.mask, settings.target_high, width)
    if not starts:
        return None
    everywhere = np.ones(len(prep.t), dtype=bool)
    other = detector_columns(base, names, everywhere, settings)
    positions, position_sigma, moment_sigma = refine(base, track, other, np.array(starts))
    # The soft iron is magnetised by the targets' field too (K_i B^b, B^b with the target's
    # field at sensor 1): ~1e-2 x 600 nT at 25 m, which the refinement without it put into
    # the positions (0.09 m, 60 sigma, off on a short line). Bilinear in K and the moments;
    # the iteration contracts by |K|, so one more refinement with B^b from the first
    # moments is within a sigma of the fixed point (4e-4 m, then 4e-7 m in the cases seen).
    moments = _moments(base, track, names, settings, positions)
    base = model_targets(base, track, positions, moments)
    base = with_targets(base, None, [], base.target_background)
    other = detector_columns(base, names, everywhere, settings)
    positions, position_sigma, moment_sigma = refine(base, track, other, positions)
    # A dipole whose fitted field nowhere reaches the detector's threshold stood in for a
    # leftover of the starts (before the joint refinement), not for a target.
    residual = residual_of(positions)
    _, sigma = noise_floor(flat(residual, prep.sensors))
    moments = _moments(base, track, names, settings, positions, moments)
    keep = []
    for k, source in enumerate(positions):
        own = np.einsum('nsak,k->nsa', unit_fields(track, source), moments[k])
        keep.append(float(_strength(base, own, sigma, width).max()) >= settings.target_high)
    if not any(keep):
        return None
    positions, position_sigma, moment_sigma = (
        positions[keep],
        position_sigma[keep],
        moment_sigma[keep],
    )
    moments = _moments(base, track, names, settings, positions, moments[keep])
    return Located(
        model_targets(base, track, positions, moments),
        positions,
        position_sigma,
        moment_sigma,
        settled.mask,
        moments,
    )
