"""The library of candidate physical effects the base model may be missing: the one
registry of effect names (:data:`CANDIDATES`, :data:`LIBRARY`).

To add an effect, add one :class:`Candidate` to :data:`CANDIDATES` (its builder, and with
``simulated`` how synthetic missions hide it); the search, the target detector, synthetic
cases, the command line's ``--candidates`` and the report all loop over the registry.

Each candidate is a named family of terms added to the per-sensor model
``B_i' = B_i + K_i B^b + B_i^h``. A builder returns, for the current model state, the
family's regressor columns as full-sensor arrays ``(N, 4, 3, p)`` (nT per unit of the
parameter), an optional fixed ``offset`` ``(N, 4, 3)`` nT (the exact remainder of a
nonlinear family at its current estimate, so that the linear columns fit the correction),
and a label ``(sensor, name)`` per column. Units: nT, s, degC, A.

The operational effects (``eddy_current``, ``thermal_drift``, ``vehicle_current``) are the
registry's (:data:`tetra_gradiometer.core.effects.EFFECTS`): their physics text and their
regressors come from there, laid out per sensor here (:func:`registry_columns`). The
thermal and current regressors are the registry's own (``Effect.regressors``, the
temperature against the run's mean, every current channel); the eddy term's regressor is
the same quantity, the background field's rate, estimated here on the whole run from the
view's ``B^b`` (smoothed, non-causal: the search has the run, the live path does not).

Families that are nonlinear in their parameters (``time_skew``: a shift of the sensor's
own prediction in time; ``sensor_misalignment``: a rotation of it) are linearised around
their current estimate and iterated (Gauss-Newton with the exact remainder as offset).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, CubicSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from ...errors import InputError
from ..effects import EFFECTS, TEMPERATURE, Channels, current_channel
from ..model import SYMMETRIC_ENTRIES, SensorInterference
from ..simulator import random_interference
from .openworld import OpenWorld

Array = NDArray[np.float64]
#: Linearisation point of a nonlinear family: (sensor, parameter label) -> value.
Estimate = dict[tuple[int, str], float]


@dataclass(frozen=True)
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
    temperature_c, current_a : (N,) or None (``current_a``: the battery's, ``/battery_state``)
    piece : (N,) index of the continuous piece of the run, or None (one piece)
    rotation : (N, 3, 3) body -> ENU with /odom, or None
    knot_s : knot spacing of the ``external_field`` spline, s
    open_world : the steps and spectral lines the scans found (:mod:`.openworld`)
    extra_currents : further current channels, (BatteryState topic, (N,) A) each (one per
        thruster, say)
    signals : further recorded signals, ``signal:TOPIC#FIELD`` -> (N,) values
    """

    t: Array
    sensors: tuple[int, ...]
    absolute: bool
    b_background: Array
    b_rate: Array
    prediction: Array
    temperature_c: Array | None
    current_a: Array | None
    piece: NDArray[np.int_] | None = None
    rotation: Array | None = None
    knot_s: float = 30.0
    open_world: OpenWorld = field(default_factory=OpenWorld)
    extra_currents: tuple[tuple[str, Array], ...] = ()
    signals: dict[str, Array] = field(default_factory=dict)


def _required(value: Array | None, what: str) -> Array:
    """``value``, which the candidate's ``requires`` guarantees (the workflow tests it first)."""
    if value is None:
        raise InputError(f'this candidate needs {what}, which the run does not have')
    return value


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


#: What a builder returns: columns (N, 4, 3, p) nT per unit, an offset (N, 4, 3) nT or None,
#: and a ``(sensor, name)`` label per column (sensor -1: common to all sensors).
Built = tuple[Array, Array | None, list[tuple[int, str]]]


@dataclass(frozen=True)
class Hidden:
    """A unit-size instance of an effect for the simulator (synthetic missions).

    Attributes
    ----------
    effects : ``core.simulator.Effects`` field -> value (SI), the effect's own terms
    interference : added to the scenario's ``SensorInterference`` (sensor-1 iron), or None
    """

    effects: dict[str, Array] = field(default_factory=dict)
    interference: SensorInterference | None = None


@dataclass(frozen=True)
class Simulated:
    """How synthetic missions hide a candidate in the simulator.

    Attributes
    ----------
    draw : ``draw(rng, mask)`` -> :class:`Hidden`, random terms of unit size in the sensors
        where ``mask`` (4,) is 1
    sensors : the sensors the effect always sits in (0-based), or None: drawn per case
    """

    draw: Callable[[np.random.Generator, Array], Hidden]
    sensors: tuple[int, ...] | None = None


