"""Which vehicle effects a calibration window fits, from a bag: its channels read onto the
window's sets, the candidates of the effects registry they allow, and the selection
(:func:`tetra_gradiometer.core.identification.terms.select_terms`) or the user's choice.

:class:`EffectsChoice` is what ``calibrate --effects auto|none|NAME,... [--effects-from
REPORT] [--current-topics T,...]`` (and the calibrator node's ``effects`` and
``current_topics``) ask for: ``auto`` (the default) offers every effect whose channels the
data have and keeps those that pass the selection's held-out test; ``none`` fits the paper's
``k``, ``b`` alone; names fit exactly those (refused when a channel they need is missing);
``--effects-from`` takes the effects a discrepancy ``report.json`` named.

:func:`window_terms` reads the bag; :func:`terms_on` is the same choice on channels already
on the sets (:func:`channels_on`), without a bag: the calibrator node calls it on the
samples and channel messages it collected. This module imports ``rosbags`` (through
``io.bag``) only where it opens a bag, so an on-vehicle node may import it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ..core.effects import (
    REFERENCE_RATE,
    SIGNAL_PREFIX,
    Channels,
    Term,
    effect,
    parse_declaration,
    term_regressors,
    terms_channels,
)
from ..core.effects.losses import USUAL_INTERVALS
from ..core.effects.recorded_signal import basis_for
from ..core.geometry import TetraGeometry
from ..core.identification.terms import (
    ALPHA,
    MIN_GAIN,
    Candidate,
    Selection,
    candidates_for,
    regional_columns,
    select_terms,
    without_redundant,
)
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import BagError, InputError
from ..io import conversions as cv
from ..io.channels import TEMPERATURE as TEMPERATURE_CHANNEL
from ..io.channels import (
    ChannelSeries,
    channel_topic,
    current_channels,
    read_channels,
    runs,
    spans_text,
)

if TYPE_CHECKING:
    from ..io.bag import MagneticBag
    from .effects_choice import EffectsChoice

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Robust standard deviation of a normal sample from its median absolute deviation.
MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class WindowTerms:
    """The terms a window is fitted with, and why.

    Attributes
    ----------
    candidates : the effects to fit, their regressors on the solve's sets
    selection : the held-out tests (None when no effect was offered)
    lacking : effect -> what it would need that the bag lacks
    channels : the recorded channels found (name -> topic)
    notes : one line on the choice, for the summary and the file
    """

    candidates: tuple[Candidate, ...] = ()
    selection: Selection | None = None
    lacking: dict[str, str] = field(default_factory=dict)
    channels: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def diagnostics(self) -> dict[str, Any]:
        """For the calibration file's diagnostics and the report."""
        out: dict[str, Any] = {
            'selected': [c.name for c in self.candidates],
            'channels': self.channels,
            'lacking': self.lacking,
        }
        if self.selection is not None:
            out['tests'] = self.selection.evidence
            if self.selection.unsolved:
                out['unsolved'] = self.selection.unsolved
        return out


def _series_noise(series: ChannelSeries) -> float:
    """A channel's own noise, its unit: the robust spread of second differences of its
    messages (``var(d^2 e) = 6 sigma^2`` for white ``e``; a ramp or a step between messages
    adds nothing or one outlier)."""
    second = np.diff(series.values, n=2)
    if len(second) < 3:
        return 0.0
    return float(MAD_TO_SIGMA * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))


def _regressor_noise(regressors: FloatArray) -> tuple[float, ...]:
    """Noise of computed regressors (the eddy rate): third differences' robust spread
    (``var(d^3 e) = 20 sigma^2`` for white ``e``)."""
    third = np.diff(regressors, n=3, axis=0)
    third = third[np.all(np.isfinite(third), axis=1)]
    if len(third) < 3:
        return (0.0,) * regressors.shape[1]
    spread = MAD_TO_SIGMA * np.median(np.abs(third - np.median(third, axis=0)), axis=0)
    return tuple(float(v) for v in spread / np.sqrt(20.0))


