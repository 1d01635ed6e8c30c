"""Stamps from the future: a reading stamped ahead of the node's clock is refused
and counted before it reaches the set former, pairing buffer or track.

Why: the set formers keep each input in stamp order, so one message stamped 500 ms ahead
(another process publishing ``mag2``, a node whose clock is wrong) made every real reading
of the next 500 ms "out of order", and they were dropped; an ``odom`` 1 s ahead and 200 m off
moved the track. A reading is a sample time, so it can never be later than the clock of the
node receiving it, give or take the clocks' offset across the vehicle's computers: refused
beyond ``max_stamp_ahead_s`` (default 0.1 s; NTP keeps a vehicle's computers within
milliseconds), it never enters the buffers and so never evicts a real reading.

The clock is the system clock (``time.time_ns``: ~0.1 us per message on the per-sample
path). Under ``use_sim_time`` the check is off: the stamps are then a bag's or a
simulation's, ``/clock`` arrives on its own topic, possibly after the readings it precedes,
and a replay at ``rate`` 0 runs sets ahead of it; ``use_sim_time`` cannot be switched on
while a node is configured.
"""

from __future__ import annotations

import time
from typing import Any

from ..core.units import NS_PER_S, S_PER_NS
from .common import ParamSpec, Throttle
from .publishers import InputPublishers

AHEAD_SPEC = ParamSpec(
    'max_stamp_ahead_s',
    0.1,
    "A message stamped more than this ahead of the node's clock (s, 0.001-3600; the system "
    'clock: off under use_sim_time) is refused and counted, and never evicts a real reading.',
    float_range=(0.001, 3600.0),
)


class StampHorizon:
    """Refuses stamps more than ``tolerance_s`` ahead of the system clock (off under
    ``use_sim_time``); counts them per input and warns (throttled) naming the publishers."""

    def __init__(self, node: Any, tolerance_s: float, warn_throttle_s: float = 5.0) -> None:
        self.node = node
        self.tolerance_s = float(tolerance_s)
        self.tolerance_ns = int(round(tolerance_s * NS_PER_S))
        self.enabled = not node.get_parameter('use_sim_time').value
        self.refused: dict[str, int] = {}
        self._warn = Throttle(warn_throttle_s)

    def refuse(self, topic: str, stamp_ns: int) -> bool:
        """True when the message of ``topic`` (as the node names it) stamped ``stamp_ns``
        must be dropped: counted, and a throttled WARN names its publishers."""
        if not self.enabled:
            return False
        ahead_ns = stamp_ns - time.time_ns()
        if ahead_ns <= self.tolerance_ns:
            return False
        self.refused[topic] = self.refused.get(topic, 0) + 1
        if self._warn():
            resolved = self.node.resolve_topic_name(topic)
            names = ', '.join(InputPublishers(self.node).publishers(resolved)) or 'none seen'
            self.node.get_logger().warning(
                f'refused a {resolved} message stamped {ahead_ns * S_PER_NS:.3f} s ahead of the '
                f'clock (max_stamp_ahead_s {self.tolerance_s:g}; {self.refused[topic]} so far): '
                f'a wrong clock or another publisher (publishers: {names})'
            )
        return True

    def values(self) -> dict[str, Any]:
        """``/diagnostics`` values: ``refused_future <topic>`` per input that had one."""
        return {f'refused_future {topic}': n for topic, n in sorted(self.refused.items())}
