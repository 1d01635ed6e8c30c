"""The compensator's calibration tracker (``track_calibration``): core/tracking.py per message,
with ``odom``'s attitude, its audit trail on a topic and its state on ``/diagnostics``.

The tracker is made at the first set after a calibration: with the attitude (all nine
offset combinations, the world gradient beside them) when ``odom`` (nav_msgs/Odometry) has
been heard by then, else the four combinations the constraints observe, as ``compensate``
chooses from the bag's ``/odom``. Each closed block's verdict and every step go out on
``calibration/tracking`` (std_msgs/String, one JSON object per event, the entries of
``compensate --report``'s ``tracking.json``: ``t_s`` the stamp, s; offsets in nT), so what
the tracker did can be read, recorded and undone (``track_calibration`` false).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from nav_msgs.msg import Odometry
from std_msgs.msg import String

from ..core.model import InterferenceParameters
from ..core.tracking import OffsetTracker
from ..core.units import NT_PER_T, S_PER_NS
from ..io import conversions as cv
from ..pipelines.window_check import AttitudeHistory
from .common import derived_qos, latched_qos

#: odom messages kept for the attitude (a minute at 50 Hz; a block needs 0.5 s).
MAX_ODOM_MESSAGES = 3000


class LiveTracking:
    """The tracker of one node (a lifecycle node's ``configure``): subscribes ``odom``,
    publishes ``calibration/tracking``; ``gated`` wraps callbacks to run only while active."""

    def __init__(self, node: Any, gated: Any, horizon: Any) -> None:
        self._node, self._horizon = node, horizon
        self._odom = AttitudeHistory(length=MAX_ODOM_MESSAGES)
        self._model: tuple[Any, InterferenceParameters, float] | None = None
        self._learn_after_ns: int | None = None
        self.tracker: OffsetTracker | None = None
        self._sent, self._last_ns = 0, 0
        self._pub = node.create_lifecycle_publisher(
            String, 'calibration/tracking', latched_qos(depth=100)
        )
        node.create_subscription(Odometry, cv.ODOM_NODE_TOPIC, gated(self._on_odom), derived_qos())

    def start(
        self, geometry: Any, parameters: Any, noise: float, learn_after_ns: int | None = None
    ) -> None:
        """Track ``parameters`` afresh (None: no calibration, nothing tracked), learning only
        from sets stamped after ``learn_after_ns`` (the calibration's last fitted set,
        pipelines/tracking.learn_after_ns: compensate's rule)."""
        self._model = None if parameters is None else (geometry, parameters, noise)
        self._learn_after_ns = learn_after_ns
        self.tracker, self._sent = None, 0

    def one(self, stamp_ns: int, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``g`` (3, 3) T/m compensated with the calibration -> tracked, and the state's
        variance (9,) (T/m)^2 (zeros while nothing is tracked). A stamp before the last (a
        replay started again) starts the tracker afresh."""
        if self._model is None or (
            self._learn_after_ns is not None and stamp_ns <= self._learn_after_ns
        ):
            return g, np.zeros(9)
        if self.tracker is not None and stamp_ns < self._last_ns:  # a replay started again
            self.tracker, self._sent = None, 0
        self._last_ns = stamp_ns
        if self.tracker is None:
            geometry, parameters, noise = self._model
            world = len(self._odom) > 0
            # The node's health monitor hands the steps over (nodes/compensator.py).
            self.tracker = OffsetTracker(
                geometry, parameters, noise, with_world=world, monitored=True
            )
            self._node.get_logger().info(
                'tracking the calibration '
                + ('with the attitude of odom' if world else 'without the attitude (no odom yet)')
            )
        tracked = self.tracker.one(stamp_ns * S_PER_NS, g, self._attitude)
        if len(self.tracker.events) > self._sent:
            for event in self.tracker.events[self._sent :]:
                self._pub.publish(String(data=json.dumps(event.to_dict())))
            self._sent = len(self.tracker.events)
        return tracked

    def step(self, sensors: tuple[int, ...], t_s: float) -> None:
        """A step the health monitor found at ``t_s`` (s, the sets' stamps)."""
        if self.tracker is not None:
            self.tracker.step(sensors, t_s)

    def values(self) -> dict[str, Any]:
        """For ``/diagnostics``: how it tracks, the largest offset change and its 1-sigma (nT),
        the steps so far and the last one."""
        tracker = self.tracker
        if tracker is None:
            return {'tracking': 'waiting for a set' if self._model else 'off: no calibration'}
        steps = [e for e in tracker.events if e.kind == 'step']
        values: dict[str, Any] = {
            'tracking': 'with the attitude' if tracker.with_world else 'without the attitude',
            'tracked_offset_change_nT': float(np.abs(tracker.offsets_t).max() * NT_PER_T),
            'tracked_offset_sigma_nT': float(tracker.offsets_sigma_t.max() * NT_PER_T),
            'tracked_steps': len(steps),
        }
        last = steps[-1].to_dict() if steps else {}
        if 'step_nT' in last:
            values['last_step'] = (
                f'sensor {last["sensors"][0]} at {last["t_s"]:.2f} s: '
                f'{np.linalg.norm(last["step_nT"]):.3g} nT '
                f'(1-sigma {max(last["step_sigma_nT"]):.2g} nT per axis)'
            )
        return values

    def _attitude(self, t_s: np.ndarray) -> np.ndarray:
        """odom's quaternions (k, 4) at ``t_s`` (k,) s, NaN where unknown."""
        return self._odom.over(np.round(np.asarray(t_s) * 1e9).astype(np.int64))

    def _on_odom(self, msg: Any) -> None:
        stamp_ns = cv.stamp_to_ns(msg.header.stamp)
        if not self._horizon.refuse(cv.ODOM_NODE_TOPIC, stamp_ns):
            self._odom.add(stamp_ns, cv.odometry_orientation(msg))
