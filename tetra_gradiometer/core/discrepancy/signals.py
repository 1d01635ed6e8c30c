"""Candidates from the signals a run records beyond the library's channels (a fin angle, a
load's current): each becomes a family of the same protocol as the declared signals'
effects (:mod:`tetra_gradiometer.core.effects.recorded_signal`), in the bases a user would
declare, so that a family the search names is the declaration ``calibrate`` takes.

One basis per signal, ``calibrate``'s for a signal it finds
(:func:`~tetra_gradiometer.core.effects.recorded_signal.basis_for`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..effects import Channels, RecordedSignal, parse_declaration
from ..effects.recorded_signal import basis_for
from .effects import Array, Built, Candidate, Context, Estimate, registry_columns

__all__ = ['signal_candidates']

def _builder(effect: RecordedSignal):
    channel = effect.declaration.channel

    def build(ctx: Context, estimate: Estimate | None) -> Built:
        x = np.asarray(ctx.signals[channel], dtype=float)
        series = Channels(ctx.t, ctx.b_background, {channel: x})
        columns = effect.regressors(series, (channel,), effect.reference(series, (channel,)))
        labels = effect.labels((channel,))
        return registry_columns(ctx, columns, lambda a, j: f'{"xyz"[a]}_nT_per[{labels[j]}]')

    return build


def signal_candidates(values: Mapping[str, Array]) -> tuple[Candidate, ...]:
    """A candidate per recorded signal channel (``signal:TOPIC#FIELD`` -> (N,) values) and
    basis."""
    out = []
    for channel, series in values.items():
        basis = basis_for(channel, np.asarray(series, dtype=float))
        if basis is not None:
            effect = RecordedSignal(parse_declaration(f'{channel}:{basis}', 'a recorded signal'))
            out.append(
                Candidate(
                    effect.name,
                    effect.physics,
                    f'a 3-vector per sensor per regressor, {effect.file_unit}',
                    (),
                    _builder(effect),
                    in_detector=False,
                    separated_by='its own time course: the recorded signal, not the attitude',
                )
            )
    return tuple(out)
