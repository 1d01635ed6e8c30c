"""The ``/odom`` attitude against the magnetometers: which convention, lag and clock it
was published in, from the field it turns.

A right attitude turns the body-frame field of sensor 1 into a world-frame field that stays
put while the vehicle turns. The fit ``b_body(t) = R(t)^T w + c`` (``w`` a constant world
field, ``c`` the vehicle's permanent field at sensor 1) carries the field in ``w``
(``|w| ~ |B|``) when the attitude is right, whatever anomaly the track crosses (an anomaly
adds variation no attitude explains, but does not move ``w``); a wrong, reversed or frozen
one leaves ``|w|`` small. The same fit over the conventions real navigation stacks publish
(an FRD body, the inverse rotation, the scalar first), over stamp lags of up to
:data:`MAX_LAG_S` and over the clock offsets of :data:`KNOWN_OFFSETS_S` names the one that
fits when it is not the declared one. A NED world frame is a constant rotation ``w``
absorbs: :func:`world_frame_fault` tells it from ``w`` against the Earth field. The test
needs the attitude to turn (:data:`MIN_TURN_RAD`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .types import FloatArray
from .units import S_PER_NS

__all__ = [
    'CONVENTIONS',
    'UNTESTED_ATTITUDE',
    'AttitudeVerdict',
    'attitude_verdict',
    'world_frame_fault',
]

#: The attitude test thins to at most this many samples.
AGREEMENT_SAMPLES = 5000

#: The orientation conventions tried against the magnetometers. A world frame other than
#: ENU (NED) is a constant rotation the fitted world field absorbs: it is told by that field
#: against the Earth field's (:func:`world_frame_fault`), not here.
#: (text, read scalar first, inverse, body FRD) of each convention tried.
CONVENTIONS: tuple[tuple[str, bool, bool, bool], ...] = (
    ('as declared (x, y, z, w; body FLU -> world)', False, False, False),
    ('with the body frame FRD (x forward, y right, z down)', False, False, True),
    ('as the inverse rotation (world -> body)', False, True, False),
    ('read scalar first (w, x, y, z)', True, False, False),
    ('inverse with the body frame FRD', False, True, True),
    ('scalar first with the body frame FRD', True, False, True),
)
_FRD = np.diag([1.0, -1.0, -1.0])


def _as_convention(to_world: FloatArray, inverse: bool, frd: bool) -> FloatArray:
    """The (n, 3, 3) matrices read as the convention's body -> world rotations."""
    out = to_world.transpose(0, 2, 1) if inverse else to_world
    return out @ _FRD if frd else out


