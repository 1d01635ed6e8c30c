"""Odometry checked before use: the one place that decides whether ``/odom``'s pose may be
used, and says what is wrong with it otherwise.

Checks, on the pose messages ``stamps_ns`` (m,) and ``pose`` (m, 7): position x, y, z (m,
ENU) then the orientation x, y, z, w (body -> ENU):

* **zero-norm or non-finite quaternions** (an unfilled orientation, common in real bags):
  dropped and counted; more than half of them and the orientation is not used.
* **unnormalized quaternions** (``| |q| - 1 | >`` :data:`NORM_TOLERANCE`): normalized (the
  same rotation) and counted.
* **a frozen pose**: the orientation (and the position) does not change over the recording.
* **agreement with the magnetometers**: a right attitude turns the body-frame field of
  sensor 1 into a world-frame field that stays put while the vehicle turns; a frozen or an
  identity attitude does not. The test fits ``b_body(t) = R(t)^T w + c`` (``w`` a constant
  world field, ``c`` a constant body-frame offset: the vehicle's permanent field at sensor 1)
  by least squares and compares the residual's RMS with the body field's own variation about
  its mean: the ratio is the share of the measured rotation the attitude does not explain
  (noise and the vehicle's induced field: a few percent with a right attitude; ~100 % with a
  frozen or identity one). Above :data:`MAX_UNEXPLAINED` the orientation is not used. The
  test needs the field to turn: below :data:`MIN_BODY_VARIATION` of ``|B|`` (about 3 degrees
  of rotation) it is not made, and the note says so.

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
    'MAX_UNEXPLAINED',
    'MIN_BODY_VARIATION',
    'NORM_TOLERANCE',
    'LiveOdometryCheck',
    'OdometryCheck',
    'attitude_agreement',
    'check_odometry',
    'pose_faults',
]

BoolArray = npt.NDArray[np.bool_]

#: A quaternion whose norm differs from 1 by more than this is counted as unnormalized.
NORM_TOLERANCE = 1e-3
#: Below this norm (or non-finite) a quaternion is no rotation: the orientation is unknown.
ZERO_NORM = 1e-6
#: Largest share of the body field's variation the attitude may leave unexplained.
MAX_UNEXPLAINED = 0.5
#: Smallest RMS variation of the body-frame field, as a fraction of its mean |B|, that
#: tests the attitude (0.05: about 3 degrees of rotation).
MIN_BODY_VARIATION = 0.05
#: Pose changes below these over the whole recording are a frozen pose.
FROZEN_ANGLE_RAD = 1e-6
FROZEN_POSITION_M = 1e-6
#: The attitude test thins to at most this many samples.
AGREEMENT_SAMPLES = 5000


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
    """Norms and a frozen pose (:func:`attitude_agreement` is the test against the
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
    return OdometryCheck(stamps, pose, not frozen_orientation, not frozen_position, tuple(faults))


def attitude_agreement(orientation_xyzw: FloatArray, body_field_t: FloatArray) -> float:
    """The share of the body field's variation the attitude leaves unexplained (see the
    module docstring), or NaN when the field turns too little to tell.

    Parameters
    ----------
    orientation_xyzw : (n, 4) body -> ENU, unit quaternions, at the field's instants
    body_field_t : (n, 3) T, sensor 1's field in the body frame
    """
    from scipy.spatial.transform import Rotation  # only the attitude paths need scipy.spatial

    step = max(1, len(body_field_t) // AGREEMENT_SAMPLES)
    b = np.asarray(body_field_t, dtype=float)[::step]
    q = np.asarray(orientation_xyzw, dtype=float)[::step]
    ok = np.all(np.isfinite(b), axis=1) & np.all(np.isfinite(q), axis=1)
    b, q = b[ok], q[ok]
    if len(b) < 10:
        return float('nan')
    variation = float(np.sqrt(np.mean(np.sum((b - b.mean(axis=0)) ** 2, axis=1))))
    if variation < MIN_BODY_VARIATION * float(np.mean(np.linalg.norm(b, axis=1))):
        return float('nan')
    to_body = Rotation.from_quat(q).as_matrix().transpose(0, 2, 1)  # (n, 3, 3) R^T
    design = np.concatenate([to_body, np.broadcast_to(np.eye(3), to_body.shape)], axis=2)
    solution, *_ = np.linalg.lstsq(design.reshape(-1, 6), b.reshape(-1), rcond=None)
    residual = b.reshape(-1) - design.reshape(-1, 6) @ solution
    return float(np.sqrt(np.mean(residual**2) * 3) / variation)


def agreement_fault(unexplained: float) -> str | None:
    """The fault line for :func:`attitude_agreement`'s ratio (None when it agrees or was
    not tested)."""
    if not unexplained > MAX_UNEXPLAINED:
        return None
    return (
        'the /odom orientation does not agree with the magnetometers: rotated into ENU by it, '
        f"sensor 1's field still varies by {unexplained:.0%} of its body-frame variation "
        f'(a right attitude leaves a few %, a frozen or identity one ~100 %; at most '
        f'{MAX_UNEXPLAINED:.0%} accepted)'
    )


#: The note when the field turns too little to test the attitude against it.
UNTESTED_ATTITUDE = (
    'the /odom orientation was not checked against the magnetometers (the field turns by '
    'less than about 3 degrees)'
)

#: What each command loses without the orientation or the position, for its notes.
COSTS = {
    'calibrate': 'no regional gradient (assumed zero) and coverage from the body-frame field',
    'discrepancy': "B^b taken as B_1' (no Earth field through /odom)",
    'locate': 'no targets',
}
