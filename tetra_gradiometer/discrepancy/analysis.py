"""The discrepancy workflow: simulate a recorded run with the base model, measure the
held-out gap against the noise floor, and add the missing physical effects one at a time.

Base model (Yu et al. 2014, eq. 10): ``B_i' = B_i + K_i B^b + B_i^h``, symmetric ``K_i``,
constant ``B_i^h``, sensor 1 clean. Two residual views:

* **absolute** (with /odom): every sensor against ``B^b = R^T E``, with ``E`` the Earth
  field (from the params, else estimated from sensor 1) refined by a constant and a linear
  drift common to all sensors. Per-sensor ``K_i`` and ``B_i^h`` (sensors 2-4) are
  observable, and so is sensor 1's own interference.
* **pair** (no /odom): ``B^b = B_1'`` (less sensor 1's named effects) and the residual is
  that of ``B_i' - B_1'`` (sensors 2-4). Fields common to all sensors cancel; sensor 1's own
  soft and hard iron is not observable, its other effects only relative to the others.

Held-out gap: blocked k-fold cross-validation (contiguous time blocks, interleaved folds):
each sample is predicted by a fit that did not see its block; the gap is the RMS over all
samples, sensors and axes of measured minus predicted, nT. The fits use per-block Gram
matrices, so every candidate model costs a few small solves.

Target passages: before the search, the base model plus every global candidate is fitted
robustly (least trimmed squares on ~2 s blocks, several starts); contiguous spans where its
residual stays far above the noise (a localized field that no candidate represents: a
target passed close to the track) are left out of every fit and of the gap, with a margin,
and reported (``Report.excluded_spans``). ``window_s`` restricts the analysis to part of the run.

Selection works on units (a family of the library in one sensor, or a term common to all
sensors): the unit with the lowest cross-validated BIC (``n ln(SS_cv/n) + p ln n``, p the
number of identifiable parameters) is added when (1) its CV-BIC is below the current
model's, (2) the held-out F-test of the added parameters has ``p < alpha`` and (3) it
explains at least ``(relevance x noise floor)^2`` of the held-out mean square of its own
sensor (an effect with an RMS contribution below the noise is not named). The step extends
the family to the other sensors whose units pass; every round re-checks the named units
(remove one no longer needed; replace one by a unit of another family with no more
parameters and a lower CV-BIC). The loop stops when no unit passes. The ``ln n`` penalty
per parameter is what makes a one-parameter delay win over a nine-parameter eddy term that
explains the same.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import linalg as scipy_linalg
from scipy import stats
from scipy.spatial.transform import Rotation

from ..core.model import SYMMETRIC_ENTRIES
from ..errors import InputError
from .effects import CANDIDATES, LIBRARY, Candidate, Context, PiecewiseSpline

NT_PER_T = 1e9

BASE_MODEL = (
    "Yu et al. 2014 eq. 10: B_i' = B_i + K_i B^b + B_i^h, symmetric K_i, constant B_i^h, "
    'sensor 1 clean (K_1 = 0, B_1^h = 0)'
)


@dataclass(frozen=True)
class Settings:
    """Tuning of the workflow (defaults are the documented method).

    n_folds : cross-validation folds (interleaved contiguous blocks)
    block_s : block length, s (default: duration / 40 within [5, 30] s)
    knot_s : knot spacing of the ``external_field`` candidate's spline, s
    relevance : minimum held-out RMS explained by an effect, in noise floors
    alpha : level of the held-out F-test
    max_effects : stop after this many effects
    adequate_ratio : the model is adequate when no effect is missing and the final gap is
        within this factor of the noise floor
    candidates : names to test (default all)
    max_samples : analyse at most this many sample sets (every k-th of a longer record)
    exclude_targets : find and leave out spans where a localized field that no candidate
        represents (a target passed close to the track) dominates the residual
    target_high, target_low : a span reaches ``target_high`` and ends below ``target_low``
        x the run's median level of the full model's residual (mean square in noise sigmas,
        averaged over ~2 s)
    target_margin : each span is widened by this share of its length (at least 2 s) each side
    target_max_fraction : spans are excluded only when they cover at most this share of the run
    target_confirm : a span is confirmed when, fitted with its samples in, its mean square
        residual stays at least this factor above the rest of the run's median
    """

    n_folds: int = 5
    block_s: float | None = None
    knot_s: float = 30.0
    relevance: float = 1.0
    alpha: float = 1e-6
    max_effects: int = 6
    adequate_ratio: float = 1.25
    candidates: tuple[str, ...] | None = None
    max_samples: int = 12000
    exclude_targets: bool = True
    target_high: float = 12.0
    target_low: float = 2.5
    target_margin: float = 0.5
    target_max_fraction: float = 0.6
    target_confirm: float = 2.0


@dataclass
class Step:
    """One named effect: the held-out gap before and after adding it, its fitted
    parameters (final joint fit) and the evidence that named it."""

    effect: str
    gap_before_nT: float
    gap_after_nT: float
    parameters: dict[str, Any]
    evidence: str
    n_parameters: int
    delta_bic: float
    f_statistic: float
    p_value: float

    def to_dict(self) -> dict[str, Any]:
        return {
            'effect': self.effect,
            'gap_before_nT': self.gap_before_nT,
            'gap_after_nT': self.gap_after_nT,
            'parameters': self.parameters,
            'evidence': self.evidence,
            'n_parameters': self.n_parameters,
            'delta_bic': self.delta_bic,
            'f_statistic': self.f_statistic,
            'p_value': self.p_value,
        }


@dataclass
class Report:
    """What the workflow found; ``to_dict()`` is ``report.json``. ``series`` holds the arrays
    for the plots (not serialised)."""

    named_effects: list[str]
    steps: list[Step]
    gap_initial_nT: float
    gap_final_nT: float
    noise_floor_nT: float
    base_model: str
    adequate: bool
    untestable: dict[str, str]
    view: str
    notes: list[str]
    rounds: list[dict[str, Any]]
    diagnostics: dict[str, Any]
    base_parameters: dict[str, Any]
    data: dict[str, Any]
    runtime_s: float
    excluded_spans: list[dict[str, Any]] = field(default_factory=list)
    series: dict[str, Any] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {
            'named_effects': list(self.named_effects),
            'steps': [s.to_dict() for s in self.steps],
            'gap_initial_nT': self.gap_initial_nT,
            'gap_final_nT': self.gap_final_nT,
            'noise_floor_nT': self.noise_floor_nT,
            'base_model': self.base_model,
            'adequate': self.adequate,
            'untestable': dict(self.untestable),
            'view': self.view,
            'notes': list(self.notes),
            'rounds': self.rounds,
            'diagnostics': self.diagnostics,
            'base_parameters': self.base_parameters,
            'data': self.data,
            'excluded_spans': list(self.excluded_spans),
            'criterion': criterion_text(),
            'library': {c.name: c.physics for c in CANDIDATES},
            'runtime_s': self.runtime_s,
        }


def criterion_text(settings: Settings | None = None) -> str:
    s = settings or Settings()
    return (
        'Blocked %d-fold cross-validation; per unit (family x sensor), the one with the lowest '
        "CV-BIC n ln(SS_cv/n) + p ln n (p: identifiable parameters) is added when its CV-BIC is lower than the current model's, "
        'the held-out F-test of its parameters gives p < %g, and it explains at least (%g x noise floor)^2 '
        'of the held-out mean square of its own sensor; the step extends the family to the other sensors '
        'that pass; named units are re-checked every round (removed when no longer needed, replaced by a '
        'unit of another family with no more parameters and a lower CV-BIC); the loop stops when no unit '
        'passes.' % (s.n_folds, s.alpha, s.relevance)
    )


# ---------------------------------------------------------------------------------------
# Data preparation


@dataclass
class _Prepared:
    t: np.ndarray
    fields: np.ndarray  # (N, 4, 3) nT
    sensors: tuple[int, ...]
    absolute: bool
    base_offset: np.ndarray  # (N, 4, 3) nT, the fixed part of the prediction
    b_background: np.ndarray  # (N, 3) nT
    b_rate: np.ndarray  # (N, 3) nT/s
    base_cols: np.ndarray  # (N, 4, 3, pb)
    base_labels: list[tuple[int, str]]
    temperature_c: np.ndarray | None
    current_a: np.ndarray | None
    attitude: np.ndarray | None  # (N, 3) yaw, pitch, roll deg
    earth_field_nT: np.ndarray | None
    notes: list[str]
    piece: np.ndarray  # (N,) index of the continuous piece of the run
    rotation: np.ndarray | None  # (N, 3, 3) body -> ENU


def _sym_columns(
    cols: np.ndarray, sensor: int, start: int, b: np.ndarray, labels: list[tuple[int, str]]
) -> int:
    """Symmetric K (6) and hard iron (3) columns of ``sensor`` from ``start``."""
    k = start
    for r, c in SYMMETRIC_ENTRIES:
        cols[:, sensor, r, k] = b[:, c]
        if r != c:
            cols[:, sensor, c, k] = b[:, r]
        labels.append((sensor, f'K{"xyz"[r]}{"xyz"[c]}'))
        k += 1
    for a in range(3):
        cols[:, sensor, a, k] = 1.0
        labels.append((sensor, f'Bh_{"xyz"[a]}_nT'))
        k += 1
    return k


def _prepare(
    recording: Any,
    earth_field_enu: Any,
    settings: Settings,
    window_s: tuple[float, float] | None = None,
    exclude_s: list[tuple[float, float]] | None = None,
) -> _Prepared:
    t_all = np.asarray(recording.t_s, dtype=float)
    fields = np.asarray(recording.fields, dtype=float) * NT_PER_T
    keep = np.isfinite(fields).all(axis=(1, 2)) & np.concatenate([[True], np.diff(t_all) > 0])
    if window_s is not None:
        inside = (t_all >= window_s[0]) & (t_all <= window_s[1])
        if inside.sum() < 50:
            raise InputError(
                f'the window {window_s[0]:g}:{window_s[1]:g} s holds {int(inside.sum())} sample sets '
                f'(the run spans 0-{t_all[-1] - t_all[0]:.1f} s); the workflow needs at least 50'
            )
        keep &= inside
    optional = {}
    for name in ('orientation_xyzw', 'temperature_c', 'current_a'):
        value = getattr(recording, name, None)
        if value is not None:
            value = np.asarray(value, dtype=float)
            keep &= np.isfinite(value).reshape(len(value), -1).all(axis=1)
        optional[name] = value
    if keep.sum() < 50:
        raise InputError(
            f'the recording has {int(keep.sum())} usable samples; the workflow needs at least 50'
        )
    notes: list[str] = []
    piece_all, jumps = _pieces(t_all, fields, optional['orientation_xyzw'], keep)
    if jumps:
        notes.append(
            f'{jumps} jump(s) in attitude or field between recorded segments: no derivative is taken '
            'across them and 2 samples either side are left out'
        )
        keep &= piece_all >= 0
    if exclude_s:
        # Excluded spans (target passages): left out, and no derivative is taken across them.
        excluded = np.zeros(len(t_all), dtype=bool)
        for t0, t1 in exclude_s:
            excluded |= (t_all >= t0) & (t_all <= t1)
        keep &= ~excluded
        starts = np.cumsum(np.diff(excluded.astype(int), prepend=0) == 1)
        piece_all = np.where(piece_all >= 0, piece_all * (len(exclude_s) + 1) + starts, -1)
        if keep.sum() < 50:
            raise InputError(
                f'{int(keep.sum())} usable samples are left outside the excluded spans; '
                'the workflow needs at least 50'
            )
    index = np.flatnonzero(keep)
    if len(index) > settings.max_samples:
        # Long or fast records: every k-th set keeps white noise white and the manoeuvre
        # resolved (it changes over seconds), and bounds memory and time.
        step = int(np.ceil(len(index) / settings.max_samples))
        index = index[::step]
        notes.append(f'{int(keep.sum())} sets: every {step}-th analysed ({len(index)} sets)')
    t, fields = t_all[index], fields[index]
    piece = piece_all[index]
    optional = {k: (v[index] if v is not None else None) for k, v in optional.items()}
    n = len(t)
    if n < 50:
        raise InputError(f'the recording has {n} usable samples; the workflow needs at least 50')
    quat = optional['orientation_xyzw']
    attitude = None
    earth = None
    if quat is not None:
        rotation = Rotation.from_quat(quat)
        r = rotation.as_matrix()
        attitude = np.degrees(rotation.as_euler('ZYX'))
        if earth_field_enu is None:
            earth = np.mean(np.einsum('nij,nj->ni', r, fields[:, 0]), axis=0)
            notes.append(
                'earth_field_enu not given: estimated from sensor 1 rotated to ENU by /odom '
                f'({np.linalg.norm(earth):.0f} nT)'
            )
        else:
            earth = np.asarray(earth_field_enu, dtype=float).reshape(3) * NT_PER_T
        b0 = np.einsum('nji,j->ni', r, earth)  # R^T E
        base_offset = np.repeat(b0[:, None, :], 4, axis=1)
        # First pass: a constant correction of the Earth field, from sensor 1.
        design = np.swapaxes(r, 1, 2).reshape(n * 3, 3)  # rows of R^T
        correction = np.linalg.lstsq(design, (fields[:, 0] - b0).reshape(-1), rcond=None)[0]
        b_background = b0 + np.einsum('nji,j->ni', r, correction)
        base_cols, labels = _base_columns(r, b_background, True, t)
        sensors: tuple[int, ...] = (0, 1, 2, 3)
        absolute = True
        notes.append(
            'B^b = R^T E from /odom, E corrected by a constant fitted with the model '
            f'(|E| = {np.linalg.norm(earth + correction):.0f} nT)'
        )
    else:
        r = None
        b_background = fields[:, 0].copy()
        base_offset = np.repeat(b_background[:, None, :], 4, axis=1)
        base_cols, labels = _base_columns(None, b_background, False)
        sensors = (1, 2, 3)
        absolute = False
        notes.append(
            "no /odom: falling back to B^b = B_1' (the paper's assumption); only the pair "
            "differences B_i' - B_1' are observable, so the residual is that of sensors 2-4 "
            'against sensor 1; a term of sensor 1 enters every pair, so only relative values are fixed'
        )
    b_rate = (
        PiecewiseSpline(t, b_background, piece)(0.0, 1)
        if quat is not None
        else _smoothed(t, b_background, piece, deriv=1)
    )
    return _Prepared(
        t,
        fields,
        sensors,
        absolute,
        base_offset,
        b_background,
        b_rate,
        base_cols,
        labels,
        optional['temperature_c'],
        optional['current_a'],
        attitude,
        earth,
        notes,
        piece,
        r,
    )


def _refresh_background(
    prep: _Prepared, correction: np.ndarray, tolerance_nT: float = 0.5
) -> bool:
    """Re-derive ``B^b = R^T (E + dE + dE' (t - t_mid))`` with the Earth-field correction of
    the joint fit (the first pass used sensor 1 alone, whose own interference biases it);
    rebuild the base columns when it moved by more than ``tolerance_nT`` (soft iron ~1e-2
    turns that into < 0.005 nT). Returns True when something changed."""
    world = correction[None, :3] + _ramp(prep.t)[:, None] * correction[None, 3:6]
    b_background = prep.base_offset[:, 0] + np.einsum('nji,nj->ni', prep.rotation, world)
    if np.max(np.abs(b_background - prep.b_background)) < tolerance_nT:
        return False
    prep.b_background = b_background
    prep.base_cols, prep.base_labels = _base_columns(prep.rotation, b_background, True, prep.t)
    prep.b_rate = PiecewiseSpline(prep.t, b_background, prep.piece)(0.0, 1)
    return True


def _smoothed(t: np.ndarray, values: np.ndarray, piece: np.ndarray, deriv: int = 0) -> np.ndarray:
    """Savitzky-Golay (5th order, ~1.3 s or 13 samples) value or derivative on each piece:
    exact to ~1e-7 for manoeuvre signals, a quarter of the noise gain of a spline derivative.
    Pieces shorter than the window get a cubic spline."""
    from scipy.signal import savgol_filter

    out = np.empty_like(values, dtype=float)
    for p in np.unique(piece):
        idx = np.flatnonzero(piece == p)
        if len(idx) < 2:
            out[idx] = 0.0 if deriv else values[idx]
            continue
        dt = float(np.median(np.diff(t[idx])))
        window = max(13, int(round(1.3 / dt)) | 1)
        if len(idx) > window:
            out[idx] = savgol_filter(values[idx], window, 5, deriv=deriv, delta=dt, axis=0)
        else:
            out[idx] = PiecewiseSpline(t[idx], values[idx])(0.0, deriv)
    return out


def _refresh_pair_background(
    prep: _Prepared, clean: np.ndarray, tolerance_nT: float = 0.01
) -> bool:
    """Pair view: take ``B^b`` (and the fixed part of every prediction) as sensor 1's reading
    less its named effects; rebuild the base columns when it moved. True when it did. (Here
    ``B^b`` is the regressor of sensor 1's own terms, hence the tight tolerance.)"""
    if np.max(np.abs(clean - prep.b_background)) < tolerance_nT:
        return False
    prep.b_background = clean
    prep.base_offset = np.repeat(clean[:, None, :], 4, axis=1)
    prep.base_cols, prep.base_labels = _base_columns(None, clean, False)
    prep.b_rate = _smoothed(prep.t, clean, prep.piece, deriv=1)
    return True


def _ramp(t: np.ndarray) -> np.ndarray:
    """(t - t_mid) / (half the span): -1 .. 1."""
    half = max(0.5 * (t[-1] - t[0]), 1e-9)
    return (t - 0.5 * (t[-1] + t[0])) / half


def _base_columns(
    r: np.ndarray | None, b_background: np.ndarray, absolute: bool, t: np.ndarray | None = None
) -> tuple[np.ndarray, list[tuple[int, str]]]:
    """Base-model regressors: (absolute view) a correction of the Earth field seen by all
    sensors, constant plus a linear drift over the run (diurnal variation, a distant target
    passed slowly), then symmetric K_i and B_i^h of sensors 2-4 on ``b_background``."""
    n = len(b_background)
    first = 6 if absolute else 0
    cols = np.zeros((n, 4, 3, first + 27))
    labels: list[tuple[int, str]] = []
    if absolute:
        ramp = _ramp(t)
        for a in range(3):
            cols[..., a] = r[:, a, :][:, None, :]
            labels.append((-1, f'dE_{"enu"[a]}_nT'))
        for a in range(3):
            cols[..., 3 + a] = (ramp[:, None] * r[:, a, :])[:, None, :]
            labels.append((-1, f'dE_drift_{"enu"[a]}_nT_at_end'))
    start = first
    for s in (1, 2, 3):
        start = _sym_columns(cols, s, start, b_background, labels)
    return cols, labels


def _pieces(
    t: np.ndarray, fields: np.ndarray, quat: np.ndarray | None, keep: np.ndarray
) -> tuple[np.ndarray, int]:
    """Split the run where the attitude (or, without /odom, sensor 1's field) jumps: a step
    at least 4 x larger than the steps on both sides of it and than 0.5 deg (50 nT). Returns
    the piece index per sample (-1: left out, 2 samples either side of a jump) and the
    number of jumps. Also splits at gaps longer than 5 sample periods."""
    idx = np.flatnonzero(keep)
    piece = np.full(len(t), -1, dtype=int)
    if len(idx) < 8:
        piece[idx] = 0
        return piece, 0
    if quat is not None:
        q = quat[idx]
        step = (Rotation.from_quat(q[1:]) * Rotation.from_quat(q[:-1]).inv()).magnitude()
        floor = np.radians(0.5)
    else:
        step = np.linalg.norm(np.diff(fields[idx, 0], axis=0), axis=1)
        floor = 50.0
    pad = np.concatenate([[np.inf, np.inf], step, [np.inf, np.inf]])
    left = np.maximum(pad[:-4], pad[1:-3])
    right = np.maximum(pad[3:-1], pad[4:])
    neighbours = np.minimum(left, right)
    neighbours = np.where(
        np.isfinite(neighbours),
        neighbours,
        np.maximum(np.where(np.isfinite(left), left, 0), np.where(np.isfinite(right), right, 0)),
    )
    jump = (step > 4.0 * neighbours) & (step > floor)
    dt = np.diff(t[idx])
    gap = dt > 5.0 * np.median(dt)
    boundary = jump | gap
    piece[idx] = np.concatenate([[0], np.cumsum(boundary)])
    for j in np.flatnonzero(jump):
        piece[idx[max(j - 1, 0) : j + 3]] = -1
    return piece, int(jump.sum())


def _testable(prep: _Prepared, names: tuple[str, ...]) -> tuple[list[Candidate], dict[str, str]]:
    out, untestable = [], {}
    for name in names:
        candidate = LIBRARY[name]
        reason = None
        if candidate.name == 'external_field' and not prep.absolute:
            reason = (
                'no /odom in the bag: the world frame is unknown, and the pair differences '
                "B_i' - B_1' cancel a field that is the same at all sensors"
            )
        elif 'odom' in candidate.requires and not prep.absolute:
            reason = (
                'no /odom in the bag: without an absolute attitude reference only the pair differences '
                "B_i' - B_1' are observable; sensor 1's own soft and hard iron is absorbed into "
                'K_i1 (I + K_1)^-1 (its small non-symmetric remainder would look like sensor_misalignment)'
            )
        elif 'temperature' in candidate.requires:
            if prep.temperature_c is None:
                reason = 'no /tetra/temperature in the bag: the drift has no regressor'
            elif np.ptp(prep.temperature_c) < 1e-3:
                reason = 'the recorded temperature does not vary (< 0.001 degC): a drift is a constant offset'
        elif 'current' in candidate.requires:
            if prep.current_a is None:
                reason = 'no /battery_state in the bag: the field has no regressor'
            elif np.ptp(prep.current_a) < 1e-3:
                reason = (
                    'the recorded current does not vary (< 1 mA): its field is a constant offset'
                )
        if reason is None:
            out.append(candidate)
        else:
            untestable[name] = reason
    return out, untestable


# ---------------------------------------------------------------------------------------
# Linear algebra: per-block Gram matrices and blocked cross-validation


def _solve_fast(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve a normalised Gram system with a tiny ridge (Cholesky); exactly degenerate
    directions get (nearly) the minimum-norm share. Falls back to the eigen-solve."""
    if not len(rhs):
        return np.zeros(0)
    ridge = 1e-10 * max(float(np.trace(gram)) / len(rhs), 1e-300)
    try:
        factor = scipy_linalg.cho_factor(gram + ridge * np.eye(len(rhs)), check_finite=False)
        return scipy_linalg.cho_solve(factor, rhs, check_finite=False)
    except np.linalg.LinAlgError:
        return _solve(gram, rhs)[0]


def _solve(gram: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, int]:
    """Eigen-solve with a relative cut-off; returns the solution and the rank."""
    w, v = np.linalg.eigh(gram)
    top = max(float(w[-1]), 1e-300) if len(w) else 1.0
    keep = w > top * 1e-11
    theta = v[:, keep] @ ((v[:, keep].T @ rhs) / w[keep])
    return theta, int(keep.sum())


class _Gram:
    """Per-fold Gram matrices of ``Z`` (N, m, q): columns are normalised regressors, then
    target and offset vectors (left unscaled)."""

    def __init__(self, z: np.ndarray, t: np.ndarray, block_s: float, n_folds: int) -> None:
        n, m, q = z.shape
        edges = np.searchsorted(t, np.arange(t[0], t[-1] + block_s, block_s)[1:], side='left')
        bounds = np.concatenate([[0], edges[edges < n], [n]])
        bounds = np.unique(bounds)
        n_blocks = len(bounds) - 1
        n_folds = max(2, min(n_folds, n_blocks))
        self.folds = np.zeros((n_folds, q, q))
        self.fold_rows = np.zeros(n_folds)
        self.fold_of_sample = np.zeros(n, dtype=int)
        for b in range(n_blocks):
            lo, hi = bounds[b], bounds[b + 1]
            zb = z[lo:hi].reshape(-1, q)
            self.folds[b % n_folds] += zb.T @ zb
            self.fold_rows[b % n_folds] += zb.shape[0]
            self.fold_of_sample[lo:hi] = b % n_folds
        self.total = self.folds.sum(axis=0)
        self.n = float(n * m)

    @staticmethod
    def _parts(
        g: np.ndarray, cols: np.ndarray, targets: np.ndarray, weights: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        """Gram of ``cols``, their products with the target ``sum_j weights_j z_targets_j``,
        and the target's square."""
        c = g[np.ix_(cols, targets)] @ weights
        s = float(weights @ g[np.ix_(targets, targets)] @ weights)
        return g[np.ix_(cols, cols)], c, s

    def evaluate(
        self, cols: np.ndarray, ty: int, offsets: list[int] = (), add_back: list[int] = ()
    ) -> dict[str, Any]:
        """Fit ``cols`` to ``z_ty - sum z_offsets + sum z_add_back``: full-data and
        cross-validated residual SS."""
        targets = np.array([ty] + list(offsets) + list(add_back), dtype=int)
        weights = np.array([1.0] + [-1.0] * len(offsets) + [1.0] * len(add_back))
        gg, c, s = self._parts(self.total, cols, targets, weights)
        theta, rank = _solve(gg, c) if len(cols) else (np.zeros(0), 0)
        rss = s - 2 * theta @ c + theta @ gg @ theta
        cv = 0.0
        for fold in self.folds:
            tg, tc, _ = self._parts(self.total - fold, cols, targets, weights)
            fg, fc, fs = self._parts(fold, cols, targets, weights)
            th = _solve_fast(tg, tc)
            cv += fs - 2 * th @ fc + th @ fg @ th
        return {'theta': theta, 'rank': rank, 'rss': max(rss, 0.0), 'cv': max(cv, 1e-300)}


ALL_SENSORS = (0, 1, 2, 3)


def _flat(arr: np.ndarray, sensors: tuple[int, ...]) -> np.ndarray:
    """Full-sensor array (N, 4, 3, ...) -> the residual view (N, 3 len(sensors), ...).

    Absolute view (sensors 0-3): as is. Pair view (sensors 1-3): the differences
    ``sensor_i - sensor_1``, so a term of sensor 1 enters every pair with a minus sign.
    """
    if tuple(sensors) == ALL_SENSORS:
        sub = arr
    else:
        sub = arr[:, list(sensors)] - arr[:, :1]
    return sub.reshape(sub.shape[0], 3 * len(sensors), *sub.shape[3:])


def _noise_floor(residual: np.ndarray) -> tuple[float, np.ndarray]:
    """White-noise RMS from the 4th difference of each channel (robust: MAD), nT.

    ``var(diff^4 n) = 70 sigma^2``; a smooth signal is suppressed by ``(omega dt)^4``.
    Returns the RMS over channels and the per-channel sigmas.
    """
    d4 = np.diff(residual, 4, axis=0)
    mad = np.median(np.abs(d4 - np.median(d4, axis=0)), axis=0)
    sigma = 1.4826 * mad / np.sqrt(70.0)
    return float(np.sqrt(np.mean(sigma**2))), sigma


def _lstsq_full(prep: _Prepared, cols: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least squares on all samples of the view (normal equations on normalised columns,
    eigen-solve with a rank cut-off); physical coefficients (per column)."""
    a = _flat(cols, prep.sensors)
    a = a.reshape(-1, a.shape[-1])
    y = _flat(target, prep.sensors).reshape(-1)
    gram = a.T @ a
    norm = np.sqrt(np.diag(gram)).copy()
    norm[norm == 0] = 1.0
    coef, _ = _solve(gram / np.outer(norm, norm), (a.T @ y) / norm)
    return coef / norm


@dataclass
class _Family:
    candidate: Candidate
    cols: np.ndarray  # (N, 4, 3, p)
    offset: np.ndarray | None  # (N, 4, 3)
    labels: list[tuple[int, str]]
    estimate: dict | None = None  # linearisation point of a nonlinear family


def _soft_iron(labels: list[tuple[int, str]], coef: np.ndarray) -> np.ndarray:
    """The fitted symmetric K_i (4, 3, 3) of the base model (zero for sensor 1)."""
    k = np.zeros((4, 3, 3))
    for (s, name), value in zip(labels, coef):
        if s >= 0 and name.startswith('K'):
            r, c = 'xyz'.index(name[1]), 'xyz'.index(name[2])
            k[s, r, c] = k[s, c, r] = value
    return k


def _reference_in_pairs(unit: _Family, k_hat: np.ndarray) -> _Family:
    """A candidate term of sensor 1 in the pair view: it enters ``B_i' - B_1'`` as
    ``-(I + K_i)`` times itself while the model's ``K_i B^b`` uses ``B^b = B_1'``, which
    carries it. The view subtracts sensor 1's column; this puts ``-K_i`` times it at sensor
    i. (Once named, the term is taken out of ``B^b`` instead and the unit is plain.)"""
    cols = unit.cols.copy()
    cols[:, 1:] = -np.einsum('sij,njp->nsip', k_hat[1:], unit.cols[:, 0])
    offset = None
    if unit.offset is not None:
        offset = unit.offset.copy()
        offset[:, 1:] = -np.einsum('sij,nj->nsi', k_hat[1:], unit.offset[:, 0])
    return _Family(unit.candidate, cols, offset, unit.labels, unit.estimate)


def _restrict(family: _Family, sensor: int) -> _Family:
    """The family's columns and offset for one sensor only."""
    idx = [k for k, (s, _) in enumerate(family.labels) if s == sensor]
    offset = None
    if family.offset is not None:
        offset = np.zeros_like(family.offset)
        offset[:, sensor] = family.offset[:, sensor]
    return _Family(
        family.candidate,
        family.cols[..., idx],
        offset,
        [family.labels[k] for k in idx],
        family.estimate,
    )


def _revise(
    steps: list[Step],
    step_units: list[list[int]],
    active: list[_Family],
    k: int,
    replacement: _Family | None,
    message: str,
) -> None:
    """Take unit ``k`` out of the model (and its step), or replace it; keep the steps
    consistent (a step whose units all changed family is renamed, an empty one dropped)."""
    owner = next(i for i, members in enumerate(step_units) if k in members)
    if replacement is None:
        del active[k]
        step_units[owner].remove(k)
        for members in step_units:
            members[:] = [m - 1 if m > k else m for m in members]
    else:
        active[k] = replacement
    steps[owner].evidence += f'; revised later: {message}'
    for i in reversed(range(len(steps))):
        names = {active[m].candidate.name for m in step_units[i]}
        if not names:
            del steps[i], step_units[i]
        elif steps[i].effect not in names:
            steps[i].effect = sorted(names)[0]
        if i < len(steps) and len(names) > 1:
            # The replaced unit now belongs to another family: move it to that family's step
            # (or a new one at the end).
            moved = [m for m in step_units[i] if active[m].candidate.name != steps[i].effect]
            step_units[i] = [m for m in step_units[i] if m not in moved]
            for m in moved:
                target = next(
                    (j for j, st in enumerate(steps) if st.effect == active[m].candidate.name),
                    None,
                )
                if target is None:
                    steps.append(
                        Step(
                            active[m].candidate.name,
                            steps[i].gap_before_nT,
                            steps[i].gap_after_nT,
                            {},
                            f'named when revising: {message}',
                            active[m].cols.shape[-1],
                            0.0,
                            0.0,
                            1.0,
                        )
                    )
                    step_units.append([m])
                else:
                    step_units[target].append(m)
    _merge_steps(steps, step_units)


def _merge_steps(steps: list[Step], step_units: list[list[int]]) -> None:
    """One step per family: a later step of a family already named is merged into the earlier
    one (its units and parameters; the gaps of the earlier step stay those it was named with,
    unless the two steps were consecutive)."""
    i = 0
    while i < len(steps):
        j = next((j for j in range(i + 1, len(steps)) if steps[j].effect == steps[i].effect), None)
        if j is None:
            i += 1
            continue
        step_units[i] += step_units[j]
        if j == i + 1:
            steps[i].gap_after_nT = steps[j].gap_after_nT
        steps[i].n_parameters += steps[j].n_parameters
        steps[i].evidence += f'; merged with a later step of the same family: {steps[j].evidence}'
        del steps[j], step_units[j]


@dataclass
class _CurrentDesign:
    """The current model's normalised design on all samples, shared by the builds of a round."""

    a: np.ndarray  # (rows, p) normalised columns
    norm: np.ndarray  # (p,)
    gram: np.ndarray  # (p, p)
    rhs: np.ndarray  # (p,) a^T target
    target: np.ndarray  # (rows,)
    sensor: np.ndarray  # (p,) sensor of each column (-2: base model)


def _current_design(
    prep: _Prepared, cur_cols: np.ndarray, cur_sensor: np.ndarray, target: np.ndarray
) -> _CurrentDesign:
    a = _flat(cur_cols, prep.sensors)
    a = a.reshape(-1, a.shape[-1])
    norm = np.sqrt(np.einsum('rp,rp->p', a, a))
    norm[norm == 0] = 1.0
    a = a / norm
    y = _flat(target, prep.sensors).reshape(-1)
    return _CurrentDesign(a, norm, a.T @ a, a.T @ y, y, cur_sensor)


def _build(candidate: Candidate, ctx: Context, prep: _Prepared, cur: _CurrentDesign) -> _Family:
    """Build a family's columns; nonlinear families are iterated at their estimate.

    The estimate for sensor ``s`` comes from the current model without its units in sensor
    ``s`` (``cur.sensor``: the sensor of each current column, -2 for the base model): a unit
    there that is nearly collinear with this family (an eddy term beside a delay) would make
    a joint estimate wild, and leaving out the other sensors' units would bias it.
    """
    cols, offset, labels = candidate.build(ctx, None)
    if not candidate.nonlinear:
        return _Family(candidate, cols, offset, labels)
    p_cur = len(cur.norm)
    fam_sensor = np.array([lab[0] for lab in labels])
    for _ in range(3):
        f = _flat(cols, prep.sensors)
        f = f.reshape(-1, f.shape[-1])
        fnorm = np.sqrt(np.einsum('rq,rq->q', f, f))
        fnorm[fnorm == 0] = 1.0
        f = f / fnorm
        y = cur.target - (_flat(offset, prep.sensors).reshape(-1) if offset is not None else 0.0)
        cross = cur.a.T @ f
        gram = np.block([[cur.gram, cross], [cross.T, f.T @ f]])
        rhs = np.concatenate([cur.a.T @ y if offset is not None else cur.rhs, f.T @ y])
        coef = np.zeros(len(labels))
        for sensor in np.unique(fam_sensor):
            own = np.flatnonzero(fam_sensor == sensor)
            sel = np.concatenate([np.flatnonzero(cur.sensor != sensor), p_cur + own])
            theta = _solve_fast(gram[np.ix_(sel, sel)], rhs[sel])
            coef[own] = theta[-len(own) :] / fnorm[own]
        estimate = {label: float(v) for label, v in zip(labels, coef)}
        cols, offset, labels = candidate.build(ctx, estimate)
    return _Family(candidate, cols, offset, labels, estimate)


def _sensor_name(s: int) -> str:
    return 'all_sensors' if s < 0 else f'sensor_{s + 1}'


def _format(labels: list[tuple[int, str]], coef: np.ndarray, absolute: bool) -> dict[str, Any]:
    per_sensor: dict[str, dict[str, float]] = {}
    for (s, name), value in zip(labels, coef):
        per_sensor.setdefault(_sensor_name(s), {})[name] = float(value)
    out: dict[str, Any] = {'per_sensor': per_sensor}
    if not absolute:
        out['note'] = (
            'pair view (no /odom): only differences between a sensor and sensor 1 are observable; '
            'a value at sensor 1 is a term common to all pairs (e.g. tau_i - tau_1 is what the data fix)'
        )
    return out


def _effect_field(family: _Family, coef: np.ndarray) -> np.ndarray:
    field_ = np.einsum('nsap,p->nsa', family.cols, coef)
    return field_ + (family.offset if family.offset is not None else 0.0)


# ---------------------------------------------------------------------------------------
# Diagnostics: where do measurement and simulation disagree?


def _diagnostics(prep: _Prepared, residual: np.ndarray) -> dict[str, Any]:
    drivers: dict[str, np.ndarray] = {
        'time_s': prep.t,
        'field_rate_nT_s': np.linalg.norm(prep.b_rate, axis=1),
    }
    if prep.attitude is not None:
        drivers.update(
            {
                'heading_deg': prep.attitude[:, 0],
                'pitch_deg': prep.attitude[:, 1],
                'roll_deg': prep.attitude[:, 2],
            }
        )
    if prep.temperature_c is not None:
        drivers['temperature_c'] = prep.temperature_c
    if prep.current_a is not None:
        drivers['current_a'] = prep.current_a
    out: dict[str, Any] = {'rms_nT': {}, 'correlation': {}}
    for s in prep.sensors:
        out['rms_nT'][f'sensor_{s + 1}'] = [
            float(v) for v in np.sqrt(np.mean(residual[:, s] ** 2, axis=0))
        ]
    for name, d in drivers.items():
        if np.ptp(d) == 0:
            continue
        if name == 'heading_deg':
            d = np.cos(np.radians(d))
        dc = d - d.mean()
        best = (0.0, '')
        for s in prep.sensors:
            for a in range(3):
                r = residual[:, s, a] - residual[:, s, a].mean()
                den = np.sqrt((dc @ dc) * (r @ r))
                corr = float(dc @ r / den) if den > 0 else 0.0
                if abs(corr) > abs(best[0]):
                    best = (corr, f'sensor {s + 1} {"xyz"[a]}')
        out['correlation'][name] = {'r': best[0], 'where': best[1]}
    out['drivers'] = list(drivers)
    return out


# ---------------------------------------------------------------------------------------
# Target passages: localized fields that no candidate represents

#: Families of the full model the detector fits (every candidate of the library that is
#: global in time; ``time_skew`` is the isotropic part of ``eddy_current`` to first order,
#: ``external_field`` is left out so that a target's common part stays in the residual).
_DETECTOR_FAMILIES = (
    'eddy_current',
    'sensor_misalignment',
    'reference_interference',
    'thermal_drift',
    'vehicle_current',
)


def _lstsq_rows(
    prep: _Prepared, cols: np.ndarray, target: np.ndarray, rows: np.ndarray
) -> np.ndarray:
    """Least squares on the samples ``rows`` (bool, N) only; physical coefficients."""
    a = _flat(cols[rows], prep.sensors)
    a = a.reshape(-1, a.shape[-1])
    y = _flat(target[rows], prep.sensors).reshape(-1)
    gram = a.T @ a
    norm = np.sqrt(np.diag(gram)).copy()
    norm[norm == 0] = 1.0
    return _solve_fast(gram / np.outer(norm, norm), (a.T @ y) / norm) / norm


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of True: (first, last) indices."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))


def _full_model_residual(
    prep: _Prepared, names: set[str], include: np.ndarray, settings: Settings
) -> np.ndarray:
    """Residual (N, 4, 3) of the base model plus every global candidate, fitted on
    ``include`` only and evaluated everywhere (the model is global in time)."""
    y = prep.fields - prep.base_offset
    for _ in range(3):
        cols = _detector_columns(prep, names, include, settings)
        coef = _lstsq_rows(prep, cols, y, include)
        if not (prep.absolute and _refresh_background(prep, coef[:6])):
            break
        y = prep.fields - prep.base_offset
    residual = prep.fields - prep.base_offset - np.einsum('nsap,p->nsa', cols, coef)
    if not prep.absolute:
        residual = residual - residual[:, :1]
    return residual


def _detector_columns(
    prep: _Prepared, names: set[str], include: np.ndarray, settings: Settings
) -> np.ndarray:
    """Columns (N, 4, 3, p) of the base model plus every global candidate."""
    y = prep.fields - prep.base_offset
    coef = _lstsq_rows(prep, prep.base_cols, y, include)
    prediction = prep.base_offset + np.einsum('nsap,p->nsa', prep.base_cols, coef)
    ctx = Context(
        prep.t,
        ALL_SENSORS,
        prep.absolute,
        prep.b_background,
        prep.b_rate,
        prediction,
        prep.temperature_c,
        prep.current_a,
        prep.piece,
        prep.rotation,
        settings.knot_s,
    )
    return np.concatenate(
        [prep.base_cols]
        + [LIBRARY[n].build(ctx, None)[0] for n in _DETECTOR_FAMILIES if n in names],
        axis=-1,
    )


def _robust_start(prep: _Prepared, names: set[str], settings: Settings, width: int) -> np.ndarray:
    """Samples (bool, N) of the half of the run that the full model fits best.

    A strong target pulls a least-squares fit over the whole run, and a slow regressor
    (temperature, a drift) can take part of it, so the fit on all samples is no guide to
    where the target is. Least trimmed squares on blocks of ~2 s (per-block Gram matrices):
    from several starts (all blocks; each contiguous half of the run; each continuous piece
    of at least a quarter of it), concentration steps keep the half of the blocks with the
    smallest mean square residual; the start with the smallest trimmed sum wins.
    """
    n = len(prep.t)
    y = prep.fields - prep.base_offset
    cols = _detector_columns(prep, names, np.ones(n, dtype=bool), settings)
    a = _flat(cols, prep.sensors)
    target = _flat(y, prep.sensors)
    norm = np.sqrt(np.einsum('nmp,nmp->p', a, a))
    norm[norm == 0] = 1.0
    a = a / norm
    # Blocks of ``width`` samples within each piece.
    block = np.empty(n, dtype=int)
    count = 0
    for p in np.unique(prep.piece):
        idx = np.flatnonzero(prep.piece == p)
        block[idx] = count + np.arange(len(idx)) // width
        count = int(block[idx].max()) + 1
    grams = np.zeros((count, a.shape[-1], a.shape[-1]))
    rhs = np.zeros((count, a.shape[-1]))
    for b in range(count):
        ab = a[block == b].reshape(-1, a.shape[-1])
        grams[b] = ab.T @ ab
        rhs[b] = ab.T @ target[block == b].reshape(-1)

    def fit(chosen: np.ndarray) -> np.ndarray:
        theta = _solve_fast(grams[chosen].sum(axis=0), rhs[chosen].sum(axis=0))
        r = target - np.einsum('nmp,p->nm', a, theta)
        return r

    r = fit(np.ones(count, dtype=bool))
    _, sigma = _noise_floor(r)  # the 4th difference does not see a smooth target
    sigma = np.maximum(sigma, 1e-12)

    def block_scores(r: np.ndarray) -> np.ndarray:
        q = np.mean((r / sigma) ** 2, axis=1)
        return np.bincount(block, q, count) / np.maximum(np.bincount(block, None, count), 1)

    starts = [np.ones(count, dtype=bool)]
    order = np.arange(count)
    for lo in (0.0, 0.25, 0.5):
        starts.append((order >= lo * count) & (order < (lo + 0.5) * count))
    for p in np.unique(prep.piece):
        if np.mean(prep.piece == p) >= 0.25 and len(np.unique(prep.piece)) > 1:
            starts.append(np.isin(order, np.unique(block[prep.piece == p])))
    half = max(1, count // 2)
    best, best_cost = starts[0], np.inf
    for chosen in starts:
        for _ in range(4):
            scores = block_scores(fit(chosen))
            new = np.zeros(count, dtype=bool)
            new[np.argsort(scores)[:half]] = True
            if np.array_equal(new, chosen):
                break
            chosen = new
        cost = float(np.sort(scores)[:half].sum())
        if cost < best_cost:
            best, best_cost = chosen, cost
    return best[block]


def _target_spans(
    prep: _Prepared, names: set[str], settings: Settings
) -> tuple[list[dict[str, Any]], list[str], dict[str, float]]:
    """Spans of the run where the residual is dominated by a localized field that no
    candidate represents (a target passed close to the track).

    The base model plus every global candidate of the library is fitted (so a genuine
    effect, which is global in time, is explained wherever it shows: turns, temperature,
    current); its residual, in units of each channel's white-noise sigma (4th difference,
    MAD), is averaged over ~2 s. A span is a contiguous stretch above ``target_low`` x the
    run's median level that reaches ``target_high`` x; it is widened by ``target_margin`` of
    its length (at least 2 s) on either side. The fit is repeated without the spans until
    they settle (a strong target distorts the first fit). Spans are only excluded when they
    are localized: together at most ``target_max_fraction`` of the run. Returns the spans
    (seconds from the first sample) with the evidence, and notes.
    """
    from scipy.ndimage import uniform_filter1d

    prep = replace(prep)  # the detector refreshes B^b on its own copy
    n = len(prep.t)
    t = prep.t
    dt = float(np.median(np.diff(t)))
    width = max(5, int(round(2.0 / dt)))
    spans: list[tuple[int, int]] = []
    notes: list[str] = []

    def score(include: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        residual = _full_model_residual(prep, names, include, settings)
        flat = _flat(residual, prep.sensors)
        _, sigma = _noise_floor(flat[include])
        sigma = np.maximum(sigma, 1e-12)
        q = np.mean((flat / sigma) ** 2, axis=1)
        z = np.empty_like(q)
        for p in np.unique(prep.piece):  # no average across a jump
            idx = np.flatnonzero(prep.piece == p)
            z[idx] = uniform_filter1d(q[idx], min(width, len(idx)), mode='nearest')
        return residual, flat, sigma, z

    include = _robust_start(prep, names, settings, width)
    last = None
    for _ in range(6):
        residual, flat, sigma, z = score(include)
        level = max(float(np.median(z)), 1.0)
        info = {
            'median_level': float(np.median(z)),
            'peak_over_level': float(np.max(z) / level),
            'high': settings.target_high,
            'low': settings.target_low,
        }
        high, low = settings.target_high * level, settings.target_low * level
        found = [(i, j) for i, j in _runs(z > low) if np.max(z[i : j + 1]) > high]
        mask = np.zeros(n, dtype=bool)
        spans = []
        for i, j in found:
            # The margin stays within the continuous piece of the run (a jump between recorded
            # segments is a different place).
            margin = float(np.clip(settings.target_margin * (t[j] - t[i]), 2.0, 15.0))
            lo = int(np.searchsorted(t, t[i] - margin, side='left'))
            hi = int(np.searchsorted(t, t[j] + margin, side='right')) - 1
            piece = prep.piece[i + int(np.argmax(z[i : j + 1]))]
            same = np.flatnonzero(prep.piece[lo : hi + 1] == piece) + lo
            if len(same):
                lo, hi = int(same[0]), int(same[-1])
            mask[lo : hi + 1] = True
        spans = _runs(mask)
        if mask.mean() > settings.target_max_fraction:
            notes.append(
                f'the residual of the full candidate model is far above the noise over '
                f'{100 * mask.mean():.0f} % of the run: not a localized target passage, nothing excluded'
            )
            return [], notes, info
        key = tuple(spans)
        if key == last:
            break
        last = key
        include = ~mask
    # Confirm each span: fitted with its own samples in, a target stays far above the rest
    # (no candidate represents it); a span that the model explains once it may fit it was
    # an extrapolation of a fit on part of the run, not a target.
    confirmed = []
    for i, j in spans:
        inside = np.zeros(n, dtype=bool)
        inside[i : j + 1] = True
        with_it = ~mask | inside
        _, _, _, z_in = score(with_it)
        ratio = float(np.mean(z_in[inside]) / max(np.median(z_in[with_it & ~inside]), 1e-12))
        if ratio >= settings.target_confirm:
            confirmed.append((i, j))
        else:
            notes.append(
                f'{t[i]:.1f}-{t[j]:.1f} s not excluded: the full candidate model explains it once '
                f'fitted on it (mean square {ratio:.2g} x the rest of the run)'
            )
    info['confirmed'] = len(confirmed)
    spans = confirmed
    if not spans:
        return [], notes, info
    residual, flat, sigma, z = score(
        ~np.isin(np.arange(n), np.concatenate([np.arange(i, j + 1) for i, j in spans]))
    )
    # Evidence per span: where the residual peaks, how much of it differs between sensors.
    common = (
        residual.mean(axis=1, keepdims=True) if prep.absolute else np.zeros_like(residual[:, :1])
    )
    diff = residual - common
    sel = list(prep.sensors)
    out = []
    for i, j in spans:
        k = i + int(np.argmax(z[i : j + 1]))
        peak = float(np.sqrt(np.mean(flat[k] ** 2)))
        window = slice(max(i, k - width // 2), min(j, k + width // 2) + 1)
        d_rms = float(np.sqrt(np.mean(diff[window][:, sel] ** 2)))
        c_rms = float(np.sqrt(np.mean(common[window] ** 2)))
        turn = None
        if prep.rotation is not None:
            turn = float(
                np.degrees(
                    (
                        Rotation.from_matrix(prep.rotation[j])
                        * Rotation.from_matrix(prep.rotation[i]).inv()
                    ).magnitude()
                )
            )
        noise = float(np.sqrt(np.mean(sigma**2)))
        reason = (
            f'localized field that no candidate represents (a target passed close to the track): the '
            f'residual of the base model plus every global candidate peaks at {peak:.3g} nT '
            f'({peak / noise:.0f} x the noise) at t = {t[k]:.1f} s and falls off on both sides; '
            f'{d_rms:.3g} nT RMS of it differs between the sensors (a gradient)'
        )
        if prep.absolute:
            reason += f', {c_rms:.3g} nT is common to them'
        if turn is not None:
            reason += f'; attitude change across the span {turn:.1f} deg'
        out.append(
            {
                'start_s': float(t[i]),
                'end_s': float(t[j]),
                'duration_s': float(t[j] - t[i]),
                'samples': int(j - i + 1),
                'peak_time_s': float(t[k]),
                'peak_residual_rms_nT': peak,
                'peak_over_noise': peak / noise,
                'peak_difference_rms_nT': d_rms,
                'peak_common_rms_nT': c_rms if prep.absolute else None,
                'attitude_change_deg': turn,
                'reason': reason,
            }
        )
    return out, notes, info


# ---------------------------------------------------------------------------------------
# The workflow


def _fit_current(
    prep: _Prepared, active: list[_Family], y: np.ndarray, settings: Settings
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Context, np.ndarray]:
    """Fit the current model on all samples, iterating what depends on the fit: ``B^b`` (the
    Earth-field correction; linear families on ``B^b`` follow it) and the linearisation point
    of the nonlinear families (Gauss-Newton: rebuilt at their current estimate). Returns the
    columns, the fixed offsets, the coefficients, the prediction of every sensor, the build
    context (each sensor's prediction without its own named effects) and the fitted K_i."""
    last = None
    for _ in range(8):
        cur_off = sum((f.offset for f in active if f.offset is not None), np.zeros_like(y))
        cur_cols = np.concatenate([prep.base_cols] + [f.cols for f in active], axis=-1)
        coef = _lstsq_full(prep, cur_cols, y - cur_off)
        prediction = prep.base_offset + np.einsum('nsap,p->nsa', cur_cols, coef) + cur_off
        moved = prep.absolute and _refresh_background(prep, coef[:6])
        # Candidates are built on each sensor's prediction without the effects already named
        # in that sensor (a delay of a reading that holds an eddy term would differentiate it).
        own = np.zeros_like(y)
        bounds = [prep.base_cols.shape[-1]]
        for f in active:
            bounds.append(bounds[-1] + f.cols.shape[-1])
            if f.labels[0][0] >= 0:
                own += _effect_field(f, coef[bounds[-2] : bounds[-1]])
        basis = prediction - own
        if not prep.absolute:
            # B^b = B_1' carries sensor 1's noise; the derivatives and shifts the builders take
            # would amplify it (an interpolating spline's derivative by ~1.4/dt).
            basis = _smoothed(prep.t, basis, prep.piece)
        ctx = Context(
            prep.t,
            ALL_SENSORS,
            prep.absolute,
            prep.b_background,
            prep.b_rate,
            basis,
            prep.temperature_c,
            prep.current_a,
            prep.piece,
            prep.rotation,
            settings.knot_s,
        )
        if not prep.absolute:
            # Pair view: B^b = B_1' less the effects named in sensor 1 (its own delay or eddy
            # term must not magnetise the other sensors' model).
            moved = _refresh_pair_background(prep, prep.fields[:, 0] - own[:, 0])
        k_hat = _soft_iron(prep.base_labels, coef[: prep.base_cols.shape[-1]])
        # Converged when the prediction no longer moves (a nonlinear family's offset is the
        # exact remainder of the prediction it was built on, so it must follow it).
        settled = (
            last is not None and float(np.max(np.abs(prediction - last))) < 1e-3 and not moved
        )
        last = prediction
        if settled or not any(f.candidate.nonlinear for f in active) and not moved:
            break
        for k, f in enumerate(active):
            sensor = f.labels[0][0]
            if f.candidate.nonlinear:
                estimate = {
                    label: float(v) for label, v in zip(f.labels, coef[bounds[k] : bounds[k + 1]])
                }
                built = f.candidate.build(ctx, estimate)
            elif moved:
                built = f.candidate.build(ctx, None)
                estimate = None
            else:
                continue
            unit = _restrict(_Family(f.candidate, *built), sensor)
            unit.estimate = estimate
            active[k] = unit
    return cur_cols, cur_off, coef, prediction, ctx, k_hat


def analyze(
    recording: Any,
    geometry: Any = None,
    earth_field_enu: Any = None,
    *,
    settings: Settings | None = None,
    keep_series: bool = True,
    window_s: tuple[float, float] | None = None,
) -> Report:
    """Find the effects the base model is missing in a recorded run.

    Parameters
    ----------
    recording : io.recording.Recording (or anything with ``t_s``, ``fields`` (N, 4, 3) T and
        the optional ``orientation_xyzw``, ``temperature_c``, ``current_a``)
    geometry : TetraGeometry, optional
        Used to express the final residual on the tensor (nT/m) as well.
    earth_field_enu : (3,) tesla, optional
        Estimated from sensor 1 and /odom when absent.
    settings : Settings, optional
    keep_series : keep the arrays for the plots in ``Report.series``
    window_s : (t0, t1) s from the first sample, optional
        Analyse only this part of the run (``t1`` may be ``inf``).

    Returns
    -------
    Report
    """
    started = time.perf_counter()
    settings = settings or Settings()
    names = settings.candidates or tuple(c.name for c in CANDIDATES)
    unknown = [n for n in names if n not in LIBRARY]
    if unknown:
        raise InputError(f'unknown candidate effects {unknown}; the library has {sorted(LIBRARY)}')
    if window_s is not None:
        window_s = (float(window_s[0]), float(window_s[1]))
        if not (np.isfinite(window_s[0]) and window_s[0] >= 0 and window_s[1] > window_s[0]):
            raise InputError(f'window_s needs 0 <= T0 < T1, got {window_s}')
    prep = _prepare(recording, earth_field_enu, settings, window_s)
    testable, untestable = _testable(prep, tuple(names))
    excluded: list[dict[str, Any]] = []
    detector: dict[str, float] = {}
    if settings.exclude_targets:
        excluded, target_notes, detector = _target_spans(
            prep, {c.name for c in testable}, settings
        )
        if excluded:
            prep = _prepare(
                recording,
                earth_field_enu,
                settings,
                window_s,
                [(e['start_s'], e['end_s']) for e in excluded],
            )
            target_notes.append(
                f'{len(excluded)} span(s) excluded from the fits and the gap ('
                + ', '.join(f'{e["start_s"]:.1f}-{e["end_s"]:.1f} s' for e in excluded)
                + '): a localized field that differs between the sensors and that no candidate represents '
                '(a target passed close to the track); see excluded_spans'
            )
        prep.notes.extend(target_notes)
    if window_s is not None:
        prep.notes.insert(
            0,
            f'analysis restricted to the window {window_s[0]:g}:{window_s[1]:g} s '
            '(seconds from the first sample)',
        )
    duration = float(prep.t[-1] - prep.t[0])
    block_s = settings.block_s or float(np.clip(duration / 40.0, 5.0, 30.0))
    n = len(prep.t)
    y = prep.fields - prep.base_offset
    active: list[_Family] = []
    steps: list[Step] = []
    rounds: list[dict[str, Any]] = []
    residuals: list[np.ndarray] = []
    gaps: list[float] = []
    floors: list[float] = []
    step_units: list[list[int]] = []
    notes_revision: list[str] = []
    revisions = 0
    base_p = prep.base_cols.shape[-1]
    while True:
        cur_cols, cur_off, coef, prediction, ctx, k_hat = _fit_current(prep, active, y, settings)
        residual = prep.fields - prediction
        if not prep.absolute:
            residual = residual - residual[:, :1]  # pair view: B_i' - B_1' against the model
        floor, _ = _noise_floor(_flat(residual, prep.sensors))
        taken = {(f.candidate.name, f.labels[0][0]) for f in active}
        cur_sensor = np.concatenate(
            [np.full(prep.base_cols.shape[-1], -2)]
            + [np.full(f.cols.shape[-1], f.labels[0][0]) for f in active]
        )
        units: list[_Family] = []
        plain: dict[int, _Family] = {}  # pair view, sensor 1: the unit as it replaces a named one
        if len(steps) < settings.max_effects:
            design = _current_design(prep, cur_cols, cur_sensor, y - cur_off)
            for c in testable:
                if all((c.name, s) in taken for s in ALL_SENSORS + (-1,)):
                    continue
                family = _build(c, ctx, prep, design)
                for s in sorted({lab[0] for lab in family.labels}):
                    if (c.name, s) not in taken:
                        unit = _restrict(family, s)
                        if s == 0 and not prep.absolute:
                            plain[len(units)] = unit
                            unit = _reference_in_pairs(unit, k_hat)
                        units.append(unit)
        # Z = [current columns | unit columns | plain units | target | unit offsets]
        extra_units = list(plain.values())
        allcols = np.concatenate([cur_cols] + [u.cols for u in units + extra_units], axis=-1)
        a = _flat(allcols, prep.sensors)
        norm = np.sqrt(np.einsum('nmp,nmp->p', a, a))
        usable = norm > 0
        norm[~usable] = 1.0
        extra = [_flat(y - cur_off, prep.sensors)[..., None]]
        ty = a.shape[-1]
        unit_cols: list[np.ndarray] = []
        unit_off: list[list[int]] = []
        start = cur_cols.shape[-1]
        for u in units + extra_units:
            p = u.cols.shape[-1]
            unit_cols.append(start + np.flatnonzero(usable[start : start + p]))
            start += p
            if u.offset is not None and np.any(u.offset):
                unit_off.append([ty + len(extra)])
                extra.append(_flat(u.offset, prep.sensors)[..., None])
            else:
                unit_off.append([])
        # Where the swap test finds each unit's columns (the plain version when there is one).
        swap_index = {k: len(units) + i for i, k in enumerate(plain)}
        # Offsets of the units already in the model, to add back when one is taken out.
        active_off: list[list[int]] = []
        for f in active:
            if f.offset is not None and np.any(f.offset):
                active_off.append([ty + len(extra)])
                extra.append(_flat(f.offset, prep.sensors)[..., None])
            else:
                active_off.append([])
        gram = _Gram(
            np.concatenate([a / norm] + extra, axis=-1), prep.t, block_s, settings.n_folds
        )
        n_obs = gram.n

        def bic(res: dict[str, Any]) -> float:
            return float(n_obs * np.log(res['cv'] / n_obs) + res['rank'] * np.log(n_obs))

        channels = 3 * len(prep.sensors)

        def compare(res: dict[str, Any], ref: dict[str, Any], sensor: int) -> dict[str, Any]:
            """``res`` (the model with a unit of ``sensor`` added) against ``ref``: the
            selection criterion. The explained RMS is over the unit's own sensor (3 channels;
            a common term, or sensor 1 in the pair view, over all channels)."""
            dp = res['rank'] - ref['rank']
            gain = ref['cv'] - res['cv']
            dof = max(n_obs - res['rank'], 1.0)
            if dp > 0 and gain > 0:
                fstat = (gain / dp) / (res['cv'] / dof)
                pval = float(stats.f.sf(fstat, dp, dof))
            else:
                fstat, pval = 0.0, 1.0
            own = 3 if (sensor >= 1 or (sensor == 0 and prep.absolute)) else channels
            explained = float(np.sqrt(max(gain, 0.0) / (n_obs / channels * own)))
            dbic = bic(res) - bic(ref)
            return {
                'n_parameters': int(dp),
                'gap_after_nT': float(np.sqrt(res['cv'] / n_obs)),
                'delta_bic': float(dbic),
                'f_statistic': float(fstat),
                'p_value': pval,
                'explained_rms_nT': explained,
                'result': res,
                'passes': bool(
                    dbic < 0 and pval < settings.alpha and explained >= settings.relevance * floor
                ),
            }

        base_idx = np.flatnonzero(usable[:base_p])
        active_cols = []
        lo = base_p
        for f in active:
            hi = lo + f.cols.shape[-1]
            active_cols.append(lo + np.flatnonzero(usable[lo:hi]))
            lo = hi
        sel_idx = np.flatnonzero(usable[: cur_cols.shape[-1]])
        sel_off: list[int] = []
        cur = gram.evaluate(sel_idx, ty)
        gap_cur = float(np.sqrt(cur['cv'] / n_obs))
        # Backward check: is every unit in the model still needed, and does a unit with
        # fewer parameters in the same sensor explain as much now that the others are in?
        revised = None
        for k, f in enumerate(active):
            rest = np.concatenate([base_idx] + [c for j, c in enumerate(active_cols) if j != k])
            without = gram.evaluate(rest, ty, add_back=active_off[k])
            if not compare(cur, without, f.labels[0][0])['passes']:
                revised = (
                    k,
                    None,
                    f'{f.candidate.name} at sensor {f.labels[0][0] + 1} is no longer needed '
                    f'once the other effects are in (removed)',
                )
                break
            best_alt = None
            for j, u in enumerate(units):
                if (
                    u.labels[0][0] != f.labels[0][0]
                    or u.candidate.name == f.candidate.name
                    or len(unit_cols[j]) > len(active_cols[k])
                ):
                    continue  # only a unit with no more parameters may replace one
                jj = swap_index.get(j, j)
                res = gram.evaluate(
                    np.concatenate([rest, unit_cols[jj]]), ty, unit_off[jj], add_back=active_off[k]
                )
                if bic(res) < bic(cur) and (best_alt is None or bic(res) < best_alt[1]):
                    best_alt = (j, bic(res))
            if best_alt is not None:
                u = plain.get(best_alt[0], units[best_alt[0]])
                revised = (
                    k,
                    u,
                    f'{f.candidate.name} at sensor {f.labels[0][0] + 1} replaced by the more '
                    f'parsimonious {u.candidate.name} (CV-BIC {best_alt[1] - bic(cur):+.4g}) once the '
                    'other effects are in',
                )
                break
        if revised is not None and revisions < 4 * settings.max_effects:
            revisions += 1
            k, replacement, message = revised
            notes_revision.append(message)
            _revise(steps, step_units, active, k, replacement, message)
            continue
        gaps.append(gap_cur)
        floors.append(floor)
        residuals.append(residual)
        chosen: list[int] = []
        first_table: list[dict[str, Any]] | None = None
        while True:
            table = []
            for k, u in enumerate(units):
                if k in chosen or (chosen and u.candidate.name != units[chosen[0]].candidate.name):
                    continue  # after the first unit, the step extends its family to other sensors
                res = gram.evaluate(
                    np.concatenate([sel_idx, unit_cols[k]]), ty, sel_off + unit_off[k]
                )
                row = compare(res, cur, u.labels[0][0])
                row.update(
                    {
                        'effect': u.candidate.name,
                        'unit': k,
                        'sensor': 'all' if u.labels[0][0] < 0 else u.labels[0][0] + 1,
                    }
                )
                table.append(row)
            table.sort(key=lambda row: row['delta_bic'])
            if first_table is None:
                first_table = table
            winners = [row for row in table if row['passes']]
            if not winners:
                break
            best = winners[0]
            chosen.append(best['unit'])
            sel_idx = np.concatenate([sel_idx, unit_cols[best['unit']]])
            sel_off = sel_off + unit_off[best['unit']]
            cur = best['result']
        rounds.append(
            {
                'gap_nT': gap_cur,
                'noise_floor_nT': floor,
                'model': [f'{f.candidate.name}@{_sensor_name(f.labels[0][0])}' for f in active],
                'candidates': [
                    {k: v for k, v in row.items() if k not in ('unit', 'result')}
                    for row in (first_table or [])
                ],
            }
        )
        if not chosen:
            break
        name = units[chosen[0]].candidate.name
        gap_after = float(np.sqrt(cur['cv'] / n_obs))
        sensors_added = [
            'all' if units[k].labels[0][0] < 0 else units[k].labels[0][0] + 1 for k in chosen
        ]
        first = [row for row in first_table if row['unit'] == chosen[0]][0]
        rivals = [row for row in first_table if row['effect'] != name]
        evidence = (
            f'added for sensor(s) {", ".join(map(str, sensors_added))}: held-out gap {gap_cur:.3g} -> '
            f'{gap_after:.3g} nT (noise floor {floor:.3g} nT); first unit (sensor {first["sensor"]}): '
            f'{first["n_parameters"]} parameters explain {first["explained_rms_nT"]:.3g} nT RMS of the '
            f'held-out residual, CV-BIC {first["delta_bic"]:+.4g}, held-out F = {first["f_statistic"]:.4g} '
            f'(p = {first["p_value"]:.3g})'
        )
        if rivals:
            r = rivals[0]
            evidence += (
                f'; best other family: {r["effect"]} at sensor {r["sensor"]} with {r["n_parameters"]} '
                f'parameters, gap {r["gap_after_nT"]:.3g} nT, CV-BIC {r["delta_bic"]:+.4g}'
            )
        n_params = sum(len(unit_cols[k]) for k in chosen)
        steps.append(
            Step(
                name,
                gap_cur,
                gap_after,
                {},
                evidence,
                n_params,
                first['delta_bic'],
                first['f_statistic'],
                first['p_value'],
            )
        )
        step_units.append(list(range(len(active), len(active) + len(chosen))))
        active.extend(units[k] for k in chosen)
        _merge_steps(steps, step_units)
    # Final joint fit: parameters of every named effect and of the base model.
    bounds = [base_p]
    for f in active:
        bounds.append(bounds[-1] + f.cols.shape[-1])
    effect_fields: list[np.ndarray] = []
    for step, members in zip(steps, step_units):
        labels: list[tuple[int, str]] = []
        values: list[np.ndarray] = []
        fld = np.zeros_like(y)
        for k in members:
            c = coef[bounds[k] : bounds[k + 1]]
            labels += active[k].labels
            values.append(c)
            fld += _effect_field(active[k], c)
        step.n_parameters = int(sum(active[k].cols.shape[-1] for k in members))
        step.parameters = _format(labels, np.concatenate(values), prep.absolute)
        step.parameters['units'] = LIBRARY[step.effect].parameters
        step.parameters['rms_contribution_nT'] = {
            f'sensor_{s + 1}': float(np.sqrt(np.mean(fld[:, s] ** 2)))
            for s in ALL_SENSORS
            if np.any(fld[:, s])
        }
        effect_fields.append(fld)
    base_params = _format(prep.base_labels, coef[:base_p], prep.absolute)
    if 'all_sensors' in base_params['per_sensor']:
        base_params['earth_field_correction_enu_nT'] = base_params['per_sensor'].pop('all_sensors')
    gap_final, floor_final = gaps[-1], floors[-1]
    adequate = gap_final <= settings.adequate_ratio * floor_final
    notes = list(prep.notes) + notes_revision
    if not adequate:
        notes.append(
            f'the final gap {gap_final:.3g} nT exceeds {settings.adequate_ratio} x the noise floor '
            f'({floor_final:.3g} nT) but no candidate in the library explains the rest: '
            'an effect outside the library (or a target close to the track) remains'
        )
        if excluded:
            notes.append(
                'target passage(s) were excluded, but the rest of the run is not at the noise floor either: '
                "the target's field may reach the manoeuvre (a trim flown near the target); analyse a run, "
                'or a --window, flown away from targets'
            )
    diagnostics = {
        'base': _diagnostics(prep, residuals[0]),
        'final': _diagnostics(prep, residuals[-1]),
    }
    if geometry is not None:
        from ..core.geometry import difference_tensor

        if prep.absolute:
            g = difference_tensor(residuals[-1] / NT_PER_T, geometry) * NT_PER_T
        else:
            g = (
                difference_tensor(
                    np.concatenate([np.zeros((n, 1, 3)), residuals[-1][:, 1:]], axis=1) / NT_PER_T,
                    geometry,
                )
                * NT_PER_T
            )
        diagnostics['final_tensor_rms_nT_per_m'] = float(np.sqrt(np.mean(g**2)))
    data = {
        'samples': n,
        'duration_s': duration,
        'sample_rate_hz': float((n - 1) / duration) if duration else 0.0,
        'cv_block_s': block_s,
        'folds': settings.n_folds,
        'has_odom': prep.absolute,
        'has_temperature': prep.temperature_c is not None,
        'has_current': prep.current_a is not None,
        'missing_topics': dict(getattr(recording, 'missing', {}) or {}),
        'window_s': None
        if window_s is None
        else [window_s[0], window_s[1] if np.isfinite(window_s[1]) else None],
        'excluded_s': float(sum(e['duration_s'] for e in excluded)),
        'target_detector': detector,
    }
    if prep.earth_field_nT is not None:
        data['earth_field_enu_nT'] = [float(v) for v in prep.earth_field_nT + coef[:3]]
        data['earth_field_drift_enu_nT'] = [float(v) for v in coef[3:6]]
        data['earth_field_source'] = (
            'params, corrected by the fit'
            if earth_field_enu is not None
            else 'estimated from sensor 1 and /odom, refined by the fit'
        )
        if earth_field_enu is not None:
            data['earth_field_params_enu_nT'] = [float(v) for v in prep.earth_field_nT]
    report = Report(
        named_effects=[s.effect for s in steps],
        steps=steps,
        gap_initial_nT=gaps[0],
        gap_final_nT=gap_final,
        noise_floor_nT=floor_final,
        base_model=BASE_MODEL
        + (
            '; B^b = R^T earth_field_enu from /odom'
            if prep.absolute
            else "; B^b = B_1' (no /odom)"
        ),
        adequate=bool(adequate),
        untestable=untestable,
        view='absolute' if prep.absolute else 'pair',
        notes=notes,
        rounds=rounds,
        diagnostics=diagnostics,
        base_parameters=base_params,
        data=data,
        runtime_s=0.0,
        excluded_spans=excluded,
    )
    if keep_series:
        report.series = {
            't': prep.t,
            'sensors': prep.sensors,
            'residuals': residuals,
            'gaps': gaps,
            'floors': floors,
            'effect_fields': effect_fields,
            'b_rate': prep.b_rate,
            'attitude': prep.attitude,
            'temperature_c': prep.temperature_c,
            'current_a': prep.current_a,
        }
    report.runtime_s = float(time.perf_counter() - started)
    return report
