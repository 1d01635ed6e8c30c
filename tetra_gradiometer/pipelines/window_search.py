"""A calibration that finds its own window: ``calibrate BAG`` without ``--window``,
and the best passing window a failing ``--window`` is pointed to.

The bag's sets are segmented by attitude excitation (:func:`~.window_check.excited_spans`:
10 s blocks where the body-frame direction of ``B_1'`` spreads, i.e. the vehicle turns, rolls
or pitches; straight legs do not). Each manoeuvring span is a candidate, ranked by the trim
guidance's predicted compensated survey sigma over the noise floor
(:func:`~tetra_gradiometer.core.guidance.assess`; without an Earth field, by the attitude
coverage condition number over the square root of the sets). In that order each is
calibrated as ``calibrate --window`` would (:func:`~.trim.calibrate_assessed`: its effects
selected, its window check and its excitation check); a candidate whose check names a passing
sub-window is followed by it. The first that passes both is the window: the best passing one
by the prediction. A localized source inside a manoeuvre fails the window check (its misfit
is field-like) and the next candidate is tried.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core import TetraGeometry, difference_tensor
from ..core.guidance import assess, trim_statistics
from ..core.identification import attitude_coverage
from ..core.timebase import DEFAULT_TIMEBASE, TimeBase
from ..core.units import S_PER_NS
from ..errors import AssumptionError, IdentifiabilityError
from ..io.bag import MagneticBag
from ..io.recording import odometry_at
from .calibration import BagCalibration, WindowSets, read_window, sensor_axes_check
from .trim import (
    DEFAULT_SENSOR_NOISE_T,
    WindowAssessment,
    calibrate_assessed,
    odom_earth_field,
)
from .window_check import EXCITED_SPREAD_DEG, excitation_refusal, excited_spans

__all__ = ['MAX_CANDIDATES', 'Candidate', 'FoundWindow', 'find_window', 'rank_candidates']

#: Candidate windows calibrated at most (each is a read of the bag up to its end and a solve).
MAX_CANDIDATES = 6


@dataclass(frozen=True)
class Candidate:
    """A manoeuvring span of the bag and how well it is predicted to calibrate.

    Attributes
    ----------
    span : (t0, t1) s from the bag's first set
    score : the ranking figure (smaller is better): ``predicted_ratio`` when known, else the
        coverage condition number over sqrt(sets)
    predicted_ratio : the guidance's predicted survey sigma / noise floor, or None (no Earth
        field to predict with)
    """

    span: tuple[float, float]
    score: float
    predicted_ratio: float | None = None
    whole: bool = False

    @property
    def text(self) -> str:
        return f'{self.span[0]:g}:{self.span[1]:g}'

    @property
    def option(self) -> str:
        """How to ask ``calibrate`` for this window."""
        return 'the whole bag (no --window)' if self.whole else f'--window {self.text}'


@dataclass(frozen=True)
class FoundWindow:
    """The window a bag's calibration was made on, and why that one."""

    result: BagCalibration
    window: WindowAssessment
    chosen: Candidate
    tried: tuple[tuple[Candidate, str], ...]
    n_candidates: int

    @property
    def why(self) -> str:
        """One line: which window and why (the candidates, the prediction, the checks)."""
        failed = '; '.join(f'{c.text} s failed: {reason}' for c, reason in self.tried)
        if self.chosen.whole:
            return (
                f'window: the whole bag (0:{self.chosen.span[1]:g} s) passes the window '
                f'check and the excitation check; of its {self.n_candidates} manoeuvring '
                'span(s) none did' + (f' ({failed})' if failed else '')
            )
        predicted = (
            f'predicted survey sigma {self.chosen.predicted_ratio:.2f}x the noise floor'
            if self.chosen.predicted_ratio is not None
            else f'attitude coverage score {self.chosen.score:.3g}'
        )
        return (
            f'window {self.chosen.text} s found in the bag: the best of '
            f"{self.n_candidates} manoeuvring span(s) (B_1' turning in the body frame, "
            f'not a straight leg) that passes the window check and the excitation check '
            f'({predicted})' + (f'; before it, {failed}' if failed else '')
        )

    def diagnostics(self) -> dict[str, Any]:
        return {
            'window_found': {
                'window_s': list(self.chosen.span),
                'predicted_ratio': self.chosen.predicted_ratio,
                'candidates': self.n_candidates,
                'failed_before': [{'window_s': list(c.span), 'reason': r} for c, r in self.tried],
            }
        }


