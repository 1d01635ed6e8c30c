"""Calibrating from a bag: read a window of matched sets and identify ``k``, ``b`` (eq. 18).

The window, in seconds from the bag's first matched set, is where the **true gradient is
taken as zero**: a trim manoeuvre in a uniform field, away from targets
(``constraint_lstsq`` and ``paper_ga`` do not use that assumption). It is read streaming;
only its sets are kept. A window of more than ``max_sets`` sets is thinned uniformly (every
k-th set) to bound the solver's memory (the design holds 9 x 36 floats per set).

The default method fits the vehicle effects the window calls for with ``k``, ``b``
(:mod:`.terms`). :mod:`.trim` adds the trim guidance on the sets the solve used
(``calibrate_assessed``: what the ``calibrate`` command and ``batch`` do before they write).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core import TetraGeometry, difference_tensor
from ..core.conventions import relative_axes
from ..core.effects import SIGNAL_PREFIX, parse_declaration
from ..core.identification import (
    DEFAULT_METHOD,
    MAX_COVERAGE_CONDITION,
    Calibration,
    Options,
    attitude_coverage,
)
from ..core.identification.paper_ga import GENERATIONS
from ..core.plausibility import DroppedSets, plausible_sets
from ..core.timebase import DEFAULT_TIMEBASE, ClockEstimate, TimeBase
from ..core.units import S_PER_NS
from ..errors import AssumptionError, BagError, InputError
from ..io import conversions as cv
from ..io.bag import MagneticBag, SetCounters
from ..io.calibration import CalibrationFile
from ..io.recording import odometry_at
from .effects_choice import EffectsChoice
from .terms import WindowTerms, window_terms
from .window_check import (
    EXPLAINING,
    KNOWN_GRADIENT_METHODS,
    REJECTED,
    UNREAD,
    CheckedCalibration,
    WindowCheck,
    forced,
    identify_checked,
    joint_attitude,
    orientation_at,
)

__all__ = [
    'DEFAULT_MAX_SETS',
    'MIN_SETS',
    'BagCalibration',
    'WindowSets',
    'calibrate_bag',
    'read_window',
    'window_text',
]

DEFAULT_MAX_SETS = 50_000
#: ``max_sets`` may not be smaller (a thinned window must still identify 36 parameters).
MIN_SETS = 10

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class WindowSets:
    """The matched sets of a window.

    Attributes
    ----------
    stamps_ns : ndarray, shape (n,), int64
        Header stamps of sensor 1, ns.
    fields : ndarray, shape (n, 4, 3)
        Sensor fields, tesla, body frame.
    span_s : float
        Seconds of the bag read (from its first matched set to the last one read).
    counters : MatchCounters or ResampleCounters
        The set former's counts over what was read.
    clocks : tuple of ClockEstimate, or None
        The sensors' clocks against the reference instants (None when pairing stamps).
    first_ns : int
        Stamp of the bag's first set (window times count from it), ns.
    skipped_messages : int
        Messages skipped as undecodable or unreadable (``MagneticBag.skipped``).
    skipped_summary : str
        The reader's line about them ('' when none).
    """

    stamps_ns: IntArray
    fields: FloatArray
    span_s: float
    counters: SetCounters
    clocks: tuple[ClockEstimate, ...] | None = None
    first_ns: int = 0
    skipped_messages: int = 0
    skipped_summary: str = ''


@dataclass(frozen=True)
class BagCalibration:
    """A calibration from a bag, with what the summary and the file's diagnostics report.

    Attributes
    ----------
    calibration : Calibration
        The solver's result.
    record : CalibrationFile
        The calibration file to save, its diagnostics including the ones below.
    window : str
        The window as text (``'whole bag'`` or ``'T0:T1 s'``).
    sets_in_window : int
        Sets with plausible readings in the window, before thinning.
    thinned_every : int
        Every how many sets one was used (1: all).
    span_s : float
        Seconds of the bag read.
    dropped : DroppedSets
        Sets of the window dropped as implausible (non-finite, ``|B|`` too large), by reason.
    counters, clocks : as in :class:`WindowSets`
    check : WindowCheck or None
        The fit's test of its own assumption (known-gradient methods).
    notes : tuple of str
        How the regional gradient was handled; the warning of a forced calibration.
    skipped_messages, skipped_summary : as in :class:`WindowSets`
    stamps_ns : ndarray, shape (n,), int64
        Stamps of the sets the solve used (after thinning), ns.
    fields : ndarray, shape (n, 4, 3)
        Their readings, tesla, body frame.
    orientation_xyzw : ndarray, shape (n, 4), or None
        Their attitude from ``/odom`` when the regional gradient was fitted jointly.
    terms : WindowTerms
        The vehicle effects fitted (or why none), with their held-out tests.
    """

    calibration: Calibration
    record: CalibrationFile
    window: str
    sets_in_window: int
    thinned_every: int
    span_s: float
    dropped: DroppedSets
    counters: SetCounters
    clocks: tuple[ClockEstimate, ...] | None = None
    check: WindowCheck | None = None
    notes: tuple[str, ...] = ()
    skipped_messages: int = 0
    skipped_summary: str = ''
    stamps_ns: IntArray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    fields: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 4, 3)))
    orientation_xyzw: FloatArray | None = None
    terms: WindowTerms = dataclasses.field(default_factory=WindowTerms)

    def with_note(self, note: str) -> BagCalibration:
        """The same calibration with ``note`` added to its notes and its file's."""
        notes = (*self.notes, note)
        diagnostics = {**self.record.diagnostics, 'notes': list(notes)}
        record = dataclasses.replace(self.record, diagnostics=diagnostics)
        return dataclasses.replace(self, notes=notes, record=record)

    def with_diagnostics(self, extra: dict[str, Any]) -> BagCalibration:
        """The same calibration with ``extra`` added to its file's diagnostics."""
        diagnostics = {**self.record.diagnostics, **extra}
        return dataclasses.replace(
            self, record=dataclasses.replace(self.record, diagnostics=diagnostics)
        )

    @property
    def checked(self) -> CheckedCalibration:
        """The solve with its window check and notes."""
        return CheckedCalibration(self.calibration, self.check, self.notes)

    @property
    def coverage_condition(self) -> float:
        """Attitude coverage condition number of the window's reference field."""
        return float(self.calibration.details['attitude_coverage_condition'])


