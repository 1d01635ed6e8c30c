"""Data preparation: the recorded run's usable samples in nT, its continuous pieces, the
background field ``B^b`` of the chosen residual view and the base model's regressors.

Every function here returns new objects: :class:`Prepared` is frozen, and a refresh of the
background returns a new one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import scipy  # submodules load on first use: see core/__init__.py
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ...errors import InputError
from ..model import SYMMETRIC_ENTRIES
from ..units import NT_PER_T
from .detectors import PiecewiseSpline
from .openworld import OpenWorld

Array = NDArray[np.float64]
Mask = NDArray[np.bool_]
Labels = list[tuple[int, str]]

_MIN_SAMPLES = 50


class RunLike(Protocol):
    """What :func:`prepare` reads from a run (``io.recording.Recording`` has it too)."""

    @property
    def t_s(self) -> Array: ...

    @property
    def fields(self) -> Array: ...

    @property
    def orientation_xyzw(self) -> Array | None: ...

    @property
    def temperature_c(self) -> Array | None: ...

    @property
    def current_a(self) -> Array | None: ...

    @property
    def missing(self) -> Mapping[str, str]: ...


@dataclass(frozen=True)
class RecordedRun:
    """A recorded run as plain arrays.

    Attributes
    ----------
    t_s : (N,) s from the first sample
    fields : (N, 4, 3) tesla, body frame
    orientation_xyzw : (N, 4) body -> ENU, or None without ``/odom``
    temperature_c : (N,) degC, or None without ``/tetra/temperature``
    current_a : (N,) A, or None without ``/battery_state``
    missing : topic -> why it is unavailable
    extra_currents : BatteryState topic -> (N,) A, the further current channels (one per
        thruster, say): ``vehicle_current`` fits a field per channel
    position_m : (N, 3) m, the body origin in the odom frame (ENU) from ``/odom``, or None:
        the track that places a target's field (:mod:`.dipoles`)
    signals : ``signal:TOPIC#FIELD`` -> (N,) values: the further signals the run records,
        candidates of their own (:mod:`.signals`)
    """

    t_s: Array
    fields: Array
    orientation_xyzw: Array | None = None
    temperature_c: Array | None = None
    current_a: Array | None = None
    missing: Mapping[str, str] = field(default_factory=dict)
    extra_currents: Mapping[str, Array] = field(default_factory=dict)
    position_m: Array | None = None
    signals: Mapping[str, Array] = field(default_factory=dict)


@dataclass(frozen=True)
class Prepared:
    """The run as the search sees it, nT and s.

    Attributes
    ----------
    t : (N,) s
    fields : (N, 4, 3) nT
    sensors : sensors of the residual view (0-3 absolute, 1-3 pair differences)
    absolute : True with /odom (every sensor against ``R^T E``)
    base_offset : (N, 4, 3) nT, the fixed part of the prediction
    b_background : (N, 3) nT, ``B^b``
    b_rate : (N, 3) nT/s, ``dB^b/dt``
    base_cols : (N, 4, 3, pb) the base model's regressors, with ``base_labels``
    temperature_c, current_a : (N,) or None
    attitude : (N, 3) yaw, pitch, roll deg, or None
    earth_field_nT : (3,) ENU, the Earth field the view starts from, or None
    notes : what preparing the data decided
    piece : (N,) index of the continuous piece of the run
    rotation : (N, 3, 3) body -> ENU, or None
    open_world : the steps and spectral lines the scans of the residual found
    extra_currents : the further current channels, (BatteryState topic, (N,) A) each
    signals : the further recorded signals, (channel, (N,) values) each
    position : (N, 3) m, the track (body origin, odom frame), or None
    target_cols : (N, 4, 3, 3K) nT per A m^2, the fitted targets' field per unit moment
        (odom axes), appended to ``base_cols`` (their moments are fitted with the base
        model), or None; ``target_labels`` label them
    target_background : (N, 3) nT, the targets' field at sensor 1 with their fitted
        moments: part of ``B^b`` (the soft iron ``K_i`` magnetised by it too), or None
    """

    t: Array
    fields: Array
    sensors: tuple[int, ...]
    absolute: bool
    base_offset: Array
    b_background: Array
    b_rate: Array
    base_cols: Array
    base_labels: Labels
    temperature_c: Array | None
    current_a: Array | None
    attitude: Array | None
    earth_field_nT: Array | None
    notes: tuple[str, ...]
    piece: NDArray[np.int_]
    rotation: Array | None
    open_world: OpenWorld = field(default_factory=OpenWorld)
    extra_currents: tuple[tuple[str, Array], ...] = ()
    position: Array | None = None
    signals: tuple[tuple[str, Array], ...] = ()
    target_cols: Array | None = None
    target_labels: Labels = field(default_factory=list)
    target_background: Array | None = None


@dataclass(frozen=True)
class _Samples:
    """The usable, possibly thinned samples of the run."""

    t: Array
    fields: Array  # (N, 4, 3) nT
    piece: NDArray[np.int_]
    quat: Array | None
    temperature_c: Array | None
    current_a: Array | None
    notes: tuple[str, ...]
    extra_currents: tuple[tuple[str, Array], ...] = ()
    position: Array | None = None
    signals: tuple[tuple[str, Array], ...] = ()


def prepare(
    recording: RunLike,
    earth_field_enu: object,
    max_samples: int,
    window_s: tuple[float, float] | None = None,
    exclude_s: list[tuple[float, float]] | None = None,
) -> Prepared:
    """The run's usable samples (inside ``window_s``, outside ``exclude_s``, at most
    ``max_samples``) with the background field of the view: absolute with /odom, pair
    differences without. ``earth_field_enu`` (3,) tesla, or None: estimated from sensor 1.

    Raises
    ------
    InputError
        Fewer than 50 usable samples.
    """
    samples = _samples(recording, max_samples, window_s, exclude_s)
    if samples.quat is not None:
        return _absolute_view(samples, samples.quat, earth_field_enu)
    return _pair_view(samples)


def _samples(
    recording: RunLike,
    max_samples: int,
    window_s: tuple[float, float] | None,
    exclude_s: list[tuple[float, float]] | None,
) -> _Samples:
    t_all = np.asarray(recording.t_s, dtype=float)
    fields = np.asarray(recording.fields, dtype=float) * NT_PER_T
    keep = np.isfinite(fields).all(axis=(1, 2)) & np.concatenate([[True], np.diff(t_all) > 0])
    if window_s is not None:
        keep &= _inside_window(t_all, window_s)
    optional: dict[str, Array | None] = {}
    for name in ('orientation_xyzw', 'temperature_c', 'current_a', 'position_m'):
        value = getattr(recording, name, None)
        if value is not None:
            value = np.asarray(value, dtype=float)
            keep &= np.isfinite(value).reshape(len(value), -1).all(axis=1)
        optional[name] = value
    extra: dict[str, Array] = {}
    for topic, value in (getattr(recording, 'extra_currents', None) or {}).items():
        extra[topic] = np.asarray(value, dtype=float)
        keep &= np.isfinite(extra[topic])
    signals = {
        k: np.asarray(v, float) for k, v in (getattr(recording, 'signals', None) or {}).items()
    }
    for value in signals.values():
        keep &= np.isfinite(value)
    if keep.sum() < _MIN_SAMPLES:
        raise InputError(
            f'the recording has {int(keep.sum())} usable samples; the workflow needs at least 50'
        )
    notes: list[str] = []
    piece_all, jumps = _pieces(t_all, fields, optional['orientation_xyzw'], keep)
    if jumps:
        notes.append(
            f'{jumps} jump(s) in attitude or field between recorded segments: no derivative is '
            'taken across them and 2 samples either side are left out'
        )
        keep &= piece_all >= 0
    if exclude_s:
        keep, piece_all = _exclude(t_all, keep, piece_all, exclude_s)
    index = np.flatnonzero(keep)
    if len(index) > max_samples:
        # Long or fast records: every k-th set keeps white noise white and the manoeuvre
        # resolved (it changes over seconds), and bounds memory and time.
        step = int(np.ceil(len(index) / max_samples))
        index = index[::step]
        notes.append(f'{int(keep.sum())} sets: every {step}-th analysed ({len(index)} sets)')
    if len(index) < _MIN_SAMPLES:
        raise InputError(
            f'the recording has {len(index)} usable samples; the workflow needs at least 50'
        )
    picked = {k: (v[index] if v is not None else None) for k, v in optional.items()}
    return _Samples(
        t_all[index],
        fields[index],
        piece_all[index],
        picked['orientation_xyzw'],
        picked['temperature_c'],
        picked['current_a'],
        tuple(notes),
        tuple((topic, value[index]) for topic, value in extra.items()),
        picked['position_m'],
        tuple((name, value[index]) for name, value in signals.items()),
    )


def _inside_window(t_all: Array, window_s: tuple[float, float]) -> Mask:
    inside = (t_all >= window_s[0]) & (t_all <= window_s[1])
    if inside.sum() < _MIN_SAMPLES:
        raise InputError(
            f'the window {window_s[0]:g}:{window_s[1]:g} s holds {int(inside.sum())} sample '
            f'sets (the run spans 0-{t_all[-1] - t_all[0]:.1f} s); the workflow needs at least 50'
        )
    return inside


def _exclude(
    t_all: Array, keep: Mask, piece_all: NDArray[np.int_], exclude_s: list[tuple[float, float]]
) -> tuple[Mask, NDArray[np.int_]]:
    """Excluded spans (target passages): left out, and no derivative is taken across them."""
    excluded = np.zeros(len(t_all), dtype=bool)
    for t0, t1 in exclude_s:
        excluded |= (t_all >= t0) & (t_all <= t1)
    keep = keep & ~excluded
    starts = np.cumsum(np.diff(excluded.astype(int), prepend=0) == 1)
    piece_all = np.where(piece_all >= 0, piece_all * (len(exclude_s) + 1) + starts, -1)
    if keep.sum() < _MIN_SAMPLES:
        raise InputError(
            f'{int(keep.sum())} usable samples are left outside the excluded spans; '
            'the workflow needs at least 50'
        )
    return keep, piece_all


def _absolute_view(samples: _Samples, quat: Array, earth_field_enu: object) -> Prepared:
    """Every sensor against ``B^b = R^T E`` (E from the params, else from sensor 1)."""
    t, fields = samples.t, samples.fields
    n = len(t)
    notes = list(samples.notes)
    rotation = Rotation.from_quat(quat)
    r = rotation.as_matrix()
    attitude = np.degrees(rotation.as_euler('ZYX'))
    if earth_field_enu is None:
        earth = np.mean(np.einsum('nij,nj->ni', r, fields[:, 0]), axis=0)
        notes.append(
            'earth_field_enu not given: estimated from sensor 1 rotated to ENU by /odom '
            f'({np.linalg.norm(earth):.0f} nT)'
        )
    else:
        earth = np.asarray(earth_field_enu, dtype=float).reshape(3) * NT_PER_T
    b0 = np.einsum('nji,j->ni', r, earth)  # R^T E
    base_offset = np.repeat(b0[:, None, :], 4, axis=1)
    # First pass: a constant correction of the Earth field, from sensor 1.
    design = np.swapaxes(r, 1, 2).reshape(n * 3, 3)  # rows of R^T
    correction = np.linalg.lstsq(design, (fields[:, 0] - b0).reshape(-1), rcond=None)[0]
    b_background = b0 + np.einsum('nji,j->ni', r, correction)
    base_cols, labels = base_columns(r, b_background, True, t)
    notes.append(
        'B^b = R^T E from /odom, E corrected by a constant fitted with the model '
        f'(|E| = {np.linalg.norm(earth + correction):.0f} nT)'
    )
    b_rate = PiecewiseSpline(t, b_background, samples.piece)(0.0, 1)
    return Prepared(
        t=t,
        fields=fields,
        sensors=(0, 1, 2, 3),
        absolute=True,
        base_offset=base_offset,
        b_background=b_background,
        b_rate=b_rate,
        base_cols=base_cols,
        base_labels=labels,
        temperature_c=samples.temperature_c,
        current_a=samples.current_a,
        extra_currents=samples.extra_currents,
        signals=samples.signals,
        attitude=attitude,
        earth_field_nT=earth,
        notes=tuple(notes),
        piece=samples.piece,
        rotation=r,
        position=samples.position,
    )


def _pair_view(samples: _Samples) -> Prepared:
    """Without /odom: ``B^b = B_1'``, sensors 2-4 against sensor 1."""
    t, fields = samples.t, samples.fields
    b_background = fields[:, 0].copy()
    base_offset = np.repeat(b_background[:, None, :], 4, axis=1)
    base_cols, labels = base_columns(None, b_background, False)
    notes = samples.notes + (
        "no /odom: falling back to B^b = B_1' (the paper's assumption); only the pair "
        "differences B_i' - B_1' are observable, so the residual is that of sensors 2-4 "
        'against sensor 1; a term of sensor 1 enters every pair, so only relative values '
        'are fixed',
    )
    b_rate = smoothed(t, b_background, samples.piece, deriv=1)
    return Prepared(
        t=t,
        fields=fields,
        sensors=(1, 2, 3),
        absolute=False,
        base_offset=base_offset,
        b_background=b_background,
        b_rate=b_rate,
        base_cols=base_cols,
        base_labels=labels,
        temperature_c=samples.temperature_c,
        current_a=samples.current_a,
        extra_currents=samples.extra_currents,
        signals=samples.signals,
        attitude=None,
        earth_field_nT=None,
        notes=notes,
        piece=samples.piece,
        rotation=None,
    )


