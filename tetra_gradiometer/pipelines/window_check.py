"""What ``calibrate`` and the calibrator node's ``~/calibrate`` add around a known-gradient
solve: the attitude from ``/odom`` so that a regional gradient is estimated
jointly, and the test of the fit's own assumption (a constant gradient over the window)
with its verdict, the part of the window that fails and a sub-window that would pass.
:func:`identify_checked` is the one path both take: solve, check, refuse or keep a forced
calibration with its warning.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core import TetraGeometry
from ..core.geometry import interp_orientation
from ..core.guidance import TrimAssessment
from ..core.identification import (
    Calibration,
    FitConsistency,
    Options,
    TensorCalibration,
    attitude_coverage,
    calibration_residual,
    fit_consistency,
    identify,
)
from ..core.identification.misfit import FIELD_SHARE, gradient_share
from ..core.odometry import LiveOdometryCheck
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import AssumptionError, IdentifiabilityError
from ..io import conversions as cv

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Methods that assume a known (zero, or jointly fitted regional) gradient over the window.
KNOWN_GRADIENT_METHODS = ('known_gradient_lstsq', 'known_gradient_lstsq_general')
#: An ``/odom`` message further than this from a set leaves that set's attitude unknown, s
#: (the joint regional gradient and the trim guidance alike).
MAX_ODOM_GAP_S = 0.5
#: Shortest sub-window worth pointing to, s.
MIN_SUB_WINDOW_S = 30.0
#: Refuse a calibration whose trim assessment predicts a compensated survey sigma above
#: this many noise floors: its attitudes do not excite the parameters asked for (a straight
#: survey leg predicts ~7x and compensates at ~5x; a trim 1.0x; the guidance's "enough" is
#: 1.1x). Loose on purpose: the prediction is linearised, the survey representative only.
MAX_PREDICTED_RATIO = 2.0
#: Seconds per block of the attitude-excitation segmentation (:func:`excited_spans`).
EXCITATION_BLOCK_S = 10.0
#: A block manoeuvres when the body-frame direction of ``B_1'`` spreads (``arccos |mean unit
#: vector|``) over the 30 s centred on it at least ``QUIET_FACTOR`` times the bag's quiet
#: level (the 20th percentile of those spreads: its straight legs' sway), and never less
#: than this, degrees; the factor's threshold is capped at :data:`MAX_EXCITED_SPREAD_DEG`
#: so that a bag that is all trim stays all manoeuvre. Measured over 30 s: straight legs
#: 1.5 (README mission), 2.5 (bags/survey, +-3 deg roll), 4.1 (+-5 deg roll); trims 20-31
#: (README mission), 6.2-9.9 (a gentle trim: 2 deg/s, roll +-8 deg, pitch +-6 deg).
EXCITED_SPREAD_DEG = 5.0
QUIET_FACTOR = 1.5
MAX_EXCITED_SPREAD_DEG = 10.0
#: A run's end block is dropped while its own 10 s spread is below this factor times the
#: bag's 20th percentile of those (a straight leg's sway: README mission 1.5, +-5 deg roll
#: 3.9; a gentle trim's 4.8-8.5), at least :data:`MIN_EDGE_SPREAD_DEG` and at most
#: :data:`EXCITED_SPREAD_DEG`, degrees.
EDGE_FACTOR = 1.25
MIN_EDGE_SPREAD_DEG = 0.5
#: Candidate spans refitted when a window fails, at most (each is a solve).
MAX_SPANS_TRIED = 4


def orientation_at(
    odom_stamps_ns: IntArray, odom_xyzw: FloatArray, stamps_ns: IntArray
) -> FloatArray:
    """``/odom`` orientations (m, 4) at ``odom_stamps_ns`` (m,) slerped onto ``stamps_ns``
    (n,), held at the ends: (n, 4) xyzw; NaN where no message lies within
    :data:`MAX_ODOM_GAP_S` (a gap in ``/odom``, or beyond its ends)."""
    if len(odom_stamps_ns) == 0:
        return np.full((len(stamps_ns), 4), np.nan)
    orientation = interp_orientation(odom_stamps_ns, odom_xyzw, stamps_ns)
    after = np.clip(np.searchsorted(odom_stamps_ns, stamps_ns), 0, len(odom_stamps_ns) - 1)
    before = np.maximum(after - 1, 0)
    gap = np.minimum(
        np.abs(odom_stamps_ns[after] - stamps_ns), np.abs(stamps_ns - odom_stamps_ns[before])
    )
    orientation[gap * S_PER_NS > MAX_ODOM_GAP_S] = np.nan
    return orientation


def joint_attitude(orientation_xyzw: FloatArray) -> tuple[FloatArray | None, str]:
    """The attitudes (n, 4) for a joint regional gradient when every sample has one (no
    NaN), else None; with the note saying which."""
    unknown = int(np.sum(~np.all(np.isfinite(orientation_xyzw), axis=1)))
    if unknown:
        return None, (
            f'{unknown} of {len(orientation_xyzw)} samples have no {cv.ODOM_TOPIC} message '
            f'within {MAX_ODOM_GAP_S:g} s: a regional gradient cannot be told from the '
            'interference and is assumed zero'
        )
    return orientation_xyzw, f'regional gradient estimated jointly (attitude from {cv.ODOM_TOPIC})'


class AttitudeHistory:
    """``/odom`` orientations received live, for the calibrator node: :meth:`at` one stamp
    as a sample arrives (the trim guidance, whose attitude bins are 30 degrees wide: the
    nearest message, no slerp, cheap per sample), :meth:`over` all the samples' stamps at
    ``~/calibrate`` (the joint regional gradient: :func:`orientation_at`, by which time
    every message around every sample has arrived). Each message is checked on the offline
    rule first (:class:`~tetra_gradiometer.core.odometry.LiveOdometryCheck`, :attr:`check`:
    an unfilled orientation dropped and counted, an unnormalized one normalized).

    Parameters
    ----------
    length : messages kept (42 min at 50 Hz: as long as the calibrator keeps samples)
    """

    def __init__(self, length: int = 125_000) -> None:
        self._stamps: deque[int] = deque(maxlen=length)
        self._quats: deque[FloatArray] = deque(maxlen=length)
        self._lock = threading.Lock()  # the two deques change together
        self.check = LiveOdometryCheck()

    def add(self, stamp_ns: int, quaternion_xyzw: FloatArray) -> bool:
        """One message; a stamp earlier than the last (a replay restarted) forgets the rest.
        False when its orientation was dropped (counted in :attr:`check`)."""
        with self._lock:
            quaternion = self.check.accept(quaternion_xyzw)
            if quaternion is None:
                return False
            if self._stamps and stamp_ns < self._stamps[-1]:
                self.clear()
            self._stamps.append(stamp_ns)
            self._quats.append(quaternion)
            return True

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        self._stamps.clear()
        self._quats.clear()

    def at(self, stamp_ns: int) -> FloatArray:
        """The nearest message's attitude to ``stamp_ns`` (ns), (4,) xyzw; NaN when none is
        within :data:`MAX_ODOM_GAP_S`."""
        with self._lock:
            after = bisect.bisect_left(self._stamps, stamp_ns)
            around = range(max(after - 1, 0), min(after + 1, len(self._stamps)))
            gaps = {abs(self._stamps[i] - stamp_ns): i for i in around}
            if not gaps or min(gaps) * S_PER_NS > MAX_ODOM_GAP_S:
                return np.full(4, np.nan)
            return self._quats[gaps[min(gaps)]]

    def over(self, stamps_ns: IntArray) -> FloatArray:
        """The attitudes at ``stamps_ns`` (n,) ns, (n, 4) xyzw, NaN where unknown. Only the
        messages around the asked span are read (the slerp needs the neighbours alone): the
        compensator's tracker asks for half a second of a minute's history at every block."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        with self._lock:
            lo, hi = 0, len(self._stamps)
            if len(stamps_ns) and hi:
                lo = max(bisect.bisect_left(self._stamps, int(stamps_ns.min())) - 1, 0)
                hi = min(bisect.bisect_right(self._stamps, int(stamps_ns.max())) + 1, hi)
            stamps = np.fromiter(itertools.islice(self._stamps, lo, hi), np.int64, hi - lo)
            quats = np.array(list(itertools.islice(self._quats, lo, hi))).reshape(-1, 4)
        return orientation_at(stamps, quats, stamps_ns)


