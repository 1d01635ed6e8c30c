"""Odometry checked before use: the one place that decides whether ``/odom``'s pose may be
used, and says what is wrong with it otherwise.

Checks, on the pose messages ``stamps_ns`` (m,) and ``pose`` (m, 7): position x, y, z (m,
ENU) then the orientation x, y, z, w (body -> ENU):

* **zero-norm or non-finite quaternions** (an unfilled orientation, common in real bags):
  dropped and counted; more than half of them and the orientation is not used.
* **unnormalized quaternions** (``| |q| - 1 | >`` :data:`NORM_TOLERANCE`): normalized (the
  same rotation) and counted.
* **a frozen pose**: the orientation (and the position) does not change over the recording.
* **jumps of the position** (:func:`position_jumps`): two navigation sources, a fix after a
  dive.
* **agreement with the magnetometers**: :mod:`.attitude` (the attitude's convention, lag
  and clock, from the field it turns), where the fields are known.

A command that finds the orientation or the position unusable goes on without it and says
what that costs (:data:`COSTS`), or refuses with one line when it cannot go on (``locate``
needs the track).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .types import FloatArray
from .units import S_PER_NS

__all__ = [
    'NORM_TOLERANCE',
    'LiveOdometryCheck',
    'OdometryCheck',
    'check_odometry',
    'pose_faults',
    'position_jumps',
]

BoolArray = npt.NDArray[np.bool_]

#: A quaternion whose norm differs from 1 by more than this is counted as unnormalized.
NORM_TOLERANCE = 1e-3
#: Below this norm (or non-finite) a quaternion is no rotation: the orientation is unknown.
ZERO_NORM = 1e-6
#: Pose changes below these over the whole recording are a frozen pose.
FROZEN_ANGLE_RAD = 1e-6
FROZEN_POSITION_M = 1e-6
#: A step of the /odom position larger than both of these (m, and times the median step)
#: is a jump.
JUMP_M = 2.0
JUMP_STEPS = 20.0


@dataclass(frozen=True)
class OdometryCheck:
    """The verdict on ``/odom``.

    Attributes
    ----------
    stamps_ns : (m,) the messages kept, ns
    pose : (m, 7) their pose, quaternions normalized
    orientation_ok, position_ok : whether the orientation, the position may be used
    faults : what was found, one line each (named with the span, s from the first message)
    unexplained : the attitude test's ratio (NaN when not made)
    """

    stamps_ns: np.ndarray
    pose: FloatArray
    orientation_ok: bool
    position_ok: bool
    faults: tuple[str, ...] = ()
    unexplained: float = float('nan')

    def text(self) -> str:
        return '; '.join(self.faults)


def pose_faults(
    orientation_xyzw: FloatArray, position: FloatArray | None = None
) -> tuple[BoolArray, BoolArray, FloatArray]:
    """The rule on m ``/odom`` messages, offline and live: which carry no pose (a zero-norm or
    non-finite quaternion, or a non-finite ``position`` when one is given: dropped), which
    quaternions are unnormalized (normalized, the same rotation), and their norms.

    ``orientation_xyzw`` (m, 4); ``position`` (m, 3) m or None (not checked); returns (m,)
    bool, (m,) bool, (m,) float.
    """
    norms = np.linalg.norm(orientation_xyzw, axis=1)
    zero = ~np.isfinite(norms) | (norms < ZERO_NORM)
    if position is not None:
        zero |= ~np.all(np.isfinite(position), axis=1)
    unnormalized = ~zero & (np.abs(norms - 1.0) > NORM_TOLERANCE)
    return zero, unnormalized, norms


class LiveOdometryCheck:
    """The nodes' ``/odom`` check, message by message, on :func:`pose_faults` (the rule of
    :func:`check_odometry`): drop and count, normalize and count, never raise.

    :attr:`dropped`, :attr:`normalized`: counts since construction; :meth:`report` says what
    changed since its previous call (the nodes' ``/diagnostics`` WARN text).
    """

    def __init__(self) -> None:
        self.dropped = 0
        self.normalized = 0
        self._norms = (np.inf, 0.0)  # the least and the largest norm normalized
        self._reported = (0, 0)
        self._position_checked = False

    def accept(
        self, orientation_xyzw: FloatArray, position: FloatArray | None = None
    ) -> FloatArray | None:
        """The orientation (4,) x, y, z, w as a unit quaternion, or None: dropped (counted).
        ``position`` (3,) m is checked when given (a node that reads only the attitude
        keeps an orientation whose position is unknown)."""
        q = np.asarray(orientation_xyzw, dtype=float).reshape(1, 4)
        p = None if position is None else np.asarray(position, dtype=float).reshape(1, 3)
        self._position_checked |= p is not None
        zero, unnormalized, norms = pose_faults(q, p)
        if zero[0]:
            self.dropped += 1
            return None
        norm = float(norms[0])
        if unnormalized[0]:
            self.normalized += 1
            self._norms = (min(self._norms[0], norm), max(self._norms[1], norm))
        return q[0] / norm

    def values(self) -> dict[str, int]:
        """The counts, for ``/diagnostics``."""
        return {'odom_dropped_zero_norm': self.dropped, 'odom_normalized': self.normalized}

    def report(self) -> str:
        """'' or, when messages were dropped or normalized since the previous report, what."""
        dropped, normalized = (
            self.dropped - self._reported[0],
            self.normalized - self._reported[1],
        )
        self._reported = (self.dropped, self.normalized)
        parts = []
        if dropped:
            what = 'orientation or position' if self._position_checked else 'orientation'
            parts.append(
                f'{dropped} odometry message{"s" * (dropped > 1)} with a zero-norm or non-finite '
                f'{what} dropped (an unfilled orientation; {self.dropped} in all)'
            )
        if normalized:
            low, high = self._norms
            norm = f'{low:.3g}' if f'{low:.3g}' == f'{high:.3g}' else f'{low:.3g}-{high:.3g}'
            parts.append(
                f'{normalized} odometry orientation{"s" * (normalized > 1)} not of unit norm '
                f'(norm {norm}) normalized ({self.normalized} in all)'
            )
        return '; '.join(parts)


def check_odometry(stamps_ns: np.ndarray, pose: FloatArray) -> OdometryCheck:
    """Norms and a frozen pose (:mod:`.attitude` is the test against the
    magnetometers, made where the fields are known)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    pose = np.array(pose, dtype=float, copy=True)
    faults: list[str] = []
    t = (stamps - (stamps[0] if len(stamps) else 0)) * S_PER_NS
    zero, unnormalized, norms = pose_faults(pose[:, 3:7], pose[:, :3])
    if zero.any():
        faults.append(
            f'{int(zero.sum())} of {len(stamps)} /odom messages have a zero-norm or non-finite '
            f'pose (an unfilled orientation; {t[zero][0]:.1f}-{t[zero][-1]:.1f} s): dropped'
        )
    if unnormalized.any():
        faults.append(
            f'{int(unnormalized.sum())} /odom orientations are not unit quaternions (norm '
            f'{norms[unnormalized].min():.3g}-{norms[unnormalized].max():.3g}): normalized'
        )
    keep = ~zero
    stamps, pose = stamps[keep], pose[keep]
    pose[:, 3:7] /= norms[keep, None]
    usable = len(stamps) >= 2 and zero.sum() <= 0.5 * len(zero)
    if not usable:
        faults.append('too few /odom messages with a pose are left: /odom is not used')
        return OdometryCheck(stamps, pose, False, False, tuple(faults))
    span = (stamps[-1] - stamps[0]) * S_PER_NS
    # q and -q are one rotation: the angle between two is 2 acos(|q1 . q2|).
    dots = np.clip(np.abs(pose[:, 3:7] @ pose[0, 3:7]), 0.0, 1.0)
    frozen_orientation = float(2 * np.arccos(dots.min())) < FROZEN_ANGLE_RAD
    frozen_position = float(np.ptp(pose[:, :3], axis=0).max()) < FROZEN_POSITION_M
    if frozen_orientation:
        faults.append(
            f'the /odom orientation is frozen (unchanged over {span:.1f} s, {len(stamps)} '
            'messages)'
        )
    if frozen_position:
        faults.append(
            f'the /odom position is frozen (unchanged over {span:.1f} s, {len(stamps)} messages)'
        )
    jumps = position_jumps(t, pose[:, :3])
    if jumps:
        faults.append(jumps)
    return OdometryCheck(stamps, pose, not frozen_orientation, not frozen_position, tuple(faults))


def position_jumps(t_s: FloatArray, position_m: FloatArray) -> str:
    """'' or the jumps of the /odom position: steps of more than :data:`JUMP_M` and
    :data:`JUMP_STEPS` times the median step (two navigation sources, a fix after a dive), with
    their times (s from the first message). A vehicle moves smoothly at a few m/s."""
    if len(t_s) < 3:
        return ''
    steps = np.linalg.norm(np.diff(position_m, axis=0), axis=1)
    median = float(np.median(steps))
    jumps = np.flatnonzero(steps > max(JUMP_M, JUMP_STEPS * median))
    if not len(jumps):
        return ''
    where = ', '.join(f'{steps[j]:.1f} m at {t_s[j + 1]:.1f} s' for j in jumps[:3])
    more = f' and {len(jumps) - 3} more' if len(jumps) > 3 else ''
    return (
        f'the /odom position jumps {len(jumps)} time{"s" * (len(jumps) > 1)} ({where}{more}; '
        f'its median step is {median:.2f} m): two navigation sources, or a fix after a dive? '
        'Targets and grids near a jump are misplaced'
    )


#: What each command loses without the orientation or the position, for its notes.
COSTS = {
    'calibrate': 'no regional gradient (assumed zero) and coverage from the body-frame field',
    'discrepancy': "B^b taken as B_1' (no Earth field through /odom)",
    'locate': 'no targets',
    'survey': 'no survey (its products are gridded on the track)',
}
