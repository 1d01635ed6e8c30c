"""Matching the four magnetometer streams into sample sets by header stamp.

Used by the tensor node (live topics) and the bag reader (recorded topics), so both drop
and count incomplete sets the same way. Each sensor's stamps must increase; a set is the
four queue heads when they lie within ``tolerance_ns`` of each other. A head that cannot
match any more (another sensor has already moved past it) is dropped and counted.
:class:`StampPairer` joins streams on identical stamps (the compensator's
``gradient/compensated`` with ``gradient/truth``).
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.streams import StreamReport
from ..core.timebase import ClockEstimate, Resampler, TimeBase
from ..core.units import NS_PER_S
from ..errors import InputError

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

N_SENSORS = 4


@dataclass
class MatchCounters:
    """Running counts of a :class:`StampMatcher`.

    Attributes
    ----------
    matched : int
        Sets emitted.
    dropped_messages : int
        Messages dropped without a set, for any reason (this total includes
        ``evicted_messages``).
    evicted_messages : int
        Of ``dropped_messages``, those pushed out of a sensor's full queue (``max_pending``):
        another sensor stayed silent for that long.
    out_of_order : int
        Messages refused because their stamp did not increase on their sensor.
    streams : StreamReport
        The streams' faults found before the sets were formed (offline reads).
    """

    matched: int = 0
    dropped_messages: int = 0
    evicted_messages: int = 0
    out_of_order: int = 0
    streams: StreamReport = field(default_factory=StreamReport)

    @property
    def sets(self) -> int:
        return self.matched

    def text(self) -> str:
        """For summaries: '3 messages unmatched (0 evicted from a full queue), 0 out of order'."""
        return (
            f'{self.dropped_messages} messages unmatched ({self.evicted_messages} evicted '
            f'from a full queue), {self.out_of_order} out of order'
        ) + (f'; {self.streams.text()}' if self.streams.faults else '')

    def as_dict(self) -> dict[str, Any]:
        """Calibration-file diagnostics."""
        return self.streams.as_dict() | {
            'sets_matched': self.matched,
            'messages_unmatched': self.dropped_messages,
            'messages_evicted': self.evicted_messages,
            'messages_out_of_order': self.out_of_order,
        }


class StampMatcher:
    """Approximate-time synchroniser for four streams.

    Parameters
    ----------
    tolerance_ns : int
        Largest spread of the four stamps within one set, nanoseconds.
    max_pending : int
        Per-sensor queue bound; older messages are dropped (a silent sensor must not grow memory).
    """

    def __init__(self, tolerance_ns: int, *, max_pending: int = 1000) -> None:
        if tolerance_ns < 0:
            raise InputError(f'tolerance_ns must be >= 0, got {tolerance_ns}')
        self.tolerance_ns = int(tolerance_ns)
        self.max_pending = int(max_pending)
        self.counters = MatchCounters()
        self._queues: list[deque[tuple[int, FloatArray]]] = [deque() for _ in range(N_SENSORS)]
        self._last: list[int | None] = [None] * N_SENSORS

    def add(self, sensor: int, stamp_ns: int, value: FloatArray) -> list[tuple[int, FloatArray]]:
        """Queue one reading (sensor 0..3) and return the sets it completes as
        ``(stamp_ns of sensor 1, fields (4, 3))``."""
        last = self._last[sensor]
        if last is not None and stamp_ns <= last:
            self.counters.out_of_order += 1
            return []
        self._last[sensor] = stamp_ns
        queue = self._queues[sensor]
        queue.append((stamp_ns, value))
        if len(queue) > self.max_pending:
            queue.popleft()
            self.counters.dropped_messages += 1
            self.counters.evicted_messages += 1
        return self._drain()

    def _drain(self) -> list[tuple[int, FloatArray]]:
        completed = []
        while all(self._queues):
            stamps = [q[0][0] for q in self._queues]
            if max(stamps) - min(stamps) <= self.tolerance_ns:
                values = [q.popleft()[1] for q in self._queues]
                completed.append((stamps[0], np.stack(values)))
                self.counters.matched += 1
            else:
                self._queues[int(np.argmin(stamps))].popleft()
                self.counters.dropped_messages += 1
        return completed

    def finish(self) -> None:
        """The recording has ended: the messages still queued can never match (another
        sensor's stream stopped); they are counted as unmatched and forgotten."""
        left = sum(len(q) for q in self._queues)
        self.counters.dropped_messages += left
        for queue in self._queues:
            queue.clear()

    def pending_oldest_ns(self) -> int | None:
        """Oldest stamp still waiting, or None."""
        heads = [q[0][0] for q in self._queues if q]
        return min(heads) if heads else None

    @property
    def last_stamps_ns(self) -> tuple[int | None, ...]:
        """Per sensor, the newest accepted stamp (ns), or None before the first."""
        return tuple(self._last)

    def take_run(self, stamps_ns: IntArray) -> bool:
        """Accept ``k`` sets whose four stamps are all ``stamps_ns`` (k,) without queueing them.

        The fast path of a synchronised driver: feeding the ``4 k`` messages to :meth:`add`
        would emit exactly these sets. Accepted (counted as matched, each sensor's last stamp
        moved to ``stamps_ns[-1]``) only when nothing is pending, ``stamps_ns`` strictly
        increases and its first stamp is newer than every sensor's last; otherwise nothing
        changes and False is returned (feed the messages to :meth:`add`).
        """
        if not len(stamps_ns) or self.pending_oldest_ns() is not None:
            return False
        first = int(stamps_ns[0])
        if not np.all(np.diff(stamps_ns) > 0) or any(
            last is not None and first <= last for last in self._last
        ):
            return False
        self._last = [int(stamps_ns[-1])] * N_SENSORS
        self.counters.matched += len(stamps_ns)
        return True


class StampPairer:
    """Joins ``n`` streams on identical header stamps (ns): :meth:`add` returns the tuple of
    values once every stream has delivered that stamp. Bounded: the oldest incomplete
    stamps are evicted beyond ``max_pending`` and counted in :attr:`evicted` (the nodes
    report it on ``/diagnostics``)."""

    def __init__(self, n: int, max_pending: int = 1000) -> None:
        self.n = int(n)
        self.max_pending = int(max_pending)
        self.evicted = 0
        self._pending: OrderedDict[int, list] = OrderedDict()

    def add(self, stream: int, stamp_ns: int, value: Any) -> tuple | None:
        slot = self._pending.get(stamp_ns)
        if slot is None:
            slot = self._pending[stamp_ns] = [None] * self.n
            while len(self._pending) > self.max_pending:
                self._pending.popitem(last=False)
                self.evicted += 1
        slot[stream] = value
        if all(v is not None for v in slot):
            del self._pending[stamp_ns]
            return tuple(slot)
        return None

    def clear(self) -> None:
        """Forget the incomplete stamps (:attr:`evicted` keeps counting)."""
        self._pending.clear()


class _BatchMatcher:
    """Pairs per-sensor batches by stamp (``sync='nearest'``); equal-stamp runs with
    arrays, the rest via StampMatcher.

    Equivalent to feeding every message to the StampMatcher: a run is taken on the fast path
    only when the matcher holds nothing and the next ``k`` stamps of all four sensors are
    identical, strictly increasing and newer than each sensor's last accepted stamp; the
    StampMatcher would emit exactly those ``k`` sets.
    """

    def __init__(self, matcher: StampMatcher) -> None:
        self.matcher = matcher
        self.counters = matcher.counters
        self.pending: list[tuple[np.ndarray, np.ndarray]] = [
            (np.zeros(0, dtype=np.int64), np.zeros((0, 3))) for _ in range(4)
        ]

    def add(
        self,
        batches: list[tuple[np.ndarray, np.ndarray]],
        *,
        final: bool = False,
        fast: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add per-sensor ``(stamps, values)``; return the completed sets as arrays."""
        self.pending = [
            (np.concatenate([p[0], b[0]]), np.concatenate([p[1], b[1]]))
            for p, b in zip(self.pending, batches, strict=True)
        ]
        out_stamps: list[np.ndarray] = []
        out_fields: list[np.ndarray] = []
        if fast and self.matcher.pending_oldest_ns() is None:
            k = min(len(p[0]) for p in self.pending)
            if k > 0:
                reference = self.pending[0][0][:k]
                same = all(np.array_equal(p[0][:k], reference) for p in self.pending[1:])
                if same and self.matcher.take_run(reference):
                    out_stamps.append(reference.copy())
                    out_fields.append(np.stack([p[1][:k] for p in self.pending], axis=1))
                    self.pending = [(p[0][k:], p[1][k:]) for p in self.pending]
                    if not final:
                        return _join(out_stamps, out_fields)
        # Generic path: everything pending, in stamp order across sensors (as logged).
        stamps = np.concatenate([p[0] for p in self.pending])
        if len(stamps):
            sensors = np.concatenate([np.full(len(p[0]), i) for i, p in enumerate(self.pending)])
            values = np.concatenate([p[1] for p in self.pending])
            order = np.argsort(stamps, kind='stable')
            matched = []
            for j in order:
                matched.extend(self.matcher.add(int(sensors[j]), int(stamps[j]), values[j]))
            if matched:
                out_stamps.append(np.array([m[0] for m in matched], dtype=np.int64))
                out_fields.append(np.array([m[1] for m in matched]))
            self.pending = [(p[0][:0], p[1][:0]) for p in self.pending]
        if final:
            self.finish()
        return _join(out_stamps, out_fields)

    def clocks(self) -> None:
        return None

    def finish(self) -> None:
        """Count what can no longer match (:meth:`StampMatcher.finish`)."""
        self.matcher.finish()


class _BatchResampler:
    """Resamples per-sensor batches (``sync='interpolate'``); same interface as
    :class:`_BatchMatcher`."""

    def __init__(self, timebase: TimeBase) -> None:
        self.resampler = Resampler(timebase)
        self.counters = self.resampler.counters

    def add(
        self,
        batches: list[tuple[np.ndarray, np.ndarray]],
        *,
        final: bool = False,
        fast: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add per-sensor ``(stamps, values)``; return the sets completed, in stamp order."""
        # Sensor 1 last: its stamps are the instants, resolved at once when the others
        # are in (not queued against max_pending while they are still to come).
        out = [self.resampler.add(sensor, *batches[sensor]) for sensor in (1, 2, 3, 0)]
        if final:
            self.finish()
        return _join([o[0] for o in out if len(o[0])], [o[1] for o in out if len(o[0])])

    def clocks(self) -> tuple[ClockEstimate, ...]:
        return self.resampler.clocks()

    def finish(self) -> None:
        """Count the instants no stream end can resolve (:meth:`Resampler.finish`)."""
        self.resampler.finish()


def set_former(timebase: TimeBase) -> _BatchMatcher | _BatchResampler:
    if timebase.sync == 'nearest':
        return _BatchMatcher(StampMatcher(int(round(timebase.tolerance_s * NS_PER_S))))
    return _BatchResampler(timebase)


def _join(stamps: list[np.ndarray], fields: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    if not stamps:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 3))
    return np.concatenate(stamps), np.concatenate(fields)
