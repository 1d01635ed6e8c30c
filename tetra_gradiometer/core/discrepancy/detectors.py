"""The search's detectors of model errors: families of terms it tests beside the registry's
effects that are not vehicle effects the operational model carries (a sensor's delay or
misalignment, interference at the reference sensor, a field from outside the vehicle, the
steps and spectral lines the scans of the residual find). Compensation cannot use them:
they are nonlinear in their parameters, need an absolute attitude, or are fixed in time.

Families that are nonlinear in their parameters (``time_skew``: a shift of the sensor's
own prediction in time; ``sensor_misalignment``: a rotation of it) are linearised around
their current estimate and iterated (Gauss-Newton with the exact remainder as offset).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, CubicSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from ..model import SYMMETRIC_ENTRIES, SensorInterference
from ..simulator import random_interference
from .candidate import (
    Array,
    Built,
    Candidate,
    Context,
    Estimate,
    Hidden,
    Simulated,
    empty,
    required,
)


class PiecewiseSpline:
    """Cubic splines through ``values`` (N, ...) on each continuous piece of the run (the
    attitude may jump between recorded segments; no derivative is taken across a jump)."""

    def __init__(self, t: Array, values: Array, piece: NDArray[np.int_] | None = None) -> None:
        self.t = t
        self.piece = np.zeros(len(t), dtype=int) if piece is None else piece
        self.shape = values.shape[1:]
        flat = values.reshape(len(t), -1)
        self.parts: list[tuple[NDArray[np.int_], Callable[..., Array] | None]] = []
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

    def __call__(self, shift: float = 0.0, nu: int = 0) -> Array:
        """Values (or the ``nu``-th derivative) at ``t - shift`` on every sample."""
        out = np.zeros((len(self.t), int(np.prod(self.shape, dtype=int))))
        for idx, spline in self.parts:
            if spline is None:
                continue
            out[idx] = spline(self.t[idx] - shift, nu, extrapolate=True)
        return out.reshape(len(self.t), *self.shape)


def _time_skew(ctx: Context, estimate: Estimate | None) -> Built:
    n = len(ctx.t)
    spline = PiecewiseSpline(ctx.t, ctx.prediction, ctx.piece)
    rate = spline(0.0, 1)
    cols = empty(n, len(ctx.sensors))
    offset = np.zeros((n, 4, 3))
    labels: list[tuple[int, str]] = []
    for k, s in enumerate(ctx.sensors):
        labels.append((s, 'tau_s'))
        tau = (estimate or {}).get((s, 'tau_s'), 0.0)
        # Linearised at the estimate: d/dtau B(t - tau) = -dB/dt (t - tau). (The slope at
        # tau = 0 makes the iteration a chord method, which diverges when another unit of the
        # sensor, an eddy term, leaves the delay little of its own to fit.)
        slope = spline(tau, 1)[:, s] if tau else rate[:, s]
        cols[:, s, :, k] = -slope
        if tau:
            offset[:, s] = spline(tau)[:, s] - ctx.prediction[:, s] + tau * slope
    return cols, offset, labels


def _misalignment(ctx: Context, estimate: Estimate | None) -> Built:
    n = len(ctx.t)
    cols = empty(n, 3 * len(ctx.sensors))
    offset = np.zeros((n, 4, 3))
    labels: list[tuple[int, str]] = []
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


def _reference(ctx: Context, estimate: Estimate | None) -> Built:
    n = len(ctx.t)
    cols = empty(n, 9)
    labels: list[tuple[int, str]] = []
    for k, (r, c) in enumerate(SYMMETRIC_ENTRIES):
        cols[:, 0, r, k] = ctx.b_background[:, c]
        if r != c:
            cols[:, 0, c, k] = ctx.b_background[:, r]
        labels.append((0, f'K{"xyz"[r]}{"xyz"[c]}'))
    for a in range(3):
        cols[:, 0, a, 6 + a] = 1.0
        labels.append((0, f'Bh_{"xyz"[a]}_nT'))
    return cols, None, labels


def spline_basis(t: Array, knot_s: float) -> Array:
    """Cubic B-spline basis (N, nk) on [t0, t1] with about ``knot_s`` between knots."""
    span = max(t[-1] - t[0], 1e-9)
    intervals = max(1, int(round(span / knot_s)))
    inner = np.linspace(t[0], t[-1], intervals + 1)
    knots = np.concatenate([[t[0]] * 3, inner, [t[-1]] * 3])
    return BSpline.design_matrix(np.clip(t, t[0], t[-1]), knots, 3).toarray()


def _external(ctx: Context, estimate: Estimate | None) -> Built:
    rotation = required(ctx.rotation, 'the attitude (/odom)')
    # A spline per continuous piece: across a jump between recorded segments the vehicle is
    # elsewhere, and a field fixed in the world (a distant target, geology) is another.
    piece = np.zeros(len(ctx.t), dtype=int) if ctx.piece is None else ctx.piece
    pieces = [np.flatnonzero(piece == p) for p in np.unique(piece)]
    bases = [spline_basis(ctx.t[idx], ctx.knot_s) for idx in pieces]
    phi = np.zeros((len(ctx.t), sum(b.shape[1] for b in bases)))
    start = 0
    for idx, basis in zip(pieces, bases, strict=True):
        phi[idx, start : start + basis.shape[1]] = basis
        start += basis.shape[1]
    n, nk = phi.shape
    cols = empty(n, 3 * nk)
    labels: list[tuple[int, str]] = []
    for a in range(3):
        # R^T e_a (world axis a seen in the body frame) is row a of R; the same at every sensor.
        cols[..., a * nk : (a + 1) * nk] = (rotation[:, a, :, None] * phi[:, None, :])[:, None]
        labels += [(-1, f'{"enu"[a]}_{k}_nT') for k in range(nk)]
    return cols, None, labels


def step_label(axis: int, t_s: float) -> str:
    """The parameter name of a step's jump on ``axis`` (0-2) at ``t_s`` s."""
    return f'jump_{"xyz"[axis]}_nT@{t_s:.3f}s'