@dataclass(frozen=True)
class AttitudeVerdict:
    """The ``/odom`` orientation against the magnetometers (:func:`attitude_verdict`).

    Attributes
    ----------
    tested : whether the attitude turns enough to be tested
    carried : for the declared convention and no lag, ``|w| / mean |B|``: the share of the
        field the attitude carries as a steady world field (about 1 when right, whatever
        the anomalies; near 0 when wrong)
    unexplained : the declared fit's residual RMS over the body field's variation
    best : the convention that fits best, its lag (s; > 0: the /odom stamps are late) and
        its ``carried`` and ``unexplained``
    world_field : the declared fit's world field ``w`` (3,) T, in the odometry's world frame
    field_turn_deg : untested, how much sensor 1's field turns (RMS, degrees)
    overlap : the share of the field's stamps within the ``/odom`` messages' span
    """

    tested: bool
    carried: float = float('nan')
    unexplained: float = float('nan')
    best: tuple[str, float, float, float] = ('', 0.0, float('nan'), float('nan'))
    world_field: FloatArray | None = None
    field_turn_deg: float = 0.0
    overlap: float = 1.0

    @property
    def agrees(self) -> bool:
        """Untested, or the declared convention carries the field and no other convention
        or lag leaves less than half its unexplained share."""
        if not self.tested:
            return self.field_turn_deg < MIN_FIELD_TURN_DEG
        _, _, carried, unexplained = self.best
        better = clear_fit(carried, unexplained) and (
            unexplained < BETTER_BY * self.unexplained - 0.01
        )
        return fits(self.carried, self.unexplained) and not better

    def fault(self) -> str | None:
        """What is wrong with the declared orientation, with the evidence (None: agrees)."""
        if self.agrees:
            return None
        if not self.tested:
            return (
                f'the /odom orientation hardly turns (less than {math.degrees(MIN_TURN_RAD):.0f} '
                f"deg RMS) while sensor 1's field turns by {self.field_turn_deg:.0f} deg RMS in "
                "the body frame: the attitude is not this vehicle's (frozen, identity, or "
                'another source)'
            )
        name, lag, carried, unexplained = self.best
        declared = (
            f'as declared the attitude carries {self.carried:.0%} of the field as a steady '
            f'world field and leaves {self.unexplained:.0%} of its variation unexplained'
        )
        if self.overlap < MIN_OVERLAP:
            declared = f"as stamped, /odom covers only {self.overlap:.0%} of the magnetometers'"
        if not clear_fit(carried, unexplained) and self.overlap < MIN_OVERLAP:
            return (
                f"the /odom stamps cover only {self.overlap:.0%} of the magnetometers' (another "
                'clock): no clock offset of a navigation stack (18, 19, 37 s, whole hours) or '
                "of the two recordings' starts makes its attitude fit the magnetometers"
            )
        if not clear_fit(carried, unexplained):
            return (
                f'the /odom orientation does not agree with the magnetometers: {declared} (a '
                f'right attitude carries ~100 % and leaves a few %); no convention or lag '
                'within 2 s fits either (a wrong, reversed or foreign attitude)'
            )
        what = name if name != CONVENTIONS_DECLARED else 'as declared'
        if abs(lag) >= 0.5 * LAG_RESOLUTION_S:
            late = 'late' if lag > 0 else 'early'
            what += f', with the /odom stamps {abs(lag):.2f} s {late}{_clock_hint(lag)}'
        return (
            f'the /odom orientation fits the magnetometers {what} ({carried:.0%} of the field '
            f'carried, {unexplained:.0%} unexplained); {declared}'
        )


CONVENTIONS_DECLARED = CONVENTIONS[0][0]
#: The lags tried, s (the /odom stamps late by this much).
MAX_LAG_S = 2.0
LAG_RESOLUTION_S = 0.05
COARSE_LAG_S = 0.25
#: The share of |B| a right attitude carries as a steady world field lies within this
#: (the rest is the vehicle's field at sensor 1: a few %; 0.5 leaves room for 50 %).
CARRIED_RANGE = (0.7, 1.3)
#: Above this unexplained share the declared attitude must carry |B| within CARRIED_CLOSE.
MAX_UNEXPLAINED = 0.3
#: Below this share of the field's stamps within the /odom span, /odom is on another clock.
MIN_OVERLAP = 0.5
#: A declared attitude that leaves less than this needs no search for a better one.
CLEAR_UNEXPLAINED = 0.02
CARRIED_CLOSE = 0.05
#: Another convention or lag is named when it leaves less than this share of the declared
#: one's unexplained variation.
BETTER_BY = 0.5
#: RMS angle of the attitude about its mean, rad, below which it is not tested (~6 deg).
MIN_TURN_RAD = 0.1
#: An attitude that does not turn while sensor 1's field turns by more than this RMS angle,
#: degrees, is not the vehicle's (an anomaly turns the field by a few degrees at most).
MIN_FIELD_TURN_DEG = 20.0


def _clock_hint(lag_s: float) -> str:
    """What a clock offset of ``lag_s`` looks like, in parentheses ('' for none known)."""
    known = {18.0: 'GPS time against UTC', 19.0: 'GPS time against TAI', 37.0: 'TAI against UTC'}
    size = abs(lag_s)
    if size in known:
        return f' ({known[size]})'
    if size >= 3600.0 and size % 3600.0 == 0.0:
        return f' ({size / 3600.0:.0f} h: a time zone)'
    return ''


