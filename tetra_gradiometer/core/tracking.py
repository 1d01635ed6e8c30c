"""Online tracking of the calibration's change: a causal, blocked Kalman filter on the pair
offsets ``b`` of eq. 18, fed by the compensated tensor.

After the trim the vehicle changes: viscous remanence relaxes, a magnetised part touches a
housing. Every such change is body-fixed and moves the hard-iron offsets; with the frozen
calibration the compensated tensor is ``G = G_true + dD``, ``vec(dD) = H db`` with ``H``
(9, 9) the offset columns of eq. 18's design and ``db`` (3, 3) the change of the pair
offsets ``B_(i+2)1^h`` (T). The tracker estimates ``db`` and removes it:
``G_tracked = G - H db_hat``.

What the data observe:

* **always, whatever the field** (4 combinations): a true gradient is symmetric and
  traceless, so ``L vec(G) = L H db + noise`` (``L`` = ``design.CONSTRAINT_ROWS``) observes
  the four combinations of ``db`` that break symmetry or trace, from a fraction of a second of
  data (the noise averages down like ``1 / sqrt(n)``). A single sensor's offset step spans 3
  of these 4 dimensions: it is re-estimated from the constraints alone.
* **with the attitude, when the body turns against the world** (the other 5): the
  symmetric traceless part of ``H db`` is a body-fixed gradient, the survey's signal a
  world-fixed one. The state then holds the world gradient too (5 coefficients in ENU, a
  random walk: geology varies along the track) and the body's rotation separates them:
  a heading reversal (U-turn, 30 s) observes the two vertical shears (body ``xz``, ``yz``:
  they change sign with the heading), the turn's quarter headings ``xx - yy`` and ``xy``.
  The vertical component (``zz``) changes only with roll and pitch: on level lines it stays
  at its prior. Before the first reversal a body-fixed offset and a world field varying
  along the line look the same.
* **the trim's permanent field** (a prior, not an observation): remanence relaxes by a
  fraction of itself, so the process noise has a part along the calibration's own ``b``
  (``relative_rate_per_sqrt_s``), beside a part of its own in the observed combinations
  (``offset_rate_t_per_sqrt_s``) and a smaller one in the hidden ones
  (``hidden_rate_t_per_sqrt_s``).
  The constraints pin the fraction within seconds and, through this prior, predict the part
  of the change the constraints do not see; what the bodies do unlike each other stays in
  the isotropic part and its covariance.

Process model: random walks (a relaxation is a slow, smooth walk), the world gradient's per
second. Blocks of ``block_s`` seconds are one update each (information form: sums over the
block's samples, then one small solve), and each sample is corrected with the state from the
blocks before its own: causal, O(1) per sample. A block whose innovation fails a chi-square
gate (a step not yet handed over, a target passing close, a burst) does not update the
state, and samples the caller flags (``exclude``: targets) never do. A step named by the
health monitor (:meth:`OffsetTracker.step`) widens the changed sensor's offset covariance,
and the blocks after it re-estimate that offset. The state's covariance adds
``diag(H P_b H^T)`` (per component, (T/m)^2) to the published variance.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ._distributions import chi2_isf
from ._validate import as_array, as_tensors, same_length
from .design import CONSTRAINT_ROWS, affine_interference_design
from .geometry import TetraGeometry
from .model import InterferenceParameters
from .types import FloatArray
from .uncertainty import noise_jacobian
from .units import NT_PER_T

__all__ = ['OffsetTracker', 'TrackedChunk', 'TrackerConfig', 'TrackerEvent', 'handed_over']

#: The 5 symmetric traceless basis tensors (xx - yy, xy, xz, yz, 2 zz - xx - yy), unit norm.
_WORLD_BASIS = np.zeros((5, 3, 3))
_WORLD_BASIS[0, 0, 0], _WORLD_BASIS[0, 1, 1] = 1.0, -1.0
for _k, (_i, _j) in enumerate(((0, 1), (0, 2), (1, 2)), start=1):
    _WORLD_BASIS[_k, _i, _j] = _WORLD_BASIS[_k, _j, _i] = 1.0
_WORLD_BASIS[4] = np.diag([-1.0, -1.0, 2.0])
_WORLD_BASIS /= np.linalg.norm(_WORLD_BASIS, axis=(1, 2))[:, None, None]
del _k, _i, _j
N_OFFSETS = 9
N_WORLD = 5


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of :class:`OffsetTracker` (units in the names).

    ``relative_rate_per_sqrt_s``: random-walk rate of the calibration's own offset pattern
    ``b``, as a fraction of it (a remanence relaxing by 0.5 % in 600 s walks at ~2e-4);
    ``offset_rate_t_per_sqrt_s``: random-walk rate of the pair offsets in the 4
    combinations the constraints observe, T; ``hidden_rate_t_per_sqrt_s``: in the other 5
    (a body-fixed gradient: kept small, it is what geology could be mistaken for);
    ``world_rate_t_per_m_sqrt_s``: of each world-gradient coefficient, T/m (geology along
    the track); ``step_sigma_t``: a handed-over step's prior per axis, T;
    ``initial_sigma_t``: the offsets' change at the start, per axis, T;
    ``gate_p``: a block whose innovation is less likely than this is not used.
    """

    block_s: float = 0.5
    relative_rate_per_sqrt_s: float = 1e-4
    offset_rate_t_per_sqrt_s: float = 1e-12
    hidden_rate_t_per_sqrt_s: float = 1e-12
    world_rate_t_per_m_sqrt_s: float = 0.1e-9
    world_sigma_t_per_m: float = 5e-9
    step_sigma_t: float = 5e-9
    initial_sigma_t: float = 0.02e-9
    gate_p: float = 1e-6

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            # A rate of zero freezes what it drives; a block, a prior or a gate cannot be 0.
            zero_ok = name.endswith('sqrt_s') or name == 'initial_sigma_t'
            if not (np.isfinite(value) and (value >= 0 if zero_ok else value > 0)):
                raise InputError(f'TrackerConfig.{name} must be positive, got {value}')
        if self.gate_p >= 1:
            raise InputError(f'TrackerConfig.gate_p must be below 1, got {self.gate_p}')


