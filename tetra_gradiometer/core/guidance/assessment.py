"""Trim assessment: predicted errors of the calibration the samples would give, "enough",
and the next manoeuvre to fly (see the package docstring for the definitions)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .._validate import as_array
from ..geometry import TetraGeometry
from ..identification._linear import AffineReduction, solve_scaled
from ..identification.lstsq import (
    MAX_COVERAGE_CONDITION,
    MIN_SAMPLES,
    noise_whitener,
    reduced_design,
)
from ..model import InterferenceParameters, n_parameters
from ..simulator import TrimManoeuvre
from ..types import ArrayLike, FloatArray
from ..uncertainty import compensated_sigma, noise_sigma
from ..units import NT_PER_T
from .statistics import (
    REGRESSOR_UNIT,
    Coverage,
    TrimStatistics,
    attitude_rotation,
    body_fields,
    coverage_condition,
    coverage_of,
)

__all__ = [
    'ENOUGH_RATIO',
    'MANOEUVRE_AMPLITUDE_DEG',
    'MANOEUVRE_DURATION_S',
    'MIN_NOISE_T',
    'PRIOR_B_T',
    'PRIOR_K',
    'SECTOR_DEG',
    'SURVEY_HEADINGS_DEG',
    'SURVEY_SWAY_DEG',
    'Advice',
    'TrimAssessment',
    'assess',
    'survey_attitudes',
]

#: "Enough": the predicted compensated sigma at most this multiple of the noise floor.
ENOUGH_RATIO = 1.1
#: Representative survey: level flight on these compass headings, degrees ...
SURVEY_HEADINGS_DEG = tuple(float(h) for h in range(0, 360, 30))
#: ... with roll and pitch each of -this, 0 and +this (sea-state sway), degrees.
SURVEY_SWAY_DEG = 5.0
#: Candidate manoeuvres: a heading sector of this width, degrees ...
SECTOR_DEG = 60.0
#: ... turned through in this time, s ...
MANOEUVRE_DURATION_S = 60.0
#: ... with roll or pitch oscillating at this amplitude, degrees (or level).
MANOEUVRE_AMPLITUDE_DEG = 15.0
#: The prior's 1-sigma per soft-iron element (dimensionless) and per hard-iron element (T):
#: a strongly magnetic vehicle; it only matters in directions the data leave unseen.
PRIOR_K = 0.1
PRIOR_B_T = 1.0e-6
#: The prediction takes the sensor noise at least this, T (1 pT, below any magnetometer):
#: on noise-free data the prior would otherwise vanish and unseen directions look exact.
MIN_NOISE_T = 1.0e-12
#: Gram eigenvalues below this fraction of the largest are directions the data do not see.
_EIG_RTOL = 1.0e-12
#: Candidate manoeuvres are sampled at this rate, Hz (their Gram is scaled to the data rate).
_CANDIDATE_RATE_HZ = 2.0
_KINDS = ('roll', 'pitch', 'level turn')


def survey_attitudes() -> FloatArray:
    """(M, 3) heading, roll, pitch in degrees of the representative survey."""
    sway = (-SURVEY_SWAY_DEG, 0.0, SURVEY_SWAY_DEG)
    grid = np.meshgrid(SURVEY_HEADINGS_DEG, sway, sway, indexing='ij')
    return np.column_stack([g.ravel() for g in grid])


# --------------------------------------------------------------------------- prediction


def _reduction(gram: FloatArray, cross: FloatArray | None = None) -> AffineReduction:
    """The 4 pseudo-samples of ``reduce_affine`` from the Gram matrix (scaled units), in SI.

    Any ``R`` with ``R^T R = X^T X`` reduces the problem exactly; with ``gram = V L V^T``,
    ``R = L^(1/2) V^T`` and ``z = L^(-1/2) V^T X^T T``. Directions with an eigenvalue below
    ``_EIG_RTOL`` of the largest are left out (the data do not see them)."""
    w, v = np.linalg.eigh(gram)
    keep = w > _EIG_RTOL * max(float(w[-1]), 0.0)
    root = np.sqrt(np.where(keep, w, 0.0))
    # X = X_scaled diag(REGRESSOR_UNIT), so R = R_scaled diag(REGRESSOR_UNIT).
    regressors = (root[:, None] * v.T) * REGRESSOR_UNIT[None, :]
    targets = np.zeros((4, 9))
    if cross is not None:
        targets = np.where(keep, 1.0 / np.where(keep, root, 1.0), 0.0)[:, None] * (v.T @ cross)
    return AffineReduction(regressors=regressors, targets=targets)


def _whitened_design(
    reduction: AffineReduction, geometry: TetraGeometry, symmetric: bool
) -> FloatArray:
    """The whitened design at the pseudo-samples, (36, P), as ``known_gradient_lstsq``."""
    design = reduced_design(reduction, geometry, symmetric=symmetric)
    p = design.shape[2]
    whitener = noise_whitener(geometry)
    return np.einsum('nRjp,jk->nRkp', design.reshape(4, 3, 3, p), whitener).reshape(-1, p)


def _fitted_noise(
    statistics: TrimStatistics, design: FloatArray, targets: FloatArray, symmetric: bool
) -> tuple[float, InterferenceParameters] | None:
    """Sensor noise (T) and parameters the solve would give, or None before MIN_SAMPLES.

    The residual sum of squares is ``sum |t|^2 - |z|^2`` (outside the span of ``X``) plus the
    reduced problem's residual; the parameters' offsets are those of the shifted targets
    (only ``k`` is used: the noise of the compensated tensor depends on it)."""
    if statistics.n < MIN_SAMPLES:
        return None
    solution = solve_scaled(design, targets.reshape(-1))
    rss = statistics.sum_sq - float(np.sum(targets**2)) + float(np.sum(solution.residual**2))
    dof = 9 * statistics.n - solution.rank
    if dof <= 0 or not rss > 0.0:
        return None
    return float(np.sqrt(rss / dof)), InterferenceParameters.from_vector(
        solution.theta, symmetric=symmetric
    )


def _covariance(design: FloatArray, sigma: float, symmetric: bool) -> FloatArray:
    """``sigma^2 (A^T A + sigma^2 P)^-1``, (P, P) SI, by an SVD of ``A`` stacked on the
    prior's rows. Not ``solve_scaled``: that one truncates weak directions, which here are
    exactly the ones the prior must bound."""
    n_k = n_parameters(symmetric=symmetric) - 9
    prior = np.concatenate([np.full(n_k, PRIOR_K), np.full(9, PRIOR_B_T)])
    stacked = np.vstack([design, np.diag(sigma / prior)])
    scale = np.linalg.norm(stacked, axis=0)
    _, singular, vt = np.linalg.svd(stacked / scale, full_matrices=False)
    return sigma**2 * ((vt.T / singular**2) @ vt) / np.outer(scale, scale)


@dataclass(frozen=True)
class _Setting:
    """What every prediction of one assessment shares."""

    geometry: TetraGeometry
    symmetric: bool
    sigma: float
    parameters: InterferenceParameters | None
    survey_fields: FloatArray  # (M, 3) T, body frame


def _survey_sigma(setting: _Setting, gram: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Predicted compensated 1-sigma at the survey attitudes with the samples of ``gram``:
    (M, 3, 3) T/m, and the parameter covariance (P, P)."""
    design = _whitened_design(_reduction(gram), setting.geometry, setting.symmetric)
    covariance = _covariance(design, setting.sigma, setting.symmetric)
    parameters = setting.parameters or InterferenceParameters.zero()
    sigma = compensated_sigma(
        setting.survey_fields, setting.geometry, setting.sigma, parameters, covariance
    )
    return sigma, covariance


