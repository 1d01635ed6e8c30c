"""The array's conventions read from its own data: each sensor's axes against sensor 1's,
and the order, frame and handedness of ``sensor_positions`` against the readings.

Two tests, each comparing a finite set of hypotheses (the mistakes made when an array is
first put on a vehicle) and naming the one the data fit; where the data cannot tell two
apart, both are named.

* **Sensor axes** (:func:`relative_axes`, on a trim): every sensor reads the same Earth field
  up to the vehicle's interference (a few % of it), so ``B_s(t) ~ M_s B_1(t)`` with ``M_s``
  near the identity. The orthogonal factor of the least-squares ``M_s`` (its polar
  decomposition), snapped to the nearest of the 48 signed permutations, is the sensor's
  axes against sensor 1's: a sign flip, a 90 or 180 degree turn, FRD against FLU. The fit
  has no offset (a hard iron of a few % of ``|B|`` leaks into ``M_s`` by as much, far from
  the 45 degrees between two signed permutations), so a trim turning in heading alone
  determines it. It needs the field to turn: the uncentred readings of sensor 1 must span
  three directions (:data:`MIN_SPAN`).
* **Positions and reading frame** (:func:`tensor_conventions`, on compensated survey
  tensors): a true gradient is symmetric and traceless. With positions listed in another
  order (or mirrored) the eq. 7 tensor is ``G a a_h^-1``; with every sensor reading in FRD it
  is ``F G``. Each hypothesis's tensor ``L G_meas a a_h^-1`` is scored by the share of its
  energy that is not symmetric and traceless (:func:`asymmetry_share`); the test is made
  only where the tensor's signal stands above the noise (:data:`MIN_SIGNAL_TO_NOISE`).
  ``F G F`` (an array consistently in FRD) is itself symmetric and traceless: a reading
  frame ``F`` and positions mirrored by ``F`` fit alike, and the finding says both.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .types import FloatArray

__all__ = [
    'FRD',
    'MIN_SPAN',
    'SIGNED_PERMUTATIONS',
    'AxesFinding',
    'TensorFinding',
    'TensorSample',
    'asymmetry_share',
    'describe_axes',
    'frame_id_hints',
    'relative_axes',
    'tensor_conventions',
]

#: x forward, y right, z down against REP 103's x forward, y left, z up.
FRD = np.diag([1.0, -1.0, -1.0])
#: The smallest singular value of sensor 1's uncentred readings, as a share of the largest,
#: that determines ``M_s`` (0.1: the field turns by about 6 degrees out of its mean plane).
MIN_SPAN = 0.1
#: A sensor is named only when its fitted axes lie within this many degrees of the signed
#: permutation named (a looser fit is no mounting: a field that is not shared).
MAX_FIT_DEG = 10.0
#: Sets whose |B| on some sensor differs from the median |B| by more than this share are
#: left out of the axes fit.
MAX_NORM_OFFSET = 0.5
#: The compensated tensor's RMS (less its noise) over its noise RMS below which the
#: position hypotheses are not tested (no gradient to tell them by).
MIN_SIGNAL_TO_NOISE = 5.0
#: A hypothesis is named when the declared one leaves at least this share of the tensor's
#: energy asymmetric or with a trace and it leaves at most a quarter of that.
MIN_DECLARED_SHARE = 0.2
BETTER_BY = 4.0
#: At most this many of the hypotheses the data cannot tell apart are named.
MAX_NAMED = 3


def _signed_permutations() -> FloatArray:
    out = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), order] = signs
            out.append(matrix)
    return np.array(out)


#: (48, 3, 3) every matrix that maps the axes onto the axes, signs included.
SIGNED_PERMUTATIONS = _signed_permutations()


def describe_axes(matrix: FloatArray) -> str:
    """A signed permutation (3, 3) in words: what a sensor whose readings are ``matrix @ B``
    reads, e.g. ``'(-x, -y, z): turned 180 deg about z'``."""
    names = ('x', 'y', 'z')
    parts = []
    for row in np.asarray(matrix):
        j = int(np.argmax(np.abs(row)))
        parts.append(('-' if row[j] < 0 else '') + names[j])
    mapping = f'({", ".join(parts)})'
    frd = ' (FRD, x forward, y right, z down, against FLU)' if np.allclose(matrix, FRD) else ''
    if np.linalg.det(matrix) > 0:
        from scipy.spatial.transform import Rotation

        rotvec = Rotation.from_matrix(matrix).as_rotvec()
        angle = float(np.degrees(np.linalg.norm(rotvec)))
        axis = rotvec / np.linalg.norm(rotvec)
        about = (
            names[int(np.argmax(np.abs(axis)))]
            if np.max(np.abs(axis)) > 0.99
            else ('(' + ', '.join(f'{v:+.2f}' for v in axis) + ')')
        )
        return f'{mapping}: turned {angle:.0f} deg about {about}{frd}'
    return f'{mapping}: mirrored (a left-handed frame)'


def _nearest_signed_permutation(matrix: FloatArray) -> tuple[FloatArray, float]:
    """The signed permutation nearest the orthogonal factor of ``matrix`` (3, 3) and the
    angle, degrees, between the two."""
    u, _, vt = np.linalg.svd(matrix)
    orthogonal = u @ vt
    scores = np.einsum('kij,ij->k', SIGNED_PERMUTATIONS, orthogonal)
    best = SIGNED_PERMUTATIONS[int(np.argmax(scores))]
    cos = np.clip((np.trace(best.T @ orthogonal) - 1.0) / 2.0, -1.0, 1.0)
    return best, float(np.degrees(np.arccos(cos)))


@dataclass(frozen=True)
class AxesFinding:
    """Sensor ``sensor`` (1-based) reads ``matrix @ B_1``: its axes are not sensor 1's.

    ``residual_angle_deg``: how far the fitted orthogonal factor lies from ``matrix``.
    """

    sensor: int
    matrix: FloatArray
    residual_angle_deg: float

    def text(self) -> str:
        return (
            f"sensor {self.sensor}'s axes are not sensor 1's: it reads sensor 1's field as "
            f'{describe_axes(self.matrix)} (fit within {self.residual_angle_deg:.1f} deg)'
        )


def relative_axes(fields: FloatArray) -> tuple[AxesFinding, ...] | None:
    """Each sensor's axes against sensor 1's, from readings that share the Earth field.

    Parameters
    ----------
    fields : (N, 4, 3) T, the four sensors' readings (a trim: the field turns)

    Returns
    -------
    The sensors whose axes are another signed permutation than the identity (empty: all
    agree), or None when sensor 1's field spans fewer than three directions (untested).
    """
    b = np.asarray(fields, dtype=float)
    b = b[np.all(np.isfinite(b), axis=(1, 2))]
    if len(b):  # readings off the common |B| (a glitch, a unit mistake) do not vote
        norms = np.linalg.norm(b, axis=2)
        b = b[np.all(np.abs(norms / np.median(norms) - 1.0) < MAX_NORM_OFFSET, axis=1)]
    if len(b) < 10:
        return None
    reference = b[:, 0]
    singular = np.linalg.svd(reference, compute_uv=False)
    if not singular[-1] > MIN_SPAN * singular[0]:
        return None
    findings = []
    for sensor in range(1, 4):
        # B_s = B_1 M^T in rows: M^T by least squares.
        m_t, *_ = np.linalg.lstsq(reference, b[:, sensor], rcond=None)
        matrix, angle = _nearest_signed_permutation(m_t.T)
        if not np.allclose(matrix, np.eye(3)) and angle <= MAX_FIT_DEG:
            findings.append(AxesFinding(sensor + 1, matrix, angle))
    return tuple(findings)


def asymmetry_share(tensors: FloatArray) -> float:
    """The share of the energy of ``tensors`` (N, 3, 3) that is not symmetric and traceless:
    ``sum |antisym|^2 + trace^2 / 3`` over ``sum |G|^2``."""
    g = np.asarray(tensors, dtype=float)
    antisym = 0.5 * (g - np.swapaxes(g, 1, 2))
    trace = np.trace(g, axis1=1, axis2=2)
    total = float(np.sum(g**2))
    if total == 0.0:
        return 0.0
    return float((np.sum(antisym**2) + np.sum(trace**2) / 3.0) / total)


@dataclass(frozen=True)
class TensorFinding:
    """The hypotheses about the positions and the reading frame the tensors fit best.

    ``declared``: the asymmetric share with the declared positions and frame; ``best``: the
    best hypotheses' (each a text), ``best_share`` theirs.
    """

    declared: float
    best: tuple[str, ...]
    best_share: float

    def text(self) -> str:
        causes = ' or '.join(self.best)
        return (
            f'the compensated tensor is not a gradient: {self.declared:.0%} of its energy is '
            f'asymmetric or has a trace (a true gradient has none); it becomes one '
            f'({self.best_share:.1%} left) if {causes}'
        )


def _position_hypotheses(positions: FloatArray) -> list[tuple[str, FloatArray]]:
    """(text, positions (4, 3)) for every order of the four rows and each mirrored by FRD."""
    out = []
    for order in itertools.permutations(range(4)):
        for mirrored in (False, True):
            if order == (0, 1, 2, 3) and not mirrored:
                continue
            candidate = positions[list(order)]
            parts = []
            if order != (0, 1, 2, 3):
                listed = (
                    'in reverse order'
                    if order == (3, 2, 1, 0)
                    else ('in the order ' + ', '.join(str(i + 1) for i in order))
                )
                parts.append(f'sensor_positions were listed {listed}')
            if mirrored:
                candidate = candidate @ FRD
                parts.append('sensor_positions are in FRD (y and z negated)')
            out.append((' and '.join(parts), candidate))
    return out


def tensor_conventions(
    tensors: FloatArray, positions: FloatArray, noise_rms: float
) -> TensorFinding | None:
    """Test the declared positions and reading frame on compensated tensors.

    Parameters
    ----------
    tensors : (N, 3, 3) T/m, compensated eq. 7 tensors made with ``positions``
    positions : (4, 3) m, the declared ``sensor_positions``
    noise_rms : T/m, the RMS of one tensor element's noise

    Returns
    -------
    None when the declared conventions fit (or the tensor's signal is too weak to tell);
    otherwise the hypotheses that make it a gradient.
    """
    g = np.asarray(tensors, dtype=float)
    g = g[np.all(np.isfinite(g), axis=(1, 2))]
    if not len(g):
        return None
    g = g - np.median(g, axis=0)  # the signal: a constant offset is the calibration's
    rms = float(np.sqrt(np.mean(g**2)))
    if not rms > MIN_SIGNAL_TO_NOISE * noise_rms:
        return None
    declared = asymmetry_share(g)
    if declared < MIN_DECLARED_SHARE:
        return None
    positions = np.asarray(positions, dtype=float)
    a = (positions[1:] - positions[0]).T
    scored = []
    for text, candidate in _position_hypotheses(positions):
        a_h = (candidate[1:] - candidate[0]).T
        if abs(np.linalg.det(a_h)) < 1e-12:
            continue
        mix = a @ np.linalg.inv(a_h)
        scored.append((asymmetry_share(g @ mix), text))
        scored.append((asymmetry_share(FRD @ g @ mix), _frd_reading(text)))
    scored.append((asymmetry_share(FRD @ g), _frd_reading('')))
    best_share = min(share for share, _ in scored)
    if not best_share * BETTER_BY <= declared:
        return None
    # Hypotheses within noise of the best are not told apart by the data (a regular
    # tetrahedron maps onto itself by some reorderings): the simplest are named.
    tied = sorted(
        (text.count(' and '), share, text) for share, text in scored if share <= best_share + 0.02
    )
    named = tuple(text for _, _, text in tied[:MAX_NAMED])
    if len(tied) > MAX_NAMED:
        more = len(tied) - MAX_NAMED
        named = (*named, f'{more} more combination{"s" * (more > 1)} of these')
    return TensorFinding(declared, named, best_share)


def _frd_reading(text: str) -> str:
    reading = 'the magnetometers read in FRD (y and z negated)'
    return f'{reading} and {text}' if text else reading


@dataclass
class TensorSample:
    """Every ``stride``-th written tensor (at most about :data:`SAMPLE_SETS`, the stride
    doubling as the bag goes on), for the self-check of :func:`conventions_text`."""

    stride: int = 1
    seen: int = 0
    chunks: list[FloatArray] = field(default_factory=list)

    def add(self, tensors: FloatArray) -> None:
        """A chunk of written tensors (n, 3, 3) T/m."""
        offset = (-self.seen) % self.stride
        self.chunks.append(tensors[offset :: self.stride])
        self.seen += len(tensors)
        if sum(len(c) for c in self.chunks) > 2 * SAMPLE_SETS:
            self.chunks = [np.concatenate(self.chunks)[::2]]
            self.stride *= 2

    def conventions_text(self, positions: FloatArray) -> str:
        """'' or what the tensors say of the declared ``positions`` (4, 3) m and reading
        frame (:func:`tensor_conventions`; the noise of one element from consecutive
        differences)."""
        if not self.chunks:
            return ''
        tensors = np.concatenate(self.chunks)
        steps = np.diff(tensors.reshape(len(tensors), 9), axis=0)
        if not len(steps):
            return ''
        # The median absolute step: the noise of one element (a target's passage moves few).
        noise = float(np.median(np.abs(steps)) / (0.6745 * np.sqrt(2.0)))
        finding = tensor_conventions(tensors, positions, noise)
        return '' if finding is None else finding.text()


#: The written tensors the self-check keeps (thinned evenly over the bag).
SAMPLE_SETS = 20_000


#: A frame_id's sensor number: ``mag3``, ``magnetometer_3``, ``sensor-3``, ``tetra_mag3``.
_SENSOR_NUMBER = re.compile(r'(?:mag|magnetometer|sensor)[_-]?(\d+)', re.IGNORECASE)
#: frame_id words that declare a frame other than REP 103's FLU.
_OTHER_FRAMES = {'frd': 'FRD (x forward, y right, z down)', 'ned': 'NED (x north, y east, z down)'}


def frame_id_hints(frame_ids: Sequence[str]) -> str:
    """'' or what the magnetometers' ``frame_id`` (sensor order, one each) say against the
    declared array: numbered sensors in another order than the topics', or a frame other
    than FLU. Evidence, not proof: a frame_id is whatever the driver was configured with."""
    hints = []
    numbers = [_SENSOR_NUMBER.search(frame) for frame in frame_ids]
    if all(numbers):
        found = [int(m.group(1)) for m in numbers if m]
        first = min(found)
        if sorted(found) == list(range(first, first + len(found))) and found != sorted(found):
            order = ', '.join(f"sensor {i + 1}: '{f}'" for i, f in enumerate(frame_ids))
            hints.append(
                f'the magnetometer topics carry frame_ids of other sensors ({order}): the '
                'topics may be listed in another order than sensor_positions'
            )
    words = {w for frame in frame_ids for w in re.split(r'[_\-/.]', frame.lower())}
    for word, frame in _OTHER_FRAMES.items():
        if word in words:
            named = sorted({f for f in frame_ids if word in re.split(r'[_\-/.]', f.lower())})
            hints.append(
                f'the frame_id {", ".join(repr(f) for f in named)} declares {frame}, not REP '
                "103's FLU: the readings' axes are checked from the data"
            )
    return '; '.join(hints)