def window_text(window: tuple[float, float] | None) -> str:
    """``'whole bag'`` or ``'T0:T1 s'``."""
    return 'whole bag' if window is None else f'{window[0]:g}:{window[1]:g} s'


def read_window(
    bag_path: str | os.PathLike[str],
    window: tuple[float, float] | None,
    *,
    timebase: TimeBase,
    progress: bool | None = None,
    earth_field_t: float | None = None,
) -> WindowSets:
    """The matched sets of ``window`` (seconds from the first set; None: the whole bag).

    Reading stops at the first set beyond the window (sets come in stamp order).

    Raises
    ------
    BagError
        The bag breaks the data contract, or the window holds no set.
    """
    stamps: list[IntArray] = []
    fields: list[FloatArray] = []
    first: int | None = None
    last = 0
    with MagneticBag(bag_path) as bag:
        sets = bag.iter_sets(timebase=timebase, progress=progress, earth_field_t=earth_field_t)
        for chunk_stamps, chunk_fields in sets:
            first = int(chunk_stamps[0]) if first is None else first
            last = int(chunk_stamps[-1])
            beyond = False
            if window is not None:
                t = (chunk_stamps - first) * S_PER_NS
                keep = (t >= window[0]) & (t <= window[1])
                chunk_stamps, chunk_fields = chunk_stamps[keep], chunk_fields[keep]
                beyond = t[-1] > window[1]
            if len(chunk_stamps):
                stamps.append(chunk_stamps)
                fields.append(chunk_fields)
            if beyond:  # sets come in stamp order: the rest of the bag lies beyond the window
                sets.close()
                break
        counters, clocks = bag.counters, bag.clocks
        skipped = bag.skipped_messages, bag.skipped_summary()
    span = 0.0 if first is None else (last - first) * S_PER_NS
    if not stamps:
        raise BagError(
            f'{bag_path}: the window {window_text(window)} holds no sample set '
            f'(the bag spans 0:{span:.3f} s from its first stamp)'
        )
    joined = np.concatenate(stamps), np.concatenate(fields)
    return WindowSets(*joined, span, counters, clocks, first or 0, *skipped)