def _rms(values: FloatArray, axis: Any = None) -> Any:
    return np.sqrt(np.mean(values**2, axis=axis))


# --------------------------------------------------------------------------- advice


@dataclass(frozen=True)
class Advice:
    """A candidate manoeuvre and what the survey's predicted sigma would become after it.

    Attributes
    ----------
    kind : str
        'roll', 'pitch' or 'level turn'.
    heading_from_deg, heading_to_deg : float
        The compass heading sector turned through, degrees (``from < to``; to <= 360).
    amplitude_deg : float
        Roll or pitch amplitude, degrees (0 for a level turn).
    duration_s : float
        Time to turn through the sector, s.
    predicted_sigma : float
        Predicted compensated sigma (RMS over the survey) after it, T/m.
    worst_sigma : float
        The largest per-attitude predicted sigma over the survey after it, T/m.
    """

    kind: str
    heading_from_deg: float
    heading_to_deg: float
    amplitude_deg: float
    duration_s: float
    predicted_sigma: float
    worst_sigma: float

    @property
    def text(self) -> str:
        """E.g. ``'roll ±15° on heading 120–180°'``."""
        sector = f'heading {self.heading_from_deg:.0f}–{self.heading_to_deg:.0f}°'
        if self.kind == 'level turn':
            return f'level turn through {sector}'
        return f'{self.kind} ±{self.amplitude_deg:.0f}° on {sector}'

    def manoeuvre(self, center: tuple[float, float, float] = (0.0, 0.0, -50.0)) -> TrimManoeuvre:
        """The manoeuvre as the simulator flies it (and as it was evaluated)."""
        return _candidate_manoeuvre(self.kind, self.heading_from_deg, center)

    def to_dict(self) -> dict[str, Any]:
        """Plain types for JSON: degrees, seconds, nT/m."""
        return {
            'text': self.text,
            'kind': self.kind,
            'heading_deg': [self.heading_from_deg, self.heading_to_deg],
            'amplitude_deg': self.amplitude_deg,
            'duration_s': self.duration_s,
            'predicted_sigma_nT_per_m': self.predicted_sigma * NT_PER_T,
            'worst_sigma_nT_per_m': self.worst_sigma * NT_PER_T,
        }


