"""The tensor node's stream checks, message by message, on the bounds of
:mod:`~tetra_gradiometer.core.streams` (the offline checks): drop and count, never raise."""

from __future__ import annotations

import numpy as np

from .streams import EARTH_RANGE_T, MAGNITUDE_FACTOR, magnitude_mismatch
from .units import NS_PER_S

__all__ = ['LiveStreamCheck']

#: A sensor's last MAX_INTERVALS intervals (up to a silence, gaps too: a window of its own
#: choosing could lock onto a wrong rate) give its period, every MIN_INTERVALS. Regular
#: stamps (the median interval at least half the mean) have the median as period and usual
#: interval: robust to losing a third of the messages, and to stalls that catch up. Stamps
#: taken on arrival come in bursts: the period is the mean interval and the usual one the
#: window's longest (a burst's boundary is no loss); there only gaps longer than any recent
#: interval are counted, fewer than were lost, never more. A gap is an interval over
#: LOSS_FACTOR usual ones; it misses (gap - usual) / period messages, less what the regular
#: stream's next intervals under a period make up (1 - interval / period each, within twice
#: the gap's periods: the late messages of a stall that catches up).
MIN_INTERVALS = 8
MAX_INTERVALS = 128
LOSS_FACTOR = 1.5


class LiveStreamCheck:
    """The tensor node's per-message checks (drop and count, never raise): a zero stamp, a
    stamp more than ``tolerance_s`` from the stamps the other sensors sent in the last
    ``recent_s``, accepted or not (another epoch or clock, a jump on one sensor; when every
    source restarts, the median of the others is on the new clock once two have moved), a
    repeated stamp with another reading; and each sensor's recent |B|
    against the Earth's range (:meth:`magnitude_text`).

    Counts per sensor in :attr:`dropped`: ``{'zero_stamp': n, 'other_clock': n,
    'duplicate_stamp': n}``; in :attr:`missing` the messages that never arrived, by the gaps in
    its stamps against its own period (gaps up to ``silence_s``: a longer one is a silence,
    which the node names stale). Times: stamps and ``now_ns`` (the node's clock) in ns.
    """

    KINDS = ('zero_stamp', 'other_clock', 'duplicate_stamp')

    def __init__(
        self,
        tolerance_s: float = 10.0,
        recent_s: float = 2.0,
        history: int = 64,
        silence_s: float = 1.0,
    ) -> None:
        self.tolerance_ns = tolerance_s * NS_PER_S
        self.silence_ns = silence_s * NS_PER_S
        self.recent_ns = recent_s * NS_PER_S
        self.dropped = [dict.fromkeys(self.KINDS, 0) for _ in range(4)]
        self._gaps = [0.0] * 4  # periods the gaps in the stamps miss
        self._early = [0.0] * 4  # periods the intervals under a period make up after a gap
        self._owed = [(0.0, 0)] * 4  # a recent gap's periods not yet made up, for n intervals
        self._intervals: list[list[int]] = [[] for _ in range(4)]
        self._period = [0.0] * 4  # the mean of the intervals, ns
        self._usual = [0.0] * 4  # the longest usual interval, ns
        self._norms = [np.zeros(history) for _ in range(4)]
        self._filled = [0] * 4
        self.reset()

    def reset(self) -> None:
        """Forget the last stamps (the source restarted); the counts stay."""
        # Per sensor: the last stamp received (accepted or not) and its arrival on the node's
        # clock: the others' reference; the last reading accepted: for repeated stamps.
        self._seen: list[tuple[int, int] | None] = [None] * 4
        self._last: list[tuple[int, tuple[float, float, float]] | None] = [None] * 4

    def accept(
        self, sensor: int, stamp_ns: int, now_ns: int, x: float, y: float, z: float
    ) -> bool:
        """True if the reading may go on to the set former; else it was counted."""
        if stamp_ns == 0:
            return self._count(sensor, 'zero_stamp')
        others = sorted(
            e[0]
            for j, e in enumerate(self._seen)
            if j != sensor and e is not None and now_ns - e[1] <= self.recent_ns
        )
        self._seen[sensor] = (stamp_ns, now_ns)  # a restart of every source moves them all
        if others and abs(stamp_ns - others[len(others) // 2]) > self.tolerance_ns:
            return self._count(sensor, 'other_clock')
        last = self._last[sensor]
        if last is not None and stamp_ns == last[0] and last[1] != (x, y, z):
            return self._count(sensor, 'duplicate_stamp')
        if last is not None and stamp_ns > last[0]:
            self._count_missing(sensor, stamp_ns - last[0])
        self._last[sensor] = (stamp_ns, (x, y, z))
        norms = self._norms[sensor]
        norms[self._filled[sensor] % len(norms)] = (x * x + y * y + z * z) ** 0.5
        self._filled[sensor] += 1
        return True

    def _count_missing(self, sensor: int, interval_ns: int) -> None:
        """Messages missing between two accepted stamps, by the sensor's own period where
        the gap exceeds its usual intervals (:data:`LOSS_FACTOR`): lost before
        the node (a queue too short, the node or the link too slow) or never sent, which
        nothing else sees."""
        if interval_ns > self.silence_ns:  # a silence (stale), no interval of the clock
            return
        period, usual = self._period[sensor], self._usual[sensor]
        owed, within = self._owed[sensor]
        if period > 0 and interval_ns > LOSS_FACTOR * usual:
            gap = max((interval_ns - usual) / period, 1.0)
            self._gaps[sensor] += gap
            owed, within = owed + gap, int(2 * (owed + gap)) + 2
        elif owed > 0 and usual == period and interval_ns < period:  # regular stamps only
            made_up = min(owed, 1.0 - interval_ns / period)
            self._early[sensor] += made_up
            owed -= made_up
        self._owed[sensor] = (owed, within - 1) if within > 1 else (0.0, 0)
        intervals = self._intervals[sensor]
        intervals.append(interval_ns)
        del intervals[:-MAX_INTERVALS]
        # Every MIN_INTERVALS intervals, not per message (the node's hot path).
        if len(intervals) >= MIN_INTERVALS and self._filled[sensor] % MIN_INTERVALS == 0:
            common, mean = float(np.median(intervals)), float(np.mean(intervals))
            if common >= 0.5 * mean:
                self._period[sensor] = self._usual[sensor] = common
            else:
                self._period[sensor], self._usual[sensor] = mean, float(max(intervals))

    @property
    def missing(self) -> list[int]:
        """Per sensor, the messages that never arrived: those its gaps miss less those that
        came late (a publisher that stalls and then catches up, stamping on sending, loses
        nothing)."""
        return [max(round(g - e), 0) for g, e in zip(self._gaps, self._early, strict=True)]

    def missing_text(self, sensor: int, received: int) -> str:
        """'' or how many messages of ``received`` + missing never reached the node."""
        missing = self.missing[sensor]
        if not missing:
            return ''
        share = missing / max(missing + received, 1)
        return (
            f'{missing} messages missing by their stamps ({share:.1%}): lost before the node '
            'or never sent (a subscription queue too short, or the node, the link or the '
            'driver too slow for the rate)'
        )

    def _count(self, sensor: int, kind: str) -> bool:
        self.dropped[sensor][kind] += 1
        return False

    def magnitude_text(self, sensor: int) -> str:
        """'' or what the sensor's recent median |B| looks like against the Earth's range."""
        n = min(self._filled[sensor], len(self._norms[sensor]))
        if not n:
            return ''
        median = float(np.median(self._norms[sensor][:n]))
        lo, hi = EARTH_RANGE_T
        if lo / MAGNITUDE_FACTOR <= median <= hi * MAGNITUDE_FACTOR or not np.isfinite(median):
            return ''
        return (
            f"median |B| {median:.4g} of the last {n} readings, outside the Earth field's "
            f'{lo * 1e6:.0f}-{hi * 1e6:.0f} µT: {magnitude_mismatch(median / np.sqrt(lo * hi))}'
        )