def _read_plausible(
    bag_path: str | os.PathLike[str],
    window: tuple[float, float] | None,
    timebase: TimeBase,
    progress: bool | None,
    earth_field_enu: FloatArray | None,
) -> tuple[WindowSets, DroppedSets]:
    """:func:`read_window` (the streams checked against ``|earth_field_enu|``), then
    :func:`_plausible`."""
    earth_t = None if earth_field_enu is None else float(np.linalg.norm(earth_field_enu))
    sets = read_window(
        bag_path, window, timebase=timebase, progress=progress, earth_field_t=earth_t
    )
    return _plausible(sets, bag_path)


def _plausible(
    sets: WindowSets, bag_path: str | os.PathLike[str]
) -> tuple[WindowSets, DroppedSets]:
    """The sets whose four readings are plausible (:func:`~tetra_gradiometer.core.
    plausibility.plausible_sets`: finite, ``|B|`` within bounds), and the others' count."""
    keep, dropped = plausible_sets(sets.fields)
    if not keep.any():
        raise BagError(
            f'{bag_path}: every set in the window has an implausible reading ({dropped.text()})'
        )
    kept = dataclasses.replace(sets, stamps_ns=sets.stamps_ns[keep], fields=sets.fields[keep])
    return kept, dropped


def calibrate_bag(
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    *,
    window: tuple[float, float] | None = None,
    method: str = DEFAULT_METHOD,
    seed: int = 0,
    generations: int | None = None,
    wide_bounds: bool = False,
    max_coverage_condition: float = MAX_COVERAGE_CONDITION,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    max_sets: int = DEFAULT_MAX_SETS,
    progress: bool | None = None,
    force: bool = False,
    effects: EffectsChoice | None = None,
    earth_field_enu: FloatArray | None = None,
) -> BagCalibration:
    """Identify the interference of the array ``geometry`` on a window of the bag.

    Known-gradient methods estimate a regional gradient jointly when the bag has ``/odom``
    (else assume zero: ``notes``) and test the residual against the noise (window_check);
    the default method fits the vehicle effects ``effects`` chooses (pipelines/terms).

    Parameters
    ----------
    bag_path, geometry : the rosbag2 folder, and the array that recorded it
    window : (t0, t1) in seconds from the first matched set, or None for the whole bag
    method : a method of ``core.identification.CALIBRATION_METHODS``
    seed, generations, wide_bounds : ``paper_ga`` only (generations default ``GENERATIONS``)
    max_coverage_condition : refuse a window whose attitude coverage condition is larger
    timebase : how the streams become sets (default: resampled to sensor 1's stamps)
    max_sets : thin the window to at most this many sets (at least :data:`MIN_SETS`)
    progress : tqdm bar on stderr (None: only on a terminal and for long bags)
    force : keep a calibration that fails a check (warning in its diagnostics)
    effects : the vehicle effects to fit (None: automatic selection)
    earth_field_enu : (3,) T: |B| for the streams' check, the direction for ``/odom``'s

    Raises
    ------
    AssumptionError : the window is not consistent with a constant gradient, or a sensor's
        axes are not sensor 1's (no ``force``)
    InputError : ``max_sets`` or ``generations`` out of range, or an unknown method
    BagError : the bag breaks the data contract, or the window holds no usable set
    IdentifiabilityError : the window cannot identify the parameters (message names it)
    CalibrationFileError : the method gives no ``k, b`` calibration"""
    _check_limits(max_sets, generations)
    sets, dropped = _read_plausible(bag_path, window, timebase, progress, earth_field_enu)
    n_window = len(sets.stamps_ns)
    thinned = max(1, int(np.ceil(n_window / max_sets)))  # every k-th set: at most max_sets
    text = window_text(window)
    options = Options(
        rng=np.random.default_rng(seed),
        generations=generations or GENERATIONS,
        wide_bounds=wide_bounds,
        max_coverage_condition=max_coverage_condition,
    )
    checked, options, terms = _solve(
        bag_path, sets, thinned, geometry, method, options, effects, text, force, earth_field_enu
    )
    result = BagCalibration(
        calibration=checked.calibration,
        record=CalibrationFile.from_calibration(checked.calibration, geometry),
        window=text,
        sets_in_window=n_window,
        thinned_every=thinned,
        span_s=sets.span_s,
        dropped=dropped,
        counters=sets.counters,
        clocks=sets.clocks,
        check=checked.check,
        notes=checked.notes,
        skipped_messages=sets.skipped_messages,
        skipped_summary=sets.skipped_summary,
        stamps_ns=sets.stamps_ns[::thinned],
        fields=sets.fields[::thinned],
        orientation_xyzw=options.orientation_xyzw,
        terms=terms,
    )
    extra = _diagnostics(result, bag_path) | ({'seed': seed} if method == 'paper_ga' else {})
    return result.with_diagnostics(extra)


