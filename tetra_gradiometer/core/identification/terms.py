"""Calibration with vehicle effects: ``k``, ``b`` and the effects' terms fitted jointly on a
known-gradient window (a trim), optionally with a constant regional gradient, and the
selection of the terms the data call for.

**The joint solve.** On the pair differences ``P_n = (G_m,n - G_known,n) a`` (3 axes x 3
pairs; ``G_known = R_n^T G_w R_n`` with a regional gradient, else 0) the model is
``P_n[r, i] = x_n^T theta[:, r, i]`` with the regressors ``x_n = (B_1', 1, x_terms)`` (4 + M)
shared by all nine outputs: the general ``K_i1`` (36 with ``b``) and every term. The pair
noise is correlated (``sigma^2 (I + 1 1^T)`` over the pairs, per axis); right-multiplying by
``W = (I + 1 1^T)^(-1/2)`` whitens it. With one design for every output the whitened least
squares is ``theta = R^-1 Q^T P W`` (QR of the column-scaled ``X``), exact and fast; a
regional gradient (5 coefficients ``c``, its columns differ per output) is solved first on
the part of the data ``X`` cannot explain (``(I - Q Q^T)``), then ``theta`` on what is left.
The covariance is exact for white sensor noise: ``sigma^2 (X^T X)^-1`` per whitened output,
plus what ``c``'s uncertainty passes to ``theta``.

**Selection** (:func:`select_terms`): forward selection on held-out data. The window is cut
into :data:`FOLDS` contiguous blocks; each is predicted by the fit on the others, so a term
must predict data it was not fitted on (a contiguous block also holds out the slow drifts a
random split would leak). A candidate enters when, against the current set, (1) the
held-out F statistic ``((RSS_0 - RSS_1) / p) / (RSS_1 / n)`` exceeds its ``1 - alpha / c``
quantile (``c`` candidates left: Bonferroni), and (2) it removes at least
:data:`MIN_GAIN` of the held-out residual's sum of squares (a term that explains less than
a tenth of the noise's RMS is not worth its parameters). The strongest passing candidate
enters first; the rest are tested again against the new set. A clean vehicle passes
neither test by chance more often than ``alpha`` per selection.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ...errors import IdentifiabilityError
from ..effects import Channels, Term, current_channel, effect
from ..geometry import TetraGeometry
from ..model import InterferenceParameters
from ..types import FloatArray
from ..units import NT_PER_T
from ..vehicle_signals import BATTERY_TOPIC
from ._selection import PAIR_WHITENER, held_out_blocks, held_out_f_test
from .lstsq import REGIONAL_BASIS, _body_tensor, _orientations
from .result import TensorCalibration

#: Contiguous held-out blocks of the selection.
FOLDS = 5
#: Family-wise false-selection probability of one selection on a clean vehicle.
ALPHA = 1.0e-3
#: Smallest held-out reduction of the residual sum of squares that keeps a term.
MIN_GAIN = 0.01
#: Fewest samples a selection is made on (5 blocks of at least 20).
MIN_SELECTION_SAMPLES = 100
_PAIR_UNWHITENER = np.linalg.inv(PAIR_WHITENER)

METHOD = 'known_gradient_lstsq_general'


@dataclass(frozen=True)
class PairSolution:
    """The joint solve on whitened pair differences.

    Attributes
    ----------
    theta : (P, 3, 3) ``[regressor, axis, pair]``, unwhitened, SI
    covariance : (9 P, 9 P) of ``theta.reshape(-1)`` (unwhitened), SI
    regional : (5,) regional coefficients, T/m, or None
    regional_covariance : (5, 5) or None
    sigma : sensor noise per axis estimated from the residual, T
    residual_w : (N, 9) whitened residual, T
    condition_number : of the column-scaled ``X``
    """

    theta: FloatArray
    covariance: FloatArray
    regional: FloatArray | None
    regional_covariance: FloatArray | None
    sigma: float
    residual_w: FloatArray
    condition_number: float


def _whiten(pairs: FloatArray) -> FloatArray:
    """(N, 3, 3) ``[n, axis, pair]`` -> (N, 9) whitened over the pairs."""
    return (pairs @ PAIR_WHITENER).reshape(len(pairs), 9)


def regional_columns(orientation_xyzw: FloatArray, geometry: TetraGeometry) -> FloatArray:
    """The regional gradient's whitened pair-difference columns, (N, 5, 9): coefficient
    ``q`` of ``G_w`` seen in the body frame, times ``a``, whitened."""
    quaternions = _orientations(orientation_xyzw, len(orientation_xyzw), 'regional_columns')
    body = np.stack([_body_tensor(quaternions, basis) for basis in REGIONAL_BASIS], axis=1)
    return (body @ geometry.a @ PAIR_WHITENER).reshape(len(body), 5, 9)


def solve_pairs(
    pairs: FloatArray, x: FloatArray, regional: FloatArray | None = None
) -> PairSolution:
    """The joint least squares of the module docstring.

    Parameters
    ----------
    pairs : (N, 3, 3) ``[n, axis, pair]`` pair differences to explain, T
    x : (N, P) regressors (``B_1'``, 1, the terms'), SI
    regional : (N, 5, 9) :func:`regional_columns`, or None

    Raises
    ------
    IdentifiabilityError
        Fewer rows than unknowns, a rank-deficient design, or attitudes that cannot separate
        the regional gradient from the interference.
    """
    n, p = x.shape
    y = _whiten(pairs)
    unknowns = 9 * p + (5 if regional is not None else 0)
    if 9 * n <= unknowns:
        raise IdentifiabilityError(f'{n} samples are too few for {unknowns} unknowns')
    scale = np.sqrt(np.mean(x**2, axis=0))
    if np.any(scale == 0):
        raise IdentifiabilityError('a regressor is zero on every sample')
    q, r = np.linalg.qr(x / scale)
    singular = np.linalg.svd(r, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float('inf')
    if not np.isfinite(condition) or condition > 1e10:
        raise IdentifiabilityError(
            f'the regressors are (nearly) dependent: condition number {condition:.3g}'
        )
    c = c_cov = None
    if regional is not None:
        flat = regional.reshape(n, 45)
        projected = flat - q @ (q.T @ flat)
        y_free = y - q @ (q.T @ y)
        f3 = projected.reshape(n, 5, 9)
        normal = np.einsum('nqo,nso->qs', f3, f3)
        full = np.einsum('nqo,nso->qs', regional, regional)
        eig = np.linalg.eigvalsh(normal)
        if eig[0] <= 1e-8 * np.max(np.diag(full)):
            raise IdentifiabilityError(
                'the attitudes cannot separate a regional gradient from the interference'
            )
        c = np.linalg.solve(normal, np.einsum('nqo,no->q', f3, y_free))
        y = y - np.einsum('nqo,q->no', regional, c)
    theta_w = np.linalg.solve(r, q.T @ y) / scale[:, None]  # (P, 9)
    residual = y - x @ theta_w
    dof = 9 * n - unknowns
    sigma2 = float(np.sum(residual**2) / dof)
    r_inv = np.linalg.inv(r) / scale[:, None]
    xtx_inv = r_inv @ r_inv.T  # (X^T X)^-1, P x P
    # Whitened covariance: sigma^2 (X^T X)^-1 per output, independent outputs...
    cov_w = np.kron(xtx_inv, np.eye(9)) * sigma2
    if regional is not None and c is not None:
        c_cov = sigma2 * np.linalg.inv(normal)
        # ... plus what c's uncertainty passes to theta: A F, A = (X^T X)^-1 X^T.
        gain = (xtx_inv @ (x.T @ regional.reshape(n, 45))).reshape(p, 5, 9)
        spread = np.einsum('pqo,qs,tsu->potu', gain, c_cov, gain).reshape(9 * p, 9 * p)
        cov_w = cov_w + spread
    # Unwhiten over the pair index: theta = theta_w W^-1.
    theta = theta_w.reshape(p, 3, 3) @ _PAIR_UNWHITENER
    transform = np.kron(np.eye(3 * p), _PAIR_UNWHITENER.T)
    covariance = transform @ cov_w @ transform.T
    return PairSolution(theta, covariance, c, c_cov, float(np.sqrt(sigma2)), residual, condition)


def _parameter_order(sizes: list[int]) -> np.ndarray:
    """Index into ``theta.reshape(-1)`` (``[regressor, axis, pair]``) of each entry of
    :meth:`InterferenceParameters.full_vector`: k ``[pair, axis, col]``, b ``[pair, axis]``,
    then each term (of ``sizes`` regressors) ``[pair, axis, regressor]``."""
    p = 4 + sum(sizes)
    index = np.arange(9 * p).reshape(p, 3, 3)  # [regressor, axis, pair]
    parts = [
        np.transpose(index[:3], (2, 1, 0)).reshape(-1),  # [pair, axis, col]
        np.transpose(index[3], (1, 0)).reshape(-1),  # [pair, axis]
    ]
    start = 4
    for size in sizes:
        block = index[start : start + size]
        parts.append(np.transpose(block, (2, 1, 0)).reshape(-1))  # [pair, axis, j]
        start += size
    return np.concatenate(parts)


@dataclass(frozen=True)
class Candidate:
    """An effect offered to the selection: its term's inputs, reference, regressors (N, m)
    on the window's samples (SI), and, once tested, its evidence (:class:`Selection`)."""

    name: str
    inputs: tuple[str, ...]
    reference: tuple[float, ...]
    regressors: FloatArray
    evidence: dict[str, Any] = field(default_factory=dict, compare=False)
    channel_noise: tuple[float, ...] = ()

    @property
    def size(self) -> int:
        return int(self.regressors.shape[1])

    def select(self, keep: np.ndarray) -> Candidate:
        """The same candidate on the samples ``keep`` (a sub-window)."""
        return replace(self, regressors=self.regressors[keep])