def _candidate_manoeuvre(
    kind: str, heading_from_deg: float, center: tuple[float, float, float] = (0.0, 0.0, -50.0)
) -> TrimManoeuvre:
    """Turn counter-clockwise (yaw up) from compass ``heading_from + SECTOR`` to
    ``heading_from`` in MANOEUVRE_DURATION_S, rolling, pitching or level."""
    amplitude = MANOEUVRE_AMPLITUDE_DEG
    return TrimManoeuvre(
        duration_s=MANOEUVRE_DURATION_S,
        center=center,
        heading_rate_deg_s=SECTOR_DEG / MANOEUVRE_DURATION_S,
        roll_amplitude_deg=amplitude if kind == 'roll' else 0.0,
        pitch_amplitude_deg=amplitude if kind == 'pitch' else 0.0,
        initial_heading_deg=90.0 - (heading_from_deg + SECTOR_DEG),
    )


def _candidate_gram(
    kind: str, heading_from_deg: float, earth: FloatArray, rate_hz: float
) -> FloatArray:
    """The Gram matrix (scaled units) the candidate adds when sampled at ``rate_hz``."""
    manoeuvre = _candidate_manoeuvre(kind, heading_from_deg)
    t = np.arange(0.0, MANOEUVRE_DURATION_S, 1.0 / _CANDIDATE_RATE_HZ)
    _, euler = manoeuvre.pose(t)
    fields = body_fields(Rotation.from_euler('ZYX', euler), earth)
    x = np.column_stack([fields, np.ones(len(t))]) / REGRESSOR_UNIT
    return (x.T @ x) * (rate_hz / _CANDIDATE_RATE_HZ)


def _advise(
    setting: _Setting, statistics: TrimStatistics, earth: FloatArray, rate_hz: float
) -> tuple[Advice, ...]:
    """Every candidate with the survey sigma it leads to, the best (least worst) first."""
    candidates = []
    for heading in np.arange(0.0, 360.0, SECTOR_DEG):
        for kind in _KINDS:
            gram = statistics.gram + _candidate_gram(kind, float(heading), earth, rate_hz)
            per_attitude = _rms(_survey_sigma(setting, gram)[0], axis=(1, 2))
            candidates.append(
                Advice(
                    kind=kind,
                    heading_from_deg=float(heading),
                    heading_to_deg=float(heading + SECTOR_DEG),
                    amplitude_deg=0.0 if kind == 'level turn' else MANOEUVRE_AMPLITUDE_DEG,
                    duration_s=MANOEUVRE_DURATION_S,
                    predicted_sigma=float(_rms(per_attitude)),
                    worst_sigma=float(per_attitude.max()),
                )
            )
    return tuple(sorted(candidates, key=lambda c: (c.worst_sigma, c.predicted_sigma)))


# --------------------------------------------------------------------------- assessment