@dataclass(frozen=True)
class TrackerEvent:
    """One entry of the audit trail: ``t_s`` (the block's end, or the step's time), s;
    ``kind`` (``update``, ``gated``, ``excluded``, ``step``); ``offsets_t`` (3, 3) the pair
    offsets' change after it, T; ``sigma_t`` (3, 3) its 1-sigma, T; ``sensors`` (1-based, a
    step's); ``statistic`` the block's innovation chi-square (NaN for a step)."""

    t_s: float
    kind: str
    offsets_t: FloatArray
    sigma_t: FloatArray
    sensors: tuple[int, ...] = ()
    statistic: float = float('nan')

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, offsets in nT."""
        return {
            't_s': float(self.t_s),
            'kind': self.kind,
            'offsets_nT': (self.offsets_t * NT_PER_T).round(6).tolist(),
            'sigma_nT': (self.sigma_t * NT_PER_T).round(6).tolist(),
            'sensors': list(self.sensors),
            'statistic': None if np.isnan(self.statistic) else float(self.statistic),
        }


@dataclass
class TrackedChunk:
    """What :meth:`OffsetTracker.update` returns for ``n`` samples: ``g`` (n, 3, 3) T/m the
    tracked tensor; ``variance`` (n, 9) (T/m)^2 the state's share of each component's
    variance (row-major); ``offsets`` (n, 9) T the pair offsets' change removed from each
    sample; ``events`` the audit entries closed in the chunk."""

    g: FloatArray
    variance: FloatArray
    offsets: FloatArray
    events: list[TrackerEvent] = field(default_factory=list)


#: ``health(start, stop, g_tracked)`` -> the steps it detected there, each ``(t_s, sensors)``.
HealthFeed = Callable[[int, int, FloatArray], Sequence[tuple[float, tuple[int, ...]]]]


class OffsetTracker:
    """The estimator of the module docstring.

    Parameters
    ----------
    geometry : TetraGeometry
    parameters : InterferenceParameters
        The frozen calibration (its ``b`` shapes the relaxation prior; its ``k`` the noise).
    sensor_noise_t : float
        Per-axis sensor noise, tesla RMS (> 0).
    config : TrackerConfig
    with_world : bool
        Estimate the world gradient too (then :meth:`update` needs the attitude): the five
        symmetric traceless combinations become observable when the body turns.
    """

    def __init__(
        self,
        geometry: TetraGeometry,
        parameters: InterferenceParameters,
        sensor_noise_t: float,
        config: TrackerConfig | None = None,
        *,
        with_world: bool = True,
    ) -> None:
        if not (np.isfinite(sensor_noise_t) and sensor_noise_t > 0):
            raise InputError(f'sensor_noise_t must be positive, got {sensor_noise_t}')
        self.config = config or TrackerConfig()
        self.with_world = with_world
        self._h = affine_interference_design(geometry, symmetric=False)[3][:, 27:]  # (9, 9)
        jacobian = noise_jacobian(geometry, parameters)
        rows = np.eye(9) if with_world else CONSTRAINT_ROWS
        noise = sensor_noise_t**2 * rows @ jacobian @ jacobian.T @ rows.T
        self._whiten = np.linalg.inv(np.linalg.cholesky(noise)) @ rows  # (m, 9)
        self._h_white = self._whiten @ self._h
        self._pattern = parameters.b_hard.reshape(9)
        seen = CONSTRAINT_ROWS @ self._h  # (4, 9): the combinations observed at every instant
        self._seen = np.linalg.pinv(seen) @ seen  # projector onto them
        self._steps = _step_directions(self._h, jacobian)
        size = N_OFFSETS + (N_WORLD if with_world else 0)
        self._x = np.zeros(size)
        self._p = np.zeros((size, size))
        self._p[:N_OFFSETS, :N_OFFSETS] = self.config.initial_sigma_t**2 * np.eye(N_OFFSETS)
        if with_world:
            self._p[N_OFFSETS:, N_OFFSETS:] = self.config.world_sigma_t_per_m**2 * np.eye(N_WORLD)
        self._origin: float | None = None
        self._open: _Block | None = None
        self.events: list[TrackerEvent] = []

    # ------------------------------------------------------------------ public

    @property
    def offsets_t(self) -> FloatArray:
        """The pair offsets' change now, (3, 3) T (row ``i``: sensor ``i + 2`` against 1)."""
        return self._x[:N_OFFSETS].reshape(3, 3).copy()

    @property
    def offsets_sigma_t(self) -> FloatArray:
        """Its 1-sigma, (3, 3) T."""
        return np.sqrt(np.diag(self._p)[:N_OFFSETS]).reshape(3, 3)

    def corrected(self, parameters: InterferenceParameters) -> InterferenceParameters:
        """``parameters`` with the tracked change added to ``b`` (the calibration in use)."""
        return InterferenceParameters(
            parameters.k_soft, parameters.b_hard + self.offsets_t, parameters.terms
        )

    def update(
        self,
        t_s: FloatArray,
        g_compensated: FloatArray,
        orientation_xyzw: FloatArray | None = None,
        exclude: FloatArray | None = None,
        health: HealthFeed | None = None,
    ) -> TrackedChunk:
        """Correct samples in time order and learn from them.

        Parameters
        ----------
        t_s : (n,) s, increasing
        g_compensated : (n, 3, 3) T/m, compensated with the frozen calibration
        orientation_xyzw : (n, 4), quaternions rotating body vectors into ENU; required
            ``with_world``
        exclude : (n,) bool, optional; samples never learnt from (targets)
        health : optional; fed each block's tracked tensor, returns the steps it detected
            there (their sensors' offsets are then re-estimated)
        """
        t_s = as_array(t_s, 't_s', (None,))
        g = as_tensors(g_compensated, 'g_compensated')
        same_length(t_s=t_s, g_compensated=g)
        n = len(t_s)
        rotation = self._rotations(orientation_xyzw, n)
        keep = np.ones(n) if exclude is None else 1.0 - np.asarray(exclude, dtype=float)
        if self._origin is None and n:
            self._origin = float(t_s[0])
        index = np.floor((t_s - (self._origin or 0.0)) / self.config.block_s).astype(np.int64)
        out = TrackedChunk(np.empty_like(g), np.empty((n, 9)), np.empty((n, 9)))
        events_before = len(self.events)
        bounds = np.flatnonzero(np.diff(index)) + 1
        for start, stop in zip(np.r_[0, bounds], np.r_[bounds, n], strict=True):
            if n == 0:
                break
            self._advance(int(index[start]))
            self._correct(g, start, stop, out)
            self._accumulate(t_s, g, rotation, keep, start, stop, index[start])
            if health is not None:
                for t_step, sensors in health(start, stop, out.g[start:stop]):
                    self.step(sensors, t_step)
        out.events = self.events[events_before:]
        return out

    def step(self, sensors: Sequence[int], t_s: float) -> None:
        """A step on ``sensors`` (1-based) at ``t_s``: their offsets' covariance widened by
        ``step_sigma_t`` per axis; the blocks after it re-estimate them."""
        sensors = tuple(int(s) for s in sensors if 1 <= int(s) <= 4)
        if not sensors:
            return
        for s in sensors:
            v = self._steps[s - 1]  # (9, 3)
            self._p[:N_OFFSETS, :N_OFFSETS] += self.config.step_sigma_t**2 * v @ v.T
        self._record(t_s, 'step', sensors=sensors)

    def audit(self) -> list[dict[str, Any]]:
        """The audit trail (every block's update, gate and step), JSON-ready."""
        return [event.to_dict() for event in self.events]

    # ------------------------------------------------------------------ internals

    def _rotations(self, orientation_xyzw: FloatArray | None, n: int) -> FloatArray | None:
        if not self.with_world:
            return None
        if orientation_xyzw is None:
            raise InputError('the tracker estimates the world gradient: give orientation_xyzw')
        q = as_array(orientation_xyzw, 'orientation_xyzw', (n, 4))
        return _quaternion_matrices(q)

    def _correct(self, g: FloatArray, start: int, stop: int, out: TrackedChunk) -> None:
        """Samples ``start:stop`` corrected with the state before their block."""
        offsets = self._x[:N_OFFSETS]
        change = (self._h @ offsets).reshape(3, 3)
        p_b = self._p[:N_OFFSETS, :N_OFFSETS]
        out.g[start:stop] = g[start:stop] - change
        out.variance[start:stop] = np.einsum('qi,ij,qj->q', self._h, p_b, self._h)
        out.offsets[start:stop] = offsets

    def _accumulate(
        self,
        t_s: FloatArray,
        g: FloatArray,
        rotation: FloatArray | None,
        keep: FloatArray,
        start: int,
        stop: int,
        index: int,
    ) -> None:
        """Add samples ``start:stop`` (of block ``index``) to the open block's sums."""
        y = (g[start:stop].reshape(-1, 9) @ self._whiten.T) * keep[start:stop, None]  # (k, m)
        w = keep[start:stop]
        block = self._open if self._open is not None and self._open.index == index else None
        if block is None:
            block = self._open = _Block(index, self._x.size)
        block.t_end = float(t_s[stop - 1])
        block.n += float(w.sum())
        block.excluded += int(np.sum(w == 0))
        h = self._h_white
        columns = [np.broadcast_to(h, (stop - start, *h.shape))]
        if rotation is not None:
            columns.append(self._whiten @ _world_columns(rotation[start:stop]))
        a = np.concatenate(columns, axis=2) * np.sqrt(w)[:, None, None]  # (k, m, size)
        block.info += np.einsum('kmi,kmj->ij', a, a)
        block.vector += np.einsum('kmi,km->i', a, y)

    def _advance(self, index: int) -> None:
        """Close the open block when ``index`` is a later one: update, then the process noise
        of the time between."""
        block = self._open
        if block is None or block.index == index:
            return
        self._close(block)
        self._diffuse((index - block.index) * self.config.block_s)
        self._open = None

    def _close(self, block: _Block) -> None:
        """One information-form update from the block's sums (or none: gated, excluded)."""
        if block.n == 0:
            self._record(block.t_end, 'excluded')
            return
        x, p = self._x, self._p
        innovation = block.vector - block.info @ x
        spread = block.info @ p @ block.info + block.info
        values, vectors = np.linalg.eigh(spread)
        rank_ok = values > values.max() * 1e-10
        projected = vectors[:, rank_ok].T @ innovation
        statistic = float(np.sum(projected**2 / values[rank_ok]))
        if statistic > chi2_isf(self.config.gate_p, _even(int(rank_ok.sum()))):
            self._record(block.t_end, 'gated', statistic=statistic)
            return
        gain = np.linalg.solve(np.eye(len(x)) + p @ block.info, p)  # (P^-1 + Lambda)^-1
        gain = 0.5 * (gain + gain.T)
        self._x = x + gain @ innovation
        self._p = gain
        self._record(block.t_end, 'update', statistic=statistic)

    def _diffuse(self, seconds: float) -> None:
        config = self.config
        pattern = self._pattern
        q = config.relative_rate_per_sqrt_s**2 * np.outer(pattern, pattern)
        q += config.offset_rate_t_per_sqrt_s**2 * self._seen
        q += config.hidden_rate_t_per_sqrt_s**2 * (np.eye(N_OFFSETS) - self._seen)
        self._p[:N_OFFSETS, :N_OFFSETS] += seconds * q
        if self.with_world:
            world = config.world_rate_t_per_m_sqrt_s**2 * seconds
            self._p[N_OFFSETS:, N_OFFSETS:] += world * np.eye(N_WORLD)

    def _record(
        self, t_s: float, kind: str, sensors: tuple[int, ...] = (), statistic: float = np.nan
    ) -> None:
        self.events.append(
            TrackerEvent(t_s, kind, self.offsets_t, self.offsets_sigma_t, sensors, statistic)
        )


