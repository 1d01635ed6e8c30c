"""Target exclusion: find the spans of the run where a localized field that no candidate
represents (a target passed close to the track) dominates the residual, with their evidence.

The detector refreshes ``B^b`` on its own: every function returns the prepared data it
leaves, and the caller's is never changed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from .candidate import Context
from .cv import ALL_SENSORS, flat, lstsq_view, noise_floor, solve_fast
from .effects import CANDIDATES
from .prepare import Prepared, refresh_background
from .result import Settings

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]
Span = tuple[int, int]


@dataclass(frozen=True)
class TargetSpans:
    """What the detector found.

    Attributes
    ----------
    spans : the excluded spans (seconds from the first sample) with their evidence
    notes : what it decided, in words
    detector : its levels (median, peak over median, thresholds, spans confirmed)
    """

    spans: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    detector: dict[str, float] = field(default_factory=dict)

    @property
    def intervals(self) -> list[tuple[float, float]]:
        """(start_s, end_s) of every excluded span."""
        return [(e['start_s'], e['end_s']) for e in self.spans]

    def exclusion_note(self) -> str:
        """The note that says which spans were left out, and why."""
        return (
            f'{len(self.spans)} span(s) excluded from the fits and the gap ('
            + ', '.join(f'{e["start_s"]:.1f}-{e["end_s"]:.1f} s' for e in self.spans)
            + '): a localized field that differs between the sensors and that no candidate '
            'represents (a target passed close to the track); see excluded_spans'
        )


@dataclass(frozen=True)
class _Score:
    """The full model's residual (N, 4, 3), in the view (N, m), each channel's noise sigma
    (m,) and the mean square in sigmas averaged over ~2 s (N,)."""

    residual: Array
    flat: Array
    sigma: Array
    z: Array


def runs(mask: Mask) -> list[Span]:
    """Contiguous runs of True: (first, last) indices."""
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    first = np.flatnonzero(edges == 1)
    last = np.flatnonzero(edges == -1) - 1
    return [(int(i), int(j)) for i, j in zip(first, last, strict=True)]


def detector_columns(
    prep: Prepared, names: frozenset[str], include: Mask, settings: Settings
) -> Array:
    """Columns (N, 4, 3, p) of the base model plus every global candidate (the library's
    ``in_detector`` families among ``names``)."""
    y = prep.fields - prep.base_offset
    coef = lstsq_view(prep.sensors, prep.base_cols, y, include)
    prediction = prep.base_offset + prep.base_cols @ coef
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
        extra_currents=prep.extra_currents,
    )
    families = [c for c in CANDIDATES if c.in_detector and c.name in names]
    return np.concatenate([prep.base_cols] + [c.build(ctx, None)[0] for c in families], axis=-1)


def full_model_residual(
    prep: Prepared, names: frozenset[str], include: Mask, settings: Settings
) -> tuple[Prepared, Array]:
    """Residual (N, 4, 3) of the base model plus every global candidate, fitted on
    ``include`` only and evaluated everywhere (the model is global in time); and the
    prepared data with ``B^b`` refreshed by that fit."""
    y = prep.fields - prep.base_offset
    for _ in range(3):
        cols = detector_columns(prep, names, include, settings)
        coef = lstsq_view(prep.sensors, cols, y, include)
        if not prep.absolute:
            break
        prep, moved = refresh_background(prep, coef[:6])
        if not moved:
            break
        y = prep.fields - prep.base_offset
    residual = prep.fields - prep.base_offset - cols @ coef
    if not prep.absolute:
        residual = residual - residual[:, :1]
    return prep, residual


def _blocks(piece: NDArray[np.int_], width: int) -> tuple[NDArray[np.int_], int]:
    """Blocks of ``width`` samples within each piece: the block of each sample, the count."""
    block = np.empty(len(piece), dtype=int)
    count = 0
    for p in np.unique(piece):
        idx = np.flatnonzero(piece == p)
        block[idx] = count + np.arange(len(idx)) // width
        count = int(block[idx].max()) + 1
    return block, count


def _lts_starts(piece: NDArray[np.int_], block: NDArray[np.int_], count: int) -> list[Mask]:
    """Starting block sets: all blocks; each contiguous half of the run; each continuous
    piece of at least a quarter of it."""
    starts = [np.ones(count, dtype=bool)]
    order = np.arange(count)
    for lo in (0.0, 0.25, 0.5):
        starts.append((order >= lo * count) & (order < (lo + 0.5) * count))
    for p in np.unique(piece):
        if np.mean(piece == p) >= 0.25 and len(np.unique(piece)) > 1:
            starts.append(np.isin(order, np.unique(block[piece == p])))
    return starts


def robust_start(prep: Prepared, names: frozenset[str], settings: Settings, width: int) -> Mask:
    """Samples (bool, N) of the half of the run that the full model fits best.

    A strong target pulls a least-squares fit over the whole run, and a slow regressor
    (temperature, a drift) can take part of it, so the fit on all samples is no guide to
    where the target is. Least trimmed squares on blocks of ~2 s (per-block Gram matrices):
    from several starts (all blocks; each contiguous half of the run; each continuous piece
    of at least a quarter of it), concentration steps keep the half of the blocks with the
    smallest mean square residual; the start with the smallest trimmed sum wins.
    """
    y = prep.fields - prep.base_offset
    cols = detector_columns(prep, names, np.ones(len(prep.t), dtype=bool), settings)
    a = flat(cols, prep.sensors)
    target = flat(y, prep.sensors)
    norm = np.sqrt(np.einsum('nmp,nmp->p', a, a))
    norm[norm == 0] = 1.0
    a = a / norm
    block, count = _blocks(prep.piece, width)
    grams = np.zeros((count, a.shape[-1], a.shape[-1]))
    rhs = np.zeros((count, a.shape[-1]))
    for b in range(count):
        ab = a[block == b].reshape(-1, a.shape[-1])
        grams[b] = ab.T @ ab
        rhs[b] = ab.T @ target[block == b].reshape(-1)

    def fit(chosen: Mask) -> Array:
        theta = solve_fast(grams[chosen].sum(axis=0), rhs[chosen].sum(axis=0))
        r: Array = target - np.einsum('nmp,p->nm', a, theta)
        return r

    _, sigma = noise_floor(fit(np.ones(count, dtype=bool)))  # blind to a smooth target
    sigma = np.maximum(sigma, 1e-12)

    def block_scores(r: Array) -> Array:
        q = np.mean((r / sigma) ** 2, axis=1)
        return np.bincount(block, q, count) / np.maximum(np.bincount(block, None, count), 1)

    starts = _lts_starts(prep.piece, block, count)
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
    result: Mask = best[block]
    return result


def _score(
    prep: Prepared, names: frozenset[str], settings: Settings, width: int, include: Mask
) -> tuple[Prepared, _Score]:
    """The full model fitted on ``include``: its residual in noise sigmas, averaged."""
    prep, residual = full_model_residual(prep, names, include, settings)
    view = flat(residual, prep.sensors)
    _, sigma = noise_floor(view[include])
    sigma = np.maximum(sigma, 1e-12)
    q = np.mean((view / sigma) ** 2, axis=1)
    z = np.empty_like(q)
    for p in np.unique(prep.piece):  # no average across a jump
        idx = np.flatnonzero(prep.piece == p)
        z[idx] = uniform_filter1d(q[idx], min(width, len(idx)), mode='nearest')
    return prep, _Score(residual, view, sigma, z)


def _span_mask(prep: Prepared, z: Array, high: float, low: float, settings: Settings) -> Mask:
    """Samples of the stretches above ``low`` that reach ``high``, widened by the margin
    within their continuous piece (a jump between recorded segments is a different place)."""
    t = prep.t
    found = [(i, j) for i, j in runs(z > low) if np.max(z[i : j + 1]) > high]
    mask = np.zeros(len(t), dtype=bool)
    for i, j in found:
        margin = float(np.clip(settings.target_margin * (t[j] - t[i]), 2.0, 15.0))
        lo = int(np.searchsorted(t, t[i] - margin, side='left'))
        hi = int(np.searchsorted(t, t[j] + margin, side='right')) - 1
        piece = prep.piece[i + int(np.argmax(z[i : j + 1]))]
        same = np.flatnonzero(prep.piece[lo : hi + 1] == piece) + lo
        if len(same):
            lo, hi = int(same[0]), int(same[-1])
        mask[lo : hi + 1] = True
    return mask


@dataclass(frozen=True)
class _Settled:
    """Spans that settled (refitting without them finds them again), with their mask."""

    prep: Prepared
    spans: list[Span]
    mask: Mask
    info: dict[str, float]
    widespread: bool


def settle(
    prep: Prepared, names: frozenset[str], settings: Settings, width: int, include: Mask
) -> _Settled:
    """Refit without the spans until they settle (a strong target distorts the first fit)."""
    last = None
    for _ in range(6):
        prep, score = _score(prep, names, settings, width, include)
        z = score.z
        level = max(float(np.median(z)), 1.0)
        info = {
            'median_level': float(np.median(z)),
            'peak_over_level': float(np.max(z) / level),
            'high': settings.target_high,
            'low': settings.target_low,
        }
        high, low = settings.target_high * level, settings.target_low * level
        mask = _span_mask(prep, z, high, low, settings)
        spans = runs(mask)
        if mask.mean() > settings.target_max_fraction:
            return _Settled(prep, spans, mask, info, widespread=True)
        key = tuple(spans)
        if key == last:
            break
        last = key
        include = ~mask
    return _Settled(prep, spans, mask, info, widespread=False)


def _confirm(
    settled: _Settled, names: frozenset[str], settings: Settings, width: int
) -> tuple[Prepared, list[Span], list[str]]:
    """Confirm each span: fitted with its own samples in, a target stays far above the rest
    (no candidate represents it); a span that the model explains once it may fit it was an
    extrapolation of a fit on part of the run, not a target."""
    prep, mask = settled.prep, settled.mask
    t = prep.t
    confirmed: list[Span] = []
    notes: list[str] = []
    # The shape of what the model fitted outside the spans leaves in them (fitted with a
    # span in, the model bends to its middle and the leftover peaks at its ends).
    prep, outside = _score(prep, names, settings, width, ~mask)
    for i, j in settled.spans:
        inside = np.zeros(len(t), dtype=bool)
        inside[i : j + 1] = True
        with_it = ~mask | inside
        prep, score = _score(prep, names, settings, width, with_it)
        z_in = score.z
        level = max(np.median(z_in[with_it & ~inside]), 1e-12)
        ratio = float(np.mean(z_in[inside]) / level)
        # Positive evidence of a passage: the disagreement peaks inside the span and falls
        # off (a dipole's mean square by (1 + x^2/d^2)^-3 along the track) to the noise or
        # to target_edge of its peak on at least one side (a deep target on a short line
        # may still be strong where the line ends). One that stays up at both ends, or
        # peaks at one, is a change that persists (a step), not a source moving past.
        z_out = outside.z
        peak = i + int(np.argmax(z_out[i : j + 1]))
        base = max(np.median(z_out[~mask]), 1.0)
        floor = max(settings.target_low * base, settings.target_edge * z_out[peak])
        edges = [k for k in (i, j) if z_out[k] > floor]
        # A source outside the vehicle reaches every sensor (at 20 m the four see nearly
        # the same field); a change of one sensor (a step) sits in that sensor alone.
        whitened = (outside.flat[i : j + 1] / outside.sigma) ** 2
        per_sensor = whitened.reshape(len(whitened), -1, 3).sum(axis=(0, 2))
        one_sensor = float(per_sensor.max() / max(per_sensor.sum(), 1e-300))
        lasting = one_sensor >= settings.target_one_sensor
        failed = [
            why
            for why, fails in (
                (f'{100 * one_sensor:.0f} % of it is in one sensor', lasting),
                (f'it does not fall below {settings.target_edge:g} x its peak on either side',
                 len(edges) == 2),
                ('it peaks at an end of the span', min(peak - i, j - peak) < width),
            )
            if fails
        ]  # fmt: skip
        if failed:
            notes.append(
                f'{t[i]:.1f}-{t[j]:.1f} s not excluded: the disagreement peaks at '
                f'{t[peak]:.1f} s and {"; ".join(failed)}: no evidence of a source passing by; '
                'a change of the vehicle is for the model to explain'
            )
        elif ratio >= settings.target_confirm:
            confirmed.append((i, j))
        else:
            notes.append(
                f'{t[i]:.1f}-{t[j]:.1f} s not excluded: the full candidate model explains it '
                f'once fitted on it (mean square {ratio:.2g} x the rest of the run)'
            )
    return prep, confirmed, notes


def find_target_spans(
    prep: Prepared, names: frozenset[str], settings: Settings, *, modelled: bool = False
) -> TargetSpans:
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

    ``modelled``: the targets' fitted field is already out of ``prep`` (their moments fixed
    at the joint fit's on every sample). The first fit is then on every sample, not the
    robust half: what pulls a fit, a target outside the model, is in it, and a fit on half
    the run cannot take up what the joint fit traded between the moments and the slow
    terms (Earth-field drift, temperature): a 0.2 % moment error, within the fit's own
    uncertainty on a short line, reads as a 26 x the noise bump at the pass.
    """
    dt = float(np.median(np.diff(prep.t)))
    width = max(5, int(round(2.0 / dt)))
    include = (
        np.ones(len(prep.t), dtype=bool)
        if modelled
        else robust_start(prep, names, settings, width)
    )
    settled = settle(prep, names, settings, width, include)
    info = dict(settled.info)
    if settled.widespread:
        note = (
            f'the residual of the full candidate model is far above the noise over '
            f'{100 * settled.mask.mean():.0f} % of the run: not a localized target passage, '
            'nothing excluded'
        )
        return TargetSpans([], [note], info)
    prep, spans, notes = _confirm(settled, names, settings, width)
    info['confirmed'] = len(spans)
    if not spans:
        return TargetSpans([], notes, info)
    n = len(prep.t)
    outside = ~np.isin(np.arange(n), np.concatenate([np.arange(i, j + 1) for i, j in spans]))
    prep, score = _score(prep, names, settings, width, outside)
    return TargetSpans([_evidence(prep, score, span, width) for span in spans], notes, info)