def refresh_background(
    prep: Prepared, correction: Array, tolerance_nT: float = 0.5
) -> tuple[Prepared, bool]:
    """Absolute view: re-derive ``B^b = R^T (E + dE + dE' (t - t_mid))`` with the
    Earth-field correction of the joint fit (the first pass used sensor 1 alone, whose own
    interference biases it); rebuild the base columns when it moved by more than
    ``tolerance_nT`` (soft iron ~1e-2 turns that into < 0.005 nT). Returns the (new)
    prepared data and whether something changed."""
    if prep.rotation is None:
        raise InputError('the Earth-field correction needs the attitude (/odom)')
    world = correction[None, :3] + ramp(prep.t)[:, None] * correction[None, 3:6]
    b_background = prep.base_offset[:, 0] + np.einsum('nji,nj->ni', prep.rotation, world)
    if prep.target_background is not None:
        b_background = b_background + prep.target_background
    if np.max(np.abs(b_background - prep.b_background)) < tolerance_nT:
        return prep, False
    base_cols, base_labels = base_columns(prep.rotation, b_background, True, prep.t)
    if prep.target_cols is not None:
        base_cols = np.concatenate([base_cols, prep.target_cols], axis=-1)
        base_labels = base_labels + prep.target_labels
    return replace(
        prep,
        b_background=b_background,
        base_cols=base_cols,
        base_labels=base_labels,
        b_rate=PiecewiseSpline(prep.t, b_background, prep.piece)(0.0, 1),
    ), True