def candidates_for(
    channels: Channels, names: tuple[str, ...] | None = None, signals: tuple[str, ...] = ()
) -> tuple[list[Candidate], dict[str, str]]:
    """The effects that ``channels`` can fit (all the registry's and the declared
    ``signals``' effect names, or ``names``), with their regressors on the samples; and, per
    effect that cannot, what it lacks."""
    from ..effects import EFFECTS

    available = tuple(channels.series)
    out, lacking = [], {}
    for name in names if names is not None else (*EFFECTS, *signals):
        spec = effect(name)
        inputs = spec.inputs(available)
        if not inputs:
            lacking[name] = spec.missing(available)
            continue
        known = channels.select(_known_rows(channels, inputs))
        if not len(known):
            # Recorded, but never near a sample (a channel that stopped, or from another
            # time): as good as missing.
            lacking[name] = f'{", ".join(inputs)} known at some sample (it never is)'
            continue
        reference = spec.reference(known, inputs)
        out.append(
            Candidate(name, inputs, reference, spec.regressors(channels, inputs, reference))
        )
    return out, lacking


#: A channel's column is redundant when what the constant and the columns before it leave
#: of it is within this many times its own noise ...
REDUNDANT_NOISE = 3.0
#: ... or this fraction of its RMS (exact dependence: float32 BatteryState values carry
#: ~1e-7 of relative rounding).
REDUNDANT_RELATIVE = 1.0e-5


