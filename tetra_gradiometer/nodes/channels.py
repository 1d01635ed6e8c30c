"""The recorded channels of the vehicle effects (:mod:`tetra_gradiometer.core.effects`), live:
what the calibrator and compensator nodes subscribe to and how a set gets its values.

Channels and topics are those of the bags (:mod:`tetra_gradiometer.io.channels`):
``temperature`` is ``/tetra/temperature`` (``sensor_msgs/Temperature``, degC) and
``current:<topic>`` the ``current`` (A) of the ``sensor_msgs/BatteryState`` on ``<topic>``
(``/battery_state``, and the calibrator's ``current_topics``). The subscriptions are best
effort (they match a reliable publisher and a sensor-data one alike), depth
:data:`CHANNEL_DEPTH`.

A set's value of a channel is the offline one (:meth:`io.channels.ChannelSeries.on`) on the
messages received so far: linear between the messages on both sides of the set's stamp when
both have arrived, else the nearest message; **unknown (NaN) when that message is further
than its kind's** ``max_gap_s`` **from the set** (:data:`~..io.channels.CHANNEL_KINDS`:
temperature 10 s, currents 2 s), or when there is none: never zero; and, for a channel that
steps (a current, a signal), when a message was lost between the two (a lost best-effort
message: the offline tools, which have it, give another value). A message whose stamp
is earlier than the channel's last (a restarted replay) forgets the channel's earlier messages.

* :class:`ChannelHistory` (calibrator): every channel's messages (thread-safe, bounded), as
  :class:`~tetra_gradiometer.io.channels.ChannelSeries` at ``~/calibrate``, where
  :func:`sample_terms` chooses and fits the terms through the same code as ``calibrate``
  (:func:`tetra_gradiometer.pipelines.terms.terms_on`).
* :class:`LiveEffects` (compensator): a calibration's terms evaluated per set
  (:class:`~tetra_gradiometer.core.effects.LiveTerms`: the eddy rate keeps its history,
  reset when the sets' stamps go back); a set where a regressor is unknown is dropped and
  counted per channel, with the reason for ``/diagnostics``. A set that arrives before a
  channel's message at or after its stamp is held until it comes (:meth:`LiveEffects.
  submit`, at most :data:`HOLD_PERIODS` of the channel's periods of later sets' stamps, or
  until the sets stop for :data:`IDLE_RELEASE_S`), so that its value is the interpolated one,
  as offline.
"""

from __future__ import annotations

import bisect
import importlib
import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core import TetraGeometry
from ..core.effects import REFERENCE_RATE, LiveTerms, Term
from ..core.effects.losses import USUAL_INTERVALS, after_loss
from ..core.identification import DEFAULT_METHOD
from ..core.units import NS_PER_S, S_PER_NS
from ..errors import InputError
from ..io import conversions as cv
from ..io.channels import ChannelSeries, channel_kind, channel_topic, max_gap_s
from ..io.signals import field_value
from ..pipelines.effects_choice import EffectsChoice
from ..pipelines.terms import WindowTerms, channels_on, terms_on

FloatArray = npt.NDArray[np.float64]

#: Queue depth of a channel subscription (a burst of a recorded replay).
CHANNEL_DEPTH = 1000
#: Messages kept per channel (a day at 1 Hz, 21 min at 100 Hz); the oldest go first.
MAX_MESSAGES = 125_000
#: The compensator forgets a channel's messages older than its gap limit before the last
#: set in steps of this many (the per-set cost stays a bisection).
PRUNE_STEP = 256
#: A channel's message period is the median spacing of its last this many messages.
PERIOD_MESSAGES = 16
#: A set waits for a lagging channel at most this many of its periods of later sets' stamps:
#: one for the next message to be due, one for its delivery.
HOLD_PERIODS = 2.0
#: When no set has come for this long on the steady clock (s; or for the hold bound, if
#: longer), the held sets go out: the sets stopped (a replay's end, a sensor outage). Not
#: shorter: a node that falls behind (a loaded machine) runs its timers before the messages
#: waiting in its queue, and a channel message already received would be passed over (seen
#: at 8x real time with a bound of two 20 Hz periods, 0.1 s).
IDLE_RELEASE_S = 1.0