def _orientation(
    bag_path: str | os.PathLike[str], sets: WindowSets, earth_field_enu: np.ndarray | None
) -> np.ndarray | None:
    """``/odom``'s attitude on the sets, checked as every command checks it
    (:func:`~tetra_gradiometer.io.recording.odometry_at`); None when absent or unusable (the
    calibration of the chosen window says so)."""
    with MagneticBag(bag_path) as bag:
        odometry = odometry_at(
            bag, sets.stamps_ns, sets.fields[:, 0], 'calibrate', earth_field_enu
        )
    return odometry.orientation_xyzw


def rank_candidates(
    sets: WindowSets,
    geometry: TetraGeometry,
    earth_field_enu: np.ndarray | None,
    orientation_xyzw: np.ndarray | None = None,
    symmetric: bool = False,
) -> list[Candidate]:
    """The manoeuvring spans of ``sets`` (:func:`~.window_check.excited_spans`), best first
    (see :class:`Candidate`). Times are s from ``sets.first_ns``."""
    t = ((sets.stamps_ns - sets.first_ns) * S_PER_NS).astype(np.float64)
    fields = sets.fields
    candidates = []
    for span in excited_spans(t, fields[:, 0]):
        inside = (t >= span[0]) & (t <= span[1])
        n = int(inside.sum())
        score = attitude_coverage(fields[inside, 0]) / np.sqrt(n)
        ratio = None
        if earth_field_enu is not None and np.isfinite(score):
            statistics = trim_statistics(
                fields[inside, 0],
                difference_tensor(fields[inside], geometry),
                geometry,
                orientation_xyzw=None if orientation_xyzw is None else orientation_xyzw[inside],
            )
            rate = (n - 1) / (span[1] - span[0]) if span[1] > span[0] else 1.0
            assessment = assess(
                statistics,
                geometry,
                earth_field_enu,
                sample_rate_hz=rate,
                sensor_noise_t=DEFAULT_SENSOR_NOISE_T,
                symmetric=symmetric,
            )
            ratio = float(assessment.ratio)
            score = ratio if np.isfinite(ratio) else np.inf
        candidates.append(Candidate(span, float(score), ratio))
    return sorted(candidates, key=lambda c: (c.score, c.span[0]))


def _verdict(result: BagCalibration, window: WindowAssessment) -> str:
    """'' when the calibration passes its window check and excitation check, else why not."""
    if result.check is not None and not result.check.passed:
        return f'window check: {result.check.consistency.text}'
    if window.assessment is not None:
        refusal = excitation_refusal(window.assessment, result.window)
        if refusal is not None:
            return (
                f'excitation: predicted survey sigma {window.assessment.ratio:.3g}x the noise '
                'floor'
            )
    return ''


