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
  along the line look the same. How fast the world varies is learnt on straight legs
  (blocks ``world_lag_s`` apart): over geology a turn then teaches the offsets little, in a
  uniform field it separates them. Where it cannot: geology that changes across a U-turn
  looks like a body-fixed gradient that flipped.
* **the trim's permanent field** (a prior, not an observation): remanence relaxes by a
  fraction of itself, so the process noise has a part along the calibration's own ``b``
  (``relative_rate_per_sqrt_s``), beside a part in the observed combinations
  (``offset_rate_t_per_sqrt_s``) and a smaller one in the hidden ones
  (``hidden_rate_t_per_sqrt_s``). The constraints pin the fraction within seconds and,
  through this prior, predict part of what they do not see; what the hull's bodies do unlike
  each other stays in the hidden part and its covariance. How fast the vehicle changes is
  learnt from the constrained combinations (their means over ``change_span_s``,
  ``change_lag_s`` apart) and scales these rates: a vehicle that does not change keeps its
  state's covariance near zero.

Process model: random walks (a relaxation is a slow, smooth walk). Blocks of ``block_s``
seconds are one update each (information form: sums over the block's samples, then one
small solve, :mod:`._kalman`), and each sample is corrected with the state from the blocks
before its own: causal, O(1) per sample. A block whose innovation fails a chi-square gate (a
step not yet handed over, a target passing close) does not update the state, and samples
the caller flags (``exclude``: targets) never do. A step named by the health monitor
(:meth:`OffsetTracker.step`), or a gate closed for ``stuck_s``, starts a search: the next
``trial_s`` seconds are fitted once per sensor, that sensor's offset freed, and the best fit
is kept (its jump and 1-sigma in the audit trail). The state's covariance adds ``diag(H P_b
H^T)`` (per component, (T/m)^2) to the published variance.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InputError
from ._distributions import chi2_isf
from ._kalman import (
    N_OFFSETS,
    N_WORLD,
    Block,
    LaggedRate,
    TrackerEvent,
    Trial,
    information_update,
    step_directions,
    world_columns,
)
from ._validate import as_array, as_tensors, same_length
from .design import CONSTRAINT_ROWS, affine_interference_design
from .geometry import TetraGeometry
from .model import InterferenceParameters
from .types import FloatArray
from .uncertainty import noise_jacobian

