"""What every vehicle effect is: a family of terms linear in recorded channels.

Each effect adds, to each sensor's reading, coefficients times a few *regressor* series
built from recorded channels (a current, a temperature, the reference field's rate). In
the pair differences ``B_i' - B_1'`` that the tensor sees (eqs. 11-13) it adds
``W_i x(t)``: ``W_i = W_(sensor i) - W_(sensor 1)``, a (3, m) matrix per pair. So an effect
extends eq. 18's regressors ``(B_1', 1)`` by ``x(t)`` (m,), and the interference on the
tensor becomes ``D = (k B_1' + b + W x) a^-1``: the paper's ``k``, ``b`` are the base terms
of the same model, the constant regressor 1 being ``b``'s.

An :class:`Effect` owns: the channels it reads (:meth:`Effect.inputs`), its regressors on a
recording (:meth:`Effect.regressors`) and on one sample live (:meth:`Effect.live`), the
values it fixes at calibration (:meth:`Effect.reference`), its physics in the simulator
(:meth:`Effect.simulate`) and its file form (:attr:`Effect.file_unit`). A fitted effect is
a :class:`Term`. Units: SI everywhere (T, s, A, degC); the file's unit per effect.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ...errors import InputError
from .._validate import frozen_array
from ..types import ArrayLike, FloatArray
from .simulation import EffectSpec, Truth, linear_field

#: Channel names. A current channel is ``current:<topic>`` (a sensor_msgs/BatteryState
#: topic: the battery, or one per thruster ESC).
TEMPERATURE = 'temperature'
CURRENT_PREFIX = 'current:'


def current_channel(topic: str) -> str:
    """The channel name of a BatteryState topic's ``current``."""
    return f'{CURRENT_PREFIX}{topic}'


@dataclass(frozen=True)
class Channels:
    """A recording's channels on its sample instants.

    Attributes
    ----------
    t_s : (N,) s, strictly increasing (any origin)
    b_reference : (N, 3) T, the reference sensor's reading ``B_1'`` (body frame)
    series : channel name -> (N,) values on the samples (``temperature`` degC,
        ``current:<topic>`` A); NaN where the channel is unknown (a gap)
    """

    t_s: np.ndarray
    b_reference: np.ndarray
    series: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.t_s)
        if self.b_reference.shape != (n, 3):
            raise InputError(f'b_reference must be ({n}, 3), got {self.b_reference.shape}')
        for name, values in self.series.items():
            if np.shape(values) != (n,):
                raise InputError(f'channel {name}: {np.shape(values)} values for {n} samples')

    def __len__(self) -> int:
        return len(self.t_s)

    def select(self, keep: np.ndarray) -> Channels:
        """The samples ``keep`` (a boolean mask or indices)."""
        return Channels(
            self.t_s[keep],
            self.b_reference[keep],
            {name: values[keep] for name, values in self.series.items()},
        )


class LiveRegressor(ABC):
    """An effect's regressors on one sample at a time (a node's per-message path); gives
    what :meth:`Effect.regressors` gives on the same sequence of samples."""

    @abstractmethod
    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        """The regressors (m,) at this sample: ``t_s`` s, ``b_reference`` (3,) T, ``values``
        the channels' values at ``t_s`` (NaN: unknown). NaN entries where unknown."""

    @abstractmethod
    def reset(self) -> None:
        """Forget the history (a gap, a restarted replay)."""


class _Memoryless(LiveRegressor):
    """An effect's regressors on each sample alone."""

    def __init__(self, effect: Effect, inputs: tuple[str, ...], reference: tuple[float, ...]):
        self.effect, self.inputs, self.reference = effect, inputs, reference

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        series = {name: np.array([values.get(name, np.nan)], dtype=float) for name in self.inputs}
        sample = Channels(np.array([t_s]), np.asarray(b_reference, float)[None], series)
        return np.asarray(self.effect.regressors(sample, self.inputs, self.reference), float)[0]

    def reset(self) -> None:
        return None