#: The keys of ``lacking`` (:meth:`WindowCheck.cause`) naming the recorded signals the fit
#: does not read, those the held-out selection keeps on the window although the fit does not
#: read them (the evidence that the vehicle causes the misfit), and those it offered and
#: rejected (the evidence that no recorded vehicle signal does).
UNREAD = 'unread signals'
EXPLAINING = 'explaining signals'
REJECTED = 'rejected signals'


@dataclass(frozen=True)
class WindowCheck:
    """The fit's test of its own assumption on the window.

    Attributes
    ----------
    consistency : FitConsistency
    first_ns : stamp of the bag's first set (window times are counted from it), ns
    passing_window : (t0, t1) s from the bag's first set: a sub-window that passes when
        refitted, or None
    """

    consistency: FitConsistency
    first_ns: int
    passing_window: tuple[float, float] | None
    field_share: float | None = None

    @property
    def passed(self) -> bool:
        return self.consistency.passed

    def cause(self, lacking: dict[str, str] | None = None) -> str:
        """What explains the misfit, from evidence: recorded vehicle signals that the held-out
        selection keeps on the window (``lacking[EXPLAINING]``) make it the vehicle's; only
        without them is a misfit of a field's shape (:mod:`~tetra_gradiometer.core.
        identification.misfit`) a target's or the geology's, saying which signals were
        tested and rejected (``lacking[REJECTED]``). A magnet or a current outside the array
        is symmetric and traceless too, so the shape alone never tells the vehicle from a
        target. Otherwise names the effects whose channels the data lack and the recorded
        signals nothing tested (``lacking[UNREAD]``)."""
        lacking = dict(lacking or {})
        unread = lacking.pop(UNREAD, '')
        rejected = lacking.pop(REJECTED, '')
        explaining = lacking.pop(EXPLAINING, '')
        if explaining:
            return (
                f'the vehicle: effects its recorded signals explain ({explaining}: kept by '
                'the held-out test of the automatic selection, --effects auto, and the window '
                'passes with them; this fit does not read them)'
            )
        vehicle = (
            f'; or a source on the vehicle that a signal it records explains ({unread}: '
            '`discrepancy` tests them, vehicle_signals declares them)'
            if unread
            else ''
        )
        if rejected:
            vehicle = f'; no signal the vehicle records explains it (tested: {rejected})'
        share = self.field_share
        if share is not None and share >= FIELD_SHARE:
            return (
                f'a target or a spatially varying field: {share:.0%} of the misfit above the '
                f'noise is symmetric and traceless, as a field gradient is{vehicle}'
            )
        shape = (
            ''
            if share is None
            else f'{share:.0%} of the misfit above the noise is symmetric and traceless, '
            'where a field gradient would be ~100 %: '
        )
        if lacking:
            names = '; '.join(f'{name} needs {what}' for name, what in lacking.items())
            return (
                f'{shape}not a field but an effect of the vehicle the model lacks; the data '
                f'lack the channel of an effect that may explain it ({names}){vehicle}'
            )
        return (
            f'{shape}not a field but an effect of the vehicle the model lacks, or a bad '
            f'stretch{vehicle}'
        )

    def text(self, sub_window: str = '--window {0:g}:{1:g}') -> str:
        """One line: the verdict with the figures, the failing part, the passing window
        (named by ``sub_window``, a format of its two ends in seconds)."""
        c = self.consistency
        line = (
            f'fit residual {c.residual_rms * NT_PER_T:.3g} nT/m is {c.ratio:.2f}x the noise '
            f'{c.noise_rms * NT_PER_T:.3g} nT/m (limit {c.threshold_ratio:.2f}x, F test at '
            f'alpha {c.alpha:g} of residual <= {c.tolerance:g} x noise)'
        )
        failing = c.failing_spans()
        if failing:
            line += '; fails in ' + ', '.join(f'{a:.0f}-{b:.0f} s' for a, b in failing[:3])
        if not self.passed:
            line += (
                f'; {sub_window.format(*self.passing_window)} would pass'
                if self.passing_window
                else '; no sub-window passes'
            )
        return line

    def to_dict(self) -> dict[str, Any]:
        return {
            **self.consistency.to_dict(),
            'passing_window_s': None if self.passing_window is None else list(self.passing_window),
            'misfit_field_share': self.field_share,
        }