def channels_on(
    stamps_ns: IntArray, b_reference: FloatArray, series: Mapping[str, ChannelSeries]
) -> Channels:
    """The channels ``series`` on the sets ``stamps_ns`` (n,) ns whose reference reading is
    ``b_reference`` (n, 3) T (:meth:`ChannelSeries.on`: NaN where stale), times from the
    first set."""
    t_s = (stamps_ns - stamps_ns[0]) * S_PER_NS
    on_sets = {name: s.on(stamps_ns) for name, s in series.items()}
    return Channels(t_s, b_reference, on_sets)


def window_channels(
    bag_path: str | os.PathLike[str],
    stamps_ns: IntArray,
    fields: FloatArray,
    current_topics: tuple[str, ...] = (),
    signal_channels: tuple[str, ...] = (),
    discover: bool = False,
) -> tuple[Channels, dict[str, ChannelSeries], tuple[str, ...]]:
    """The recorded channels on the sets ``stamps_ns`` (n,) with readings ``fields``
    (n, 4, 3) T: the temperature and the currents the bag has: ``/battery_state``,
    ``current_topics`` and every other ``sensor_msgs/BatteryState`` topic it records (one per
    thruster ESC, say: a current the calibration does not read would be misfit), the
    ``signal_channels`` and, with ``discover``, every numeric signal the bag records beyond
    the contract (``io/discovery.discover_signals``); and a line per channel topic of another
    type, not read, and per signal left out."""
    from ..io.bag import MagneticBag
    from ..io.discovery import discover_signals

    with MagneticBag(bag_path) as bag:
        recorded = bag.topics_of_type(cv.BATTERY_STATE)
        absent = [topic for topic in current_topics if topic not in recorded]
        if absent:
            raise InputError(
                f'--current-topics {",".join(absent)}: not a sensor_msgs/BatteryState topic of '
                f'{bag_path} (its BatteryState topics: {", ".join(recorded) or "none"}; all its '
                f'topics: {", ".join(bag.topics())})'
            )
        found, left_out = discover_signals(bag) if discover else ({}, [])
        names = (
            TEMPERATURE_CHANNEL,
            *current_channels((*current_topics, *recorded)),
            *(name for name in signal_channels if name not in found),
        )
        series = read_channels(bag, names)
        for name, signal in found.items():
            series[name] = ChannelSeries(name, signal.stamps_ns, signal.values[:, 0])
    notes = (*bag.unread.values(), *(f'signal left out: {note}' for note in left_out))
    return channels_on(stamps_ns, fields[:, 0, :], series), series, notes


#: The note of ``--effects none``.
NONE_NOTE = "effects: none (the paper's k, b only)"


def window_terms(
    bag_path: str | os.PathLike[str],
    stamps_ns: IntArray,
    fields: FloatArray,
    used: npt.NDArray[np.intp],
    geometry: TetraGeometry,
    choice: EffectsChoice,
    orientation_xyzw: FloatArray | None,
) -> WindowTerms:
    """The terms to fit on the window's sets ``stamps_ns`` (n,) / ``fields`` (n, 4, 3) T, of
    which the solve uses ``used`` (a thinned window: regressors are computed on every set,
    an eddy rate needs the neighbours), with the attitude of the used sets when the regional
    gradient is fitted jointly (:func:`terms_on` on the bag's channels).

    Raises
    ------
    InputError
        Effects asked for by name whose channels the bag lacks (named with the channel).
    """
    if choice.names == ():
        return WindowTerms(notes=(NONE_NOTE,))
    discover = choice.automatic and choice.discover
    channels, series, unread = window_channels(
        bag_path, stamps_ns, fields, choice.current_topics, choice.signal_channels, discover
    )
    declared = {parse_declaration(name).channel for name in choice.signals}
    found = []
    for name in channels.series if discover else ():
        if name.startswith(SIGNAL_PREFIX) and name not in declared:
            basis = basis_for(name, channels.series[name])
            if basis is not None:
                found.append(f'{name}:{basis}')
    if found:  # what the bag records is offered beside the declared signals
        choice = replace(choice, signals=(*choice.signals, *found))
        unread = (*unread, f'signals found in the bag, offered to the selection: '
                  f'{", ".join(n.removeprefix(SIGNAL_PREFIX) for n in found)}')
    pairs = _pairs(fields[used], geometry)
    terms = terms_on(channels, series, pairs, used, geometry, choice, orientation_xyzw)
    return replace(terms, notes=(*unread, *terms.notes)) if unread else terms


