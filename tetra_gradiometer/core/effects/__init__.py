"""Vehicle effects beyond the paper's soft and hard iron: the one registry.

Each effect is one module here (:mod:`.vehicle_current`, :mod:`.eddy_current`,
:mod:`.thermal_drift`) owning its physics, the channels it reads, its regressors offline
and live, and its file form (:mod:`.base` says what an effect is). :data:`EFFECTS` is the
registry that calibration (selection and the joint fit), compensation (offline and in the
compensator node), the calibration file, the simulator and the discrepancy search read.
Adding an effect is one of:

* for a signal the vehicle records, one line in the params file's ``vehicle_signals``
  (:mod:`.recorded_signal`: :func:`effect` makes the effect of a ``signal:`` name);
* for what a declaration cannot express, one module in any installed package, named by an
  entry point of the group :data:`ENTRY_POINT_GROUP` (``name = module:EffectClass``): an
  :class:`Effect` subclass setting ``name`` (the entry point's), ``physics``, ``file_unit``,
  ``file_factor``, ``channels`` (the recorded channels it reads), optionally
  ``separated_by``, and implementing ``labels`` and ``regressors`` (``live`` defaults to
  ``regressors`` on each sample);
* here, one module and one line in :data:`EFFECTS`.

Model: ``D = (k B_1' + b + sum_terms W x(t)) a^-1`` (the pair differences' interference
times eq. 7's ``a^-1``): :func:`pair_interference` is the terms' part.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ...errors import InputError
from ..types import FloatArray
from .base import (
    CURRENT_PREFIX,
    TEMPERATURE,
    Channels,
    Effect,
    LiveRegressor,
    Term,
    current_channel,
)
from .eddy_current import REFERENCE_RATE, EddyCurrent, causal_rate
from .recorded_signal import SIGNAL_PREFIX, Declaration, RecordedSignal, parse_declaration
from .thermal_drift import ThermalDrift
from .vehicle_current import VehicleCurrent

__all__ = [
    'CURRENT_PREFIX',
    'EFFECTS',
    'ENTRY_POINT_GROUP',
    'REFERENCE_RATE',
    'SIGNAL_PREFIX',
    'Declaration',
    'RecordedSignal',
    'parse_declaration',
    'TEMPERATURE',
    'Channels',
    'Effect',
    'LiveTerms',
    'Term',
    'causal_rate',
    'current_channel',
    'effect',
    'pair_interference',
    'term_from_dict',
    'term_regressors',
    'term_to_dict',
    'terms_channels',
]

#: The entry-point group of the effects other installed packages add to :data:`EFFECTS`.
ENTRY_POINT_GROUP = 'tetra_gradiometer.effects'


def _installed_effects(taken: Mapping[str, Effect]) -> dict[str, Effect]:
    """The effects of the entry points of :data:`ENTRY_POINT_GROUP`; one that does not load,
    is not an :class:`Effect` named as its entry point, or takes a name in ``taken`` is left
    out with a warning naming it and why (the others still work)."""
    from importlib.metadata import entry_points

    out: dict[str, Effect] = {}
    for point in entry_points(group=ENTRY_POINT_GROUP):
        where = f'effect entry point {point.name} = {point.value}'
        try:
            made = point.load()
            made = made() if isinstance(made, type) else made
        except Exception as error:  # another package's bug: its effect is missing, named
            warnings.warn(f'{where}: not loaded: {error!r}', stacklevel=2)
            continue
        if not isinstance(made, Effect) or made.name != point.name or point.name in taken:
            why = (
                'a built-in effect has that name'
                if point.name in taken
                else f'not an Effect named {point.name!r}'
            )
            warnings.warn(f'{where}: left out: {why}', stacklevel=2)
            continue
        out[made.name] = made
    return out


_BUILT_IN = {effect.name: effect for effect in (VehicleCurrent(), EddyCurrent(), ThermalDrift())}
#: name -> effect: the one registry of the vehicle effects the operational model carries
#: (the built-in ones, then the installed packages').
EFFECTS: dict[str, Effect] = {**_BUILT_IN, **_installed_effects(_BUILT_IN)}


def effect(name: str) -> Effect:
    """The registry's effect ``name``, or a declared signal's (``signal:TOPIC#FIELD:BASIS``),
    or an :class:`InputError` listing the known ones."""
    if str(name).startswith(SIGNAL_PREFIX):
        return RecordedSignal(parse_declaration(name, 'effect'))
    if name not in EFFECTS:
        raise InputError(
            f'unknown effect {name!r}; known: {", ".join(EFFECTS)}, or signal:TOPIC#FIELD:BASIS'
        )
    return EFFECTS[name]


def terms_channels(terms: Sequence[Term]) -> tuple[str, ...]:
    """The recorded channels the terms read (the computed reference rate left out)."""
    names = {name for term in terms for name in term.inputs if name != REFERENCE_RATE}
    return tuple(sorted(names))


def term_regressors(terms: Sequence[Term], channels: Channels) -> FloatArray:
    """Every term's regressors side by side, (N, M), SI; NaN where a channel is unknown.

    Raises
    ------
    InputError
        A channel a term reads is not in ``channels`` (never taken as zero).
    """
    missing = [name for name in terms_channels(terms) if name not in channels.series]
    if missing:
        raise InputError(
            f'the calibration has terms that read {", ".join(missing)}, which the data lack'
        )
    blocks = [
        effect(term.effect).regressors(channels, term.inputs, term.reference) for term in terms
    ]
    return np.concatenate(blocks, axis=1) if blocks else np.zeros((len(channels), 0))


def pair_interference(terms: Sequence[Term], regressors: np.ndarray) -> FloatArray:
    """The terms' interference on the pair differences, (N, 3, 3) ``[n, axis, pair]`` T,
    from :func:`term_regressors`' (N, M): the columns of ``(k B_1m + b)`` of eq. 18 get it."""
    if not terms:
        return np.zeros((len(regressors), 3, 3))
    coefficients = np.concatenate([term.coefficients for term in terms], axis=2)  # (3, 3, M)
    return np.einsum('irm,nm->nri', coefficients, regressors)


class LiveTerms:
    """The terms' regressors one sample at a time (the compensator node), equal to
    :func:`term_regressors` on the same sequence of samples."""

    def __init__(self, terms: Sequence[Term]) -> None:
        self.terms = tuple(terms)
        self.channels = terms_channels(self.terms)
        self._live: list[LiveRegressor] = [
            effect(term.effect).live(term.inputs, term.reference) for term in self.terms
        ]

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        """Regressors (M,) at this sample (see :meth:`LiveRegressor.push`)."""
        if not self._live:
            return np.zeros(0)
        return np.concatenate([live.push(t_s, b_reference, values) for live in self._live])

    def reset(self) -> None:
        for live in self._live:
            live.reset()


def term_to_dict(term: Term) -> dict[str, Any]:
    """The calibration file's form of a term: coefficients in the effect's file unit
    (``nT/A``, ``s``, ``nT/degC``) as ``[pair][axis][regressor]``, plain types."""
    spec = effect(term.effect)
    out = {
        'effect': term.effect,
        'inputs': list(term.inputs),
        'labels': list(spec.labels(term.inputs)),
        'unit': spec.file_unit,
        'coefficients': (term.coefficients * spec.file_factor).tolist(),
        'reference': list(term.reference),
        'channel_noise': list(term.channel_noise),
        'evidence': term.evidence,
    }
    if term.window_mean:
        out['window'] = {
            'mean': list(term.window_mean),
            'covariance': [list(row) for row in term.window_covariance],
        }
    return out


def term_from_dict(data: Any, where: str) -> Term:
    """A term from its file form (:func:`term_to_dict`); :class:`InputError` naming
    ``where`` and the key when it is not one."""
    if not isinstance(data, dict):
        raise InputError(f'{where}: a term must be a mapping, got {type(data).__name__}')
    name = str(data.get('effect'))
    try:
        spec = effect(name)
    except InputError as error:
        raise InputError(f'{where}: {error}') from None
    try:
        inputs = tuple(str(v) for v in data.get('inputs', ()))
        coefficients = np.asarray(data['coefficients'], dtype=float) / spec.file_factor
        reference = tuple(float(v) for v in data.get('reference', ()))
        noise = tuple(float(v) for v in data.get('channel_noise', ()))
        window = data.get('window') or {}
        window_mean = tuple(float(v) for v in window.get('mean', ()))
        window_covariance = tuple(
            tuple(float(v) for v in row) for row in window.get('covariance', ())
        )
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise InputError(f'{where} ({name}): not a term: {error}') from None
    labels = spec.labels(inputs)
    if coefficients.shape != (3, 3, len(labels)) or not np.all(np.isfinite(coefficients)):
        raise InputError(
            f'{where} ({name}): coefficients must be finite (3, 3, {len(labels)}) '
            f'[pair][axis][regressor], got {coefficients.shape}'
        )
    evidence = data.get('evidence', {})
    return Term(
        name,
        inputs,
        coefficients,
        reference,
        noise,
        evidence if evidence else {},
        window_mean,
        window_covariance,
    )