def excited_spans(
    t_s: FloatArray, b_reference: FloatArray, min_s: float = MIN_SUB_WINDOW_S
) -> list[tuple[float, float]]:
    """The spans of the samples where the vehicle manoeuvres (turns, rolls, pitches; a
    straight leg does not): maximal runs of consecutive :data:`EXCITATION_BLOCK_S` blocks
    whose ``B_1'`` direction spreads over the 30 s around them (see
    :data:`EXCITED_SPREAD_DEG`), the run's end blocks dropped while their own spread is at
    the quiet level (the 30 s smear a run by one block), each run at least ``min_s`` long;
    as (first, last) sample times in the time base of ``t_s``, s.

    ``t_s`` (n,) increasing, s; ``b_reference`` (n, 3), T (any unit: only its direction
    counts). An empty block (a gap) ends a run.
    """
    if len(t_s) < 3:
        return []
    norms = np.linalg.norm(b_reference, axis=1, keepdims=True)
    unit = np.divide(b_reference, norms, out=np.zeros_like(b_reference), where=norms > 0)
    block = np.floor((t_s - t_s[0]) / EXCITATION_BLOCK_S).astype(np.int64)
    n_blocks = int(block[-1]) + 1
    counts: FloatArray = np.bincount(block, minlength=n_blocks).astype(np.float64)
    sums: FloatArray = np.stack(
        [np.bincount(block, unit[:, i], minlength=n_blocks) for i in range(3)], 1
    ).astype(np.float64)

    def spread(total: FloatArray, n: FloatArray) -> FloatArray:
        mean = np.linalg.norm(total, axis=1) / np.maximum(n, 1.0)
        return np.degrees(np.arccos(np.clip(mean, 0.0, 1.0)))

    own = spread(sums, counts)
    around = spread(_neighbours(sums), _neighbours(counts[:, None])[:, 0])
    valid = counts >= 3
    if not valid.any():
        return []
    quiet = float(np.percentile(around[valid], 20))
    threshold = max(EXCITED_SPREAD_DEG, min(QUIET_FACTOR * quiet, MAX_EXCITED_SPREAD_DEG))
    # An end block at the quiet level of its own (10 s) spread is a straight leg's.
    quiet_own = float(np.percentile(own[valid], 20)) * EDGE_FACTOR
    quiet_own = min(max(quiet_own, MIN_EDGE_SPREAD_DEG), EXCITED_SPREAD_DEG)
    excited = valid & (around >= threshold)
    first = np.full(n_blocks, np.inf)
    last = np.full(n_blocks, -np.inf)
    np.minimum.at(first, block, t_s)
    np.maximum.at(last, block, t_s)
    spans = []
    for start, stop in _runs(excited):
        while start < stop and own[start] < quiet_own:
            start += 1
        while stop > start and own[stop - 1] < quiet_own:
            stop -= 1
        if stop > start and last[stop - 1] - first[start] >= min_s:
            spans.append((float(first[start]), float(last[stop - 1])))
    return spans