def terms_on(
    channels: Channels,
    series: Mapping[str, ChannelSeries],
    pairs: FloatArray,
    used: npt.NDArray[np.intp],
    geometry: TetraGeometry,
    choice: EffectsChoice,
    orientation_xyzw: FloatArray | None,
    data: str = 'the bag',
) -> WindowTerms:
    """The terms to fit, without a bag: ``channels`` on every set of the window
    (:func:`channels_on` of the recorded ``series``), the pair differences ``B_i' - B_1'``
    of the sets the solve uses (``used``), (len(used), 3 axes, 3 pairs) T, and their
    attitude (or None). ``data`` names where the channels come from, in errors.

    Raises
    ------
    InputError
        Effects asked for by name whose channels ``data`` lacks (named with the channel).
    """
    if choice.names == ():
        return WindowTerms(notes=(NONE_NOTE,))
    found = {name: channel_topic(name) for name in series}
    candidates, lacking = candidates_for(channels, choice.names, choice.signals)
    if choice.names is not None and lacking:
        raise InputError(
            'effects asked for ('
            + choice.source
            + f') need channels {data} lacks: '
            + '; '.join(f'{name} needs {what}' for name, what in lacking.items())
        )
    candidates, redundant = _independent(
        [
            replace(
                c.select(used),
                channel_noise=(
                    tuple(_series_noise(series[name]) for name in c.inputs)
                    if all(name in series for name in c.inputs)
                    and len(c.inputs) == c.regressors.shape[1]  # one regressor per channel
                    else _regressor_noise(c.regressors)
                ),
            )
            for c in candidates
        ],
        lacking,
    )
    if choice.names is not None and set(choice.names) & set(lacking):
        raise InputError(
            f'effects asked for ({choice.source}) cannot be fitted on this window: '
            + '; '.join(
                f'{name} needs {lacking[name]}' for name in choice.names if name in lacking
            )
        )
    regional = None if orientation_xyzw is None else regional_columns(orientation_xyzw, geometry)
    # Named effects are all kept (their tests are still reported); auto keeps what passes.
    strict = choice.automatic
    selection = select_terms(
        pairs,
        channels.b_reference[used],
        candidates,
        regional=regional,
        alpha=ALPHA if strict else np.inf,
        min_gain=MIN_GAIN if strict else -np.inf,
    )
    chosen = selection.chosen
    notes = (
        _note(choice, selection, lacking),
        *_unsolved_notes(selection, candidates),
        *redundant,
    )
    return WindowTerms(chosen, selection, lacking, found, notes)


def _independent(
    candidates: list[Candidate], lacking: dict[str, str]
) -> tuple[list[Candidate], tuple[str, ...]]:
    """The candidates without their redundant channels
    (:func:`~tetra_gradiometer.core.identification.terms.without_redundant`: a constant
    current, a battery current that is a constant plus the thrusters' it also records), and
    the notes; a candidate left without a channel goes to ``lacking`` (needs a channel that
    varies independently on the window)."""
    out, notes = [], []
    for candidate in candidates:
        reduced, why = without_redundant(candidate)
        notes += why
        if reduced is None:
            lacking[candidate.name] = (
                f'a channel that varies on the window ({", ".join(candidate.inputs)}: '
                'constant, or the sum of the others)'
            )
        else:
            out.append(reduced)
    return out, tuple(notes)