def _solve(
    bag_path: str | os.PathLike[str],
    sets: WindowSets,
    thinned: int,
    geometry: TetraGeometry,
    method: str,
    options: Options,
    effects: EffectsChoice | None,
    window: str,
    force: bool,
    earth_field_enu: FloatArray | None,
) -> tuple[CheckedCalibration, Options, WindowTerms]:
    """The checked solve (:func:`~.window_check.identify_checked`) on every ``thinned``-th
    set of ``sets``, with the ``/odom`` attitude and the vehicle effects' terms."""
    stamps, fields = sets.stamps_ns[::thinned], sets.fields[::thinned]
    axes_note = sensor_axes_check(fields, window, force)
    options, note = _with_attitude(
        options, method, bag_path, stamps, fields[:, 0], earth_field_enu
    )
    terms = _terms(bag_path, sets, thinned, geometry, method, effects, options)
    fitted = dataclasses.replace(options, terms=terms.candidates)
    solve = functools.partial(
        identify_checked,
        method,
        stamps,
        difference_tensor(fields, geometry),
        fields[:, 0],
        geometry,
        window=window,
        first_ns=sets.first_ns,
        notes=(*axes_note, *note, *terms.notes),
    )
    lacking = {**terms.lacking, **_unread_signals(bag_path, effects)}
    try:
        checked = solve(fitted, force=force, lacking=lacking)
        if checked.check is None or checked.check.passed:
            return checked, fitted, terms
    except AssumptionError:
        pass
    # The check failed: its cause from evidence, the held-out selection on the bag's signals
    # (a second solve, on this path only).
    def passes(candidates: tuple[Any, ...]) -> bool:
        with_them = dataclasses.replace(options, terms=candidates)
        check = solve(with_them, force=True, lacking={}).check
        return check is not None and check.passed

    offer = functools.partial(_terms, bag_path, sets, thinned, geometry, method, options=options)
    evidence = _signal_evidence(bag_path, effects, terms, offer, passes)
    return solve(fitted, force=force, lacking={**lacking, **evidence}), fitted, terms