def _neighbours(values: FloatArray) -> FloatArray:
    """Each row (blocks, k) summed with the rows before and after it."""
    padded = np.pad(values, ((1, 1), (0, 0)))
    return padded[:-2] + padded[1:-1] + padded[2:]


def _runs(flags: npt.NDArray[np.bool_]) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in ``flags`` (stop exclusive)."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()
    return list(zip(starts, stops, strict=True))


def _candidate_spans(
    consistency: FitConsistency, t_s: FloatArray, b_reference: FloatArray
) -> list[tuple[float, float]]:
    """Sub-windows worth refitting when the window fails: the longest run of passing blocks,
    then the manoeuvring spans (:func:`excited_spans`) best excited first (the attitude
    coverage condition number over the square root of the samples: the parameters' error
    grows with both), the window itself left out."""
    spans = []
    longest = consistency.longest_passing_span()
    if longest is not None and longest[1] - longest[0] >= MIN_SUB_WINDOW_S:
        spans.append(longest)

    def score(span: tuple[float, float]) -> float:
        inside = (t_s >= span[0]) & (t_s <= span[1])
        return attitude_coverage(b_reference[inside]) / np.sqrt(inside.sum())

    whole = (float(t_s[0]), float(t_s[-1]))
    excited = [span for span in excited_spans(t_s, b_reference) if span != whole]
    spans += [span for span in sorted(excited, key=score) if span not in spans]
    return spans[:MAX_SPANS_TRIED]