def line_label(wave: str, axis: int, frequency_hz: float) -> str:
    """The parameter name of a line's ``wave`` ('sin' or 'cos') term on ``axis`` (0-2)."""
    return f'{wave}_{"xyz"[axis]}_nT@{frequency_hz:.6f}Hz'


def _steps(ctx: Context, estimate: Estimate | None) -> Built:
    steps = [st for st in ctx.open_world.steps if st.sensor in ctx.sensors]
    cols = empty(len(ctx.t), 3 * len(steps))
    labels: list[tuple[int, str]] = []
    for k, step in enumerate(steps):
        after = (ctx.t >= step.t_s).astype(float)
        for a in range(3):
            cols[:, step.sensor, a, 3 * k + a] = after
            labels.append((step.sensor, step_label(a, step.t_s)))
    return cols, None, labels


def _lines(ctx: Context, estimate: Estimate | None) -> Built:
    terms = [
        (line.frequency_hz, s)
        for line in ctx.open_world.lines
        for s in line.sensors
        if s in ctx.sensors
    ]
    cols = empty(len(ctx.t), 6 * len(terms))
    labels: list[tuple[int, str]] = []
    for k, (frequency, s) in enumerate(terms):
        phase = 2 * np.pi * frequency * (ctx.t - ctx.t[0])
        for j, (name, wave) in enumerate((('sin', np.sin(phase)), ('cos', np.cos(phase)))):
            for a in range(3):
                cols[:, s, a, 6 * k + 3 * j + a] = wave
                labels.append((s, line_label(name, a, frequency)))
    return cols, None, labels


# Unit-size instances for the simulator (synthetic missions)