def clear_fit(carried: float, unexplained: float) -> bool:
    """Whether an alternative convention or lag fits well enough to be named."""
    return fits(carried, unexplained) and unexplained < MAX_UNEXPLAINED


def fits(carried: float, unexplained: float) -> bool:
    """Whether an attitude that carries ``carried`` of |B| and leaves ``unexplained`` of the
    field's variation fits: variation it leaves (an anomaly's) is accepted only while it
    carries the field closely (a reversed or foreign one carries part of it)."""
    close = abs(carried - 1.0) <= CARRIED_CLOSE or unexplained < MAX_UNEXPLAINED
    return CARRIED_RANGE[0] <= carried <= CARRIED_RANGE[1] and close


def _fit(to_world: FloatArray, b: FloatArray) -> tuple[float, float, FloatArray]:
    """``b = R^T w + c`` by least squares: (``|w| / mean |B|``, residual RMS over the
    variation of ``b``, ``w``)."""
    # The normal equations of the rows [R^T, I]: [[n I, sum R], [sum R^T, n I]] (R R^T = I).
    n = len(b)
    total = to_world.sum(axis=0)
    normal = np.block([[n * np.eye(3), total], [total.T, n * np.eye(3)]])
    rhs = np.concatenate([np.einsum('nij,nj->i', to_world, b), b.sum(axis=0)])
    solution = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    residual = b - np.einsum('nji,j->ni', to_world, solution[:3]) - solution[3:]
    variation = float(np.sqrt(np.mean(np.sum((b - b.mean(axis=0)) ** 2, axis=1))))
    unexplained = float(np.sqrt(np.mean(residual**2) * 3) / max(variation, 1e-30))
    carried = float(np.linalg.norm(solution[:3]) / np.mean(np.linalg.norm(b, axis=1)))
    return carried, unexplained, solution[:3]