def _check_window(
    calibration: TensorCalibration,
    method: str,
    stamps_ns: IntArray,
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    options: Options,
    first_ns: int,
) -> WindowCheck:
    """Test the fit on its window; when it fails, refit the longest passing run of blocks
    and point to it if that passes. Times are seconds from ``first_ns``.

    ``stamps_ns`` (n,) strictly increasing, ns; ``g_measured`` (n, 3, 3) T/m and
    ``b_reference`` (n, 3) T: the samples ``calibration`` was fitted on, with the attitude
    in ``options.orientation_xyzw`` when the regional gradient was fitted jointly.
    """
    consistency, share = _consistency(
        calibration, stamps_ns, g_measured, b_reference, geometry, options, first_ns
    )
    passing = None
    if not consistency.passed:
        t = ((stamps_ns - first_ns) * S_PER_NS).astype(np.float64)
        for span in _candidate_spans(consistency, t, b_reference):
            keep = (t >= span[0]) & (t <= span[1])
            if _passes_alone(
                keep, method, stamps_ns, g_measured, b_reference, geometry, options, first_ns
            ):
                passing = span
                break
    return WindowCheck(consistency, first_ns, passing, share)


def _passes_alone(
    keep: npt.NDArray[np.bool_],
    method: str,
    stamps_ns: IntArray,
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    options: Options,
    first_ns: int,
) -> bool:
    """Whether the samples ``keep`` (n,) pass the check when refitted alone, with the same
    terms and attitude."""
    orientation = options.orientation_xyzw
    sub = dataclasses.replace(
        options,
        orientation_xyzw=None if orientation is None else orientation[keep],
        terms=tuple(term.select(keep) for term in options.terms),
    )
    g_kept, b_kept = g_measured[keep], b_reference[keep]
    try:
        refit = identify(method, g_kept, b_kept, geometry, sub)
    except IdentifiabilityError:
        return False
    if not isinstance(refit, TensorCalibration):
        return False
    again, _ = _consistency(refit, stamps_ns[keep], g_kept, b_kept, geometry, sub, first_ns)
    return again.passed


def _consistency(
    calibration: TensorCalibration,
    stamps_ns: IntArray,
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    options: Options,
    first_ns: int,
) -> tuple[FitConsistency, float | None]:
    """The check of the fit on its samples (the terms' regressors from ``options.terms``;
    samples where one is unknown, e.g. the first of an eddy term, left out) and the misfit's
    share that looks like a field."""
    terms = options.terms
    regressors = np.concatenate([term.regressors for term in terms], axis=1) if terms else None
    residual = calibration_residual(
        calibration,
        g_measured,
        b_reference,
        geometry,
        orientation_xyzw=options.orientation_xyzw,
        regressors=regressors,
    )
    known = np.all(np.isfinite(residual.reshape(len(residual), 9)), axis=1)
    regional = calibration.regional_gradient_enu is not None
    n_parameters = calibration.n_parameters + (5 if regional else 0)
    t_s = (stamps_ns[known] - first_ns) * S_PER_NS
    consistency = fit_consistency(residual[known], t_s, geometry, n_parameters)
    share = gradient_share(residual[known], geometry, consistency.sensor_noise)
    return consistency, share


def _refusal(
    check: WindowCheck, window: str, force: str, sub_window: str, lacking: dict[str, str]
) -> AssumptionError:
    """The error of a failed check, with what the misfit looks like (:meth:`WindowCheck.
    cause`); ``force`` and ``sub_window`` say how the caller may act."""
    return AssumptionError(
        f'the window ({window}) does not fit the model ({check.cause(lacking)}): '
        f'{check.text(sub_window)}; no calibration written ({force})'
    )


@dataclass(frozen=True)
class CheckedCalibration:
    """A solve with its window check (None for the methods that do not assume a known
    gradient) and its notes: how the regional gradient was handled, a forced calibration's
    warning."""

    calibration: Calibration
    check: WindowCheck | None
    notes: tuple[str, ...]

    def diagnostics(self) -> dict[str, Any]:
        """What the calibration file's diagnostics say about the window check, the regional
        gradient (nT/m, ENU, with its 1-sigma: the solver's summary) and the notes."""
        out: dict[str, Any] = {'notes': list(self.notes)} if self.notes else {}
        if self.check is not None:
            out['window_check'] = self.check.to_dict()
        summary = self.calibration.summary()
        for key in ('regional_gradient_enu_nT_per_m', 'regional_gradient_sigma_nT_per_m'):
            if key in summary:
                out[key] = summary[key]
        return out

    def regional_text(self) -> str:
        """The fitted regional gradient's six components with their 1-sigma, nT/m, ENU
        (``gxx +1.234 +- 0.010, ...``); '' when none was fitted."""
        gradient = getattr(self.calibration, 'regional_gradient_enu', None)
        sigma = getattr(self.calibration, 'regional_gradient_sigma', None)
        if gradient is None or sigma is None:
            return ''
        g_nt, sigma_nt = gradient * NT_PER_T, sigma * NT_PER_T
        return ', '.join(
            f'g{"xyz"[i]}{"xyz"[j]} {g_nt[i, j]:+.3f} +- {sigma_nt[i, j]:.3f}'
            for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        )


