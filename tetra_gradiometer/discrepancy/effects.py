"""The library of candidate physical effects the base model may be missing.

Each candidate is a named family of terms added to the per-sensor model
``B_i' = B_i + K_i B^b + B_i^h``. A builder returns, for the current model state, the
family's regressor columns as full-sensor arrays ``(N, 4, 3, p)`` (nT per unit of the
parameter), an optional fixed ``offset`` ``(N, 4, 3)`` nT (the exact remainder of a
nonlinear family at its current estimate, so that the linear columns fit the correction),
and a label ``(sensor, name)`` per column. Units: nT, s, degC, A.

Families that are nonlinear in their parameters (``time_skew``: a shift of the sensor's
own prediction in time; ``sensor_misalignment``: a rotation of it) are linearised around
their current estimate and iterated (Gauss-Newton with the exact remainder as offset).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from ..core.model import SYMMETRIC_ENTRIES


@dataclass
class Context:
    """What builders may use. Arrays in nT (fields), s (time), degC, A.

    Attributes
    ----------
    t : (N,) s
    sensors : sensors in the residual view (0..3 absolute, 1..3 pair differences)
    absolute : True with /odom (each sensor against ``R^T E``), False for pair differences
    b_background : (N, 3) ``B^b`` used by the model
    b_rate : (N, 3) ``dB^b/dt``, nT/s
    prediction : (N, 4, 3) the current model's prediction of every sensor (no noise)
    temperature_c, current_a : (N,) or None
    """

    t: np.ndarray
    sensors: tuple[int, ...]
    absolute: bool
    b_background: np.ndarray
    b_rate: np.ndarray
    prediction: np.ndarray
    temperature_c: np.ndarray | None
    current_a: np.ndarray | None
    piece: np.ndarray | None = None
    rotation: np.ndarray | None = None  # (N, 3, 3) body -> ENU, with /odom
    knot_s: float = 30.0


class PiecewiseSpline:
    """Cubic splines through ``values`` (N, ...) on each continuous piece of the run (the
    attitude may jump between recorded segments; no derivative is taken across a jump)."""

    def __init__(self, t: np.ndarray, values: np.ndarray, piece: np.ndarray | None = None) -> None:
        self.t = t
        self.piece = np.zeros(len(t), dtype=int) if piece is None else piece
        self.shape = values.shape[1:]
        flat = values.reshape(len(t), -1)
        self.parts = []
        for p in np.unique(self.piece):
            idx = np.flatnonzero(self.piece == p)
            if len(idx) >= 8:
                # Quintic: a 10 Hz record of a fast manoeuvre in a 60 000 nT field is
                # interpolated to ~1e-4 nT, where a cubic spline errs by tenths of a nT.
                self.parts.append((idx, make_interp_spline(t[idx], flat[idx], k=5, axis=0)))
            elif len(idx) >= 2:
                self.parts.append((idx, CubicSpline(t[idx], flat[idx], axis=0)))
            else:
                self.parts.append((idx, None))

    def __call__(self, shift: float = 0.0, nu: int = 0) -> np.ndarray:
        """Values (or the ``nu``-th derivative) at ``t - shift`` on every sample."""
        out = np.zeros((len(self.t), int(np.prod(self.shape, dtype=int))))
        for idx, spline in self.parts:
            if spline is None:
                continue
            out[idx] = spline(self.t[idx] - shift, nu, extrapolate=True)
        return out.reshape(len(self.t), *self.shape)


Built = tuple[np.ndarray, np.ndarray | None, list[tuple[int, str]]]


@dataclass(frozen=True)
class Candidate:
    """A named, physically explained family of terms.

    ``requires`` names the recorded inputs the family needs ('odom', 'temperature',
    'current'); ``nonlinear`` families get their offset re-evaluated at the estimate.
    """

    name: str
    physics: str
    parameters: str
    requires: tuple[str, ...]
    build: Callable[[Context, dict[tuple[int, str], float] | None], Built]
    nonlinear: bool = False


def _empty(n: int, p: int) -> np.ndarray:
    return np.zeros((n, 4, 3, p))


def _eddy(ctx: Context, estimate: dict | None) -> Built:
    n, labels = len(ctx.t), []
    cols = _empty(n, 9 * len(ctx.sensors))
    k = 0
    for s in ctx.sensors:
        for r in range(3):
            for c in range(3):
                cols[:, s, r, k] = ctx.b_rate[:, c]
                labels.append((s, f'E{"xyz"[r]}{"xyz"[c]}_s'))
                k += 1
    return cols, None, labels


def _time_skew(ctx: Context, estimate: dict | None) -> Built:
    n = len(ctx.t)
    spline = PiecewiseSpline(ctx.t, ctx.prediction, ctx.piece)
    rate = spline(0.0, 1)
    cols = _empty(n, len(ctx.sensors))
    offset = np.zeros((n, 4, 3))
    labels = []
    for k, s in enumerate(ctx.sensors):
        cols[:, s, :, k] = -rate[:, s]
        labels.append((s, 'tau_s'))
        tau = (estimate or {}).get((s, 'tau_s'), 0.0)
        if tau:
            shifted = spline(tau)[:, s]
            offset[:, s] = shifted - ctx.prediction[:, s] + tau * rate[:, s]
    return cols, offset, labels


def _misalignment(ctx: Context, estimate: dict | None) -> Built:
    n = len(ctx.t)
    cols = _empty(n, 3 * len(ctx.sensors))
    offset = np.zeros((n, 4, 3))
    labels = []
    k = 0
    for s in ctx.sensors:
        p = ctx.prediction[:, s]
        for a in range(3):
            cols[:, s, :, k] = np.cross(np.eye(3)[a], p)
            labels.append((s, f'omega_{"xyz"[a]}_rad'))
            k += 1
        omega = np.array(
            [(estimate or {}).get((s, f'omega_{"xyz"[a]}_rad'), 0.0) for a in range(3)]
        )
        if np.any(omega):
            rotated = Rotation.from_rotvec(omega).apply(p)
            offset[:, s] = rotated - p - np.cross(omega, p)
    return cols, offset, labels


def _reference(ctx: Context, estimate: dict | None) -> Built:
    n = len(ctx.t)
    cols = _empty(n, 9)
    labels = []
    for k, (r, c) in enumerate(SYMMETRIC_ENTRIES):
        cols[:, 0, r, k] = ctx.b_background[:, c]
        if r != c:
            cols[:, 0, c, k] = ctx.b_background[:, r]
        labels.append((0, f'K{"xyz"[r]}{"xyz"[c]}'))
    for a in range(3):
        cols[:, 0, a, 6 + a] = 1.0
        labels.append((0, f'Bh_{"xyz"[a]}_nT'))
    return cols, None, labels


def _per_sensor_scalar(
    ctx: Context, series: np.ndarray, unit: str, reference_offset: bool
) -> Built:
    n = len(ctx.t)
    extra = 3 if (reference_offset and 0 in ctx.sensors) else 0
    cols = _empty(n, 3 * len(ctx.sensors) + extra)
    labels = []
    k = 0
    for s in ctx.sensors:
        for a in range(3):
            cols[:, s, a, k] = series
            labels.append((s, f'{"xyz"[a]}_{unit}'))
            k += 1
    if extra:
        for a in range(3):
            cols[:, 0, a, k] = 1.0
            labels.append((0, f'offset_{"xyz"[a]}_nT'))
            k += 1
    return cols, None, labels


def _thermal(ctx: Context, estimate: dict | None) -> Built:
    temperature = ctx.temperature_c - np.mean(ctx.temperature_c)
    # The drift is c (T - T_ref) with T_ref unknown: sensors 2-4 absorb the constant in
    # their hard iron, the clean reference sensor needs its own offset.
    return _per_sensor_scalar(ctx, temperature, 'nT_per_degC', reference_offset=True)


def _current(ctx: Context, estimate: dict | None) -> Built:
    # No current, no field: the family has no offset of its own.
    return _per_sensor_scalar(ctx, ctx.current_a, 'nT_per_A', reference_offset=False)


def spline_basis(t: np.ndarray, knot_s: float) -> np.ndarray:
    """Cubic B-spline basis (N, nk) on [t0, t1] with about ``knot_s`` between knots."""
    from scipy.interpolate import BSpline

    span = max(t[-1] - t[0], 1e-9)
    intervals = max(1, int(round(span / knot_s)))
    inner = np.linspace(t[0], t[-1], intervals + 1)
    knots = np.concatenate([[t[0]] * 3, inner, [t[-1]] * 3])
    return BSpline.design_matrix(np.clip(t, t[0], t[-1]), knots, 3).toarray()


def _external(ctx: Context, estimate: dict | None) -> Built:
    phi = spline_basis(ctx.t, ctx.knot_s)
    n, nk = phi.shape
    cols = _empty(n, 3 * nk)
    labels = []
    for a in range(3):
        # R^T e_a (world axis a seen in the body frame) is row a of R; the same at every sensor.
        cols[..., a * nk : (a + 1) * nk] = (ctx.rotation[:, a, :, None] * phi[:, None, :])[:, None]
        labels += [(-1, f'{"enu"[a]}_{k}_nT') for k in range(nk)]
    return cols, None, labels


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        'eddy_current',
        'Eddy currents induced in the conducting hull and pressure housings by the change of '
        'the field they see as the vehicle turns; by Lenz their field opposes the change and, '
        'for a hull whose time constant is short against the manoeuvre, is proportional to '
        'the rate of change of the body-frame background field: E_i dB^b/dt with a general '
        '3x3 E_i (seconds) per sensor (the Tolles-Lawson eddy term).',
        'E_i, 3x3 per sensor, seconds (nT per nT/s)',
        (),
        _eddy,
    ),
    Candidate(
        'sensor_misalignment',
        "A sensor's axes rotated against the array (body) frame by a small mounting error: it "
        'reads R_i B instead of B. To first order that is omega_i x B, a skew-symmetric '
        'matrix times the field, which the symmetric soft-iron K_i of the base model cannot '
        'represent (the second-order part is symmetric and is absorbed by K_i).',
        'rotation vector omega_i per sensor, rad',
        (),
        _misalignment,
        nonlinear=True,
    ),
    Candidate(
        'reference_interference',
        "The reference sensor (sensor 1) is not clean: the vehicle's soft iron K_1 B^b and "
        'hard iron B_1^h reach it too. Only an absolute reference (attitude from /odom and the '
        'Earth field) shows it: the pair differences absorb it into K_i1 (I + K_1)^-1. Its '
        'isotropic part K_1 = c I is indistinguishable from a different Earth-field strength.',
        'symmetric K_1 (6) and B_1^h (3, nT)',
        ('odom',),
        _reference,
    ),
    Candidate(
        'time_skew',
        "A sensor's samples stamped late or early by a constant delay tau_i (a filter group "
        'delay or a clock offset in its driver): it reads B_i(t - tau_i), to first order '
        'B_i(t) - tau_i dB_i/dt. One parameter per sensor, the same delay on all three axes '
        '(an isotropic eddy term would look alike, with nine times the parameters).',
        'delay tau_i per sensor, s (positive: the reading is late)',
        (),
        _time_skew,
        nonlinear=True,
    ),
    Candidate(
        'thermal_drift',
        'Offsets of the fluxgates (and of the hard iron near them) that change with the '
        'temperature of the electronics and the housing: c_i (T - T_ref) with the temperature '
        'from /tetra/temperature, c_i in nT/degC per sensor and axis.',
        'c_i per sensor and axis, nT/degC (plus the reference offset)',
        ('temperature',),
        _thermal,
    ),
    Candidate(
        'vehicle_current',
        'The field of the currents drawn from the battery (thrusters, payload) along the '
        "vehicle's wiring: by Biot-Savart proportional to the current, v_i I(t) with I from "
        '/battery_state, v_i in nT/A per sensor and axis.',
        'v_i per sensor and axis, nT/A',
        ('current',),
        _current,
    ),
    Candidate(
        'external_field',
        'A field from outside the vehicle that the Earth-field model lacks: a distant target or '
        'geology along the track, or the diurnal variation. It is fixed in the world frame (it does '
        'not turn with the vehicle), the same at all four sensors, and varies slowly: x(t) in ENU '
        '(a cubic B-spline in time, knots every 30 s), seen in the body frame as R^T x(t).',
        'spline weights per ENU axis, nT (all sensors)',
        ('odom',),
        _external,
    ),
)

#: name -> candidate.
LIBRARY: dict[str, Candidate] = {c.name: c for c in CANDIDATES}