def refresh_pair_background(
    prep: Prepared, clean: Array, tolerance_nT: float = 0.01
) -> tuple[Prepared, bool]:
    """Pair view: take ``B^b`` (and the fixed part of every prediction) as sensor 1's reading
    less its named effects; rebuild the base columns when it moved. (Here ``B^b`` is the
    regressor of sensor 1's own terms, hence the tight tolerance.)"""
    if np.max(np.abs(clean - prep.b_background)) < tolerance_nT:
        return prep, False
    base_cols, base_labels = base_columns(None, clean, False)
    return replace(
        prep,
        b_background=clean,
        base_offset=np.repeat(clean[:, None, :], 4, axis=1),
        base_cols=base_cols,
        base_labels=base_labels,
        b_rate=smoothed(prep.t, clean, prep.piece, deriv=1),
    ), True


def with_targets(
    prep: Prepared, cols: Array | None, labels: Labels, background: Array | None = None
) -> Prepared:
    """``prep`` with the targets' columns (N, 4, 3, 3K) nT per A m^2 (None: no targets) in
    place of the previous ones at the end of the base model, and their field at sensor 1
    ``background`` (N, 3) nT (None: not known yet) in ``B^b``: the simulator and the
    vehicle magnetise the soft iron with the whole field, targets included."""
    b_background = prep.b_background
    if prep.target_background is not None:
        b_background = b_background - prep.target_background
    if background is not None:
        b_background = b_background + background
    if prep.rotation is not None and b_background is not prep.b_background:
        base_cols, base_labels = base_columns(prep.rotation, b_background, True, prep.t)
        prep = replace(
            prep,
            b_background=b_background,
            base_cols=np.concatenate([base_cols, prep.base_cols[..., base_cols.shape[-1] :]], -1),
            b_rate=PiecewiseSpline(prep.t, b_background, prep.piece)(0.0, 1),
        )
    prep = replace(prep, target_background=background)
    keep = prep.base_cols.shape[-1] - len(prep.target_labels)
    base_cols = prep.base_cols[..., :keep]
    base_labels = prep.base_labels[:keep]
    if cols is not None and cols.shape[-1]:
        base_cols = np.concatenate([base_cols, cols], axis=-1)
        base_labels = base_labels + list(labels)
    else:
        cols, labels = None, []
    return replace(
        prep,
        base_cols=base_cols,
        base_labels=base_labels,
        target_cols=cols,
        target_labels=list(labels),
    )


