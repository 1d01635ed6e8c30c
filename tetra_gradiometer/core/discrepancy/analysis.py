"""Orchestration of the discrepancy workflow (:func:`analyze`): simulate a recorded run with
the base model, measure the held-out gap against the noise floor, and add the missing
physical effects one at a time.

The stages: :mod:`.prepare` (data, residual view, base model), :mod:`.targets` (target
passages), :mod:`.search` with :mod:`.fit` and :mod:`.cv` (the effects), :mod:`.summary`
with :mod:`.diagnostics` (the report).

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
from dataclasses import replace

import numpy as np

from ...errors import InputError
from ..geometry import TetraGeometry
from .candidate import Candidate
from .dipoles import Located, Track, locate_targets, model_targets, track_of
from .effects import CANDIDATES, LIBRARY, signal_candidates, testable
from .prepare import Prepared, RunLike, prepare
from .relocation import outside_detector, relocate
from .result import Report, Settings
from .search import SearchResult, search_effects
from .summary import RunInfo, build_report
from .targets import TargetSpans, find_target_spans


def analyze(
    recording: RunLike,
    geometry: TetraGeometry | None = None,
    earth_field_enu: object = None,
    *,
    settings: Settings | None = None,
    keep_series: bool = True,
    window_s: tuple[float, float] | None = None,
) -> Report:
    """Find the effects the base model is missing in a recorded run.

    Parameters
    ----------
    recording : RecordedRun (or anything with ``t_s`` (N,) s, ``fields`` (N, 4, 3) T and
        the optional ``orientation_xyzw``, ``temperature_c``, ``current_a``, ``missing``,
        such as ``io.recording.Recording``)
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

    Raises
    ------
    InputError
        An unknown candidate, a bad window, or too few usable samples.
    """
    started = time.perf_counter()
    settings = settings or Settings()
    candidates = _candidates(settings)
    window_s = _checked_window(window_s)
    prep = prepare(recording, earth_field_enu, settings.max_samples, window_s)
    if settings.candidates is None:  # the recorded signals beside the library
        candidates += signal_candidates(dict(prep.signals))
    testable_candidates, untestable = testable(prep, candidates)
    targets, located, target_notes = TargetSpans(), None, []
    track: Track | None = None
    if settings.exclude_targets:
        names = frozenset(c.name for c in testable_candidates)
        track = track_of(prep, geometry)
        if track is not None and settings.model_targets:
            localized = locate_targets(prep, track, names, settings)
            located = localized if isinstance(localized, Located) else None
        elif settings.model_targets:
            target_notes.append(_no_track_note(prep, geometry))
        # What no dipole explains is left out, with its evidence (and the detector's levels
        # are reported).
        targets = find_target_spans(
            located.fixed() if located else prep, names, settings, modelled=located is not None
        )
        if targets.spans:
            prep = prepare(
                recording, earth_field_enu, settings.max_samples, window_s, targets.intervals
            )
            if located is not None:
                track = track_of(prep, geometry)
                prep = model_targets(prep, track, located.positions, located.moments)  # type: ignore[arg-type]
        elif located is not None:
            prep = located.prep
    search, located = _search(prep, track, located, testable_candidates, settings, target_notes)
    info = RunInfo(
        settings=settings,
        window_s=window_s,
        earth_from_params=earth_field_enu is not None,
        missing=getattr(recording, 'missing', {}) or {},
        untestable=untestable,
        targets=targets,
        notes=target_notes + _run_notes(prep, targets, window_s),
        located=located,
        track=track_of(search.prep, geometry) if located is not None else None,
    )
    report = build_report(search, info, geometry, keep_series=keep_series, runtime_s=0.0)
    return replace(report, runtime_s=float(time.perf_counter() - started))


def _search(
    prep: Prepared,
    track: Track | None,
    located: Located | None,
    testable_candidates: tuple[Candidate, ...],
    settings: Settings,
    notes: list[str],
) -> tuple[SearchResult, Located | None]:
    """The search, repeated once on targets placed again when it named what their placing
    did not have (a note in ``notes`` says so)."""
    search = search_effects(prep, testable_candidates, settings)
    if located is None or track is None:
        return search, located
    relocated = relocate(search, prep, track, located)
    if relocated is None:
        return search, located
    notes.append(
        'targets refined again with the named '
        + ', '.join(outside_detector(search))
        + ' (moved '
        + ', '.join(f'{m:.3f}' for m in relocated.moved_m)
        + ' m) and the search repeated'
    )
    return search_effects(relocated.located.prep, testable_candidates, settings), (
        relocated.located
    )


def _no_track_note(prep: Prepared, geometry: TetraGeometry | None) -> str:
    """Why the targets cannot be fitted as dipoles in this run."""
    if geometry is None:
        missing = 'the array geometry was not given'
    elif prep.rotation is None:
        missing = 'no /odom (attitude and position)'
    else:
        missing = 'no position on /odom'
    return (
        f'{missing}: targets cannot be fitted as dipoles (their field needs the track and the '
        'sensor positions); target passages are left out of the fits instead'
    )


def _candidates(settings: Settings) -> tuple[Candidate, ...]:
    """The library's candidates that ``settings`` names (all by default), in its order."""
    names = settings.candidates or tuple(c.name for c in CANDIDATES)
    unknown = [n for n in names if n not in LIBRARY]
    if unknown:
        raise InputError(f'unknown candidate effects {unknown}; the library has {sorted(LIBRARY)}')
    return tuple(LIBRARY[n] for n in names)


def _checked_window(window_s: tuple[float, float] | None) -> tuple[float, float] | None:
    if window_s is None:
        return None
    window = (float(window_s[0]), float(window_s[1]))
    if not (np.isfinite(window[0]) and window[0] >= 0 and window[1] > window[0]):
        raise InputError(f'window_s needs 0 <= T0 < T1, got {window}')
    return window


def _run_notes(
    prep: Prepared,
    targets: TargetSpans,
    window_s: tuple[float, float] | None,
) -> list[str]:
    """What the window, the data preparation and the target detector decided."""
    notes = list(prep.notes) + targets.notes
    if targets.spans:
        notes.append(targets.exclusion_note())
    if window_s is not None:
        notes.insert(
            0,
            f'analysis restricted to the window {window_s[0]:g}:{window_s[1]:g} s '
            '(seconds from the first sample)',
        )
    return notes