def _signal_evidence(
    bag_path: str | os.PathLike[str],
    effects: EffectsChoice | None,
    terms: WindowTerms,
    offer: Callable[[EffectsChoice], WindowTerms],
    passes: Callable[[tuple[Any, ...]], bool],
) -> dict[str, str]:
    """Whether the vehicle's recorded signals explain a window that fails its check:
    ``{EXPLAINING: names}`` for the effects the automatic selection (every recorded signal
    offered, each held-out tested) keeps and the fit does not read, when the window
    ``passes`` its check with them (an effect that explains part of a target's pass, e.g.
    an eddy term on the field's rate along the track, is no evidence); else ``{REJECTED:
    topics}`` for the signal topics tested and not kept; {} when none was tested."""
    choice = effects or EffectsChoice()
    if not (choice.automatic and choice.discover):
        automatic = dataclasses.replace(choice, names=None, discover=True, source='auto')
        fitted = {c.name for c in terms.candidates}
        terms = offer(automatic)  # the window's terms under automatic selection
        kept = [c.name for c in terms.candidates if c.name not in fitted]
        if kept and passes(terms.candidates):
            return {EXPLAINING: ', '.join(kept)}
    from ..io.discovery import signal_topics

    with MagneticBag(bag_path) as bag:
        tested = signal_topics(bag)
    kept_topics = {
        parse_declaration(c.name).topic
        for c in terms.candidates
        if c.name.startswith(SIGNAL_PREFIX)
    }
    rejected = [t for t in tested if t not in kept_topics]
    return {REJECTED: ', '.join(rejected)} if rejected else {}


def _unread_signals(
    bag_path: str | os.PathLike[str], effects: EffectsChoice | None
) -> dict[str, str]:
    """``{UNREAD: 'topic, ...'}`` for the bag's topics that may carry a vehicle signal and
    that no declared signal reads, or {}."""
    from ..io.discovery import signal_topics

    with MagneticBag(bag_path) as bag:
        choice = effects or EffectsChoice()
        declared = {
            parse_declaration(n).topic
            for n in (*choice.signals, *(choice.names or ()))
            if n.startswith(SIGNAL_PREFIX)
        }
        unread = [t for t in signal_topics(bag) if t not in declared]
    return {UNREAD: ', '.join(unread[:6]) + (' ...' if len(unread) > 6 else '')} if unread else {}


def sensor_axes_check(fields: FloatArray, window: str, force: bool) -> tuple[str, ...]:
    """Refuse a window whose sensors' axes are not sensor 1's (:func:`~tetra_gradiometer.
    core.conventions.relative_axes` on ``fields`` (N, 4, 3) T): a calibration fitted around
    a turned or mirrored sensor gives a wrong tensor. With ``force`` the finding becomes a
    warning note; () when they agree or the field turns too little to tell."""
    findings = relative_axes(fields)
    if not findings:
        return ()
    text = '; '.join(f.text() for f in findings)
    cause = (
        f'window {window}: {text}. Every sensor reads the same Earth field in the body frame '
        "up to the vehicle interference, so its axes against sensor 1's follow from the "
        "data: mount the sensor as declared or rotate its readings (its driver's frame) "
        'before calibrating'
    )
    return forced([AssumptionError(cause)], force)


def _terms(
    bag_path: str | os.PathLike[str],
    sets: WindowSets,
    thinned: int,
    geometry: TetraGeometry,
    method: str,
    effects: EffectsChoice | None,
    options: Options,
) -> WindowTerms:
    """The vehicle effects the window is fitted with (the default method only: the others
    fit the paper's form; none on a window the solve will refuse for its attitudes)."""
    choice = effects or EffectsChoice()
    if method != DEFAULT_METHOD:
        if choice.names:
            raise InputError(
                f'--effects {",".join(choice.names)}: vehicle effects are fitted with '
                f'{DEFAULT_METHOD}, not {method}'
            )
        return WindowTerms(notes=(f'effects: none ({method} fits k, b only)',))
    if choice.names != () and not (
        attitude_coverage(sets.fields[::thinned, 0]) <= options.max_coverage_condition
    ):  # the solve refuses these attitudes, naming their condition number
        return WindowTerms(notes=('effects: none offered (the field spans too few directions)',))
    used = np.arange(0, len(sets.stamps_ns), thinned)
    return window_terms(
        bag_path, sets.stamps_ns, sets.fields, used, geometry, choice, options.orientation_xyzw
    )