class ChannelBuffer:
    """One channel's messages by header stamp (not thread-safe: see :class:`ChannelHistory`).

    Attributes
    ----------
    name : channel name; ``max_gap_s`` its staleness limit, s
    received : messages taken; ``restarts``: times a stamp went back (messages forgotten)
    """

    def __init__(self, name: str, capacity: int = MAX_MESSAGES) -> None:
        self.name = name
        self.topic = channel_topic(name)
        self.max_gap_s = max_gap_s(name)
        self.steps = channel_kind(name).steps
        self.capacity = capacity
        self.stamps: list[int] = []
        self.values: list[float] = []
        self.received = 0
        self.restarts = 0
        self._judged = (-1, False)  # (a message's stamp, whether a message was lost before it)

    def __len__(self) -> int:
        return len(self.stamps)

    def add(self, stamp_ns: int, value: float) -> None:
        """One message (a NaN value stays: the channel is unknown around it)."""
        if self.stamps and stamp_ns < self.stamps[-1]:
            self.stamps, self.values = [], []
            self.restarts += 1
            self._judged = (-1, False)
        self.stamps.append(int(stamp_ns))
        self.values.append(float(value))
        self.received += 1
        if len(self.stamps) > self.capacity:
            drop = len(self.stamps) - self.capacity
            del self.stamps[:drop], self.values[:drop]

    def at(self, stamp_ns: int) -> float:
        """The value at ``stamp_ns``: :meth:`ChannelSeries.on` on the messages so far."""
        n = len(self.stamps)
        if n == 0:
            return float('nan')
        after = min(bisect.bisect_left(self.stamps, stamp_ns), n - 1)
        before = max(after - 1, 0)
        gap = min(abs(self.stamps[after] - stamp_ns), abs(self.stamps[before] - stamp_ns))
        if gap * S_PER_NS > self.max_gap_s:
            return float('nan')
        if self._lost_before(after, stamp_ns):
            return float('nan')
        lo, hi = max(after - 1, 0), after + 1
        return float(np.interp(stamp_ns, self.stamps[lo:hi], self.values[lo:hi]))

    def _lost_before(self, after: int, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` lies strictly between message ``after`` and the one before,
        with a message lost between them, on a channel that steps."""
        if not self.steps or after == 0:
            return False
        if not self.stamps[after - 1] < stamp_ns < self.stamps[after]:
            return False
        if self._judged[0] != self.stamps[after]:  # the sets between two messages ask once
            recent = self.stamps[max(after - USUAL_INTERVALS - 1, 0) : after + 1]
            self._judged = (self.stamps[after], bool(after_loss(np.array(recent))[-1]))
        return self._judged[1]

    def gap_s(self, stamp_ns: int) -> float:
        """Distance from ``stamp_ns`` to the nearest message, s (inf: none)."""
        if not self.stamps:
            return float('inf')
        after = bisect.bisect_left(self.stamps, stamp_ns)
        near = self.stamps[max(after - 1, 0) : after + 1]
        return min(abs(s - stamp_ns) for s in near) * S_PER_NS

    def period_s(self) -> float:
        """The channel's message period, s: the median spacing of its last
        :data:`PERIOD_MESSAGES` messages, at most its gap limit (the limit with one message:
        a set within it of that message has its value, offline too)."""
        recent = np.diff(np.asarray(self.stamps[-PERIOD_MESSAGES:], dtype=np.int64))
        if not len(recent):
            return self.max_gap_s
        return min(float(np.median(recent)) * S_PER_NS, self.max_gap_s)

    def prune(self, stamp_ns: int) -> None:
        """Forget the messages no set at or after ``stamp_ns`` can use (all but the last one
        more than the gap limit before it), in steps of :data:`PRUNE_STEP`."""
        cut = bisect.bisect_right(self.stamps, stamp_ns - int(self.max_gap_s * NS_PER_S)) - 1
        cut -= USUAL_INTERVALS + 1  # the intervals that judge a loss (:meth:`at`)
        if cut >= PRUNE_STEP:
            del self.stamps[:cut], self.values[:cut]

    def series(self) -> ChannelSeries:
        return ChannelSeries(
            self.name, np.array(self.stamps, dtype=np.int64), np.array(self.values, dtype=float)
        )

    def why_unknown(self, stamp_ns: int) -> str:
        """Why the channel has no value at ``stamp_ns``, for a message."""
        what = f'{self.name} ({self.topic})'
        if not self.stamps:
            return f'{what}: no message yet'
        after = min(bisect.bisect_left(self.stamps, stamp_ns), len(self.stamps) - 1)
        if self.gap_s(stamp_ns) <= self.max_gap_s and self._lost_before(after, stamp_ns):
            span_s = (self.stamps[after] - self.stamps[after - 1]) * S_PER_NS
            return (
                f'{what}: a message lost around the set (its neighbours {span_s:.3g} s apart, '
                f'period {self.period_s():.3g} s)'
            )
        if not np.isfinite(self.at(stamp_ns)) and self.gap_s(stamp_ns) <= self.max_gap_s:
            return f'{what}: the message near the set is NaN'
        return (
            f'{what}: stale, the nearest message is {self.gap_s(stamp_ns):.3g} s from the set '
            f'(limit {self.max_gap_s:g} s)'
        )


def channel_message(name: str, msg: Any) -> float:
    """The channel's value in ``msg``: its kind's field (:data:`~..io.channels.CHANNEL_KINDS`:
    a Temperature's degC, a BatteryState's A, a signal's declared field); NaN when this
    message lacks it (a joint not reported) or it is not finite."""
    try:
        return field_value(msg, channel_kind(name).field)
    except (ValueError, TypeError):
        return float('nan')


def channel_stamp(msg: Any, now_ns: int) -> int:
    """A channel message's stamp, ns: its header's, or ``now_ns`` (the node's clock) for a
    message without one (``std_msgs/Float64``, as offline its log time)."""
    header = getattr(msg, 'header', None)
    return now_ns if header is None else cv.stamp_to_ns(header.stamp)


def message_class(node: Any, topic: str) -> Any:
    """The message class of ``topic`` as the ROS graph has it now, or None (not published
    yet, or a type whose package this install lacks)."""
    for name, types in node.get_topic_names_and_types():
        if name == topic and types:
            return message_class_named(types[0])
    return None


def message_class_named(msgtype: str) -> Any:
    """The message class of ``msgtype`` (``package/msg/Name``), or None when this install
    lacks its package."""
    package, _, kind = msgtype.partition('/msg/')
    try:
        return getattr(importlib.import_module(f'{package}.msg'), kind, None)
    except ImportError:
        return None


def subscribe_channels(
    node: Any, names: Iterable[str], on_message: Callable[[str, Any], None], **kwargs: Any
) -> dict[str, Any]:
    """Subscriptions of ``node`` to the channels ``names`` (name -> subscription), each
    calling ``on_message(name, msg)``; ``kwargs`` go to ``create_subscription``. A declared
    signal's message type is the graph's when the node configures: one not published then
    is logged and not read (its channel has no message: named on ``/diagnostics``)."""
    from .common import sensor_qos

    out = {}
    for name in names:
        msgtype = channel_kind(name).msgtype  # '' for a signal: the graph's type
        topic = channel_topic(name)
        kind = message_class_named(msgtype) if msgtype else message_class(node, topic)
        if kind is None:
            node.get_logger().warning(
                f'{channel_topic(name)} is not published (or its message package is not '
                f'installed): {name} is not read; configure the node again once it is'
            )
            continue
        out[name] = node.create_subscription(
            kind,
            channel_topic(name),
            lambda msg, n=name: on_message(n, msg),
            sensor_qos(CHANNEL_DEPTH),
            **kwargs,
        )
    return out


class ChannelHistory:
    """The channels' messages the calibrator received (thread-safe; each bounded to
    :data:`MAX_MESSAGES`), kept whether or not it collects, like its ``odom``."""

    def __init__(self, names: Iterable[str]) -> None:
        self._buffers = {name: ChannelBuffer(name) for name in names}
        self._lock = threading.Lock()

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._buffers)

    def add(self, name: str, stamp_ns: int, value: float) -> None:
        with self._lock:
            self._buffers[name].add(stamp_ns, value)

    def series(self) -> dict[str, ChannelSeries]:
        """The channels with at least one message, as recorded series (a bag's)."""
        with self._lock:
            return {name: b.series() for name, b in self._buffers.items() if len(b)}

    def counts(self) -> dict[str, int]:
        """Messages received per channel (for ``/diagnostics``)."""
        with self._lock:
            return {name: b.received for name, b in self._buffers.items()}


def sample_terms(
    method: str,
    stamps_ns: npt.NDArray[np.int64],
    g_measured: FloatArray,
    b_reference: FloatArray,
    series: dict[str, ChannelSeries],
    geometry: TetraGeometry,
    choice: EffectsChoice,
    orientation_xyzw: FloatArray | None,
) -> WindowTerms:
    """The terms the calibrator's samples are fitted with: ``calibrate``'s choice
    (:func:`~tetra_gradiometer.pipelines.terms.terms_on`) on the samples ``stamps_ns`` (n,)
    ns, ``G_m`` (n, 3, 3) T/m, ``B_1'`` (n, 3) T, with the channels' received ``series``
    and the samples' attitude (or None); none for a ``method`` other than the default (it
    fits the paper's form), as ``calibrate``. A channel none of whose messages is near a
    sample counts as missing.

    Raises
    ------
    InputError
        Effects asked for by name whose channels the node has received no message on, or
        with another method.
    """
    if method != DEFAULT_METHOD:
        if choice.names:
            raise InputError(
                f'effects {",".join(choice.names)}: vehicle effects are fitted with '
                f'{DEFAULT_METHOD}, not {method}'
            )
        return WindowTerms(notes=(f'effects: none ({method} fits k, b only)',))
    # A channel with no value near any sample (messages of another time) is one the data
    # lack: offered, it would leave no sample to select on.
    series = {name: s for name, s in series.items() if np.isfinite(s.on(stamps_ns)).any()}
    channels = channels_on(stamps_ns, b_reference, series)
    pairs = g_measured @ geometry.a  # B_i' - B_1' per axis and pair (eq. 7 times a)
    used = np.arange(len(stamps_ns))
    data = 'the node has received no message on (or none near the samples): it'
    return terms_on(channels, series, pairs, used, geometry, choice, orientation_xyzw, data)


class LiveEffects:
    """A calibration's terms on the compensator's sets, one at a time.

    Parameters
    ----------
    terms : the calibration's
    buffers : channel buffers to keep (a previous calibration's: their messages stay)

    Attributes
    ----------
    channels : channel name -> :class:`ChannelBuffer` (the channels the terms read)
    dropped : channel name (or ``reference_rate``: the eddy rate not yet known, after a
        start or a jump) -> sets dropped for it
    reason : why the last dropped set was, '' before any
    resets : times the sets' stamps went back (a restarted replay): the terms' history
        forgotten
    """

    def __init__(
        self, terms: tuple[Term, ...], buffers: Mapping[str, ChannelBuffer] | None = None
    ) -> None:
        self.terms = LiveTerms(terms)
        buffers = buffers or {}
        self.channels = {
            name: buffers[name] if name in buffers else ChannelBuffer(name)
            for name in self.terms.channels
        }
        self.dropped: dict[str, int] = {}
        self.reason = ''
        self.resets = 0
        self.held = 0
        self.released_at_bound = 0
        self._dropped_reported = 0  # channel drops already on /diagnostics
        self._origin_ns: int | None = None
        self._last_ns: int | None = None
        self._queue: deque[tuple[int, Any]] = deque()  # (stamp, the set)
        self._newest_ns = 0
        self._last_set_s = 0.0  # steady clock of the last set submitted

    @property
    def names(self) -> str:
        return ', '.join(term.effect for term in self.terms.terms)

    def add(self, name: str, stamp_ns: int, value: float) -> None:
        """A channel message."""
        self.channels[name].add(stamp_ns, value)

    def regressors(self, stamp_ns: int, b_reference: np.ndarray) -> FloatArray | None:
        """The terms' regressors (M,) of the set at ``stamp_ns`` with ``B_1'`` (3,) T, or
        None when one is unknown (the set is dropped: counted, :attr:`reason` says why)."""
        if self._last_ns is not None and stamp_ns <= self._last_ns:
            self.terms.reset()  # the stamps went back: a restarted replay
            self._origin_ns = None
            self.resets += 1
        if self._origin_ns is None:
            self._origin_ns = stamp_ns
        self._last_ns = stamp_ns
        values = {name: buffer.at(stamp_ns) for name, buffer in self.channels.items()}
        t_s = (stamp_ns - self._origin_ns) * S_PER_NS
        x = self.terms.push(t_s, b_reference, values)
        for buffer in self.channels.values():
            buffer.prune(stamp_ns)
        if np.all(np.isfinite(x)):
            return x
        unknown = [name for name, value in values.items() if not np.isfinite(value)]
        for name in unknown or [REFERENCE_RATE]:
            self.dropped[name] = self.dropped.get(name, 0) + 1
        self.reason = (
            '; '.join(self.channels[name].why_unknown(stamp_ns) for name in unknown)
            if unknown
            else f'{REFERENCE_RATE}: the eddy rate needs the sets before (a start or a jump)'
        )
        return None

    def submit(self, stamp_ns: int, item: Any, now_s: float) -> list[Any]:
        """Queue the set ``item`` at ``stamp_ns`` (arrived at ``now_s``, a steady clock, s);
        returns the sets to compensate now, in order (:meth:`release`). A set is held until
        every channel with messages has one at or after its stamp (its value is then
        interpolated, as offline), for at most :data:`HOLD_PERIODS` periods of the lagging
        channel of later sets' stamps; a stamp that goes back (a restarted replay) releases
        the queue."""
        out = self.release(now_s, flush=True) if stamp_ns <= self._newest_ns else []
        self._newest_ns, self._last_set_s = stamp_ns, now_s
        self._queue.append((stamp_ns, item))
        out += self.release(now_s)
        self.held += bool(self._queue)
        return out

    def release(self, now_s: float, *, flush: bool = False) -> list[Any]:
        """The queued sets that need wait no longer, in order: their channels' messages have
        reached their stamp, or later sets' stamps passed them by :data:`HOLD_PERIODS`
        periods of a lagging channel, or no set came for that long and at least
        :data:`IDLE_RELEASE_S` on the steady clock ``now_s`` (those two counted in
        :attr:`released_at_bound`), or ``flush``."""
        out = []
        idle_s = now_s - self._last_set_s
        while self._queue:
            stamp_ns, item = self._queue[0]
            bound = HOLD_PERIODS * max(
                (
                    b.period_s()
                    for b in self.channels.values()
                    if b.stamps and b.stamps[-1] < stamp_ns
                ),
                default=0.0,
            )
            if bound > 0.0:
                passed = (self._newest_ns - stamp_ns) * S_PER_NS > bound
                stopped = idle_s > max(bound, IDLE_RELEASE_S)
                if not (passed or stopped or flush):
                    break
                self.released_at_bound += 1
            out.append(item)
            self._queue.popleft()
        return out

    def report(self) -> tuple[bool, str, dict[str, Any]]:
        """``tetra/compensator: channels`` as (warn, message, values): WARN while sets are
        dropped for a missing or stale channel (since the last report) or a channel the terms
        read has no message yet, naming it; OK otherwise."""
        values: dict[str, Any] = {
            'terms': self.names,
            'replay_restarts': self.resets,
            'sets held for a channel message': self.held,
            'sets released at the hold bound': self.released_at_bound,
        }
        for name, buffer in self.channels.items():
            values[f'{name} ({buffer.topic}) messages'] = buffer.received
        for name, count in self.dropped.items():
            values[f'sets dropped without {name}'] = count
        by_channel = sum(n for name, n in self.dropped.items() if name in self.channels)
        new, self._dropped_reported = by_channel - self._dropped_reported, by_channel
        waiting = self.stale()
        if new > 0:
            text = (
                f'{new} sets dropped since the last report, never compensated with zero: '
                f'{self.reason}'
            )
            return True, text, values
        if waiting:
            listed = ', '.join(f'{n} ({self.channels[n].topic})' for n in waiting)
            return True, f'no message yet on {listed}: its sets are dropped', values
        return False, f'terms {self.names}: channels fresh', values

    def stale(self) -> list[str]:
        """The channels the terms read that have no message yet."""
        return [name for name, buffer in self.channels.items() if not buffer.received]