def _draw_misalignment(rng: np.random.Generator, mask: Array) -> Hidden:
    return Hidden({'sensor_misalignment': rng.normal(0, 1.0, (4, 3)) * mask[:, None]})


def _draw_reference(rng: np.random.Generator, mask: Array) -> Hidden:
    ref = random_interference(rng, reference_clean=False)
    k = np.zeros((4, 3, 3))
    b = np.zeros((4, 3))
    k[0], b[0] = ref.k_soft[0], ref.b_hard[0] * rng.uniform(0.3, 1.0)
    return Hidden(interference=SensorInterference(k, b))


def _draw_time_skew(rng: np.random.Generator, mask: Array) -> Hidden:
    return Hidden({'time_skew': rng.choice([-1.0, 1.0], 4) * rng.uniform(0.5, 1.0, 4) * mask})


DETECTORS: tuple[Candidate, ...] = (
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
        simulated=Simulated(_draw_misalignment),
        separated_by=(
            'manoeuvres that turn the field through all three body axes (a rotation of the '
            'axes is skew-symmetric in the field, soft iron symmetric)'
        ),
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
        simulated=Simulated(_draw_reference, sensors=(0,)),
        separated_by=(
            'an absolute reference (/odom and the Earth field) over a wide range of headings'
        ),
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
        # The isotropic part of eddy_current to first order: the detector fits that one.
        in_detector=False,
        simulated=Simulated(_draw_time_skew),
        separated_by=(
            'a manoeuvre with a different spectrum of field rates (fast, short turns, where a'
            " delay's higher-order terms and its sameness on all three axes show)"
        ),
    ),
    Candidate(
        'external_field',
        'A field from outside the vehicle that the Earth-field model lacks: a distant target or '
        'geology along the track, or the diurnal variation. It is fixed in the world frame '
        '(it does not turn with the vehicle), the same at all four sensors, and varies slowly: '
        'x(t) in ENU '
        '(a cubic B-spline in time, knots every 30 s), seen in the body frame as R^T x(t).',
        'spline weights per ENU axis, nT (all sensors)',
        ('odom',),
        _external,
        # Left out of the detector, so that a target's common part stays in its residual.
        in_detector=False,
        separated_by=(
            'headings that differ on the same stretch (a world-fixed field turns in the body '
            'frame)'
        ),
        no_odom_reason=(
            'no usable /odom: the world frame is unknown, and the pair differences '
            "B_i' - B_1' cancel a field that is the same at all sensors"
        ),
    ),
    Candidate(
        'hard_iron_step',
        "A sensor's constant offset changes at a time t_s (a magnetized part picked up or "
        'lost, a component switched for good): a jump vector from t_s on. Found by '
        'a change-point scan of the residual (binary segmentation, '
        'likelihood-ratio statistic of a mean shift, Bonferroni over the possible times).',
        'jump vector per step, nT, from t_s (s from the first sample) on',
        (),
        _steps,
        in_detector=False,
        separated_by=(
            'a run long enough on each side of the change, at steady temperature and current'
        ),
    ),
    Candidate(
        'periodic_interference',
        'A rotating magnet near some sensors (a shaft, a pump, a fan) adds a sinusoid at its '
        'rotation frequency. Found as a spectral line of the residual '
        '(periodogram over its local noise level, with a false-alarm probability), its '
        'frequency refined by least squares; fitted as sine and cosine terms per axis of the '
        'sensors that carry it; a recorded channel with a line there too is named with it.',
        'sine and cosine amplitudes per axis, nT, at frequency_hz',
        (),
        _lines,
        in_detector=False,
        separated_by=(
            'a record of the candidate source (shaft or pump speed), or a run with it stopped'
        ),
    ),
)

#: The open-world families: built from what the scans of the residual found
#: (:mod:`.openworld`), offered when no other family explains the rest.
OPEN_WORLD = ('hard_iron_step', 'periodic_interference')