def without_redundant(candidate: Candidate) -> tuple[Candidate | None, list[str]]:
    """``candidate`` without the channels whose regressor column the constant (``b``'s) and
    the candidate's earlier columns already span on the window, and a note on each.

    A constant current (a hotel load alone, held on the trim) is hard iron: ``b`` takes
    it; a battery current that is a constant hotel load plus the thrusters' currents it
    also records is their sum. Fitted, such a column makes the joint solve (nearly)
    singular: huge, cancelling coefficients, or an effect the selection cannot test. The
    rows where every column is known decide; the residual of each column after least
    squares on the constant and the columns kept before it must exceed
    :data:`REDUNDANT_NOISE` times the channel's noise and :data:`REDUNDANT_RELATIVE` of the
    column's RMS. The columns are taken in ``inputs`` order but the battery's
    (``/battery_state``, the sum of the circuits) last, so that of a dependent set the sum
    is the one left out. Only channel regressors (one column per input) are checked.
    Returns None for the candidate when no column is left.
    """
    x = candidate.regressors
    if not candidate.inputs or x.shape[1] != len(candidate.inputs):
        return candidate, []
    rows = x[np.all(np.isfinite(x), axis=1)]
    if len(rows) < 2:
        return candidate, []
    noise = candidate.channel_noise or (0.0,) * x.shape[1]
    kept: list[int] = []
    notes = []
    battery = current_channel(BATTERY_TOPIC)
    order = sorted(range(len(candidate.inputs)), key=lambda j: candidate.inputs[j] == battery)
    for j in order:
        name = candidate.inputs[j]
        basis = np.column_stack([np.ones(len(rows)), rows[:, kept]])
        coefficients = np.linalg.lstsq(basis, rows[:, j], rcond=None)[0]
        left = float(np.sqrt(np.mean((rows[:, j] - basis @ coefficients) ** 2)))
        tolerance = max(
            REDUNDANT_NOISE * noise[j], REDUNDANT_RELATIVE * np.sqrt(np.mean(rows[:, j] ** 2))
        )
        if left > tolerance:
            kept.append(j)
            continue
        if kept:
            terms = ' '.join(
                f'{c:+.4g} x {candidate.inputs[k]}'
                for c, k in zip(coefficients[1:], kept, strict=True)
            )
            notes.append(
                f'{candidate.name}: {name} = {coefficients[0]:.4g} {terms} on the window '
                f'(within {left:.2g}, its noise {noise[j]:.2g}): left out, the others and b '
                'carry its field'
            )
        else:
            notes.append(
                f'{candidate.name}: {name} is constant on the window ({coefficients[0]:.4g}, '
                f"within {left:.2g}; its noise {noise[j]:.2g}): its field is hard iron, b's; "
                'left out'
            )
    if len(kept) == len(candidate.inputs):
        return candidate, notes
    if not kept:
        return None, notes
    kept.sort()
    inputs = tuple(candidate.inputs[k] for k in kept)
    channel_noise = tuple(noise[k] for k in kept)
    return replace(
        candidate, inputs=inputs, regressors=x[:, kept], channel_noise=channel_noise
    ), notes