@dataclass(frozen=True)
class Candidate:
    """A named, physically explained family of terms: one entry of the library.

    Attributes
    ----------
    name : the effect's one name (report, ``--candidates``, synthetic cases)
    physics : what it is, for the report
    parameters : its parameters with their units
    requires : the recorded inputs the family needs ('odom', 'temperature', 'current')
    build : ``build(ctx, estimate)`` -> :data:`Built`, the regressors at ``estimate``
    nonlinear : the offset is re-evaluated at the estimate (Gauss-Newton)
    in_detector : the target detector fits it (a family global in time whose columns are
        not a special case of another's)
    simulated : how synthetic missions hide it, or None (not simulated that way)
    no_odom_reason : why it is untestable without /odom, when more than ``requires`` says
    separated_by : the data that make its regressors differ from those of look-alikes (the
        report's advice when it is confounded)
    """

    name: str
    physics: str
    parameters: str
    requires: tuple[str, ...]
    build: Callable[[Context, Estimate | None], Built]
    nonlinear: bool = False
    in_detector: bool = True
    simulated: Simulated | None = None
    no_odom_reason: str | None = None
    separated_by: str = ''


def _empty(n: int, p: int) -> Array:
    return np.zeros((n, 4, 3, p))


def registry_columns(ctx: Context, x: Array, label: Callable[[int, int], str]) -> Built:
    """A registry effect's regressors ``x`` (N, m) as per-sensor columns: for each sensor of
    the view, axis ``a`` and regressor ``j`` a column ``x[:, j]`` at (sensor, axis) with the
    label ``label(a, j)`` (the coefficient is in nT per unit of ``x``)."""
    n, m = x.shape
    cols = _empty(n, 3 * m * len(ctx.sensors))
    labels: list[tuple[int, str]] = []
    k = 0
    for s in ctx.sensors:
        for a in range(3):
            for j in range(m):
                cols[:, s, a, k] = x[:, j]
                labels.append((s, label(a, j)))
                k += 1
    return cols, None, labels


def _eddy(ctx: Context, estimate: Estimate | None) -> Built:
    # The registry's regressor, the background's rate (nT/s), as the search estimates it.
    return registry_columns(ctx, ctx.b_rate, lambda a, j: f'E{"xyz"[a]}{"xyz"[j]}_s')


def _time_skew(ctx: Context, estimate: Estimate | None) -> Built:
    n = len(ctx.t)
    spline = PiecewiseSpline(ctx.t, ctx.prediction, ctx.piece)
    rate = spline(0.0, 1)
    cols = _empty(n, len(ctx.sensors))
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
    cols = _empty(n, 3 * len(ctx.sensors))
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
    cols = _empty(n, 9)
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


def recorded_currents(
    current_a: Array | None, extra: tuple[tuple[str, Array], ...]
) -> list[tuple[str, Array]]:
    """Every current channel of the run, (BatteryState topic, (N,) A): the battery's first."""
    battery = [] if current_a is None else [('/battery_state', current_a)]
    return battery + list(extra)


def _thermal(ctx: Context, estimate: Estimate | None) -> Built:
    recorded = _required(ctx.temperature_c, 'the temperature (/tetra/temperature)')
    # The registry's regressor T - T_ref, with T_ref the run's mean temperature.
    channels = Channels(ctx.t, ctx.b_background, {TEMPERATURE: recorded})
    reference = (float(np.mean(recorded)),)
    x = EFFECTS['thermal_drift'].regressors(channels, (TEMPERATURE,), reference)
    cols, _, labels = registry_columns(ctx, x, lambda a, j: f'{"xyz"[a]}_nT_per_degC')
    if 0 not in ctx.sensors:
        return cols, None, labels
    # The drift is c (T - T_ref) with T_ref unknown: sensors 2-4 absorb the constant in
    # their hard iron, the clean reference sensor needs its own offset.
    offsets = _empty(len(ctx.t), 3)
    for a in range(3):
        offsets[:, 0, a, a] = 1.0
        labels.append((0, f'offset_{"xyz"[a]}_nT'))
    return np.concatenate([cols, offsets], axis=-1), None, labels