def smoothed(t: Array, values: Array, piece: NDArray[np.int_], deriv: int = 0) -> Array:
    """Savitzky-Golay (5th order, ~1.3 s or 13 samples) value or derivative on each piece:
    exact to ~1e-7 for manoeuvre signals, a quarter of the noise gain of a spline derivative.
    Pieces shorter than the window get a cubic spline."""
    out = np.empty_like(values, dtype=float)
    for p in np.unique(piece):
        idx = np.flatnonzero(piece == p)
        if len(idx) < 2:
            out[idx] = 0.0 if deriv else values[idx]
            continue
        dt = float(np.median(np.diff(t[idx])))
        window = max(13, int(round(1.3 / dt)) | 1)
        if len(idx) > window:
            out[idx] = scipy.signal.savgol_filter(
                values[idx], window, 5, deriv=deriv, delta=dt, axis=0
            )
        else:
            out[idx] = PiecewiseSpline(t[idx], values[idx])(0.0, deriv)
    return out


def ramp(t: Array) -> Array:
    """(t - t_mid) / (half the span): -1 .. 1."""
    half = max(0.5 * (t[-1] - t[0]), 1e-9)
    result: Array = (t - 0.5 * (t[-1] + t[0])) / half
    return result


def _sym_columns(cols: Array, sensor: int, start: int, b: Array, labels: Labels) -> int:
    """Symmetric K (6) and hard iron (3) columns of ``sensor`` from ``start``."""
    k = start
    for r, c in SYMMETRIC_ENTRIES:
        cols[:, sensor, r, k] = b[:, c]
        if r != c:
            cols[:, sensor, c, k] = b[:, r]
        labels.append((sensor, f'K{"xyz"[r]}{"xyz"[c]}'))
        k += 1
    for a in range(3):
        cols[:, sensor, a, k] = 1.0
        labels.append((sensor, f'Bh_{"xyz"[a]}_nT'))
        k += 1
    return k


