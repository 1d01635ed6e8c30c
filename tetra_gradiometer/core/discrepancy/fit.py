"""The current model: the candidate families as regressor units, their Gauss-Newton
linearisation, and the joint fit of the base model plus every named unit on all samples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...errors import IdentifiabilityError
from .candidate import Candidate, Context, Estimate
from .cv import ALL_SENSORS, flat, lstsq_view, solve_fast
from .prepare import Prepared, refresh_background, refresh_pair_background, smoothed

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Family:
    """A candidate's regressors: columns (N, 4, 3, p) nT per unit, a fixed offset (N, 4, 3)
    nT or None, a ``(sensor, name)`` label per column, and the linearisation point of a
    nonlinear family. A *unit* is a family restricted to one sensor (-1: common term)."""

    candidate: Candidate
    cols: Array
    offset: Array | None
    labels: list[tuple[int, str]]
    estimate: Estimate | None = None

    @property
    def sensor(self) -> int:
        """The sensor of a unit (its first column's)."""
        return self.labels[0][0]


def soft_iron(labels: list[tuple[int, str]], coef: Array) -> Array:
    """The fitted symmetric K_i (4, 3, 3) of the base model (zero for sensor 1)."""
    k = np.zeros((4, 3, 3))
    for (s, name), value in zip(labels, coef, strict=False):
        if s >= 0 and name.startswith('K'):
            r, c = 'xyz'.index(name[1]), 'xyz'.index(name[2])
            k[s, r, c] = k[s, c, r] = value
    return k


def reference_in_pairs(unit: Family, k_hat: Array) -> Family:
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
    return Family(unit.candidate, cols, offset, unit.labels, unit.estimate)


def restrict(family: Family, sensor: int) -> Family:
    """The family's columns and offset for one sensor only."""
    idx = [k for k, (s, _) in enumerate(family.labels) if s == sensor]
    offset = None
    if family.offset is not None:
        offset = np.zeros_like(family.offset)
        offset[:, sensor] = family.offset[:, sensor]
    return Family(
        family.candidate,
        family.cols[..., idx],
        offset,
        [family.labels[k] for k in idx],
        family.estimate,
    )


def effect_field(family: Family, coef: Array) -> Array:
    """The field (N, 4, 3) nT the family adds with coefficients ``coef``."""
    field_: Array = np.einsum('nsap,p->nsa', family.cols, coef)
    return field_ + (family.offset if family.offset is not None else 0.0)


@dataclass(frozen=True)
class CurrentDesign:
    """The current model's normalised design on all samples, shared by the builds of a round.

    Attributes
    ----------
    a : (rows, p) normalised columns; norm : (p,); gram : (p, p); rhs : (p,) a^T target
    target : (rows,); sensor : (p,) sensor of each column (-2: base model)
    """

    a: Array
    norm: Array
    gram: Array
    rhs: Array
    target: Array
    sensor: NDArray[np.int_]


def current_design(
    sensors: tuple[int, ...], cur_cols: Array, cur_sensor: NDArray[np.int_], target: Array
) -> CurrentDesign:
    """:class:`CurrentDesign` of the columns ``cur_cols`` against ``target`` in the view."""
    a = flat(cur_cols, sensors)
    a = a.reshape(-1, a.shape[-1])
    norm = np.sqrt(np.einsum('rp,rp->p', a, a))
    norm[norm == 0] = 1.0
    a = a / norm
    y = flat(target, sensors).reshape(-1)
    return CurrentDesign(a, norm, a.T @ a, a.T @ y, y, cur_sensor)


def build(
    candidate: Candidate, ctx: Context, sensors: tuple[int, ...], cur: CurrentDesign
) -> Family:
    """Build a family's columns; nonlinear families are iterated at their estimate.

    The estimate for sensor ``s`` comes from the current model without its units in sensor
    ``s`` (``cur.sensor``: the sensor of each current column, -2 for the base model): a unit
    there that is nearly collinear with this family (an eddy term beside a delay) would make
    a joint estimate wild, and leaving out the other sensors' units would bias it. In the pair
    view a unit of sensor 1 enters every pair difference, so it counts as a unit there too
    (named in sensors 1, 3 and 4, an eddy term spans one in sensor 2), and for sensor 1's own
    estimate every named unit does.
    """
    cols, offset, labels = candidate.build(ctx, None)
    if not candidate.nonlinear:
        return Family(candidate, cols, offset, labels)
    p_cur = len(cur.norm)
    fam_sensor = np.array([lab[0] for lab in labels])
    pair = tuple(sensors) != ALL_SENSORS
    estimate: Estimate = {}
    for _ in range(3):
        f = flat(cols, sensors)
        f = f.reshape(-1, f.shape[-1])
        fnorm = np.sqrt(np.einsum('rq,rq->q', f, f))
        fnorm[fnorm == 0] = 1.0
        f = f / fnorm
        y = cur.target - (flat(offset, sensors).reshape(-1) if offset is not None else 0.0)
        cross = cur.a.T @ f
        gram = np.block([[cur.gram, cross], [cross.T, f.T @ f]])
        rhs = np.concatenate([cur.a.T @ y if offset is not None else cur.rhs, f.T @ y])
        coef = np.zeros(len(labels))
        for sensor in np.unique(fam_sensor):
            own = np.flatnonzero(fam_sensor == sensor)
            there = cur.sensor == sensor
            if pair:
                there |= cur.sensor >= 0 if sensor == 0 else cur.sensor == 0
            sel = np.concatenate([np.flatnonzero(~there), p_cur + own])
            theta = solve_fast(gram[np.ix_(sel, sel)], rhs[sel])
            coef[own] = theta[-len(own) :] / fnorm[own]
        estimate = {label: float(v) for label, v in zip(labels, coef, strict=True)}
        cols, offset, labels = candidate.build(ctx, estimate)
    return Family(candidate, cols, offset, labels, estimate)


@dataclass(frozen=True)
class CurrentFit:
    """The current model fitted on all samples.

    Attributes
    ----------
    prep : the prepared data with ``B^b`` refreshed by the fit
    active : the named units, rebuilt where ``B^b`` or their estimate moved
    cols : (N, 4, 3, p) base columns then every unit's; offset : (N, 4, 3) their offsets
    coef : (p,) the fitted coefficients; prediction : (N, 4, 3) nT, every sensor
    ctx : the build context (each sensor's prediction without its own named effects)
    k_hat : (4, 3, 3) the fitted K_i
    """

    prep: Prepared
    active: tuple[Family, ...]
    cols: Array
    offset: Array
    coef: Array
    prediction: Array
    ctx: Context
    k_hat: Array


def _context(prep: Prepared, basis: Array, knot_s: float) -> Context:
    return Context(
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
        knot_s,
        prep.open_world,
        prep.extra_currents,
        dict(prep.signals),
    )


def column_bounds(prep: Prepared, active: tuple[Family, ...]) -> list[int]:
    """Column bounds: unit ``k`` has columns ``bounds[k]:bounds[k + 1]`` of the design."""
    bounds = [prep.base_cols.shape[-1]]
    for f in active:
        bounds.append(bounds[-1] + f.cols.shape[-1])
    return bounds


def _relinearised(
    active: tuple[Family, ...], coef: Array, bounds: list[int], ctx: Context, moved: bool
) -> tuple[Family, ...]:
    """Nonlinear units rebuilt at their new estimate, the linear ones on the new ``B^b``
    when it moved."""
    out = list(active)
    for k, f in enumerate(active):
        estimate: Estimate | None
        if f.candidate.nonlinear:
            values = coef[bounds[k] : bounds[k + 1]]
            estimate = {label: float(v) for label, v in zip(f.labels, values, strict=True)}
        elif moved:
            estimate = None
        else:
            continue
        cols, offset, labels = f.candidate.build(ctx, estimate)
        out[k] = restrict(Family(f.candidate, cols, offset, labels, estimate), f.sensor)
    return tuple(out)


def fit_current(prep: Prepared, active: tuple[Family, ...], y: Array, knot_s: float) -> CurrentFit:
    """Fit the current model on all samples, iterating what depends on the fit: ``B^b`` (the
    Earth-field correction; linear families on ``B^b`` follow it) and the linearisation point
    of the nonlinear families (Gauss-Newton: rebuilt at their current estimate)."""
    last = None
    for _ in range(8):
        cur_off = sum((f.offset for f in active if f.offset is not None), np.zeros_like(y))
        cur_cols = np.concatenate([prep.base_cols] + [f.cols for f in active], axis=-1)
        coef = lstsq_view(prep.sensors, cur_cols, y - cur_off)
        prediction = prep.base_offset + np.einsum('nsap,p->nsa', cur_cols, coef) + cur_off
        if not np.all(np.isfinite(prediction)):
            raise IdentifiabilityError(
                'the joint fit of the named effects '
                f'({", ".join(f"{f.candidate.name}@{f.sensor + 1}" for f in active)}) diverged: '
                'the run does not fix their nonlinear parameters; leave those effects out '
                '(--candidates) or analyse another part of the run (--window)'
            )
        moved = False
        if prep.absolute:
            prep, moved = refresh_background(prep, coef[:6])
        # Candidates are built on each sensor's prediction without the effects already named
        # in that sensor (a delay of a reading that holds an eddy term would differentiate it).
        bounds = column_bounds(prep, active)
        own = np.zeros_like(y)
        for k, f in enumerate(active):
            if f.sensor >= 0:
                own += effect_field(f, coef[bounds[k] : bounds[k + 1]])
        basis = prediction - own
        if not prep.absolute:
            # B^b = B_1' carries sensor 1's noise; the derivatives and shifts the builders take
            # would amplify it (an interpolating spline's derivative by ~1.4/dt).
            basis = smoothed(prep.t, basis, prep.piece)
        ctx = _context(prep, basis, knot_s)
        if not prep.absolute:
            # Pair view: B^b = B_1' less the effects named in sensor 1 (its own delay or eddy
            # term must not magnetise the other sensors' model).
            prep, moved = refresh_pair_background(prep, prep.fields[:, 0] - own[:, 0])
        k_hat = soft_iron(prep.base_labels, coef[: prep.base_cols.shape[-1]])
        # Converged when the prediction no longer moves (a nonlinear family's offset is the
        # exact remainder of the prediction it was built on, so it must follow it).
        settled = (
            last is not None and float(np.max(np.abs(prediction - last))) < 1e-3 and not moved
        )
        last = prediction
        if settled or not any(f.candidate.nonlinear for f in active) and not moved:
            break
        active = _relinearised(active, coef, bounds, ctx, moved)
    return CurrentFit(prep, active, cur_cols, cur_off, coef, prediction, ctx, k_hat)
