"""Candidates from the signals a run records beyond the library's channels (a fin angle, a
load's current): each becomes a family of the same protocol as the declared signals'
effects (:mod:`tetra_gradiometer.core.effects.recorded_signal`), in the bases a user would
declare, so that a family the search names is the declaration ``calibrate`` takes.

Bases offered, one per signal (chosen, and written down: two bases of one signal are
nearly collinear for small angles, sin x ~ x, and the search would split one physical
source between them): ``harmonic`` for an angle, a field whose name says so (a
``JointState`` position, or a name with angle, yaw, pitch, roll, heading, rudder, fin,
servo) and whose values stay within +-2 pi: a magnet turning with a fin is cos, sin of its
angle; ``linear`` for everything else (a current, a switched load: two levels are linear).
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np

from ..effects import Channels, RecordedSignal, parse_declaration
from .effects import Array, Built, Candidate, Context, Estimate, registry_columns

__all__ = ['signal_candidates']

#: An angle's values stay within this of zero, rad.
ANGLE_BOUND_RAD = 2 * np.pi
_ANGLE_WORDS = re.compile(r'position\[|angle|yaw|pitch|roll|heading|rudder|fin|servo', re.I)


def _bases(channel: str, values: Array) -> tuple[str, ...]:
    finite = values[np.isfinite(values)]
    if not len(finite):
        return ()
    field = channel.partition('#')[2]
    angle = bool(_ANGLE_WORDS.search(field)) and np.abs(finite).max() <= ANGLE_BOUND_RAD
    return ('harmonic',) if angle else ('linear',)


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
        for basis in _bases(channel, np.asarray(series, dtype=float)):
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