def _pairs(fields: FloatArray, geometry: TetraGeometry) -> FloatArray:
    """The pair differences ``B_i' - B_1'`` as (n, 3 axes, 3 pairs), T (eq. 7 times a)."""
    return np.swapaxes(fields[:, 1:, :] - fields[:, :1, :], 1, 2)


def _unsolved_notes(selection: Selection, candidates: list[Candidate]) -> tuple[str, ...]:
    """One note per candidate whose held-out solve failed (:attr:`Selection.unsolved`): it
    was not kept, and the note says which effect, on which channels, and why."""
    inputs = {c.name: c.inputs for c in candidates}
    return tuple(
        f'effects: {name}'
        + (f' ({", ".join(inputs[name])})' if inputs.get(name) else '')
        + f' could not be tested, its held-out solve failed ({why}): not kept'
        for name, why in selection.unsolved.items()
    )


def _note(choice: EffectsChoice, selection: Selection, lacking: dict[str, str]) -> str:
    chosen = [c.name for c in selection.chosen]
    tested = selection.evidence
    parts = [f'effects ({choice.source}): ' + (', '.join(chosen) if chosen else 'none selected')]
    for name, test in tested.items():
        parts.append(
            f'{name}: held-out {test["heldout_rms_without_nT"]:.3g} -> '
            f'{test["heldout_rms_with_nT"]:.3g} nT ({"kept" if test["kept"] else "not kept"})'
        )
    if lacking:
        parts.append('cannot fit: ' + '; '.join(f'{n} needs {w}' for n, w in lacking.items()))
    return '; '.join(parts)


@dataclass(frozen=True)
class HeldTerms:
    """What compensating without a channel does (``--allow-missing-channels``): the
    regressor columns of the absent channels held at their calibration-window mean, and the
    1-sigma that adds.

    Attributes
    ----------
    absent : the absent channels
    columns : (h,) indices of the held columns among the terms' regressors (M)
    values : (h,) their values, the window means, SI
    sigma_t_per_m : (3, 3) 1-sigma per tensor component of what the held columns' terms
        contributed over the window: ``sqrt(diag(L C L^T))`` per component, ``C`` the held
        columns' covariance on the window (per term), ``L`` their map onto the component
        (``W`` times ``a^-1``), T/m
    """

    absent: tuple[str, ...]
    columns: npt.NDArray[np.intp]
    values: FloatArray
    sigma_t_per_m: FloatArray

    def text(self) -> str:
        """One line for the summary and the CSV's comment."""
        names = ', '.join(f'{name} ({channel_topic(name)})' for name in self.absent)
        return (
            f'compensated WITHOUT {names}: absent from the bag; the terms reading it held at '
            'their calibration-window mean and the 1-sigma widened by their spread over that '
            f'window (up to {float(np.max(self.sigma_t_per_m)) * NT_PER_T:.3g} nT/m)'
        )


def held_terms(
    terms: tuple[Term, ...], absent: tuple[str, ...], geometry: TetraGeometry, where: str
) -> HeldTerms:
    """:class:`HeldTerms` of the channels ``absent`` for the calibration's ``terms``.

    Raises
    ------
    BagError
        A term that reads an absent channel has no window statistics (a calibration made
        before they were stored: calibrate again) or does not have one regressor per channel.
    """
    columns, values, variance = [], [], np.zeros((3, 3))
    start = 0
    for term in terms:
        held = [j for j, name in enumerate(term.inputs) if name in absent]
        if held and (not term.window_mean or term.size != len(term.inputs)):
            raise BagError(
                f'{where}: the calibration term {term.effect} reads {", ".join(absent)} but '
                'carries no window statistics to compensate without it (calibrate again)'
            )
        if held:
            # L[r, c, j] = sum over pairs of W[pair, r, j] a_inv[pair, c].
            gain = np.einsum('prj,pc->rcj', term.coefficients[:, :, held], geometry.a_inv)
            c = np.asarray(term.window_covariance)[np.ix_(held, held)]
            variance += np.einsum('rcj,jk,rck->rc', gain, c, gain)
            columns += [start + j for j in held]
            values += [term.window_mean[j] for j in held]
        start += term.size
    return HeldTerms(
        absent,
        np.asarray(columns, dtype=np.intp),
        np.asarray(values, dtype=float),
        np.sqrt(np.maximum(variance, 0.0)),
    )