@dataclass(frozen=True)
class TrimAssessment:
    """How well the samples would calibrate, and what to fly next. SI units.

    Attributes
    ----------
    n_samples : int
    sensor_noise : float
        Per-axis sensor noise used, T RMS.
    noise_source : str
        'fit residual' (the solve's own estimate) or 'configured' (fewer than MIN_SAMPLES).
    symmetric : bool
        27 parameters (symmetric ``K_i1``) or 36.
    parameter_sigma : ndarray, shape (P,)
        Predicted 1-sigma of each parameter, SI units of ``InterferenceParameters.to_vector``.
    survey_attitudes : ndarray, shape (M, 3)
        Heading, roll, pitch of the representative survey, degrees.
    survey_sigma : ndarray, shape (M,)
        Predicted compensated sigma per survey attitude (RMS over components), T/m.
    compensated_sigma : ndarray, shape (3, 3)
        Predicted compensated sigma per component (RMS over the survey), T/m.
    floor_sigma : ndarray, shape (3, 3)
        The noise floor per component, T/m.
    condition_number : float
        Attitude coverage condition number (:func:`coverage_condition`).
    enough : bool
    coverage : Coverage
    candidates : tuple of Advice
        Every candidate manoeuvre, the best first (empty when enough).
    """

    n_samples: int
    sensor_noise: float
    noise_source: str
    symmetric: bool
    parameter_sigma: FloatArray
    survey_attitudes: FloatArray
    survey_sigma: FloatArray
    compensated_sigma: FloatArray
    floor_sigma: FloatArray
    condition_number: float
    enough: bool
    coverage: Coverage
    candidates: tuple[Advice, ...] = field(default_factory=tuple)

    @property
    def predicted_sigma(self) -> float:
        """Predicted compensated sigma, RMS over components and survey attitudes, T/m."""
        return float(_rms(self.survey_sigma))

    @property
    def noise_floor(self) -> float:
        """RMS over components of the sensor-noise floor, T/m."""
        return float(_rms(self.floor_sigma))

    @property
    def ratio(self) -> float:
        """``predicted_sigma / noise_floor``."""
        floor = self.noise_floor
        return float('inf') if floor == 0.0 else self.predicted_sigma / floor

    @property
    def worst(self) -> tuple[float, FloatArray]:
        """The largest per-attitude predicted sigma (T/m) and its heading, roll, pitch (deg)."""
        i = int(np.argmax(self.survey_sigma))
        return float(self.survey_sigma[i]), self.survey_attitudes[i]

    @property
    def advice(self) -> Advice | None:
        """The manoeuvre that most reduces the worst predicted sigma; None when enough."""
        return None if self.enough or not self.candidates else self.candidates[0]

    def text(self) -> str:
        """One line: enough or not, the figures and the advice."""
        ratio = f'{self.ratio:.2f}' if self.ratio < 100 else f'{self.ratio:.3g}'
        head = (
            f'predicted compensated sigma {self.predicted_sigma * NT_PER_T:.3g} nT/m = '
            f'{ratio} x noise floor {self.noise_floor * NT_PER_T:.3g} nT/m '
            f'({self.n_samples} samples, sensor noise {self.sensor_noise * NT_PER_T:.3g} nT '
            f'{self.noise_source})'
        )
        if self.enough:
            return f'enough: {head}'
        advice = self.advice
        return f'not enough: {head}; next: {advice.text if advice else "collect more samples"}'

    def to_dict(self) -> dict[str, Any]:
        """Plain types for JSON: nT, nT/m, degrees (an infinite number is None)."""
        sigma = InterferenceParameters.from_vector(self.parameter_sigma, symmetric=self.symmetric)
        worst, attitude = self.worst
        headings = self.survey_attitudes[:, 0]
        per_heading = [_rms(self.survey_sigma[headings == h]) for h in SURVEY_HEADINGS_DEG]
        advice = self.advice
        return {
            'enough': self.enough,
            'text': self.text(),
            'samples': self.n_samples,
            'predicted_sigma_nT_per_m': self.predicted_sigma * NT_PER_T,
            'noise_floor_nT_per_m': self.noise_floor * NT_PER_T,
            'ratio': _finite(self.ratio),
            'enough_ratio': ENOUGH_RATIO,
            'worst_sigma_nT_per_m': worst * NT_PER_T,
            'worst_attitude_deg': dict(
                zip(('heading', 'roll', 'pitch'), map(float, attitude), strict=True)
            ),
            'compensated_sigma_nT_per_m': (self.compensated_sigma * NT_PER_T).tolist(),
            'survey': {
                'headings_deg': list(SURVEY_HEADINGS_DEG),
                'sway_deg': SURVEY_SWAY_DEG,
                'sigma_per_heading_nT_per_m': [float(s) * NT_PER_T for s in per_heading],
            },
            'sensor_noise_nT': self.sensor_noise * NT_PER_T,
            'sensor_noise_source': self.noise_source,
            'condition_number': _finite(self.condition_number),
            'parameter_sigma': {
                'n_parameters': len(self.parameter_sigma),
                'k_soft': sigma.k_soft.tolist(),
                'b_hard_nT': (sigma.b_hard * NT_PER_T).tolist(),
            },
            'coverage': self.coverage.to_dict(),
            'advice': None if advice is None else advice.to_dict(),
            'candidates': [c.to_dict() for c in self.candidates],
        }


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def assess(
    statistics: TrimStatistics,
    geometry: TetraGeometry,
    earth_field_enu: ArrayLike,
    *,
    sample_rate_hz: float,
    sensor_noise_t: float,
    symmetric: bool = False,
    max_coverage_condition: float = MAX_COVERAGE_CONDITION,
    noise_given: str = '',
) -> TrimAssessment:
    """Assess trim samples: predicted errors, coverage, enough, and the next manoeuvre.

    Parameters
    ----------
    statistics : TrimStatistics
        The samples (:func:`trim_statistics`, sums of them).
    geometry : TetraGeometry
        The array the statistics were made with.
    earth_field_enu : array_like, shape (3,)
        The site's Earth field, tesla, ENU: the survey's and the candidates' body fields.
    sample_rate_hz : float
        Samples per second: a candidate adds this many per second it lasts.
    sensor_noise_t : float
        Per-axis sensor noise, T RMS, used until the samples estimate their own
        (at least ``MIN_SAMPLES``).
    symmetric : bool
        Assess the 27-parameter model (``known_gradient_lstsq``) instead of the 36.
    max_coverage_condition : float
        "Enough" also needs a coverage condition number the solver accepts.
    noise_given : str
        Non-empty: take ``sensor_noise_t`` as the noise whatever the samples' own fit says,
        this text naming where it came from (a calibration with vehicle-effect terms: the
        statistics fit ``k``, ``b`` only, whose residual holds the terms' effect).
    """
    earth = as_array(earth_field_enu, 'earth_field_enu', (3,))
    reduction = _reduction(statistics.gram, statistics.cross)
    design = _whitened_design(reduction, geometry, symmetric)
    fitted = (
        None if noise_given else _fitted_noise(statistics, design, reduction.targets, symmetric)
    )
    sigma, parameters = fitted if fitted is not None else (float(sensor_noise_t), None)
    attitudes = survey_attitudes()
    setting = _Setting(
        geometry=geometry,
        symmetric=symmetric,
        sigma=max(sigma, MIN_NOISE_T),
        parameters=parameters,
        survey_fields=body_fields(attitude_rotation(*attitudes.T), earth),
    )
    survey, covariance = _survey_sigma(setting, statistics.gram)
    floor = noise_sigma(geometry, setting.sigma, parameters)
    per_attitude = _rms(survey, axis=(1, 2))
    condition = coverage_condition(statistics)
    enough = bool(
        statistics.n >= MIN_SAMPLES
        and condition <= max_coverage_condition
        and _rms(per_attitude) <= ENOUGH_RATIO * _rms(floor)
    )
    rate = float(sample_rate_hz) if sample_rate_hz > 0 else 1.0
    return TrimAssessment(
        n_samples=statistics.n,
        sensor_noise=setting.sigma,
        noise_source=noise_given or ('configured' if fitted is None else 'fit residual'),
        symmetric=symmetric,
        parameter_sigma=np.sqrt(np.diag(covariance)),
        survey_attitudes=attitudes,
        survey_sigma=per_attitude,
        compensated_sigma=_rms(survey, axis=0),
        floor_sigma=floor,
        condition_number=condition,
        enough=enough,
        coverage=coverage_of(statistics),
        candidates=() if enough else _advise(setting, statistics, earth, rate),
    )