def _known_rows(channels: Channels, inputs: tuple[str, ...]) -> np.ndarray:
    """The samples where every recorded channel of ``inputs`` is known."""
    known = np.ones(len(channels), dtype=bool)
    for name in inputs:
        if name in channels.series:
            known &= np.isfinite(channels.series[name])
    return known


def _design(b_reference: FloatArray, chosen: list[Candidate]) -> FloatArray:
    blocks = [b_reference, np.ones((len(b_reference), 1))]
    blocks += [c.regressors for c in chosen]
    return np.concatenate(blocks, axis=1)


def _heldout_rss(
    pairs: FloatArray, x: FloatArray, regional: FloatArray | None, folds: np.ndarray
) -> float:
    """Sum of squares of the whitened residual of each fold predicted by the others.

    Raises
    ------
    IdentifiabilityError
        The fit on the other folds cannot be solved (the message says which fold it left
        out, e.g. a channel that varies only in that fold).
    """
    total = 0.0
    blocks = np.unique(folds)
    for fold in blocks:
        test = folds == fold
        train = ~test
        try:
            fit = solve_pairs(
                pairs[train], x[train], None if regional is None else regional[train]
            )
        except (IdentifiabilityError, np.linalg.LinAlgError) as error:
            raise IdentifiabilityError(
                f'fitted without block {fold + 1} of {len(blocks)}: {error}'
            ) from None
        predicted = x[test] @ (
            fit.theta.reshape(x.shape[1], 9) @ np.kron(np.eye(3), PAIR_WHITENER)
        )
        y = _whiten(pairs[test])
        if regional is not None and fit.regional is not None:
            y = y - np.einsum('nqo,q->no', regional[test], fit.regional)
        total += float(np.sum((y - predicted) ** 2))
    return total


