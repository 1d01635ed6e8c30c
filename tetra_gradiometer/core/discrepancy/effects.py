"""The search's candidates: every effect of the one registry, then the detectors.

The registry's effects (:data:`tetra_gradiometer.core.effects.EFFECTS`: the built-in ones
and the installed packages' entry points) and the recorded signals' effects
(:class:`~tetra_gradiometer.core.effects.RecordedSignal`) enter through the
:class:`~tetra_gradiometer.core.effects.Effect` protocol alone (:func:`effect_candidate`):
the channels it reads (:meth:`~.Effect.inputs`), its regressors and their labels, its
physics, what separates it from look-alikes, and its simulator spec for synthetic missions.
Each regressor becomes a column per sensor of the view and axis, its coefficient in the
effect's file unit. The search estimates the reference reading's rate (the eddy term's
regressor, :data:`~tetra_gradiometer.core.effects.REFERENCE_RATE`) on the whole run from
the view's ``B^b`` (smoothed, non-causal: the search has the run, the live path does not).

What only the search tests, the model errors the operational model does not carry, are the
detectors of :mod:`.detectors`. Adding an effect to the registry adds it here.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial

import numpy as np

from ..effects import (
    CURRENT_PREFIX,
    EFFECTS,
    REFERENCE_RATE,
    TEMPERATURE,
    Channels,
    Effect,
    RecordedSignal,
    current_channel,
    parse_declaration,
)
from ..effects.recorded_signal import basis_for
from ..effects.simulation import EffectSpec
from ..units import NT_PER_T, T_PER_NT
from .candidate import (
    Array,
    Built,
    Candidate,
    Context,
    Estimate,
    Hidden,
    Simulated,
    empty,
    registry_columns,
    required,
)
from .detectors import DETECTORS, OPEN_WORLD
from .prepare import Prepared

__all__ = [
    'CANDIDATES',
    'LIBRARY',
    'OPEN_WORLD',
    'effect_candidate',
    'recorded_series',
    'signal_candidates',
    'testable',
]


def recorded_series(run: Context | Prepared) -> dict[str, Array]:
    """The channels a run records (its :class:`Context` or :class:`Prepared`), as the
    registry names them: ``temperature`` degC, ``current:TOPIC`` A (the battery's first),
    ``signal:TOPIC#FIELD``."""
    series: dict[str, Array] = {}
    if run.temperature_c is not None:
        series[TEMPERATURE] = run.temperature_c
    if run.current_a is not None:
        series[current_channel('/battery_state')] = run.current_a
    series.update((current_channel(topic), values) for topic, values in run.extra_currents)
    series.update(dict(run.signals))
    return series


def _build(effect: Effect, ctx: Context, estimate: Estimate | None) -> Built:
    """The effect's regressors per sensor of the view and axis (coefficients in its file
    unit), with an offset per axis at sensor 1 in the absolute view when the regressor's
    zero is arbitrary (sensor 1 has no hard iron there to take the constant)."""
    channels = Channels(ctx.t, ctx.b_background * T_PER_NT, recorded_series(ctx))
    inputs = effect.inputs((*channels.series, REFERENCE_RATE))
    if not inputs:
        required(None, effect.missing(tuple(channels.series)))
    if inputs == (REFERENCE_RATE,):
        x = ctx.b_rate * T_PER_NT  # the whole run's estimate of the reference's rate, T/s
    else:
        x = effect.regressors(channels, inputs, effect.reference(channels, inputs))
    labels = effect.labels(inputs)
    unit = effect.file_unit
    cols, _, names = registry_columns(
        ctx,
        np.asarray(x, float) * (NT_PER_T / effect.file_factor),
        lambda a, j: f'{"xyz"[a]}[{labels[j]}]_{unit}',
    )
    if not effect.arbitrary_zero or 0 not in ctx.sensors:
        return cols, None, names
    offsets = empty(len(ctx.t), 3)
    for a in range(3):
        offsets[:, 0, a, a] = 1.0
        names.append((0, f'offset_{"xyz"[a]}_nT'))
    return np.concatenate([cols, offsets], axis=-1), None, names


#: The end of a registry effect's physics text that describes the operational path's
#: estimate of its regressor, not the search's (see the module).
_OPERATIONAL_ONLY = "; the rate is B_1''s, differentiated causally."


def _requires(effect: Effect) -> tuple[str, ...]:
    """The recorded kinds of input the effect reads ('temperature', 'current')."""
    reads = effect.inputs((TEMPERATURE, current_channel('/battery_state')))
    return tuple(
        kind
        for kind, hit in (
            ('temperature', TEMPERATURE in reads),
            ('current', any(name.startswith(CURRENT_PREFIX) for name in reads)),
        )
        if hit
    )


def effect_candidate(effect: Effect, in_detector: bool = True) -> Candidate:
    """The candidate of a registry effect (``in_detector``: the target detector fits it)."""
    physics = effect.physics
    if physics.endswith(_OPERATIONAL_ONLY):
        physics = physics.removesuffix(_OPERATIONAL_ONLY) + '.'
    spec = effect.simulation
    return Candidate(
        effect.name,
        physics,
        f'per sensor, axis and regressor, {effect.file_unit}'
        + (' (plus the reference offset)' if effect.arbitrary_zero else ''),
        _requires(effect),
        partial(_build, effect),
        in_detector=in_detector,
        simulated=None if spec is None else Simulated(partial(_draw_effect, effect.name, spec)),
        separated_by=effect.separated_by,
        effect=effect,
    )


def _draw_effect(name: str, spec: EffectSpec, rng: np.random.Generator, mask: Array) -> Hidden:
    """Random coefficients of unit size of effect ``name`` in the sensors where ``mask``
    (4,) is 1 (one regressor where the scenario sets their number)."""
    shape = tuple(size for size in spec.shape if size is not None)
    return Hidden({name: rng.normal(0, 1.0, shape) * mask.reshape((4,) + (1,) * (len(shape) - 1))})


def signal_candidates(values: Mapping[str, Array]) -> tuple[Candidate, ...]:
    """A candidate per recorded signal channel (``signal:TOPIC#FIELD`` -> (N,) values), in
    the basis ``calibrate`` gives a signal it finds
    (:func:`~tetra_gradiometer.core.effects.recorded_signal.basis_for`): a family the search
    names is the declaration ``calibrate`` takes."""
    out = []
    for channel, series in values.items():
        basis = basis_for(channel, np.asarray(series, dtype=float))
        if basis is not None:
            declaration = parse_declaration(f'{channel}:{basis}', 'a recorded signal')
            out.append(effect_candidate(RecordedSignal(declaration), in_detector=False))
    return tuple(out)


#: A recorded channel that varies by less than this (its unit) is constant on the run.
CONSTANT_CHANNEL = 1e-3

#: Why a candidate that needs the attitude cannot be tested without it.
_NO_ODOM = (
    'no usable /odom: without an absolute attitude reference only the pair differences '
    "B_i' - B_1' are observable; sensor 1's own soft and hard iron is absorbed into "
    'K_i1 (I + K_1)^-1 (its small non-symmetric remainder would look like sensor_misalignment)'
)


def _untestable_reason(candidate: Candidate, prep: Prepared) -> str | None:
    """Why the run cannot test ``candidate`` (None: it can): no attitude for one that needs
    it, a channel the effect reads not recorded, or none of them varying (its field is then
    a constant offset, hard iron)."""
    if 'odom' in candidate.requires and not prep.absolute:
        return candidate.no_odom_reason or _NO_ODOM
    effect = candidate.effect
    if effect is None:
        return None
    recorded = recorded_series(prep)
    inputs = effect.inputs((*recorded, REFERENCE_RATE))
    if not inputs:
        return f'{effect.missing(tuple(recorded))} not recorded: the effect has no regressor'
    values = [recorded[name] for name in inputs if name in recorded]
    if values and all(np.ptp(v) < CONSTANT_CHANNEL for v in values):
        return (
            f'{", ".join(inputs)} does not vary (< {CONSTANT_CHANNEL:g} of its unit: 0.001 '
            'degC, 1 mA): its field is a constant offset'
        )
    return None


def testable(
    prep: Prepared, candidates: tuple[Candidate, ...]
) -> tuple[tuple[Candidate, ...], dict[str, str]]:
    """The candidates the run can test, and why each of the others cannot."""
    out: list[Candidate] = []
    untestable: dict[str, str] = {}
    for candidate in candidates:
        reason = _untestable_reason(candidate, prep)
        if reason is None:
            out.append(candidate)
        else:
            untestable[candidate.name] = reason
    return tuple(out), untestable


#: The search's candidates: the registry's effects, then the detectors.
CANDIDATES: tuple[Candidate, ...] = (
    *(effect_candidate(effect) for effect in EFFECTS.values()),
    *DETECTORS,
)

#: name -> candidate.
LIBRARY: dict[str, Candidate] = {c.name: c for c in CANDIDATES}