def handed_over(alarms: Sequence[Any]) -> list[tuple[float, tuple[int, ...]]]:
    """The steps a health monitor's alarms (``core.health.Alarm``) hand to the tracker:
    ``(t_s, (sensor,))`` for each offset change, its best-fitting sensor only (two sensors'
    offsets, 6 unknowns, are more than the 4 constraints re-estimate at once)."""
    return [
        (float(alarm.t_s), alarm.sensors[:1])
        for alarm in alarms
        if alarm.kind == 'offset_change' and alarm.sensors
    ]


class _Block:
    """The sums of one block: information ``A^T A`` and ``A^T y`` (whitened), the samples
    learnt from, those excluded, and its last stamp."""

    def __init__(self, index: int, size: int) -> None:
        self.index = index
        self.info = np.zeros((size, size))
        self.vector = np.zeros(size)
        self.n = 0.0
        self.excluded = 0
        self.t_end = float('nan')


def _even(dof: int) -> int:
    """The even degree of freedom at or above ``dof`` (the closed chi-square tails)."""
    return max(2, dof + dof % 2)


def _world_columns(rotation: FloatArray) -> FloatArray:
    """(k, 9, 5): ``vec(R^T E_c R)`` of each world basis tensor ``E_c`` in the body frame."""
    body = np.einsum('kji,cjl,klm->kcim', rotation, _WORLD_BASIS, rotation)
    return np.swapaxes(body.reshape(len(rotation), N_WORLD, 9), 1, 2)


def _quaternion_matrices(q: FloatArray) -> FloatArray:
    """(n, 3, 3) rotation matrices of unit quaternions (x, y, z, w) (n, 4)."""
    q = q / np.linalg.norm(q, axis=1)[:, None]
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _step_directions(h: FloatArray, jacobian: FloatArray) -> list[FloatArray]:
    """Per sensor (9, 3): how a step of its offset moves the pair offsets (``H^-1 J_s``: for
    sensors 2-4 their own pair, for sensor 1 all three pairs and the soft iron's share)."""
    inverse = np.linalg.inv(h)
    return [inverse @ jacobian[:, 3 * s : 3 * s + 3] for s in range(4)]