def _check_limits(max_sets: int, generations: int | None) -> None:
    if max_sets < MIN_SETS:
        raise InputError(f'--max-sets must be at least {MIN_SETS}, got {max_sets}')
    if generations is not None and generations < 1:
        raise InputError(f'--generations must be >= 1, got {generations}')


def _with_attitude(
    options: Options,
    method: str,
    bag_path: str | os.PathLike[str],
    stamps_ns: IntArray,
    body_field_t: FloatArray,
    earth_field_enu: FloatArray | None,
) -> tuple[Options, tuple[str, ...]]:
    """Known-gradient methods: the ``/odom`` attitude of each set, for the joint regional
    gradient (none without a usable ``/odom``: assumed zero, as the notes say)."""
    if method not in KNOWN_GRADIENT_METHODS:
        return options, ()
    orientation, notes = odom_orientation(bag_path, stamps_ns, body_field_t, earth_field_enu)
    return dataclasses.replace(options, orientation_xyzw=orientation), notes


def _diagnostics(result: BagCalibration, bag_path: str | os.PathLike[str]) -> dict[str, Any]:
    """What the calibration file's diagnostics add about the bag, the window and matching."""
    return {
        'bag': str(bag_path),
        'window_s': result.window,
        # The first and last fitted sets' stamps, s (the calibrator node's key too): where the
        # tracker starts learning (pipelines/tracking.learn_after_ns).
        'samples_window_s': [float(result.stamps_ns[i]) * S_PER_NS for i in (0, -1)],
        'sets_in_window': result.sets_in_window,
        'thinned_every': result.thinned_every,
        'attitude_coverage_condition': result.calibration.details['attitude_coverage_condition'],
        'read_span_s': result.span_s,
        **result.dropped.as_dict(),
        **result.counters.as_dict(),
        **_clock_diagnostics(result.clocks),
        **result.checked.diagnostics(),
        'effects': result.terms.diagnostics(),
        'messages_skipped_undecodable': result.skipped_messages,
    }


def _clock_diagnostics(clocks: tuple[ClockEstimate, ...] | None) -> dict[str, Any]:
    """Each sensor's clock against the reference (absent when stamps were paired)."""
    return {} if clocks is None else {'sensor_clocks': [c.to_dict() for c in clocks]}


def odom_orientation(
    bag_path: str | os.PathLike[str],
    stamps_ns: IntArray,
    body_field_t: FloatArray | None = None,
    earth_field_enu: FloatArray | None = None,
) -> tuple[FloatArray | None, tuple[str, ...]]:
    """``/odom``'s orientation slerped onto ``stamps_ns`` (n, 4), or None, with notes why.

    None when the bag has no usable ``/odom`` (checked: :func:`~tetra_gradiometer.io.
    recording.odometry_at`, the attitude against ``body_field_t`` (n, 3) T, sensor 1's
    field) or some set lies further than ``MAX_ODOM_GAP_S`` from every ``/odom`` message
    (the joint solve needs every attitude).
    """
    with MagneticBag(bag_path) as bag:
        odometry = odometry_at(bag, stamps_ns, body_field_t, 'calibrate', earth_field_enu)
    check = odometry.check
    if odometry.orientation_xyzw is None or check is None:
        return None, odometry.notes
    orientation = orientation_at(check.stamps_ns, check.pose[:, cv.POSE_ORIENTATION], stamps_ns)
    attitude, note = joint_attitude(orientation)
    return attitude, (*odometry.notes, note)
