"""The blocked information-form Kalman update of :mod:`.tracking` and its pieces: a block's
sums, the update with its innovation gate, the hypotheses of a step being sought, the world
gradient's body-frame columns, each sensor's step directions, the rates learnt from lagged
means, and the audit trail's entry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ._distributions import chi2_isf
from .identification.lstsq import REGIONAL_BASIS
from .types import FloatArray
from .units import NT_PER_T

#: The pair offsets (3 pairs x 3 axes) and the world gradient's coefficients.
N_OFFSETS = 9
N_WORLD = 5
#: Two blocks are on one heading when their forward axes are within 10 degrees.
STRAIGHT = float(np.cos(np.radians(10.0)))
#: The world gradient's coefficients: the regional fit's basis (the calibration's joint
#: solve) made orthonormal, so that a random walk on them is the same in every direction.
WORLD_BASIS = np.linalg.qr(REGIONAL_BASIS.reshape(5, 9).T)[0].T.reshape(5, 3, 3)


class Trial:
    """A step being sought: one (state, covariance) per candidate (a sensor, or 0: no step)
    and its summed innovation chi-square."""

    def __init__(
        self,
        t_s: float,
        candidates: tuple[int, ...],
        states: list[tuple[FloatArray, FloatArray]],
        before: FloatArray,
    ) -> None:
        self.t_s = t_s
        self.before = before
        self.candidates = candidates
        self.states = states
        self.scores = np.zeros(len(candidates))
        self.limit = 0.0  # the sum of the blocks' gates
        self.blocks = 0
        self.duration_s = 1.0  # how long the hypotheses are fitted
        self.follow = True  # the output follows the best hypothesis while they are

    def blocks_done(self, block_s: float) -> float:
        """Count one more block; the seconds fitted so far."""
        self.blocks += 1
        return self.blocks * block_s


def information_update(
    x: FloatArray, p: FloatArray, block: Block, gate_p: float
) -> tuple[float, float, FloatArray, FloatArray]:
    """The block's innovation chi-square, its gate (``gate_p``, over the observed rank), and
    the updated state and covariance (information form: ``(P^-1 + Lambda)^-1``)."""
    innovation = block.vector - block.info @ x
    spread = block.info @ p @ block.info + block.info
    values, vectors = np.linalg.eigh(spread)
    observed = values > values.max() * 1e-10
    projected = vectors[:, observed].T @ innovation
    statistic = float(np.sum(projected**2 / values[observed]))
    limit = chi2_isf(gate_p, even(int(observed.sum())))
    covariance = np.linalg.solve(np.eye(len(x)) + p @ block.info, p)
    covariance = 0.5 * (covariance + covariance.T)
    return statistic, limit, x + covariance @ innovation, covariance


class Block:
    """The sums of one block: information ``A^T A`` and ``A^T y`` (whitened), the samples
    learnt from, those excluded, and its last stamp."""

    def __init__(self, index: int, size: int) -> None:
        self.index = index
        self.info = np.zeros((size, size))
        self.vector = np.zeros(size)
        self.n = 0.0
        self.excluded = 0
        self.world = np.zeros(N_WORLD)
        self.world_noise = 0.0
        self.heading = np.zeros(3)
        self.seen = np.zeros(4)  # the whitened constrained combinations' sum
        self.t_end = float('nan')


def even(dof: int) -> int:
    """The even degree of freedom at or above ``dof`` (the closed chi-square tails)."""
    return max(2, dof + dof % 2)


def world_columns(rotation: FloatArray) -> FloatArray:
    """(k, 9, 5): ``vec(R^T E_c R)`` of each world basis tensor ``E_c`` in the body frame."""
    body = np.einsum('kji,cjl,klm->kcim', rotation, WORLD_BASIS, rotation)
    return np.swapaxes(body.reshape(len(rotation), N_WORLD, 9), 1, 2)


def step_directions(h: FloatArray, jacobian: FloatArray) -> list[FloatArray]:
    """Per sensor (9, 3): how a step of its offset moves the pair offsets (``H^-1 J_s``: for
    sensors 2-4 their own pair, for sensor 1 all three pairs and the soft iron's share)."""
    inverse = np.linalg.inv(h)
    return [inverse @ jacobian[:, 3 * s : 3 * s + 3] for s in range(4)]


class LaggedRate:
    """A random walk's variance per second, learnt from the means of spans of ``group``
    blocks, ``lag`` spans apart: they differ by the walk over the lag plus the noise of both
    means (known), so the excess over the noise, over ``lag * unit`` (``unit``: the walk's
    variance per span at rate 1, summed over the mean's components) and averaged with
    ``weight`` per pair, is the walk's :attr:`rate` (it starts at ``start``). With headings,
    only pairs on one heading count (within 10 degrees)."""

    def __init__(self, lag: int, weight: float, unit: float, start: float, group: int = 1):
        self.lag, self.weight, self.unit, self.rate, self.group = lag, weight, unit, start, group
        self._means: dict[int, tuple[FloatArray, float, FloatArray | None]] = {}
        self._open: list[Any] = []  # the open span: its index, sums, samples, noise, heading

    def add(
        self,
        index: int,
        total: FloatArray,
        n: float,
        noise: float,
        heading: FloatArray | None = None,
    ) -> None:
        """Block ``index``'s sum of values over its ``n`` samples, the sum of their noise
        variances (over the components) and its heading (unit)."""
        span = index // self.group
        if self._open and self._open[0] != span:
            self._pair(*self._open)
        if not self._open or self._open[0] != span:
            self._open = [span, 0.0, 0.0, 0.0, heading]
        self._open[1:4] = self._open[1] + total, self._open[2] + n, self._open[3] + noise
        if index % self.group == self.group - 1:
            self._pair(*self._open)

    def _pair(
        self, span: int, total: FloatArray, n: float, noise: float, heading: FloatArray | None
    ) -> None:
        self._open = []
        mean, noise = total / n, noise / n**2
        self._means[span] = (mean, noise, heading)
        earlier = self._means.pop(span - self.lag, None)
        for stale in [k for k in self._means if k <= span - self.lag]:
            del self._means[stale]
        if earlier is None:
            return
        if heading is not None and earlier[2] is not None and heading @ earlier[2] < STRAIGHT:
            return
        excess = float(np.sum((mean - earlier[0]) ** 2)) - noise - earlier[1]
        self.rate += self.weight * (excess / (self.lag * self.unit) - self.rate)

    def restart(self) -> None:
        """Forget the spans before a step (pairs across it are not a walk)."""
        self._means.clear()
        self._open = []


@dataclass(frozen=True)
class TrackerEvent:
    """One entry of the audit trail: ``t_s`` (the block's end, or the step's time), s;
    ``kind`` (``update``, ``gated``, ``excluded``, ``step``, ``transient``: a closed gate
    no sensor's step explains); ``offsets_t`` (3, 3) the pair
    offsets' change after it, T; ``sigma_t`` (3, 3) its 1-sigma, T; ``sensors`` (1-based, a
    step's); ``statistic`` the block's innovation chi-square (a step's: its hypothesis's,
    summed over ``trial_s``); a step's ``step_t`` (3,) the sensor's offset jump and
    ``step_sigma_t`` (3,) its 1-sigma, T (its axes)."""

    t_s: float
    kind: str
    offsets_t: FloatArray
    sigma_t: FloatArray
    sensors: tuple[int, ...] = ()
    statistic: float = float('nan')
    step_t: FloatArray | None = None
    step_sigma_t: FloatArray | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, offsets in nT."""
        return {
            't_s': float(self.t_s),
            'kind': self.kind,
            'offsets_nT': (self.offsets_t * NT_PER_T).round(6).tolist(),
            'sigma_nT': (self.sigma_t * NT_PER_T).round(6).tolist(),
            'sensors': list(self.sensors),
            'statistic': None if np.isnan(self.statistic) else float(self.statistic),
        } | (
            {}
            if self.step_t is None or self.step_sigma_t is None
            else {
                'step_nT': (self.step_t * NT_PER_T).round(6).tolist(),
                'step_sigma_nT': (self.step_sigma_t * NT_PER_T).round(6).tolist(),
            }
        )