@dataclass(frozen=True)
class Selection:
    """What :func:`select_terms` chose and why.

    Attributes
    ----------
    chosen : the selected candidates, in order of entry
    evidence : effect name -> its test (held-out RMS without and with it, nT per sensor
        axis; F, p-value, gain, kept), for every candidate tested
    lacking : effect name -> what it would need that the data lack
    heldout_rms_nT : held-out RMS of the final set (whitened pair residual, nT)
    unsolved : effect name -> why its held-out solve failed (against which set, which
        block, the solver's reason), for every candidate that could not be tested the last
        time it was offered: it is not kept, and says so rather than vanish
    """

    chosen: tuple[Candidate, ...]
    evidence: dict[str, dict[str, Any]]
    lacking: dict[str, str] = field(default_factory=dict)
    heldout_rms_nT: float = float('nan')
    unsolved: dict[str, str] = field(default_factory=dict)


def select_terms(
    pairs: FloatArray,
    b_reference: FloatArray,
    candidates: list[Candidate],
    *,
    regional: FloatArray | None = None,
    alpha: float = ALPHA,
    min_gain: float = MIN_GAIN,
    folds: int = FOLDS,
) -> Selection:
    """Forward selection of the candidates on held-out blocks (the module docstring).

    ``pairs`` (N, 3, 3) and ``b_reference`` (N, 3) in time order; rows where a candidate's
    regressor is NaN are left out of every comparison (a candidate without a known row is
    not offered: it cannot be tested). Data the base model fits exactly (noise-free) keep
    no term: there is nothing left to explain.
    """
    usable = np.all(np.isfinite(pairs.reshape(len(pairs), 9)), axis=1)
    # A candidate known on fewer than half the samples is not offered (its channel stopped):
    # the comparison needs the same samples for every model.
    known = {c.name: np.all(np.isfinite(c.regressors), axis=1) & usable for c in candidates}
    candidates = [c for c in candidates if known[c.name].sum() >= 0.5 * usable.sum()]
    for candidate in candidates:
        usable &= known[candidate.name]
    keep = np.flatnonzero(usable)
    n = len(keep)
    if n < MIN_SELECTION_SAMPLES:
        return Selection((), {})
    fold_of = np.zeros(n, dtype=int)
    for start, stop, fold in held_out_blocks(np.arange(n, dtype=float), n / folds, folds):
        fold_of[start:stop] = fold
    y = pairs[keep]
    b1 = b_reference[keep]
    reg = None if regional is None else regional[keep]
    sub = [c.select(keep) for c in candidates]
    chosen: list[Candidate] = []
    rss = _heldout_rss(y, _design(b1, chosen), reg, fold_of)
    evidence: dict[str, dict[str, Any]] = {}
    unsolved: dict[str, str] = {}
    rows = 9 * n
    remaining = list(sub)
    while remaining and rss > 0:
        tests = []
        for candidate in remaining:
            rss_with, why = _candidate_rss(y, b1, chosen, candidate, reg, fold_of)
            if why:
                unsolved[candidate.name] = why
                continue
            unsolved.pop(candidate.name, None)
            f_stat, p_value = held_out_f_test(rss, rss_with, 9 * candidate.size, rows)
            gain = 1.0 - rss_with / rss
            passed = p_value < alpha / len(remaining) and gain >= min_gain
            tests.append((passed, gain, candidate, rss_with, f_stat, p_value))
            evidence[candidate.name] = {
                'heldout_rms_without_nT': float(np.sqrt(rss / rows) * NT_PER_T),
                'heldout_rms_with_nT': float(np.sqrt(rss_with / rows) * NT_PER_T),
                'F': float(f_stat),
                'p_value': p_value,
                'gain': float(gain),
                'kept': False,
            }
        passing = [test for test in tests if test[0]]
        if not passing:
            break
        _, _, best, rss, _, _ = max(passing, key=lambda test: test[1])
        evidence[best.name]['kept'] = True
        chosen.append(best)
        remaining = [c for c in remaining if c.name != best.name]
    names = [c.name for c in chosen]
    final = tuple(
        replace(c, evidence=evidence.get(c.name, {}))
        for c in sorted(
            (c for c in candidates if c.name in names), key=lambda c: names.index(c.name)
        )
    )
    return Selection(
        final, evidence, heldout_rms_nT=float(np.sqrt(rss / rows) * NT_PER_T), unsolved=unsolved
    )