__all__ = [
    'OffsetTracker',
    'TrackedChunk',
    'TrackerConfig',
    'TrackerEvent',
    'handed_over',
    'monitor_feed',
]


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of :class:`OffsetTracker` (units in the names).

    * ``block_s``: the samples of one update, s.
    * ``relative_rate_per_sqrt_s``: random-walk rate of the calibration's own offset pattern
      ``b``, as a fraction of it per sqrt(s) (a remanence relaxing by 0.5 % in 600 s walks
      at ~2e-4; slower here, because over geology a fast one lets turns move the offsets).
    * ``offset_rate_t_per_sqrt_s``, ``hidden_rate_t_per_sqrt_s``: of the pair offsets in the
      4 combinations the constraints observe, and in the other 5 (a body-fixed gradient:
      kept small, it is what geology could be taken for), T per sqrt(s).
    * ``world_rate_t_per_m_sqrt_s``: of each world-gradient coefficient at the start, T/m per
      sqrt(s); then learnt from blocks ``world_lag_s`` apart on one heading, averaged over
      ``world_memory_s``, times ``world_margin`` (geology is smoother than a walk: a turn is
      trusted less), never below ``world_rate_min_t_per_m_sqrt_s``;
      ``world_sigma_t_per_m``: its prior at the start.
    * ``step_sigma_t``: a step's prior per axis, T; ``trial_s``: how long each sensor's
      hypothesis is fitted before the best is kept, s; ``stuck_s``: a gate closed this long
      is taken for a step no monitor handed over, and fitted ``confirm_s`` (a source passing
      close fits one sensor's step for a second, not for five), s.
    * ``initial_sigma_t``: the offsets' change at the start, per axis, T (0: the start is
      the calibration; a prior there slows what the constraints teach the hidden part).
    * ``change_span_s``, ``change_lag_s``, ``change_memory_s``, ``change_scale_min``: the
      offsets' process noise (the rates above) is scaled by how fast the constrained
      combinations change (their means over ``change_span_s``, ``change_lag_s`` apart,
      averaged over ``change_memory_s``), within ``change_scale_min`` (where it starts) and
      1: a vehicle that does not change keeps its state's 1-sigma near zero.
    * ``gate_p``: a block whose innovation is less likely than this is not learnt from.
    """

    block_s: float = 0.5
    relative_rate_per_sqrt_s: float = 3e-5
    offset_rate_t_per_sqrt_s: float = 1e-12
    hidden_rate_t_per_sqrt_s: float = 2e-12
    world_rate_t_per_m_sqrt_s: float = 0.1e-9
    world_rate_min_t_per_m_sqrt_s: float = 0.01e-9
    world_memory_s: float = 120.0
    world_lag_s: float = 20.0
    world_margin: float = 4.0
    world_sigma_t_per_m: float = 5e-9
    step_sigma_t: float = 5e-9
    trial_s: float = 1.0
    stuck_s: float = 3.0
    confirm_s: float = 5.0
    initial_sigma_t: float = 0.0
    change_span_s: float = 10.0
    change_lag_s: float = 60.0
    change_memory_s: float = 120.0
    change_scale_min: float = 0.001
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
#: ``attitude(t_s)`` -> the quaternions (k, 4) xyzw body -> ENU at the times ``t_s`` (k,) s.
Attitude = Callable[[FloatArray], FloatArray]


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
    monitored : bool
        A health monitor hands the steps over (:meth:`step`): a gate closed for ``stuck_s``
        is then not searched for a step (a large target's pass closes it for seconds, and a
        sensor's step fitted to it was taken for one on the shipped survey, 1.3x the floor).
    """

    def __init__(
        self,
        geometry: TetraGeometry,
        parameters: InterferenceParameters,
        sensor_noise_t: float,
        config: TrackerConfig | None = None,
        *,
        with_world: bool = True,
        monitored: bool = False,
    ) -> None:
        if not (np.isfinite(sensor_noise_t) and sensor_noise_t > 0):
            raise InputError(f'sensor_noise_t must be positive, got {sensor_noise_t}')
        self.config = config or TrackerConfig()
        self.with_world = with_world
        self.monitored = monitored
        self._h = affine_interference_design(geometry, symmetric=False)[3][:, 27:]  # (9, 9)
        jacobian = noise_jacobian(geometry, parameters)

        def whitening(rows: FloatArray) -> FloatArray:  # (m, 9): unit noise per sample
            noise = sensor_noise_t**2 * rows @ jacobian @ jacobian.T @ rows.T
            return np.linalg.inv(np.linalg.cholesky(noise)) @ rows

        self._whiten = whitening(np.eye(9) if with_world else CONSTRAINT_ROWS)
        self._seen_white = whitening(CONSTRAINT_ROWS)
        self._h_white = self._whiten @ self._h
        self._pattern = parameters.b_hard.reshape(9)
        seen = CONSTRAINT_ROWS @ self._h  # (4, 9): the combinations observed at every instant
        self._seen = np.linalg.pinv(seen) @ seen  # projector onto them
        self._steps = step_directions(self._h, jacobian)
        rates = self.config
        # The offsets' process noise per second: along b and in the observed part (scaled by
        # the learnt change), in the hidden part (without the attitude nothing observes it,
        # so nothing scales it down).
        self._offset_rate = (
            rates.relative_rate_per_sqrt_s**2 * np.outer(self._pattern, self._pattern)
            + rates.offset_rate_t_per_sqrt_s**2 * self._seen
        )
        self._hidden_rate = rates.hidden_rate_t_per_sqrt_s**2 * (np.eye(N_OFFSETS) - self._seen)
        size = N_OFFSETS + (N_WORLD if with_world else 0)
        self._x = np.zeros(size)
        self._p = np.zeros((size, size))
        self._p[:N_OFFSETS, :N_OFFSETS] = rates.initial_sigma_t**2 * np.eye(N_OFFSETS)
        rate = self._offset_rate + self._hidden_rate
        seen_rate = self._seen_white @ self._h @ rate @ self._h.T @ self._seen_white.T
        group = max(1, round(rates.change_span_s / rates.block_s))
        self._change = LaggedRate(
            max(1, round(rates.change_lag_s / rates.change_span_s)),
            rates.change_span_s / rates.change_memory_s,
            float(np.trace(seen_rate)) * rates.block_s * group,
            rates.change_scale_min,
            group,
        )
        # The world's pairs on one heading: a body-fixed error turning would read as world.
        self._world = LaggedRate(
            max(1, round(rates.world_lag_s / rates.block_s)),
            rates.block_s / rates.world_memory_s,
            N_WORLD * rates.block_s,
            rates.world_rate_t_per_m_sqrt_s**2,
        )
        if with_world:
            self._p[N_OFFSETS:, N_OFFSETS:] = self.config.world_sigma_t_per_m**2 * np.eye(N_WORLD)
        self._origin: float | None = None
        self._open: Block | None = None
        self._pending: list[tuple[float, FloatArray, FloatArray]] = []  # one()'s open block
        self._pending_index = 0
        self._trial: Trial | None = None
        self._gated = 0
        self._noise = sensor_noise_t**2 * jacobian @ jacobian.T  # (9, 9) of vec(G), (T/m)^2
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
            self._accumulate(t_s, g, out.g, rotation, keep, (start, stop), index[start])
            if health is not None:
                for t_step, sensors in health(start, stop, out.g[start:stop]):
                    self.step(sensors, t_step)
        out.events = self.events[events_before:]
        return out

    def one(
        self, t_s: float, g_compensated: FloatArray, attitude: Attitude | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """One sample, unchecked (a node's per-message path, a few microseconds): ``t_s`` s,
        ``g_compensated`` (3, 3) T/m; returns the tracked tensor (3, 3) T/m and the state's
        variance per component (9,) (T/m)^2. The same as :meth:`update` on that sample: the
        correction needs only the blocks before, so the block's samples are learnt from
        together when it closes, and ``attitude`` (``with_world``) is asked then for their
        quaternions (k, 4) at their times (k,) s (NaN rows: unknown, not learnt from); by
        then the navigation has caught up with them."""
        if self._origin is None:
            self._origin = float(t_s)
        index = int(np.floor((t_s - self._origin) / self.config.block_s))
        if self._pending and index != self._pending_index:
            self._learn_pending(attitude)
        self._advance(index)
        h, p_b = self._h, self._p[:N_OFFSETS, :N_OFFSETS]
        tracked = g_compensated - (h @ self._x[:N_OFFSETS]).reshape(3, 3)
        self._pending.append((float(t_s), g_compensated, tracked))
        self._pending_index = index
        return tracked, np.sum((h @ p_b) * h, axis=1)

    def _learn_pending(self, attitude: Attitude | None) -> None:
        """The samples :meth:`one` corrected in the open block, into its sums."""
        t_s, g, tracked = (np.array(column) for column in zip(*self._pending, strict=True))
        self._pending = []
        keep = np.ones(len(t_s))
        rotation = None
        if self.with_world:
            if attitude is None:
                raise InputError('the tracker estimates the world gradient: give the attitude')
            q = np.array(attitude(t_s), dtype=float).reshape(len(t_s), 4)
            known = np.all(np.isfinite(q), axis=1)
            keep[~known] = 0.0
            q[~known] = (0.0, 0.0, 0.0, 1.0)
            rotation = self._rotations(q, len(t_s))
        self._accumulate(t_s, g, tracked, rotation, keep, (0, len(t_s)), self._pending_index)

    def step(self, sensors: Sequence[int], t_s: float) -> None:
        """A step detected at ``t_s`` (s), ``sensors`` (1-based) the likeliest first: the
        next ``trial_s`` seconds of blocks are fitted once per sensor, each hypothesis with
        that sensor's offset widened by ``step_sigma_t``, and the best fit is kept (the
        monitor's first guess, on a fraction of a second, is not always right)."""
        named = tuple(dict.fromkeys(int(s) for s in sensors if 1 <= int(s) <= 4))
        if named and self._trial is None:
            self._start_trial(t_s, named, self.config.trial_s)

    # ------------------------------------------------------------------ internals

    def _rotations(self, orientation_xyzw: FloatArray | None, n: int) -> FloatArray | None:
        if not self.with_world:
            return None
        if orientation_xyzw is None:
            raise InputError('the tracker estimates the world gradient: give orientation_xyzw')
        # Imported here, as in identification/lstsq.py: a node without the attitude never pays it.
        from scipy.spatial.transform import Rotation

        q = as_array(orientation_xyzw, 'orientation_xyzw', (n, 4))
        return Rotation.from_quat(q).as_matrix().reshape(n, 3, 3)

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
        corrected: FloatArray,
        rotation: FloatArray | None,
        keep: FloatArray,
        rows: tuple[int, int],
        index: int,
    ) -> None:
        """Add samples ``rows`` (of block ``index``) to the open block's sums: the whitened
        information of the frozen tensor ``g``, and the world-frame gradient of the
        ``corrected`` one (for the world rate)."""
        start, stop = rows
        w = keep[start:stop]
        y = (g[start:stop].reshape(-1, 9) @ self._whiten.T) * w[:, None]  # (k, m)
        seen = g[start:stop].reshape(-1, 9) @ self._seen_white.T  # (k, 4)
        block = self._open if self._open is not None and self._open.index == index else None
        if block is None:
            block = self._open = Block(index, self._x.size)
        block.t_end = float(t_s[stop - 1])
        block.n += float(w.sum())
        block.excluded += int(np.sum(w == 0))
        block.seen += w @ seen
        h = self._h_white
        columns = [np.broadcast_to(h, (stop - start, *h.shape))]
        if rotation is not None:
            world = world_columns(rotation[start:stop])  # (k, 9, 5)
            columns.append(self._whiten @ world)
            tensors = corrected[start:stop].reshape(-1, 9)
            block.world += np.einsum('kqc,kq,k->c', world, tensors, w)
            spread = np.sum(world * (self._noise @ world), axis=(1, 2))  # trace(T^T R T)
            block.world_noise += float(spread @ w)
            block.heading += np.einsum('kq,k->q', rotation[start:stop, :, 0], w)
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

    def _close(self, block: Block) -> None:
        """One information-form update from the block's sums (or none: gated, excluded); a
        gate that holds for ``stuck_s`` with no monitor is a step nobody handed over: its
        sensor is sought as for one that was."""
        if block.n == 0:
            self._record(block.t_end, 'excluded')
            return
        if self.with_world:
            heading = block.heading / np.linalg.norm(block.heading)
            self._world.add(block.index, block.world, block.n, block.world_noise, heading)
        if self._trial is not None:
            self._try(block)
            return
        statistic, limit, x, p = information_update(self._x, self._p, block, self.config.gate_p)
        if statistic > limit:
            self._gated += 1
            self._record(block.t_end, 'gated', statistic=statistic)
            if not self.monitored and self._gated * self.config.block_s >= self.config.stuck_s:
                self._start_trial(block.t_end, (), self.config.confirm_s)
            return
        self._gated = 0
        self._x, self._p = x, p
        self._change.add(block.index, block.seen, block.n, 4.0 * block.n)
        self._record(block.t_end, 'update', statistic=statistic)

    def _start_trial(self, t_s: float, named: tuple[int, ...], duration_s: float) -> None:
        """One hypothesis per sensor (the named ones first), its offsets' covariance widened
        by ``step_sigma_t``, beside the hypothesis of no step (candidate 0: a source passing
        close, a burst); the output follows the named sensor's (none named: no step's)."""
        candidates = [0, *named] + [s for s in range(1, 5) if s not in named]
        states = []
        for sensor in candidates:
            p = self._p.copy()
            if sensor:
                v = self._steps[sensor - 1]  # (9, 3)
                p[:N_OFFSETS, :N_OFFSETS] += self.config.step_sigma_t**2 * v @ v.T
            states.append((self._x.copy(), p))
        self._trial = Trial(t_s, tuple(candidates), states, self._x[:N_OFFSETS].copy())
        self._trial.duration_s = duration_s
        # A handed-over step is followed at once; one the gate suspects only once confirmed.
        self._trial.follow = bool(named)
        self._x, self._p = states[1 if named else 0]
        self._gated = 0
        self._change.restart()

    def _try(self, block: Block) -> None:
        """Every hypothesis updated on the block (no step: only through the gate) and scored
        by its innovation; the output follows the best sensor while its fit is within the
        gates' sum, else no step; after ``trial_s`` that choice is kept."""
        trial = self._trial
        if trial is None:
            return
        for i, (x, p) in enumerate(trial.states):
            statistic, limit, x_new, p_new = information_update(x, p, block, self.config.gate_p)
            trial.scores[i] += statistic
            if trial.candidates[i] or statistic <= limit:
                trial.states[i] = (x_new, p_new)
        trial.limit += limit
        best = 1 + int(np.argmin(trial.scores[1:]))
        best = best if trial.scores[best] <= trial.limit else 0
        self._x, self._p = trial.states[best if trial.follow else 0]
        if trial.blocks_done(self.config.block_s) < trial.duration_s:
            return
        self._trial = None
        sensor = trial.candidates[best]
        self._x, self._p = trial.states[best]
        jump = spread = np.zeros(3)
        if sensor:
            # The jump: the offsets' change across the trial seen through the sensor's step
            # directions (what the drift did in 1 s is far below it).
            back = np.linalg.pinv(self._steps[sensor - 1])  # (3, 9)
            jump = back @ (self._x[:N_OFFSETS] - trial.before)
            spread = np.sqrt(np.diag(back @ self._p[:N_OFFSETS, :N_OFFSETS] @ back.T))
        if not sensor or np.sum((jump / spread) ** 2) < chi2_isf(self.config.gate_p, 4):
            # No sensor's step explains the closed gate, or none moved: a source passing
            # close, a burst. The vehicle is taken as it was.
            self._x, self._p = trial.states[0]
            self._record(block.t_end, 'transient', statistic=float(trial.scores[1:].min()))
            return
        self.events.append(
            TrackerEvent(
                trial.t_s,
                'step',
                self.offsets_t,
                self.offsets_sigma_t,
                (sensor,),
                float(trial.scores[best]),
                jump,
                spread,
            )
        )

    def _diffuse(self, seconds: float) -> None:
        """The process noise of ``seconds`` added to the state's covariance (and to every
        hypothesis of a step being sought)."""
        config = self.config
        q = np.zeros_like(self._p)
        scale = min(max(self._change.rate, config.change_scale_min), 1.0)
        hidden = scale if self.with_world else 1.0
        q[:N_OFFSETS, :N_OFFSETS] = seconds * (
            scale * self._offset_rate + hidden * self._hidden_rate
        )
        if self.with_world:
            learnt = config.world_margin * self._world.rate
            rate2 = max(learnt, config.world_rate_min_t_per_m_sqrt_s**2)
            q[N_OFFSETS:, N_OFFSETS:] = rate2 * seconds * np.eye(N_WORLD)
        self._p = self._p + q
        if self._trial is not None:
            self._trial.states = [(x, p + q) for x, p in self._trial.states]

    def _record(
        self, t_s: float, kind: str, sensors: tuple[int, ...] = (), statistic: float = np.nan
    ) -> None:
        self.events.append(
            TrackerEvent(t_s, kind, self.offsets_t, self.offsets_sigma_t, sensors, statistic)
        )


def monitor_feed(monitor: Any, t_s: FloatArray, b_reference: FloatArray) -> HealthFeed:
    """A :data:`HealthFeed` over a ``core.health.HealthMonitor`` for one chunk: ``t_s`` (n,)
    s and ``B_1'`` (n, 3) T of the chunk :meth:`OffsetTracker.update` is given."""

    def feed(start: int, stop: int, g_tracked: FloatArray) -> list[tuple[float, tuple[int, ...]]]:
        trace = monitor.update(t_s[start:stop], g_tracked, b_reference[start:stop])
        return handed_over(trace.alarms)

    return feed


def handed_over(alarms: Sequence[Any]) -> list[tuple[float, tuple[int, ...]]]:
    """The steps a health monitor's alarms (``core.health.Alarm``) hand to the tracker:
    ``(t_s, sensors)`` for each offset change, the sensors best first."""
    return [
        (float(alarm.t_s), tuple(alarm.sensors))
        for alarm in alarms
        if alarm.kind == 'offset_change' and alarm.sensors
    ]
