"""The target node's live survey track: compensated tensors averaged over sample periods,
the odometry pose interpolated onto each one, a bounded history and the count of completed
passes: the :class:`~tetra_gradiometer.core.targets.Survey` that ``locate`` searches.

Choices:

* **Rate.** Tensors are averaged over bins of ``1 / sample_rate_hz`` (bin ``k`` holds the
  stamps in ``[k, k + 1)`` periods since the epoch; its stamp is their mean): the detector
  and the fit need no more than 10 Hz at survey speeds, and an hour at the chain's 200 Hz
  would hold 720 000 samples and take minutes to search. The mean is an anti-alias filter:
  the noise of the averaged tensor falls as the square root of the samples per bin. A bin
  closes when a sample of a later bin arrives.
* **Pose.** A bin waits until odometry reaches its stamp (or until the tensors are
  :data:`ODOM_WAIT_S` past it: odometry late or gone), then takes the position interpolated
  linearly and the orientation slerped between the messages around it, held at the ends, as
  the calibrator and ``calibrate`` do (:func:`~.window_check.orientation_at`). A bin whose
  nearest message is more than :data:`~.window_check.MAX_ODOM_GAP_S` away is dropped and
  counted (``dropped_no_odom``).
* **Drops.** A non-finite tensor, a stamp not after the previous one (``dropped_...``); an
  odometry message with a zero-norm or non-finite quaternion or a non-finite position (the
  offline rule: :class:`~tetra_gradiometer.core.odometry.LiveOdometryCheck`, which also
  normalizes and counts an unnormalized one) or an old stamp (``odom_dropped``). A stamp
  more than :data:`JUMP_BACK_S` before the previous one (a new replay) starts a new track
  (``restarts``).
* **Passes.** The straight legs are cut as ``core.targets.legs`` cuts them (heading off the
  leg's first heading by more than ``max_turn_deg``, a step over ``max_step_m``, a gap over
  ``max_gap_s``); a leg of at least ``min_leg_s`` that ends is a completed pass.
* **History.** Samples older than ``history_s`` before the newest are forgotten.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.odometry import LiveOdometryCheck
from ..core.targets import DetectorSettings, Survey
from ..core.targets.detection import ends_leg, headings
from ..core.types import FloatArray, IntArray
from ..core.units import NS_PER_S, S_PER_NS
from ..io import conversions as cv
from ..pipelines.window_check import orientation_at

#: A tensor or odometry stamp this far before the previous one starts a new track, s.
JUMP_BACK_S = 1.0
#: A bin waits for odometry until the tensors are this far past its stamp, s.
ODOM_WAIT_S = 10.0


@dataclass
class TrackCounts:
    """Running counts of a :class:`SurveyTrack` (tensor samples unless named odometry)."""

    received: int = 0
    dropped_non_finite: int = 0
    dropped_out_of_order: int = 0
    dropped_no_odom: int = 0
    odom_dropped: int = 0
    restarts: int = 0
    passes: int = 0


@dataclass(frozen=True)
class TrackSnapshot:
    """A copy of the track: the ``survey`` (times in s from ``t0_ns``), the orientations
    (N, 4) x, y, z, w behind its rotations, and the stamps of its first and last sample
    (integer ns)."""

    survey: Survey
    orientation_xyzw: FloatArray
    t0_ns: int
    last_ns: int


class SurveyTrack:
    """The bounded, pose-resolved track of one survey (module docstring).

    Parameters
    ----------
    sample_rate_hz : rate of the averaged samples, Hz
    history_s : samples older than this before the newest are forgotten, s
    legs : where the straight legs end (``max_turn_deg``, ``max_step_m``, ``max_gap_s``,
        ``min_leg_s``: the detector's own settings)
    """

    def __init__(self, *, sample_rate_hz: float, history_s: float, legs: DetectorSettings) -> None:
        self._period_ns = max(1, round(NS_PER_S / sample_rate_hz))
        self._history_ns = round(history_s * NS_PER_S)
        self._legs = legs
        self.counts = TrackCounts()
        self.odom_check = LiveOdometryCheck()
        #: Samples added since construction (a restart does not reset it).
        self.added = 0
        self._odom_t: deque[int] = deque()
        self._odom_pose: deque[FloatArray] = deque()
        self._restart()

    def _restart(self) -> None:
        self._bin: list[tuple[int, FloatArray]] = []
        self._bin_index = 0
        self._pending: deque[tuple[int, FloatArray]] = deque()
        self._last_ns: int | None = None
        self._t: deque[int] = deque()
        self._q: deque[FloatArray] = deque()
        self._r: deque[FloatArray] = deque()
        self._p: deque[FloatArray] = deque()
        self._g: deque[FloatArray] = deque()
        self._leg: tuple[int, float, int, FloatArray] | None = None  # start, heading, last

    def __len__(self) -> int:
        return len(self._t)

    @property
    def pending(self) -> int:
        """Samples received and not yet resolved (open bin and bins waiting for odometry)."""
        return len(self._bin) + len(self._pending)

    # ------------------------------------------------------------------ input

    def add_tensor(self, stamp_ns: int, g: FloatArray) -> str | None:
        """One compensated tensor (3, 3) T/m, body frame, at ``stamp_ns``; the reason it is
        dropped (counted), or None."""
        self.counts.received += 1
        if not np.all(np.isfinite(g)):
            self.counts.dropped_non_finite += 1
            return 'a non-finite tensor'
        if self._last_ns is not None and stamp_ns <= self._last_ns:
            if (self._last_ns - stamp_ns) * S_PER_NS <= JUMP_BACK_S:
                self.counts.dropped_out_of_order += 1
                return 'a tensor stamp not after the previous one'
            self.counts.restarts += 1
            self._restart()
        self._last_ns = stamp_ns
        index = stamp_ns // self._period_ns
        if self._bin and index != self._bin_index:
            self._close_bin()
        self._bin_index = index
        self._bin.append((stamp_ns, np.asarray(g, dtype=float)))
        return None

    def _close_bin(self) -> None:
        stamps = [stamp for stamp, _ in self._bin]
        stamp = stamps[0] + round(sum(s - stamps[0] for s in stamps) / len(stamps))
        self._pending.append((stamp, np.mean([g for _, g in self._bin], axis=0)))
        self._bin = []

    def add_odom(self, stamp_ns: int, pose: FloatArray) -> str | None:
        """One odometry pose (7,): position (3,) m, orientation (4,) x, y, z, w (body ->
        odom) at ``stamp_ns``; the reason it is dropped (counted), or None."""
        pose = np.array(pose, dtype=float)
        orientation = self.odom_check.accept(pose[cv.POSE_ORIENTATION], pose[cv.POSE_POSITION])
        if orientation is None:
            self.counts.odom_dropped += 1
            return 'an odometry pose with a zero-norm or non-finite orientation or position'
        pose[cv.POSE_ORIENTATION] = orientation
        if self._odom_t and stamp_ns <= self._odom_t[-1]:
            if (self._odom_t[-1] - stamp_ns) * S_PER_NS <= JUMP_BACK_S:
                self.counts.odom_dropped += 1
                return 'an odometry stamp not after the previous one'
            self._odom_t.clear()
            self._odom_pose.clear()
        self._odom_t.append(stamp_ns)
        self._odom_pose.append(pose)
        return None

    # ------------------------------------------------------------------ resolution

    def resolve(self) -> int:
        """Give the waiting bins their pose (module docstring); return how many were added
        to the track (the others that were ready are dropped and counted)."""
        if not self._pending:
            return 0
        stamps = np.array([stamp for stamp, _ in self._pending], dtype=np.int64)
        waited = stamps < stamps[-1] - round(ODOM_WAIT_S * NS_PER_S)
        reached = stamps <= (self._odom_t[-1] if self._odom_t else stamps[0] - 1)
        n = int(np.sum(waited | reached))  # a prefix: the stamps increase
        if n == 0:
            return 0
        taken = [self._pending.popleft()[1] for _ in range(n)]
        t = stamps[:n]
        positions, orientation = self._poses(t)
        known = np.flatnonzero(np.all(np.isfinite(orientation), axis=1))
        self.counts.dropped_no_odom += n - len(known)
        if len(known):
            rotations = Rotation.from_quat(orientation[known]).as_matrix()
            for k, i in enumerate(known):
                self._append(int(t[i]), positions[i], orientation[i], rotations[k], taken[i])
        self._forget(int(t[-1]))
        return len(known)

    def _poses(self, t: IntArray) -> tuple[FloatArray, FloatArray]:
        """Positions (n, 3) and orientations (n, 4) at ``t`` (NaN where unknown)."""
        if not self._odom_t:
            return np.full((len(t), 3), np.nan), np.full((len(t), 4), np.nan)
        odom_t = np.array(self._odom_t, dtype=np.int64)
        pose = np.array(self._odom_pose)
        since = ((t - odom_t[0]) * S_PER_NS, (odom_t - odom_t[0]) * S_PER_NS)
        positions = np.column_stack([np.interp(*since, c) for c in pose[:, cv.POSE_POSITION].T])
        return positions, orientation_at(odom_t, pose[:, cv.POSE_ORIENTATION], t)

    def _append(
        self, stamp_ns: int, p: FloatArray, q: FloatArray, r: FloatArray, g: FloatArray
    ) -> None:
        self._end_of_leg(stamp_ns, p, float(headings(r[None])[0]))
        self._t.append(stamp_ns)
        self._p.append(p)
        self._q.append(q)
        self._r.append(r)
        self._g.append(g)
        self.added += 1

    def _end_of_leg(self, stamp_ns: int, p: FloatArray, heading: float) -> None:
        """Follow the current leg; count a pass when a leg of ``min_leg_s`` ends."""
        legs, leg = self._legs, self._leg
        if leg is not None:
            start, first_heading, last, last_p = leg
            cut = ends_leg(
                legs,
                heading - first_heading,
                float(np.linalg.norm(p - last_p)),
                (stamp_ns - last) * S_PER_NS,
            )
            if cut and (last - start) * S_PER_NS >= legs.min_leg_s:
                self.counts.passes += 1
            if not cut:
                self._leg = (start, first_heading, stamp_ns, p)
                return
        self._leg = (stamp_ns, heading, stamp_ns, p)

    def _forget(self, newest_ns: int) -> None:
        """Drop samples beyond the history and odometry no later bin can need."""
        while self._t and newest_ns - self._t[0] > self._history_ns:
            for column in (self._t, self._p, self._q, self._r, self._g):
                column.popleft()
        while len(self._odom_t) >= 2 and self._odom_t[1] <= newest_ns:
            self._odom_t.popleft()
            self._odom_pose.popleft()

    # ------------------------------------------------------------------ output

    def snapshot(self) -> TrackSnapshot | None:
        """A copy of the track (None while empty)."""
        if not self._t:
            return None
        t = np.array(self._t, dtype=np.int64)
        survey = Survey(
            (t - t[0]) * S_PER_NS, np.array(self._p), np.array(self._r), np.array(self._g)
        )
        return TrackSnapshot(survey, np.array(self._q), int(t[0]), int(t[-1]))