def _current(ctx: Context, estimate: Estimate | None) -> Built:
    # No current, no field: the family has no offset of its own. Every current channel
    # (the battery's and each further BatteryState's) has its own coefficients.
    recorded = recorded_currents(ctx.current_a, ctx.extra_currents)
    if not recorded:
        _required(None, 'a current (/battery_state or another BatteryState topic)')
    series = {current_channel(topic): values for topic, values in recorded}
    names = tuple(series)
    x = EFFECTS['vehicle_current'].regressors(Channels(ctx.t, ctx.b_background, series), names, ())
    topics = [topic for topic, _ in recorded]
    suffix = [''] if topics == ['/battery_state'] else [f'[{topic}]' for topic in topics]
    return registry_columns(ctx, x, lambda a, j: f'{"xyz"[a]}_nT_per_A{suffix[j]}')


def spline_basis(t: Array, knot_s: float) -> Array:
    """Cubic B-spline basis (N, nk) on [t0, t1] with about ``knot_s`` between knots."""
    span = max(t[-1] - t[0], 1e-9)
    intervals = max(1, int(round(span / knot_s)))
    inner = np.linspace(t[0], t[-1], intervals + 1)
    knots = np.concatenate([[t[0]] * 3, inner, [t[-1]] * 3])
    return BSpline.design_matrix(np.clip(t, t[0], t[-1]), knots, 3).toarray()


def _external(ctx: Context, estimate: Estimate | None) -> Built:
    rotation = _required(ctx.rotation, 'the attitude (/odom)')
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
    cols = _empty(n, 3 * nk)
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
    cols = _empty(len(ctx.t), 3 * len(steps))
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
    cols = _empty(len(ctx.t), 6 * len(terms))
    labels: list[tuple[int, str]] = []
    for k, (frequency, s) in enumerate(terms):
        phase = 2 * np.pi * frequency * (ctx.t - ctx.t[0])
        for j, (name, wave) in enumerate((('sin', np.sin(phase)), ('cos', np.cos(phase)))):
            for a in range(3):
                cols[:, s, a, 6 * k + 3 * j + a] = wave
                labels.append((s, line_label(name, a, frequency)))
    return cols, None, labels


# ---------------------------------------------------------------------------------------
# Unit-size instances for the simulator (synthetic missions)


def _draw_eddy(rng: np.random.Generator, mask: Array) -> Hidden:
    return Hidden({'eddy_current': rng.normal(0, 1.0, (4, 3, 3)) * mask[:, None, None]})


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


def _draw_thermal(rng: np.random.Generator, mask: Array) -> Hidden:
    return Hidden({'thermal_drift': rng.normal(0, 1.0, (4, 3)) * mask[:, None]})


def _draw_current(rng: np.random.Generator, mask: Array) -> Hidden:
    return Hidden({'vehicle_current': rng.normal(0, 1.0, (4, 3)) * mask[:, None]})


#: The end of a registry effect's physics text that describes the operational path's
#: estimate of its regressor, not the search's (see the module).
_OPERATIONAL_ONLY = "; the rate is B_1''s, differentiated causally."


def _physics(name: str) -> str:
    """The registry effect's physics text, for the report."""
    text = EFFECTS[name].physics
    return text.removesuffix(_OPERATIONAL_ONLY) + '.' if text.endswith(_OPERATIONAL_ONLY) else text


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        'eddy_current',
        _physics('eddy_current'),
        'E_i, 3x3 per sensor, seconds (nT per nT/s)',
        (),
        _eddy,
        simulated=Simulated(_draw_eddy),
        separated_by=(
            'turns about different axes at different rates (a general 3x3 response to the '
            "field rate; a delay is isotropic and also follows the field's curvature, which "
            'fast, short manoeuvres bring out)'
        ),
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
        'thermal_drift',
        _physics('thermal_drift'),
        'c_i per sensor and axis, nT/degC (plus the reference offset)',
        ('temperature',),
        _thermal,
        simulated=Simulated(_draw_thermal),
        separated_by=(
            'a temperature change while the attitude and the current stay steady (or a run '
            'whose temperature does not follow its manoeuvres)'
        ),
    ),
    Candidate(
        'vehicle_current',
        _physics('vehicle_current'),
        'v_i per sensor, axis and current channel, nT/A',
        ('current',),
        _current,
        simulated=Simulated(_draw_current),
        separated_by=(
            'current changes at steady attitude and temperature (thruster steps during a '
            'straight leg)'
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
        'lost, a component switched for good): a jump vector from t_s on. Outside the '
        'library: found by a change-point scan of the residual (binary segmentation, '
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
        'rotation frequency. Outside the library: found as a spectral line of the residual '
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
#: (:mod:`.openworld`), offered when no library family explains the rest.
OPEN_WORLD = ('hard_iron_step', 'periodic_interference')

#: name -> candidate: the one registry of effect names.
LIBRARY: dict[str, Candidate] = {c.name: c for c in CANDIDATES}
