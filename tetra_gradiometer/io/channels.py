"""The recorded channels the vehicle effects read (:mod:`tetra_gradiometer.core.effects`),
from a bag onto the sample sets' stamps.

Channels and their topics: ``temperature`` is ``/tetra/temperature``
(``sensor_msgs/Temperature``, degC); ``current:<topic>`` is the ``current`` (A) of the
``sensor_msgs/BatteryState`` on ``<topic>``: ``/battery_state`` by default, and any further
BatteryState topics the user names (one per thruster ESC, say); :data:`CHANNEL_KINDS`
declares each kind's message type, field, staleness limit and unit. A channel is
interpolated linearly between its messages (by header stamp) onto each set's stamp; a set
further than its kind's ``max_gap_s`` from every message of the channel (a gap, or beyond
the channel's ends) gets NaN there: **stale, never taken as zero**; so does a set between two
messages of a channel that can step (a current, a signal) when a message was lost between
them (:mod:`~tetra_gradiometer.core.effects.losses`: the interval is longer than the
channel's usual one): a step there would be interpolated over. The pipelines drop and count
such sets, and say which channel and when. ``signal:TOPIC#FIELD`` is a declared
signal's field (:mod:`.signals`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from ..core.effects import CURRENT_PREFIX, SIGNAL_PREFIX, TEMPERATURE, current_channel
from ..core.effects.losses import after_loss
from ..core.effects.recorded_signal import parse_channel
from ..core.units import S_PER_NS
from ..errors import BagError
from . import conversions as cv
from .signals import read_signal

if TYPE_CHECKING:  # only an annotation: the nodes import this module without rosbags
    from .bag import MagneticBag

@dataclass(frozen=True)
class ChannelKind:
    """What a channel's messages are, declared as data: ``msgtype`` (``package/msg/Name``;
    '' for a signal: whatever the bag or the graph carries), ``field`` (the number in it, a
    :func:`~.signals.field_value` path), ``max_gap_s`` (the furthest a set may lie from the
    channel's nearest message, s), its ``unit``, and whether it ``steps`` between messages
    (then a set where a message was lost has no value: see the module)."""

    msgtype: str
    field: str
    max_gap_s: float
    unit: str
    steps: bool = True


#: The channels' kinds: a temperature changes slowly (sensors report at ~1 Hz or less), a
#: current steps with the thrusters, a signal is held to a current's limit.
CHANNEL_KINDS = {
    TEMPERATURE: ChannelKind(cv.TEMPERATURE, 'temperature', 10.0, 'degC', steps=False),
    CURRENT_PREFIX: ChannelKind(cv.BATTERY_STATE, 'current', 2.0, 'A'),
    SIGNAL_PREFIX: ChannelKind('', '', 2.0, 'as recorded'),
}


def channel_kind(name: str) -> ChannelKind:
    """The kind of channel ``name`` (a signal's with its own field)."""
    if name == TEMPERATURE:
        return CHANNEL_KINDS[TEMPERATURE]
    for prefix in (CURRENT_PREFIX, SIGNAL_PREFIX):
        if name.startswith(prefix):
            kind = CHANNEL_KINDS[prefix]
            if prefix == SIGNAL_PREFIX:
                return ChannelKind(kind.msgtype, parse_channel(name)[1], kind.max_gap_s, kind.unit)
            return kind
    raise BagError(f'{name!r} is not a recorded channel')


def max_gap_s(name: str) -> float:
    """The staleness limit of channel ``name``, s (:data:`CHANNEL_KINDS`)."""
    return channel_kind(name).max_gap_s


def channel_topic(name: str) -> str:
    """The bag topic of channel ``name``."""
    if name == TEMPERATURE:
        return cv.TEMPERATURE_TOPIC
    if name.startswith(CURRENT_PREFIX):
        return name.removeprefix(CURRENT_PREFIX)
    if name.startswith(SIGNAL_PREFIX):
        return parse_channel(name)[0]
    raise BagError(f'{name!r} is not a recorded channel')


def current_channels(topics: Iterable[str] = ()) -> tuple[str, ...]:
    """The current channels: ``/battery_state`` and the further ``topics`` (duplicates
    dropped)."""
    names = [current_channel(cv.BATTERY_TOPIC)]
    names += [current_channel(topic) for topic in topics]
    return tuple(dict.fromkeys(names))


@dataclass(frozen=True)
class ChannelSeries:
    """One channel as recorded: header stamps (m,) ns, values (m,), its name."""

    name: str
    stamps_ns: np.ndarray
    values: np.ndarray

    def on(self, stamps_ns: np.ndarray) -> np.ndarray:
        """The values at ``stamps_ns`` (n,): linear between messages, NaN where stale."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        values = np.interp(stamps, self.stamps_ns, self.values)
        after = np.clip(np.searchsorted(self.stamps_ns, stamps), 0, len(self.stamps_ns) - 1)
        before = np.clip(after - 1, 0, len(self.stamps_ns) - 1)
        gap = np.minimum(
            np.abs(self.stamps_ns[after] - stamps), np.abs(self.stamps_ns[before] - stamps)
        )
        values[gap * S_PER_NS > max_gap_s(self.name)] = np.nan
        if channel_kind(self.name).steps:
            lost = self.after_loss[after] & (stamps > self.stamps_ns[before])
            values[lost & (stamps < self.stamps_ns[after])] = np.nan
        return values

    @cached_property
    def after_loss(self) -> np.ndarray:
        """(m,) True at each message that follows a lost one (:func:`~tetra_gradiometer.core.
        effects.losses.after_loss`; once: a compensation asks for every chunk)."""
        return after_loss(self.stamps_ns)

    def stale_spans(self, stamps_ns: np.ndarray, origin_ns: int) -> list[tuple[float, float]]:
        """The runs of ``stamps_ns`` where the channel is stale, (t0, t1) s from
        ``origin_ns``."""
        stale = ~np.isfinite(self.on(stamps_ns))
        return runs(stamps_ns, stale, origin_ns)


def runs(stamps_ns: np.ndarray, flag: np.ndarray, origin_ns: int) -> list[tuple[float, float]]:
    """The runs of consecutive ``flag`` samples as (t0, t1) s from ``origin_ns``."""
    if not np.any(flag):
        return []
    edges = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    t = (np.asarray(stamps_ns) - origin_ns) * S_PER_NS
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends, strict=True)]


def read_channels(bag: MagneticBag, names: Sequence[str]) -> dict[str, ChannelSeries]:
    """The channels ``names`` the bag records (an absent topic is left out), each by header
    stamp."""
    out = {}
    for name in names:
        if name.startswith(SIGNAL_PREFIX):
            series = read_signal(bag, *parse_channel(name))
        else:
            series = bag.read_series(channel_topic(name))
        if series is not None and len(series.stamps_ns):
            out[name] = ChannelSeries(name, series.stamps_ns, series.values[:, 0])
    return out


def spans_text(spans: list[tuple[float, float]], limit: int = 3) -> str:
    """``'12.0-15.5 s, 80.2-80.9 s'`` (at most ``limit``, then how many more)."""
    text = ', '.join(f'{a:.1f}-{b:.1f} s' for a, b in spans[:limit])
    return text + (f' and {len(spans) - limit} more' if len(spans) > limit else '')