class Effect(ABC):
    """One physical effect of the vehicle; subclasses are the registry's entries."""

    #: The effect's one name (registry key, calibration file, reports).
    name: str
    #: What it is, for reports and docs.
    physics: ClassVar[str]
    #: Unit of a coefficient in the calibration file (nT per regressor unit), and the
    #: factor from SI to it.
    file_unit: str
    file_factor: float

    #: The recorded channels the effect reads, declared as data (``temperature``,
    #: ``current:TOPIC``, ``signal:TOPIC#FIELD``): what the default :meth:`inputs`,
    #: :meth:`missing` and the bag readers and nodes go by. The built-in effects that read
    #: whichever of a family is recorded (every current) say so in :meth:`inputs` instead.
    channels: ClassVar[tuple[str, ...]] = ()

    #: The data that tell the effect's field from look-alikes (a report's advice when two
    #: effects explain the same part of a residual); '' when not said.
    separated_by: ClassVar[str] = ''
    #: The regressor's zero is a value :meth:`reference` fixes at calibration (a reference
    #: temperature), not a physical zero: the field holds an unknown constant besides, which
    #: each sensor's hard iron takes (a model whose sensor has no hard iron of its own fits
    #: a constant beside the term).
    arbitrary_zero: ClassVar[bool] = False

    def inputs(self, available: tuple[str, ...]) -> tuple[str, ...]:
        """The channels the effect reads, from the channel names ``available``; () when a
        channel it needs is missing (the effect cannot be fitted)."""
        return self.channels if set(self.channels) <= set(available) else ()

    def missing(self, available: tuple[str, ...]) -> str:
        """What the effect needs that ``available`` lacks, for a message ('' if nothing)."""
        return ', '.join(name for name in self.channels if name not in available)

    @abstractmethod
    def labels(self, inputs: tuple[str, ...]) -> tuple[str, ...]:
        """One name per regressor."""

    def reference(self, channels: Channels, inputs: tuple[str, ...]) -> tuple[float, ...]:
        """Values fixed when the term is fitted (e.g. a reference temperature)."""
        return ()

    @abstractmethod
    def regressors(
        self, channels: Channels, inputs: tuple[str, ...], reference: tuple[float, ...]
    ) -> FloatArray:
        """Regressors (N, m) on every sample of ``channels``, SI; NaN where unknown."""

    def history_s(self, reference: tuple[float, ...]) -> float:
        """How far back, s, a sample's regressors reach into the samples before it (a
        differentiation window; 0: the sample alone). A reader in chunks keeps that much."""
        return 0.0

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        """The per-sample form of :meth:`regressors` (by default :meth:`regressors` on each
        sample alone: right for an effect without memory of earlier samples)."""
        return _Memoryless(self, inputs, reference)

    #: How the simulator and a scenario file give the effect's per-sensor coefficients
    #: (None: the simulator does not produce it).
    simulation: ClassVar[EffectSpec | None] = None

    def simulated_regressors(self, truth: Truth) -> FloatArray:
        """The exact regressors (N, m) of the simulated mission, SI: what
        :meth:`regressors` estimates from the recorded channels."""
        raise InputError(f'the simulator does not produce {self.name}')

    def simulate(self, coefficients: ArrayLike, truth: Truth) -> FloatArray:
        """The effect's field (N, 4, 3) T at the four sensors: the per-sensor coefficients
        ``coefficients`` (4, 3, m) SI (:attr:`simulation`'s shape) times
        :meth:`simulated_regressors`. This is the simulator's physics of the effect."""
        return linear_field(coefficients, self.simulated_regressors(truth))


@dataclass(frozen=True)
class Term:
    """A fitted effect: its coefficients in the pair differences, and how to evaluate it.

    Attributes
    ----------
    effect : registry name (:data:`tetra_gradiometer.core.effects.EFFECTS`)
    inputs : the channels it reads
    coefficients : (3, 3, m) ``W[i, r, j]``: pair ``i`` (sensor ``i+2`` minus sensor 1),
        axis ``r``, regressor ``j``; SI (T per regressor unit)
    reference : the values fixed when it was fitted (e.g. the reference temperature)
    channel_noise : (m,) RMS noise of each regressor, its unit (enters the 1-sigma)
    evidence : how it was selected (held-out gaps with and without it, the test), plain types
    window_mean : (m,) mean of each regressor over the samples it was fitted on, SI; ()
        when unknown (older files). Compensating without a channel holds the regressor there
    window_covariance : (m, m) covariance of the regressors over those samples, SI, as
        nested tuples; () when unknown. It widens the 1-sigma of such a compensation
    """

    effect: str
    inputs: tuple[str, ...]
    coefficients: np.ndarray
    reference: tuple[float, ...] = ()
    channel_noise: tuple[float, ...] = ()
    evidence: dict[str, Any] = field(default_factory=dict, compare=False)
    window_mean: tuple[float, ...] = ()
    window_covariance: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        coefficients = np.asarray(self.coefficients, dtype=float)
        if coefficients.ndim != 3 or coefficients.shape[:2] != (3, 3):
            raise InputError(
                f'{self.effect}: coefficients must be (3, 3, m), got {coefficients.shape}'
            )
        object.__setattr__(
            self, 'coefficients', frozen_array(coefficients, self.effect, coefficients.shape)
        )
        object.__setattr__(self, 'inputs', tuple(self.inputs))
        object.__setattr__(self, 'reference', tuple(float(v) for v in self.reference))
        noise = tuple(float(v) for v in self.channel_noise) or (0.0,) * self.size
        if len(noise) != self.size:
            raise InputError(f'{self.effect}: {len(noise)} channel noises for {self.size}')
        object.__setattr__(self, 'channel_noise', noise)
        mean = tuple(float(v) for v in self.window_mean)
        covariance = tuple(tuple(float(v) for v in row) for row in self.window_covariance)
        if (mean and len(mean) != self.size) or (
            covariance and np.shape(covariance) != (self.size, self.size)
        ):
            raise InputError(
                f'{self.effect}: window mean {len(mean)} / covariance {np.shape(covariance)} '
                f'for {self.size} regressors'
            )
        object.__setattr__(self, 'window_mean', mean)
        object.__setattr__(self, 'window_covariance', covariance)

    @property
    def size(self) -> int:
        """Regressors ``m``."""
        return int(self.coefficients.shape[2])

    @property
    def n_parameters(self) -> int:
        return 9 * self.size