def attitude_verdict(
    odom_stamps_ns: np.ndarray,
    orientation_xyzw: FloatArray,
    stamps_ns: np.ndarray,
    body_field_t: FloatArray,
) -> AttitudeVerdict:
    """Test the ``/odom`` orientation against sensor 1's field, over the conventions of
    :data:`CONVENTIONS` and lags of up to :data:`MAX_LAG_S`.

    A right attitude turns the body-frame field into a world field that stays put: the fit
    ``b(t) = R(t)^T w + c`` carries the field in ``w`` (``|w| ~ |B|``) and leaves ``c``, the
    vehicle's field at sensor 1, small. An anomaly under the track adds variation no
    attitude explains but leaves ``w`` the Earth field: the test reads ``|w|``, not the
    residual alone (the residual ranks the conventions).

    Parameters
    ----------
    odom_stamps_ns : (m,) ns, the checked ``/odom`` messages' stamps
    orientation_xyzw : (m, 4) their unit quaternions, as read
    stamps_ns : (n,) ns, the field's stamps
    body_field_t : (n, 3) T, sensor 1's field
    """
    step = max(1, len(stamps_ns) // AGREEMENT_SAMPLES)
    stamps = np.asarray(stamps_ns, dtype=np.int64)[::step]
    b = np.asarray(body_field_t, dtype=float)[::step]
    finite = np.all(np.isfinite(b), axis=1)
    stamps, b = stamps[finite], b[finite]
    covered = (stamps >= odom_stamps_ns[0]) & (stamps <= odom_stamps_ns[-1])
    if len(b) >= 10 and covered.mean() < MIN_OVERLAP:  # another clock: its offset, if known
        nan = float('nan')
        found = _offset_search(odom_stamps_ns, orientation_xyzw, stamps, b)
        best = found or (CONVENTIONS_DECLARED, 0.0, nan, nan)
        return AttitudeVerdict(True, nan, nan, best, None, 0.0, float(covered.mean()))
    margin = int(MAX_LAG_S * 1e9)
    inside = (stamps >= odom_stamps_ns[0] + margin) & (stamps <= odom_stamps_ns[-1] - margin)
    inside &= np.all(np.isfinite(b), axis=1)
    if inside.sum() < 10:
        inside = np.all(np.isfinite(b), axis=1)
        margin = 0
    stamps, b = stamps[inside], b[inside]
    if len(b) < 10:
        return AttitudeVerdict(False)
    from scipy.spatial.transform import Rotation, Slerp

    t_odom = (np.asarray(odom_stamps_ns) - odom_stamps_ns[0]) * S_PER_NS
    t = (stamps - odom_stamps_ns[0]) * S_PER_NS
    orders = {
        first: Slerp(t_odom, Rotation.from_quat(np.roll(orientation_xyzw, -int(first), axis=1)))
        for first in (False, True)
    }

    def at(first: bool, lag: float) -> FloatArray:
        return orders[first](np.clip(t + lag, 0.0, t_odom[-1])).as_matrix()

    declared = at(False, 0.0)
    if _turn_rms(declared) < MIN_TURN_RAD:
        return AttitudeVerdict(False, field_turn_deg=_field_turn_deg(b))
    carried, unexplained, world = _fit(declared, b)
    if unexplained < CLEAR_UNEXPLAINED and abs(carried - 1.0) <= CARRIED_CLOSE:
        # Nothing can leave less than half of so little: the search is not needed.
        return AttitudeVerdict(
            True, carried, unexplained, (CONVENTIONS_DECLARED, 0.0, carried, unexplained), world
        )
    best = (CONVENTIONS_DECLARED, 0.0, carried, unexplained)
    # Coarse lags for every convention, then the best convention's lag refined.
    coarse = np.arange(-MAX_LAG_S, MAX_LAG_S + 1e-9, COARSE_LAG_S) if margin else [0.0]
    for lag in coarse:
        matrices = {first: at(first, float(lag)) for first in (False, True)}
        for convention in CONVENTIONS:
            best = _better(best, convention, float(lag), matrices[convention[1]], b)
    if margin:
        convention = next(c for c in CONVENTIONS if c[0] == best[0])
        for lag in best[1] + np.arange(-COARSE_LAG_S, COARSE_LAG_S + 1e-9, LAG_RESOLUTION_S):
            if abs(lag) <= MAX_LAG_S:
                best = _better(best, convention, float(lag), at(convention[1], float(lag)), b)
    if best[:2] == (CONVENTIONS_DECLARED, 0.0):  # nothing within 2 s: another clock?
        found = _offset_search(odom_stamps_ns, orientation_xyzw, stamps, b)
        if found is not None and found[3] < BETTER_BY * unexplained - 0.01:
            best = found
    return AttitudeVerdict(True, carried, unexplained, best, world)


#: Clock offsets navigation stacks really have, s: GPS time against UTC (18 s), TAI against
#: UTC (37 s), and whole hours (a time zone), either way.
KNOWN_OFFSETS_S = tuple(
    sign * value
    for value in (18.0, 19.0, 37.0, *(3600.0 * h for h in range(1, 15)))
    for sign in (1.0, -1.0)
)


def _offset_search(
    odom_stamps_ns: np.ndarray,
    orientation_xyzw: FloatArray,
    stamps: np.ndarray,
    b: FloatArray,
) -> tuple[str, float, float, float] | None:
    """The declared convention at the clock offsets of :data:`KNOWN_OFFSETS_S` and at the
    offset of the two streams' starts: the best clear fit (``best`` of
    :class:`AttitudeVerdict`), or None."""
    from scipy.spatial.transform import Rotation, Slerp

    t_odom = (np.asarray(odom_stamps_ns) - odom_stamps_ns[0]) * S_PER_NS
    slerp = Slerp(t_odom, Rotation.from_quat(orientation_xyzw))
    t = (stamps - odom_stamps_ns[0]) * S_PER_NS
    starts = round(float(-t[0]), 1)
    best = None
    for lag in (*KNOWN_OFFSETS_S, starts):
        inside = (t + lag >= 0.0) & (t + lag <= t_odom[-1])
        if inside.sum() < 50:
            continue
        matrices = slerp(t[inside] + lag).as_matrix()
        if _turn_rms(matrices) < MIN_TURN_RAD:
            continue
        carried, unexplained, _ = _fit(matrices, b[inside])
        if clear_fit(carried, unexplained) and (best is None or unexplained < best[3]):
            best = (CONVENTIONS_DECLARED, float(lag), carried, unexplained)
    return best


def _field_turn_deg(b: FloatArray) -> float:
    """RMS angle, degrees, of the field's directions (n, 3) about their mean."""
    unit = b / np.linalg.norm(b, axis=1, keepdims=True)
    mean = unit.mean(axis=0)
    cos = unit @ (mean / np.linalg.norm(mean))
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)) ** 2))))