def _evidence(prep: Prepared, score: _Score, span: Span, width: int) -> dict[str, Any]:
    """Where the residual peaks in the span, and how much of it differs between sensors."""
    i, j = span
    t, residual = prep.t, score.residual
    common = (
        residual.mean(axis=1, keepdims=True) if prep.absolute else np.zeros_like(residual[:, :1])
    )
    diff = residual - common
    k = i + int(np.argmax(score.z[i : j + 1]))
    peak = float(np.sqrt(np.mean(score.flat[k] ** 2)))
    window = slice(max(i, k - width // 2), min(j, k + width // 2) + 1)
    d_rms = float(np.sqrt(np.mean(diff[window][:, list(prep.sensors)] ** 2)))
    c_rms = float(np.sqrt(np.mean(common[window] ** 2)))
    turn = None
    if prep.rotation is not None:
        change = (
            Rotation.from_matrix(prep.rotation[j]) * Rotation.from_matrix(prep.rotation[i]).inv()
        )
        turn = float(np.degrees(change.magnitude()))
    noise = float(np.sqrt(np.mean(score.sigma**2)))
    reason = (
        f'localized field that no candidate represents (a target passed close to the track): '
        f'the residual of the base model plus every global candidate peaks at {peak:.3g} nT '
        f'({peak / noise:.0f} x the noise) at t = {t[k]:.1f} s and falls off on both sides; '
        f'{d_rms:.3g} nT RMS of it differs between the sensors (a gradient)'
    )
    if prep.absolute:
        reason += f', {c_rms:.3g} nT is common to them'
    if turn is not None:
        reason += f'; attitude change across the span {turn:.1f} deg'
    return {
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