def _candidate_rss(
    y: FloatArray,
    b1: FloatArray,
    chosen: list[Candidate],
    candidate: Candidate,
    regional: FloatArray | None,
    folds: np.ndarray,
) -> tuple[float, str]:
    """The held-out sum of squares with ``candidate`` added to ``chosen``, or NaN and why
    that solve failed (singular on some fold's complement, non-finite)."""
    against = ' + '.join(['k, b', *(c.name for c in chosen)])
    try:
        rss_with = _heldout_rss(y, _design(b1, [*chosen, candidate]), regional, folds)
    except IdentifiabilityError as error:
        return float('nan'), f'with {against}, {error}'
    if not np.isfinite(rss_with):
        return float('nan'), f'with {against}, the held-out residual is not finite'
    return rss_with, ''


def fit_with_terms(
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    chosen: tuple[Candidate, ...],
    *,
    g_true: FloatArray | None = None,
    orientation_xyzw: FloatArray | None = None,
) -> TensorCalibration:
    """``k``, ``b`` (general), the chosen terms and (with ``orientation_xyzw``) the regional
    gradient, jointly, as a :class:`TensorCalibration` whose parameters carry the terms and
    whose covariance is of :meth:`InterferenceParameters.full_vector`.

    ``g_measured`` (N, 3, 3) T/m and ``b_reference`` (N, 3) T on the window; samples where a
    chosen regressor is NaN are left out.
    """
    target = g_measured if g_true is None else g_measured - g_true
    x = _design(b_reference, list(chosen))
    usable = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(target.reshape(-1, 9)), axis=1)
    if orientation_xyzw is not None:
        usable &= np.all(np.isfinite(orientation_xyzw), axis=1)
    pairs = target[usable] @ geometry.a
    regional = (
        None
        if orientation_xyzw is None
        else regional_columns(np.asarray(orientation_xyzw)[usable], geometry)
    )
    solution = solve_pairs(pairs, x[usable], regional)
    p = x.shape[1]
    theta = solution.theta  # [regressor, axis, pair]
    k_soft = np.transpose(theta[:3], (2, 1, 0))
    b_hard = theta[3].T
    terms = []
    column = 4
    for candidate in chosen:
        coefficients = np.transpose(theta[column : column + candidate.size], (2, 1, 0))
        fitted = x[usable, column : column + candidate.size]
        column += candidate.size
        terms.append(
            Term(
                candidate.name,
                candidate.inputs,
                coefficients,
                candidate.reference,
                candidate.channel_noise,
                dict(candidate.evidence),
                tuple(np.mean(fitted, axis=0)),
                tuple(map(tuple, np.atleast_2d(np.cov(fitted, rowvar=False, bias=True)))),
            )
        )
    order = _parameter_order([c.size for c in chosen])
    covariance = solution.covariance[np.ix_(order, order)]
    regional_g = regional_sigma = None
    if solution.regional is not None and solution.regional_covariance is not None:
        regional_g = np.tensordot(solution.regional, REGIONAL_BASIS, axes=1)
        var = np.einsum(
            'qij,qs,sij->ij', REGIONAL_BASIS, solution.regional_covariance, REGIONAL_BASIS
        )
        regional_sigma = np.sqrt(np.maximum(var, 0.0))
    residual_pairs = solution.residual_w.reshape(-1, 3, 3) @ _PAIR_UNWHITENER
    residual_rms = float(np.sqrt(np.mean((residual_pairs @ geometry.a_inv) ** 2)))
    return TensorCalibration(
        method=METHOD,
        n_samples=int(np.sum(usable)),
        n_parameters=9 * p,
        rank=9 * p,
        condition_number=solution.condition_number,
        residual_rms=residual_rms,
        details={
            'sensor_noise_nT': solution.sigma * NT_PER_T,
            'terms': [term.effect for term in terms],
        },
        parameters=InterferenceParameters(k_soft, b_hard, tuple(terms)),
        symmetric=False,
        covariance=covariance,
        regional_gradient_enu=regional_g,
        regional_gradient_sigma=regional_sigma,
    )
