"""The tensor node's stream checks, message by message, on the bounds of
:mod:`~tetra_gradiometer.core.streams` (the offline checks): drop and count, never raise."""

from __future__ import annotations

import numpy as np

from .streams import EARTH_RANGE_T, MAGNITUDE_FACTOR, magnitude_mismatch
from .units import NS_PER_S

__all__ = ['LiveStreamCheck']


class LiveStreamCheck:
    """The tensor node's per-message checks (drop and count, never raise): a zero stamp, a
    stamp more than ``tolerance_s`` from the stamps the other sensors sent in the last
    ``recent_s``, accepted or not (another epoch or clock, a jump on one sensor; when every
    source restarts, the median of the others is on the new clock once two have moved), a
    repeated stamp with another reading; and each sensor's recent |B|
    against the Earth's range (:meth:`magnitude_text`).

    Counts per sensor in :attr:`dropped`: ``{'zero_stamp': n, 'other_clock': n,
    'duplicate_stamp': n}``. Times: stamps and ``now_ns`` (the node's clock) in ns.
    """

    KINDS = ('zero_stamp', 'other_clock', 'duplicate_stamp')

    def __init__(
        self, tolerance_s: float = 10.0, recent_s: float = 2.0, history: int = 64
    ) -> None:
        self.tolerance_ns = tolerance_s * NS_PER_S
        self.recent_ns = recent_s * NS_PER_S
        self.dropped = [dict.fromkeys(self.KINDS, 0) for _ in range(4)]
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
        self._last[sensor] = (stamp_ns, (x, y, z))
        norms = self._norms[sensor]
        norms[self._filled[sensor] % len(norms)] = (x * x + y * y + z * z) ** 0.5
        self._filled[sensor] += 1
        return True

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