def _better(
    best: tuple[str, float, float, float],
    convention: tuple[str, bool, bool, bool],
    lag: float,
    to_world: FloatArray,
    b: FloatArray,
) -> tuple[str, float, float, float]:
    """``best`` or the convention at ``lag`` (its matrices ``to_world`` (n, 3, 3)) when it fits
    clearly and leaves less unexplained."""
    name, _, inverse, frd = convention
    carried, unexplained, _ = _fit(_as_convention(to_world, inverse, frd), b)
    if clear_fit(carried, unexplained) and unexplained < best[3]:
        return (name, lag, carried, unexplained)
    return best


def _turn_rms(to_world: FloatArray) -> float:
    """RMS angle, rad, of the rotations (n, 3, 3) about their chordal mean."""
    u, _, vt = np.linalg.svd(to_world.mean(axis=0))
    mean = u @ vt
    cos = (np.einsum('nij,ij->n', to_world, mean) - 1.0) / 2.0
    return float(np.sqrt(np.mean(np.arccos(np.clip(cos, -1.0, 1.0)) ** 2)))


def world_frame_fault(world_field_t: FloatArray, earth_field_enu_t: FloatArray) -> str | None:
    """A line when the world field ``w`` (3,) T a tested attitude makes steady does not point
    where ``earth_field_enu_t`` (3,) T does (NED named when it points there in NED), else
    None. A right attitude's ``w`` is the Earth field plus the survey's mean anomaly: within
    a few degrees of it."""
    ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    earth = np.asarray(earth_field_enu_t, dtype=float)

    def angle(u: FloatArray, v: FloatArray) -> float:
        cos = float(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    as_enu, as_ned = angle(world_field_t, earth), angle(world_field_t, ned @ earth)
    if as_enu <= MAX_WORLD_FIELD_DEG:
        return None
    if as_ned <= MAX_WORLD_FIELD_DEG:
        return (
            f'the /odom world frame looks NED, not ENU: the field it makes steady points '
            f"{as_ned:.0f} deg from the Earth field's direction in NED and {as_enu:.0f} deg "
            'from it in ENU (REP 103 odometry is ENU)'
        )
    return (
        f'the /odom orientation does not agree with the Earth field: the field it makes '
        f'steady points {as_enu:.0f} deg from it (a right attitude: within a few degrees): the '
        'attitude (reversed, foreign, another convention) or the Earth field declared '
        '(earth_field_enu, or IGRF at the origin) is wrong'
    )


#: The largest angle, degrees, between a right attitude's world field and the Earth field.
MAX_WORLD_FIELD_DEG = 15.0


#: The note when the attitude turns too little to test it against the field.
UNTESTED_ATTITUDE = (
    'the /odom orientation was not checked against the magnetometers (it turns by less than '
    f'about {math.degrees(MIN_TURN_RAD):.0f} degrees)'
)
