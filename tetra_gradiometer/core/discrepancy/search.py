"""The candidate search and its criterion: round by round, re-check the named units, then
add the unit (and its family in other sensors) that passes CV-BIC, the held-out F-test and
the relevance threshold, until none does.

Each round's state is rebuilt from the previous one; the result is a frozen
:class:`SearchResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..effects import SIGNAL_PREFIX
from ..identification._selection import held_out_f_test
from .candidate import Candidate
from .cv import ALL_SENSORS, Fit, Gram, block_length, flat, noise_floor
from .discovery import open_world_move
from .fit import (
    CurrentFit,
    Family,
    build,
    current_design,
    fit_current,
    reference_in_pairs,
    restrict,
)
from .prepare import Prepared
from .result import Settings, Step, sensor_name

Array = NDArray[np.float64]
Index = NDArray[np.int_]

#: A candidate that, in a named unit's place, explains at least this share of the held-out
#: sum of squares the unit explains is confounded with it.
CONFOUNDED_SHARE = 0.8


@dataclass(frozen=True)
class SearchResult:
    """What the search found.

    Attributes
    ----------
    prep : the prepared data with ``B^b`` as the last fit left it
    active : the named units; ``step_units[i]`` are the indices of step ``i``'s units
    steps : one per named family (parameters still empty: the report fills them)
    fit : the last fit of the current model (the final joint fit)
    rounds : each round's gap, floor, model and candidate table
    residuals, gaps, floors : per round (base model first), nT
    notes : the revisions made on the way
    block_s : cross-validation block length, s
    confounded : per named unit, the candidates that explain the same part of the residual
        in its place, with the share of the unit's held-out explained sum of squares they
        explain (at least :data:`CONFOUNDED_SHARE`)
    """

    prep: Prepared
    active: tuple[Family, ...]
    steps: tuple[Step, ...]
    step_units: tuple[tuple[int, ...], ...]
    fit: CurrentFit
    rounds: list[dict[str, Any]]
    residuals: list[Array]
    gaps: list[float]
    floors: list[float]
    notes: list[str]
    block_s: float
    confounded: list[list[tuple[str, float]]]


@dataclass(frozen=True)
class _Candidates:
    """A round's candidate units (``plain``: in the pair view, sensor 1's units as they
    replace a named one, by their index in ``units``)."""

    units: list[Family]
    plain: dict[int, Family] = field(default_factory=dict)


@dataclass(frozen=True)
class _Round:
    """A round's Gram matrices and where each unit's columns and offsets sit in them, with
    the selection criterion."""

    gram: Gram
    ty: int
    base_idx: Index
    sel_idx: Index
    unit_cols: list[Index]
    unit_off: list[list[int]]
    swap_index: dict[int, int]
    active_cols: list[Index]
    active_off: list[list[int]]
    absolute: bool
    channels: int
    floor: float
    settings: Settings

    def without(self, k: int) -> tuple[Index, Fit]:
        """The current model less named unit ``k``: its columns and its fit."""
        rest = np.concatenate(
            [self.base_idx] + [c for j, c in enumerate(self.active_cols) if j != k]
        )
        return rest, self.gram.evaluate(rest, self.ty, add_back=self.active_off[k])

    def swapped(self, rest: Index, j: int, k: int) -> Fit:
        """The fit with candidate unit ``j`` in the place of named unit ``k`` (``rest``:
        :meth:`without`'s columns)."""
        jj = self.swap_index.get(j, j)
        return self.gram.evaluate(
            np.concatenate([rest, self.unit_cols[jj]]),
            self.ty,
            self.unit_off[jj],
            add_back=self.active_off[k],
        )

    def bic(self, res: Fit) -> float:
        """Cross-validated BIC, ``n ln(SS_cv/n) + p ln n``."""
        n_obs = self.gram.n
        return float(n_obs * np.log(res.cv / n_obs) + res.rank * np.log(n_obs))

    def compare(self, res: Fit, ref: Fit, sensor: int) -> dict[str, Any]:
        """``res`` (the model with a unit of ``sensor`` added) against ``ref``: the
        selection criterion. The explained RMS is over the unit's own sensor (3 channels;
        a common term, or sensor 1 in the pair view, over all channels)."""
        n_obs = self.gram.n
        dp = res.rank - ref.rank
        gain = ref.cv - res.cv
        fstat, pval = held_out_f_test(ref.cv, res.cv, dp, max(n_obs - res.rank, 1.0))
        own = 3 if (sensor >= 1 or (sensor == 0 and self.absolute)) else self.channels
        explained = float(np.sqrt(max(gain, 0.0) / (n_obs / self.channels * own)))
        dbic = self.bic(res) - self.bic(ref)
        s = self.settings
        return {
            'n_parameters': int(dp),
            'gap_after_nT': float(np.sqrt(res.cv / n_obs)),
            'delta_bic': float(dbic),
            'f_statistic': float(fstat),
            'p_value': pval,
            'explained_rms_nT': explained,
            'result': res,
            'passes': bool(dbic < 0 and pval < s.alpha and explained >= s.relevance * self.floor),
        }


def search_effects(
    prep: Prepared, testable: tuple[Candidate, ...], settings: Settings
) -> SearchResult:
    """Add the missing effects one family at a time (see the package docstring)."""
    block_s = block_length(prep.t, settings.block_s)
    y = prep.fields - prep.base_offset
    active: tuple[Family, ...] = ()
    steps: list[Step] = []
    step_units: list[list[int]] = []
    rounds: list[dict[str, Any]] = []
    residuals: list[Array] = []
    gaps: list[float] = []
    floors: list[float] = []
    notes: list[str] = []
    scanned = False
    while True:
        fit = fit_current(prep, active, y, settings.knot_s)
        prep, active = fit.prep, fit.active
        residual = prep.fields - fit.prediction
        if not prep.absolute:
            residual = residual - residual[:, :1]  # pair view: B_i' - B_1' against the model
        floor, _ = noise_floor(flat(residual, prep.sensors))
        pool = _pool(testable, steps, settings)
        more = bool(pool)
        cands = _candidates(prep, fit, pool, y) if more else _Candidates([])
        rnd = _round(prep, fit, cands, y, floor, block_s, settings)
        cur = rnd.gram.evaluate(rnd.sel_idx, rnd.ty)
        gap_cur = float(np.sqrt(cur.cv / rnd.gram.n))
        revised = _backward_check(rnd, cur, active, cands)
        if revised is not None and len(notes) < 4 * settings.max_effects:
            notes.append(revised[2])
            # What a revision brings in enters after the last recorded round.
            steps, step_units, active = _revise(
                steps, step_units, active, *revised[:3], gap_before=gaps[-1], gap_after=revised[3]
            )
            continue
        chosen, after, table = _forward_step(rnd, cur, cands.units)
        if not chosen:
            # Nothing in the library explains the rest: the open world (once per state).
            moved = open_world_move(
                prep, residual, fit, active, testable, settings, floor, scan=more and not scanned
            )
            scanned = scanned or more
            if moved is not None:
                prep, active = moved
                continue
        gaps.append(gap_cur)
        floors.append(floor)
        residuals.append(residual)
        rounds.append(_round_record(gap_cur, floor, active, table))
        if not chosen:
            confounded = _confounding(rnd, cur, active, cands)
            break
        scanned = False
        units = [cands.units[k] for k in chosen]
        steps.append(_step(units, chosen, rnd, gap_cur, after, floor, table))
        step_units.append(list(range(len(active), len(active) + len(chosen))))
        active = active + tuple(units)
        steps, step_units = _merge_steps(steps, step_units)
    return SearchResult(
        prep,
        active,
        tuple(steps),
        tuple(tuple(m) for m in step_units),
        fit,
        rounds,
        residuals,
        gaps,
        floors,
        notes,
        block_s,
        confounded,
    )


#: The recorded signals the search may name beside ``Settings.max_effects`` library effects.
MAX_SIGNAL_EFFECTS = 16


def _pool(
    testable: tuple[Candidate, ...], steps: list[Step], settings: Settings
) -> tuple[Candidate, ...]:
    """The candidates still offered: the library's until ``max_effects`` of its effects are
    named, the recorded signals' until :data:`MAX_SIGNAL_EFFECTS` of theirs are."""
    signal = [s.effect.startswith(SIGNAL_PREFIX) for s in steps]
    room = {
        True: sum(signal) < MAX_SIGNAL_EFFECTS,
        False: len(signal) - sum(signal) < settings.max_effects,
    }
    return tuple(c for c in testable if room[c.name.startswith(SIGNAL_PREFIX)])


def _candidates(
    prep: Prepared, fit: CurrentFit, testable: tuple[Candidate, ...], y: Array
) -> _Candidates:
    """Every unit (family x sensor) not yet in the model, built on the current fit."""
    taken = {(f.candidate.name, f.sensor) for f in fit.active}
    cur_sensor = np.concatenate(
        [np.full(prep.base_cols.shape[-1], -2)]
        + [np.full(f.cols.shape[-1], f.sensor) for f in fit.active]
    )
    units: list[Family] = []
    plain: dict[int, Family] = {}
    design = current_design(prep.sensors, fit.cols, cur_sensor, y - fit.offset)
    for c in testable:
        if all((c.name, s) in taken for s in ALL_SENSORS + (-1,)):
            continue
        family = build(c, fit.ctx, prep.sensors, design)
        for s in sorted({lab[0] for lab in family.labels}):
            if (c.name, s) not in taken:
                unit = restrict(family, s)
                if s == 0 and not prep.absolute:
                    plain[len(units)] = unit
                    unit = reference_in_pairs(unit, fit.k_hat)
                units.append(unit)
    return _Candidates(units, plain)


def _offsets(
    families: list[Family] | tuple[Family, ...],
    sensors: tuple[int, ...],
    extra: list[Array],
    ty: int,
) -> list[list[int]]:
    """Where each family's offset sits in Z (appended to ``extra``; [] when it has none)."""
    out: list[list[int]] = []
    for f in families:
        if f.offset is not None and np.any(f.offset):
            out.append([ty + len(extra)])
            extra.append(flat(f.offset, sensors)[..., None])
        else:
            out.append([])
    return out


def _column_ranges(usable: NDArray[np.bool_], start: int, widths: list[int]) -> list[Index]:
    """The usable column indices of consecutive blocks of ``widths`` columns from ``start``."""
    out = []
    for p in widths:
        out.append(start + np.flatnonzero(usable[start : start + p]))
        start += p
    return out


def _round(
    prep: Prepared,
    fit: CurrentFit,
    cands: _Candidates,
    y: Array,
    floor: float,
    block_s: float,
    settings: Settings,
) -> _Round:
    """Z = [current columns | unit columns | plain units | target | unit offsets | active
    offsets], its per-fold Gram matrices and the index of each part."""
    units = cands.units + list(cands.plain.values())
    extra = [flat(y - fit.offset, prep.sensors)[..., None]]
    ty = fit.cols.shape[-1] + sum(u.cols.shape[-1] for u in units)
    n_cur = fit.cols.shape[-1]
    unit_off = _offsets(units, prep.sensors, extra, ty)
    active_off = _offsets(fit.active, prep.sensors, extra, ty)  # added back when taken out
    # Z filled in place: a long record's columns are 100s of MB.
    z = np.empty((len(prep.t), 3 * len(prep.sensors), ty + len(extra)))
    start = 0
    for block in [fit.cols] + [u.cols for u in units] + extra:
        part = flat(block, prep.sensors) if block.ndim == 4 else block
        z[..., start : start + part.shape[-1]] = part
        start += part.shape[-1]
    gram = Gram(z, prep.t, block_s, settings.n_folds, n_regressors=ty)
    usable = gram.usable
    unit_cols = _column_ranges(usable, n_cur, [u.cols.shape[-1] for u in units])
    base_p = prep.base_cols.shape[-1]
    active_cols = _column_ranges(usable, base_p, [f.cols.shape[-1] for f in fit.active])
    return _Round(
        gram=gram,
        ty=ty,
        base_idx=np.flatnonzero(usable[:base_p]),
        sel_idx=np.flatnonzero(usable[:n_cur]),
        unit_cols=unit_cols,
        unit_off=unit_off,
        # Where the swap test finds each unit's columns (the plain version when there is one).
        swap_index={k: len(cands.units) + i for i, k in enumerate(cands.plain)},
        active_cols=active_cols,
        active_off=active_off,
        absolute=prep.absolute,
        channels=3 * len(prep.sensors),
        floor=floor,
        settings=settings,
    )


def _backward_check(
    rnd: _Round, cur: Fit, active: tuple[Family, ...], cands: _Candidates
) -> tuple[int, Family | None, str, float] | None:
    """Is every unit in the model still needed, and does a unit with fewer parameters in the
    same sensor explain as much now that the others are in? The first unit that fails:
    (its index, its replacement or None to remove it, why, the held-out gap of the revised
    model, nT)."""
    for k, f in enumerate(active):
        rest, without = rnd.without(k)
        if not rnd.compare(cur, without, f.sensor)['passes']:
            return (
                k,
                None,
                f'{f.candidate.name} at sensor {f.sensor + 1} is no longer needed '
                f'once the other effects are in (removed)',
                float(np.sqrt(without.cv / rnd.gram.n)),
            )
        best_alt = _best_replacement(rnd, cur, k, f, rest, cands.units)
        if best_alt is not None:
            j, swapped = best_alt
            u = cands.plain.get(j, cands.units[j])
            return (
                k,
                u,
                f'{f.candidate.name} at sensor {f.sensor + 1} replaced by the more '
                f'parsimonious {u.candidate.name} (CV-BIC {rnd.bic(swapped) - rnd.bic(cur):+.4g}) '
                'once the other effects are in',
                float(np.sqrt(swapped.cv / rnd.gram.n)),
            )
    return None


def _best_replacement(
    rnd: _Round, cur: Fit, k: int, f: Family, rest: Index, units: list[Family]
) -> tuple[int, Fit] | None:
    """The unit of another family in ``f``'s sensor, with no more parameters, whose CV-BIC
    in place of ``f`` is lowest and below the current model's: (its index, that fit)."""
    best_alt = None
    for j, u in enumerate(units):
        if (
            u.sensor != f.sensor
            or u.candidate.name == f.candidate.name
            or len(rnd.unit_cols[j]) > len(rnd.active_cols[k])
        ):
            continue  # only a unit with no more parameters may replace one
        res = rnd.swapped(rest, j, k)
        if rnd.bic(res) < rnd.bic(cur) and (
            best_alt is None or rnd.bic(res) < rnd.bic(best_alt[1])
        ):
            best_alt = (j, res)
    return best_alt


def _forward_step(
    rnd: _Round, cur: Fit, units: list[Family]
) -> tuple[list[int], Fit, list[dict[str, Any]]]:
    """The unit that passes with the lowest CV-BIC, then its family in the other sensors
    that pass: the chosen unit indices, the fit with them, and the first candidate table."""
    chosen: list[int] = []
    first_table: list[dict[str, Any]] | None = None
    sel_idx = rnd.sel_idx
    sel_off: list[int] = []
    while True:
        table = []
        for k, u in enumerate(units):
            if k in chosen or (chosen and u.candidate.name != units[chosen[0]].candidate.name):
                continue  # after the first unit, the step extends its family to other sensors
            res = rnd.gram.evaluate(
                np.concatenate([sel_idx, rnd.unit_cols[k]]), rnd.ty, sel_off + rnd.unit_off[k]
            )
            row = rnd.compare(res, cur, u.sensor)
            row.update(
                {
                    'effect': u.candidate.name,
                    'unit': k,
                    'sensor': 'all' if u.sensor < 0 else u.sensor + 1,
                }
            )
            table.append(row)
        table.sort(key=lambda row: row['delta_bic'])
        if first_table is None:
            first_table = table
        winners = [row for row in table if row['passes']]
        if not winners:
            return chosen, cur, first_table
        best = winners[0]
        chosen.append(best['unit'])
        sel_idx = np.concatenate([sel_idx, rnd.unit_cols[best['unit']]])
        sel_off = sel_off + rnd.unit_off[best['unit']]
        cur = best['result']


def _round_record(
    gap: float, floor: float, active: tuple[Family, ...], table: list[dict[str, Any]]
) -> dict[str, Any]:
    return {
        'gap_nT': gap,
        'noise_floor_nT': floor,
        'model': [f'{f.candidate.name}@{sensor_name(f.sensor)}' for f in active],
        'candidates': [
            {k: v for k, v in row.items() if k not in ('unit', 'result')} for row in table
        ],
    }


def _step(
    units: list[Family],
    chosen: list[int],
    rnd: _Round,
    gap_cur: float,
    after: Fit,
    floor: float,
    table: list[dict[str, Any]],
) -> Step:
    """The step that adds ``units`` (one family), with the evidence that named it."""
    name = units[0].candidate.name
    gap_after = float(np.sqrt(after.cv / rnd.gram.n))
    sensors_added = ['all' if u.sensor < 0 else u.sensor + 1 for u in units]
    first = [row for row in table if row['unit'] == chosen[0]][0]
    rivals = [row for row in table if row['effect'] != name]
    evidence = (
        f'added for sensor(s) {", ".join(map(str, sensors_added))}: held-out gap '
        f'{gap_cur:.3g} -> {gap_after:.3g} nT (noise floor {floor:.3g} nT); first unit '
        f'(sensor {first["sensor"]}): {first["n_parameters"]} parameters explain '
        f'{first["explained_rms_nT"]:.3g} nT RMS of the held-out residual, CV-BIC '
        f'{first["delta_bic"]:+.4g}, held-out F = {first["f_statistic"]:.4g} '
        f'(p = {first["p_value"]:.3g})'
    )
    if rivals:
        r = rivals[0]
        evidence += (
            f'; best other family: {r["effect"]} at sensor {r["sensor"]} with '
            f'{r["n_parameters"]} parameters, gap {r["gap_after_nT"]:.3g} nT, CV-BIC '
            f'{r["delta_bic"]:+.4g}'
        )
    n_params = sum(len(rnd.unit_cols[k]) for k in chosen)
    return Step(
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


def _revise(
    steps: list[Step],
    step_units: list[list[int]],
    active: tuple[Family, ...],
    k: int,
    replacement: Family | None,
    message: str,
    gap_after: float,
    gap_before: float,
) -> tuple[list[Step], list[list[int]], tuple[Family, ...]]:
    """Take unit ``k`` out of the model (and its step), or replace it by a unit of another
    family, which joins that family's step. A family the replacement brings in gets a step at
    the end (the old step itself, renamed, when the unit was its last), with the gaps of the
    model just before and after it entered: ``gap_before`` (the last recorded round's) and
    ``gap_after`` (the revised model's). A step left empty is dropped. Returns new steps,
    step units and units."""
    steps = list(steps)
    step_units = [list(members) for members in step_units]
    units = list(active)
    owner = next(i for i, members in enumerate(step_units) if k in members)
    steps[owner] = replace(
        steps[owner], evidence=steps[owner].evidence + f'; revised later: {message}'
    )
    step_units[owner].remove(k)
    if replacement is None:
        del units[k]
        step_units = [[m - 1 if m > k else m for m in members] for members in step_units]
    else:
        units[k] = replacement
        name = replacement.candidate.name
        target = next((j for j, st in enumerate(steps) if st.effect == name), None)
        if target is not None:
            step_units[target].append(k)
        else:
            entered = (
                steps[owner]
                if not step_units[owner]
                else Step(
                    name,
                    0.0,
                    0.0,
                    {},
                    f'named when revising: {message}',
                    replacement.cols.shape[-1],
                    0.0,
                    0.0,
                    1.0,
                )
            )
            steps.append(
                replace(entered, effect=name, gap_before_nT=gap_before, gap_after_nT=gap_after)
            )
            step_units.append([k])
    kept = [i for i, members in enumerate(step_units) if members]
    return [steps[i] for i in kept], [step_units[i] for i in kept], tuple(units)


def _merge_steps(
    steps: list[Step], step_units: list[list[int]]
) -> tuple[list[Step], list[list[int]]]:
    """One step per family: a later step of a family already named is merged into the earlier
    one (its units and parameters; the gaps of the earlier step stay those it was named with,
    unless the two steps were consecutive). Returns new lists."""
    steps = list(steps)
    step_units = [list(members) for members in step_units]
    i = 0
    while i < len(steps):
        j = next((j for j in range(i + 1, len(steps)) if steps[j].effect == steps[i].effect), None)
        if j is None:
            i += 1
            continue
        step_units[i] += step_units[j]
        steps[i] = replace(
            steps[i],
            gap_after_nT=steps[j].gap_after_nT if j == i + 1 else steps[i].gap_after_nT,
            n_parameters=steps[i].n_parameters + steps[j].n_parameters,
            evidence=steps[i].evidence
            + f'; merged with a later step of the same family: {steps[j].evidence}',
        )
        del steps[j], step_units[j]
    return steps, step_units


def _confounding(
    rnd: _Round, cur: Fit, active: tuple[Family, ...], cands: _Candidates
) -> list[list[tuple[str, float]]]:
    """Per named unit, the units of other families in its sensor that explain at least
    :data:`CONFOUNDED_SHARE` of what it explains (held out) when put in its place."""
    out: list[list[tuple[str, float]]] = []
    for k, f in enumerate(active):
        rest, without = rnd.without(k)
        explained = without.cv - cur.cv
        found: dict[str, float] = {}
        for j, u in enumerate(cands.units):
            if explained <= 0 or u.sensor != f.sensor or u.candidate.name == f.candidate.name:
                continue
            share = float((without.cv - rnd.swapped(rest, j, k).cv) / explained)
            if share >= CONFOUNDED_SHARE:
                found[u.candidate.name] = max(share, found.get(u.candidate.name, 0.0))
        out.append(sorted(found.items(), key=lambda item: -item[1]))
    return out