def find_window(
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    earth_field_enu: np.ndarray | None = None,
    *,
    exclude: tuple[float, float] | None = None,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    **options: Any,
) -> FoundWindow:
    """Find the best passing calibration window of the bag (see the module) and calibrate on
    it; ``options`` are :func:`~.trim.calibrate_assessed`'s keywords (not ``window``,
    ``force``); ``exclude`` is a window already tried (``--window``): skipped.

    Raises
    ------
    AssumptionError : no manoeuvring span of the bag passes (each one's reason named), or
        the bag holds none
    BagError : as :func:`~.calibration.read_window`
    """
    earth_norm = None if earth_field_enu is None else float(np.linalg.norm(earth_field_enu))
    sets = read_window(
        bag_path,
        None,
        timebase=timebase,
        progress=options.get('progress'),
        earth_field_t=earth_norm,
    )
    sensor_axes_check(sets.fields, f'0:{sets.span_s:.1f} s (the whole bag)', force=False)
    orientation = _orientation(bag_path, sets, earth_field_enu)
    earth = earth_field_enu
    if earth is None and orientation is not None:
        earth = odom_earth_field(orientation, sets.fields[:, 0])
    symmetric = options.get('method') == 'known_gradient_lstsq'
    queue = rank_candidates(sets, geometry, earth, orientation, symmetric)
    n_candidates = len(queue)
    tried: list[tuple[Candidate, str]] = []
    seen = {exclude} if exclude is not None else set()
    while queue and len(tried) < MAX_CANDIDATES:
        candidate = queue.pop(0)
        if candidate.span in seen:
            continue
        seen.add(candidate.span)
        try:
            result, window = calibrate_assessed(
                bag_path,
                geometry,
                earth_field_enu,
                window=candidate.span,
                force=True,
                timebase=timebase,
                **options,
            )
        except (AssumptionError, IdentifiabilityError) as error:
            tried.append((candidate, str(error)))
            continue
        reason = _verdict(result, window)
        if not reason:
            return _found(result, window, candidate, tried, n_candidates)
        tried.append((candidate, reason))
        sub = None if result.check is None else result.check.passing_window
        if sub is not None and sub not in seen:
            queue.insert(0, Candidate(sub, candidate.score, candidate.predicted_ratio))
    return _whole_bag(
        bag_path,
        geometry,
        earth_field_enu,
        tried,
        n_candidates,
        exclude,
        sets.span_s,
        timebase,
        options,
    )


def _found(
    result: BagCalibration,
    window: WindowAssessment,
    candidate: Candidate,
    tried: list[tuple[Candidate, str]],
    n_candidates: int,
) -> FoundWindow:
    found = FoundWindow(result, window, candidate, tuple(tried), n_candidates)
    return FoundWindow(
        result.with_diagnostics(found.diagnostics()), window, candidate, tuple(tried), n_candidates
    )


def _whole_bag(
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    earth_field_enu: np.ndarray | None,
    tried: list[tuple[Candidate, str]],
    n_candidates: int,
    exclude: tuple[float, float] | None,
    span_s: float,
    timebase: TimeBase,
    options: dict[str, Any],
) -> FoundWindow:
    """No manoeuvring span passed (or the bag has none): the whole bag, as ``calibrate``
    without a window did before it searched. Its refusal is the bag's when there was no span
    to try, else one line naming every span tried and why it failed."""
    whole = Candidate((0.0, span_s), np.inf, whole=True)
    try:
        if exclude is not None and not tried:
            raise AssumptionError('no other window to try')
        result, window = calibrate_assessed(
            bag_path, geometry, earth_field_enu, window=None, timebase=timebase, **options
        )
    except (AssumptionError, IdentifiabilityError) as error:
        if not tried and exclude is None:
            raise AssumptionError(
                f"{error}; no span of the bag manoeuvres (the direction of B_1' in the body "
                f'frame spreads less than {EXCITED_SPREAD_DEG:g} deg, or than 1.5x its '
                f"straight legs' sway, in every 30 s of {span_s:.0f} s): fly a trim "
                'manoeuvre (turns, roll and pitch) in a uniform field, away from targets'
            ) from None
        spans = '; '.join(f'{c.text} s: {reason}' for c, reason in tried)
        raise AssumptionError(
            f'{bag_path}: no window of the bag passes: of {n_candidates} manoeuvring '
            f'span(s), {spans or "none"}; nor the whole bag; fly a trim manoeuvre in a '
            'uniform field away from targets, or give --window (with --force to keep a '
            'failing one)'
        ) from None
    return _found(result, window, whole, tried, n_candidates)
