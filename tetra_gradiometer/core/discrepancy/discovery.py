"""Discovery: the open-world families' scans (:mod:`.openworld`) run on the current model's
residual, and the steps a later fit shows were not needed taken out again."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from .candidate import Candidate
from .fit import CurrentFit, Family, column_bounds, restrict
from .openworld import OpenWorld, find_lines, find_steps
from .prepare import Prepared
from .result import Settings

Array = NDArray[np.float64]


def open_world_move(
    prep: Prepared,
    residual: Array,
    fit: CurrentFit,
    active: tuple[Family, ...],
    testable: tuple[Candidate, ...],
    settings: Settings,
    floor: float,
    *,
    scan: bool,
) -> tuple[Prepared, tuple[Family, ...]] | None:
    """When no library family passes: new structure in ``residual`` (N, 4, 3) nT from the
    scans (when ``scan``), offered as families; else the steps the fit no longer needs
    (below ``relevance`` x ``floor`` nT) taken out. None: nothing changes."""
    if scan:
        found = scan_residual(prep, residual, active, testable, settings.alpha)
        if found != prep.open_world:
            return replace(prep, open_world=found), active
    return pruned_steps(prep, fit, active, settings.relevance * floor)


def scan_residual(
    prep: Prepared,
    residual: Array,
    active: tuple[Family, ...],
    testable: tuple[Candidate, ...],
    alpha: float,
) -> OpenWorld:
    """``prep.open_world`` with what the scans of ``residual`` (N, 4, 3) nT add: steps in
    the sensors without a named ``hard_iron_step``, lines not found before (only for the
    open-world families among ``testable``)."""
    names = {c.name for c in testable}
    found = prep.open_world
    if 'hard_iron_step' in names:
        named = {f.sensor for f in active if f.candidate.name == 'hard_iron_step'}
        scanned = {st.sensor for st in found.steps}
        for s in prep.sensors:
            if s not in named and s not in scanned:
                steps = find_steps(prep.t, residual[:, s], alpha, s)
                found = found.with_steps(tuple(steps))
    if 'periodic_interference' in names:
        recorded = [prep.b_rate]
        channels = ['field_rate_x', 'field_rate_y', 'field_rate_z']
        for name, series in (('temperature', prep.temperature_c), ('current', prep.current_a)):
            if series is not None:
                recorded.append(series[:, None])
                channels.append(name)
        for topic, values in prep.extra_currents:
            recorded.append(values[:, None])
            channels.append(f'current[{topic}]')
        lines = find_lines(
            prep.t,
            residual[:, list(prep.sensors)],
            np.concatenate(recorded, axis=1),
            alpha,
            found.lines,
            tuple(channels),
        )
        # The scan's sensors are positions in prep.sensors (pair view: sensors 2-4).
        lines = [
            replace(line, sensors=tuple(prep.sensors[i] for i in line.sensors)) for line in lines
        ]
        found = found.with_lines(tuple(lines))
    return found


def pruned_steps(
    prep: Prepared, fit: CurrentFit, active: tuple[Family, ...], least_nT: float
) -> tuple[Prepared, tuple[Family, ...]] | None:
    """Steps of the named ``hard_iron_step`` units whose RMS contribution in the final fit
    is below ``least_nT`` (a scan on the residual of a model that was still wrong splits
    at what that model left), taken out of the scans' record and of their units; None
    when every step is needed. A unit keeps its strongest step."""
    bounds = column_bounds(prep, active)
    weak: set[tuple[int, float]] = set()
    for k, f in enumerate(active):
        if f.candidate.name != 'hard_iron_step':
            continue
        coef = fit.coef[bounds[k] : bounds[k + 1]].reshape(-1, 3)
        own = [st for st in prep.open_world.steps if st.sensor == f.sensor]
        contribution = []
        for j, step in enumerate(own):
            after = float(np.mean(prep.t >= step.t_s))
            contribution.append(float(np.linalg.norm(coef[j])) * np.sqrt(after * (1 - after) / 3))
        strongest = int(np.argmax(contribution))  # the unit was named for it: it stays
        weak |= {
            (st.sensor, st.t_s)
            for j, st in enumerate(own)
            if contribution[j] < least_nT and j != strongest
        }
    if not weak:
        return None
    kept = tuple(st for st in prep.open_world.steps if (st.sensor, st.t_s) not in weak)
    prep = replace(prep, open_world=OpenWorld(kept, prep.open_world.lines))
    ctx = replace(fit.ctx, open_world=prep.open_world)
    units = []
    for f in active:
        if f.candidate.name == 'hard_iron_step':
            cols, offset, labels = f.candidate.build(ctx, None)
            f = restrict(Family(f.candidate, cols, offset, labels), f.sensor)
        units.append(f)
    return prep, tuple(units)