class WindowRanges:
    """Where the terms' regressors fall against the calibration window's: a regressor beyond
    its window mean +- (4 sigma + 5 % of |mean|) on more than 1 % of the sets is extrapolated
    (another sign convention, another unit, a load the trim never saw), and :meth:`text`
    names it. Recorded channels with window statistics are checked."""

    def __init__(self, terms: tuple[Term, ...]) -> None:
        self.names: list[str] = []
        means, sigmas = [], []
        recorded = terms_channels(terms)
        for term in terms:
            for j in range(term.size):
                label = term.inputs[j] if len(term.inputs) == term.size else ''
                # Recorded channels only: a computed regressor (the eddy rate) is not a
                # convention or a unit that can change.
                have = bool(term.window_mean and term.window_covariance) and label in recorded
                self.names.append(f'{term.effect} ({channel_topic(label)})' if have else '')
                means.append(term.window_mean[j] if have else np.nan)
                sigmas.append(np.sqrt(term.window_covariance[j][j]) if have else np.nan)
        self.mean, sigma = np.array(means), np.array(sigmas)
        self.bound = 4.0 * sigma + 0.05 * np.abs(self.mean)
        self.outside = np.zeros(len(means), dtype=int)
        self.outside_sum = np.zeros(len(means))
        self.low, self.high = np.full(len(means), np.inf), np.full(len(means), -np.inf)
        self.sets = 0

    def add(self, regressors: FloatArray) -> None:
        """A chunk's regressors (n, M), NaN where unknown."""
        x = regressors[np.all(np.isfinite(regressors), axis=1)]
        if not len(x):
            return
        self.sets += len(x)
        beyond = np.abs(x - self.mean) > self.bound
        self.outside += np.sum(beyond, axis=0)
        self.outside_sum += np.sum(np.where(beyond, x, 0.0), axis=0)
        self.low = np.minimum(self.low, x.min(axis=0))
        self.high = np.maximum(self.high, x.max(axis=0))

    def text(self) -> str:
        """'' or the extrapolated regressors, each with its range against the window's."""
        parts = []
        for j in np.flatnonzero(self.outside > 0.01 * max(self.sets, 1)):
            mean, bound = self.mean[j], self.bound[j]
            middle = self.outside_sum[j] / self.outside[j]  # the mean of the values beyond
            hint = ''
            if abs(-middle - mean) <= bound:
                hint = ': another sign convention than at the calibration?'
            elif any(abs(middle * f - mean) <= bound for f in (1e-3, 1e3)):
                hint = ': another unit than at the calibration?'
            parts.append(
                f'{self.names[j]} regressor {self.low[j]:.4g} to {self.high[j]:.4g} on '
                f'{self.outside[j] / self.sets:.0%} of the sets, beyond the calibration '
                f"window's {mean - bound:.4g} to {mean + bound:.4g}{hint}"
            )
        return ('extrapolated beyond the calibration: ' + '; '.join(parts)) if parts else ''