def base_columns(
    r: Array | None, b_background: Array, absolute: bool, t: Array | None = None
) -> tuple[Array, Labels]:
    """Base-model regressors: (absolute view) a correction of the Earth field seen by all
    sensors, constant plus a linear drift over the run (diurnal variation, a distant target
    passed slowly), then symmetric K_i and B_i^h of sensors 2-4 on ``b_background``."""
    n = len(b_background)
    first = 6 if absolute else 0
    cols = np.zeros((n, 4, 3, first + 27))
    labels: Labels = []
    if absolute:
        if r is None or t is None:
            raise InputError('the absolute view needs the attitude (/odom) and the times')
        drift = ramp(t)
        for a in range(3):
            cols[..., a] = r[:, a, :][:, None, :]
            labels.append((-1, f'dE_{"enu"[a]}_nT'))
        for a in range(3):
            cols[..., 3 + a] = (drift[:, None] * r[:, a, :])[:, None, :]
            labels.append((-1, f'dE_drift_{"enu"[a]}_nT_at_end'))
    start = first
    for s in (1, 2, 3):
        start = _sym_columns(cols, s, start, b_background, labels)
    return cols, labels


def _pieces(
    t: Array, fields: Array, quat: Array | None, keep: Mask
) -> tuple[NDArray[np.int_], int]:
    """Split the run where the attitude (or, without /odom, sensor 1's field) jumps: a step
    at least 4 x larger than the steps on both sides of it and than 0.5 deg (50 nT). Returns
    the piece index per sample (-1: left out, 2 samples either side of a jump) and the
    number of jumps. Also splits at gaps longer than 5 sample periods."""
    idx = np.flatnonzero(keep)
    piece = np.full(len(t), -1, dtype=int)
    if len(idx) < 8:
        piece[idx] = 0
        return piece, 0
    if quat is not None:
        q = quat[idx]
        step = (Rotation.from_quat(q[1:]) * Rotation.from_quat(q[:-1]).inv()).magnitude()
        floor = np.radians(0.5)
    else:
        step = np.linalg.norm(np.diff(fields[idx, 0], axis=0), axis=1)
        floor = 50.0
    pad = np.concatenate([[np.inf, np.inf], step, [np.inf, np.inf]])
    left = np.maximum(pad[:-4], pad[1:-3])
    right = np.maximum(pad[3:-1], pad[4:])
    neighbours = np.minimum(left, right)
    neighbours = np.where(
        np.isfinite(neighbours),
        neighbours,
        np.maximum(np.where(np.isfinite(left), left, 0), np.where(np.isfinite(right), right, 0)),
    )
    jump = (step > 4.0 * neighbours) & (step > floor)
    dt = np.diff(t[idx])
    gap = dt > 5.0 * np.median(dt)
    boundary = jump | gap
    piece[idx] = np.concatenate([[0], np.cumsum(boundary)])
    for j in np.flatnonzero(jump):
        piece[idx[max(j - 1, 0) : j + 3]] = -1
    return piece, int(jump.sum())