def excitation_refusal(
    assessment: TrimAssessment, window: str, force_name: str = '--force'
) -> AssumptionError | None:
    """The error for samples whose attitudes do not excite the parameters (the assessment's
    predicted survey sigma above :data:`MAX_PREDICTED_RATIO` noise floors), else None (also
    for noise-free samples: a zero floor predicts nothing)."""
    if assessment.noise_floor == 0.0 or assessment.ratio <= MAX_PREDICTED_RATIO:
        return None
    advice = assessment.advice
    return AssumptionError(
        f'the window ({window}) does not excite the attitudes enough for '
        f'{assessment.parameter_sigma.size} parameters: predicted compensated sigma '
        f'{assessment.predicted_sigma * NT_PER_T:.3g} nT/m = {assessment.ratio:.3g} x noise '
        f'floor {assessment.noise_floor * NT_PER_T:.3g} nT/m (limit {MAX_PREDICTED_RATIO:g}x; '
        f'attitude coverage condition number {assessment.condition_number:.3g}); next: '
        f'{advice.text if advice else "fly a trim manoeuvre"}; no calibration written '
        f'({force_name} writes it anyway, with this warning in the file)'
    )


def identify_checked(
    method: str,
    stamps_ns: IntArray,
    g_measured: FloatArray,
    b_reference: FloatArray,
    geometry: TetraGeometry,
    options: Options,
    *,
    window: str,
    first_ns: int,
    force: bool = False,
    force_name: str = '--force',
    sub_window: str = '--window {0:g}:{1:g}',
    notes: tuple[str, ...] = (),
    assessment: TrimAssessment | None = None,
    lacking: dict[str, str] | None = None,
) -> CheckedCalibration:
    """Identify on the samples, then (known-gradient methods) test the fit's window, and
    with the samples' trim ``assessment`` their attitude excitation
    (:func:`excitation_refusal`).

    ``window`` names the samples in messages; ``force_name`` is how the caller forces a
    failed check (``--force``; the node's ``force:=true``) and ``sub_window`` how it names a
    passing sub-window (a format of its ends, s from ``first_ns``).

    ``options.terms`` are the vehicle effects fitted with ``k``, ``b`` (their regressors on
    the samples); ``lacking`` names the effects whose channels the data lack (effect ->
    what it needs), for the refusal's cause.

    Raises
    ------
    IdentifiabilityError : the samples cannot identify the parameters (naming ``window``)
    AssumptionError : the check fails and ``force`` is False
    """
    try:
        calibration = identify(method, g_measured, b_reference, geometry, options)
    except IdentifiabilityError as error:
        n = len(g_measured)
        raise IdentifiabilityError(f'the window ({window}, {n} sets): {error}') from None
    refusals = [] if assessment is None else [excitation_refusal(assessment, window, force_name)]
    check = None
    if method in KNOWN_GRADIENT_METHODS and isinstance(calibration, TensorCalibration):
        check = _check_window(
            calibration, method, stamps_ns, g_measured, b_reference, geometry, options, first_ns
        )
        hint = f'{force_name} writes it anyway, with this warning in the file'
        refusal = _refusal(check, window, hint, sub_window, lacking or {})
        refusals.append(None if check.passed else refusal)
    return CheckedCalibration(calibration, check, (*notes, *forced(refusals, force, force_name)))


def forced(
    refusals: list[AssumptionError | None], force: bool, force_name: str = '--force'
) -> tuple[str, ...]:
    """The rule of every refusal of a calibration: raise the first unless ``force``; with it,
    the warnings to keep in the file's notes (``WARNING (--force): ...``)."""
    errors = [refusal for refusal in refusals if refusal is not None]
    if errors and not force:
        raise errors[0]
    return tuple(f'WARNING ({force_name}): {error}' for error in errors)