class StreamRegressors:
    """The terms' regressors over a bag's sets chunk by chunk (compensation), equal to
    :func:`~tetra_gradiometer.core.effects.term_regressors` on the whole run: an eddy term's
    rate takes the end of the previous chunk as its history. Counts the sets each channel
    left unknown (stale, or the first set's rate) and their time spans.

    With ``geometry`` given (``--allow-missing-channels``), a channel the bag lacks
    altogether is not refused: its columns are held (:attr:`held`, :func:`held_terms`).

    Raises
    ------
    BagError
        (At construction) a channel the terms read is not in the bag at all (without
        ``geometry``), or cannot be held.
    """

    def __init__(
        self,
        terms: tuple[Term, ...],
        bag: MagneticBag,
        bag_path: str | os.PathLike[str],
        geometry: TetraGeometry | None = None,
    ) -> None:
        self.terms = terms
        names = terms_channels(terms)
        self.series = read_channels(bag, names)
        missing = tuple(name for name in names if name not in self.series)
        self.held: HeldTerms | None = None
        if missing and geometry is not None:
            self.held = held_terms(terms, missing, geometry, str(bag_path))
        elif missing:
            raise BagError(
                f'{bag_path}: the calibration has terms that read '
                + ', '.join(f'{name} ({channel_topic(name)})' for name in missing)
                + ', which the bag lacks: a channel is never taken as zero (record it, '
                'calibrate with --effects none, or compensate with --allow-missing-channels)'
            )
        self.history_s = max(
            (effect(term.effect).history_s(term.reference) for term in terms), default=0.0
        )
        self._tail: tuple[IntArray, FloatArray] | None = None
        self.origin_ns: int | None = None
        self.unknown: dict[str, int] = {}
        self.spans: dict[str, list[tuple[float, float]]] = {}
        self.ranges = WindowRanges(terms)

    def __call__(self, stamps_ns: IntArray, fields: FloatArray) -> FloatArray:
        """Regressors (n, M) of the chunk's sets, NaN where a channel is unknown."""
        if self.origin_ns is None:
            self.origin_ns = int(stamps_ns[0])
        prefix = 0
        if self._tail is not None:
            tail_stamps, tail_b = self._tail
            prefix = len(tail_stamps)
            stamps_all = np.concatenate([tail_stamps, stamps_ns])
            b_all = np.concatenate([tail_b, fields[:, 0, :]])
        else:
            stamps_all, b_all = stamps_ns, fields[:, 0, :]
        on_sets = {name: s.on(stamps_all) for name, s in self.series.items()}
        t_s = (stamps_all - self.origin_ns) * S_PER_NS
        absent = () if self.held is None else self.held.absent
        every = {**on_sets, **{name: np.full(len(t_s), np.nan) for name in absent}}
        regressors = term_regressors(self.terms, Channels(t_s, b_all, every))[prefix:]
        if self.held is not None:
            regressors[:, self.held.columns] = self.held.values
        # the eddy window's history, and the intervals that judge a loss (core.effects.losses)
        keep = (stamps_all[-1] - stamps_all) * S_PER_NS < self.history_s + 1e-9
        keep[-(USUAL_INTERVALS + 1) :] = True
        self._tail = (stamps_all[keep], b_all[keep])
        self._count(stamps_ns, {name: v[prefix:] for name, v in on_sets.items()}, regressors)
        self.ranges.add(regressors)
        return regressors

    def _count(
        self, stamps_ns: IntArray, on_sets: dict[str, FloatArray], regressors: FloatArray
    ) -> None:
        unknown_any = ~np.all(np.isfinite(regressors), axis=1)
        flags = {name: ~np.isfinite(values) for name, values in on_sets.items()}
        channel_any = np.zeros(len(stamps_ns), dtype=bool)
        for flag in flags.values():
            channel_any |= flag
        flags[REFERENCE_RATE] = unknown_any & ~channel_any  # no rate yet (first set, a gap)
        for name, flag in flags.items():
            if np.any(flag):
                self.unknown[name] = self.unknown.get(name, 0) + int(np.sum(flag))
                self.spans.setdefault(name, []).extend(
                    runs(stamps_ns, flag, self.origin_ns or int(stamps_ns[0]))
                )

    def text(self) -> str:
        """One line on the sets dropped for an unknown channel ('' when none)."""
        if not self.unknown:
            return ''
        parts = [
            f'{count} without {name} ({spans_text(self.spans.get(name, []))})'
            for name, count in self.unknown.items()
        ]
        return 'sets dropped for a channel the terms read: ' + '; '.join(parts)
