"""Signals the vehicle records on its own topics (a fin's angle, a load's current, a pump
switching), declared without code: ``TOPIC#FIELD:BASIS`` in the params file's
``vehicle_signals``, e.g. ``/joint_states#position[fin1]:harmonic``,
``/power/sonar#data:linear``.

``FIELD`` is a path into the message: attribute names joined by dots, an element by index
(``data[2]``) or, in an array beside a ``name`` array (``sensor_msgs/JointState``), by name
(``position[fin1]``). ``BASIS`` says how the signal ``x`` enters the field at the sensors,
each regressor with a 3-vector per sensor (per pair in the tensor):

* ``linear``: ``x`` (a current through a cable: Biot-Savart, proportional to it);
* ``harmonic``: ``cos x``, ``sin x``, ``x`` in radians (a magnet turning with a fin or a
  rudder: a dipole turned by ``x`` about a fixed axis is ``m_par + cos x m_perp + sin x
  (a x m_perp)``; its constant part is hard iron, ``b``'s);
* ``onoff``: 1 while ``x`` is above the middle of its range on the calibration window, else
  0 (a load switched on and off: a sonar, a pump);
* ``rate``: ``dx/dt``, causal, over the last 4 sample periods as the eddy currents' rate
  (eddy currents in a conducting fin as it turns, an inductive load as its current changes).

The effect of a declaration is named ``signal:`` + the declaration; it reads the channel
``signal:TOPIC#FIELD``. Chosen, and written down: the harmonic basis stops at the first
harmonic (a finite magnet 2 m away differs from a dipole by ~(size / distance)^2, 1 %);
a signal found in a recording rather than declared (``calibrate``'s automatic selection,
the discrepancy search) gets one basis, :func:`basis_for`: two bases of one signal are
nearly collinear for small angles (sin x ~ x) and would split one physical source between
them, so a rate is declared, not discovered.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ..types import FloatArray
from ..units import NT_PER_T
from .base import Channels, Effect, LiveRegressor
from .eddy_current import LiveRate, causal_rate, window_for

#: The prefix of a declared signal's effect and channel names.
SIGNAL_PREFIX = 'signal:'
BASES = ('linear', 'harmonic', 'onoff', 'rate')
_PATH = re.compile(r'[A-Za-z_]\w*(\[[^\[\]]+\])?(\.[A-Za-z_]\w*(\[[^\[\]]+\])?)*')
_TOPIC = re.compile(r'(/[A-Za-z_~][\w]*)+')


@dataclass(frozen=True)
class Declaration:
    """One declared signal: ``topic`` (absolute), ``field`` (a path into its message),
    ``basis`` (one of :data:`BASES`)."""

    topic: str
    field: str
    basis: str

    @property
    def channel(self) -> str:
        """The channel name of the recorded value: ``signal:TOPIC#FIELD``."""
        return f'{SIGNAL_PREFIX}{self.topic}#{self.field}'

    @property
    def effect_name(self) -> str:
        return f'{self.channel}:{self.basis}'

    @property
    def text(self) -> str:
        """The declaration as the params file writes it."""
        return f'{self.topic}#{self.field}:{self.basis}'


def parse_channel(name: str) -> tuple[str, str]:
    """A signal channel's ``(topic, field)``: ``signal:TOPIC#FIELD`` split."""
    topic, _, field = name.removeprefix(SIGNAL_PREFIX).partition('#')
    return topic, field


def parse_declaration(text: str, where: str = 'vehicle_signals') -> Declaration:
    """``TOPIC#FIELD:BASIS`` (or the effect name, ``signal:`` in front) as a declaration.

    Raises
    ------
    InputError
        Naming the part that is not one: the topic, the field path or the basis.
    """
    body = str(text).strip().removeprefix(SIGNAL_PREFIX)
    topic, hash_, rest = body.partition('#')
    path, colon, basis = rest.rpartition(':')
    if not hash_ or not colon:
        raise InputError(
            f'{where}: {text!r} is not TOPIC#FIELD:BASIS (e.g. /joint_states#position[fin1]:'
            f'harmonic; bases: {", ".join(BASES)})'
        )
    if not _TOPIC.fullmatch(topic):
        raise InputError(f'{where}: {text!r}: {topic!r} is not an absolute topic name')
    if not _PATH.fullmatch(path):
        raise InputError(
            f'{where}: {text!r}: {path!r} is not a field path (names joined by dots, an '
            'element as [index] or [joint name])'
        )
    if basis not in BASES:
        raise InputError(f'{where}: {text!r}: basis {basis!r} is not one of {", ".join(BASES)}')
    return Declaration(topic, path, basis)


#: An angle's values stay within this of zero, rad.
ANGLE_BOUND_RAD = 2 * np.pi
_ANGLE_WORDS = re.compile(r'position\[|angle|yaw|pitch|roll|heading|rudder|fin|servo', re.I)


def basis_for(channel: str, values: FloatArray) -> str | None:
    """The basis a recorded signal found in the data is offered in: ``harmonic`` for an angle
    (a field whose name says so: a ``JointState`` position, or a name with angle, yaw, pitch,
    roll, heading, rudder, fin, servo; and whose values stay within +-2 pi: a magnet turning
    with a fin is cos, sin of its angle), ``linear`` for everything else (a current; a
    switched load's two levels are linear); None when ``values`` (N,) has no finite value."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if not len(finite):
        return None
    field = parse_channel(channel)[1]
    angle = bool(_ANGLE_WORDS.search(field)) and np.abs(finite).max() <= ANGLE_BOUND_RAD
    return 'harmonic' if angle else 'linear'


def basis_columns(basis: str, x: FloatArray, reference: tuple[float, ...]) -> FloatArray:
    """The regressors (N, m) of signal values ``x`` (N,) in ``basis``, but ``rate`` (which
    needs the times: :meth:`RecordedSignal.regressors`); NaN where ``x`` is."""
    x = np.asarray(x, dtype=float)
    if basis == 'harmonic':
        return np.column_stack([np.cos(x), np.sin(x)])
    if basis == 'onoff':
        on = np.where(x > reference[0], 1.0, 0.0)
        return np.where(np.isfinite(x), on, np.nan)[:, None]
    return x[:, None]


class _Live(LiveRegressor):
    def __init__(self, channel: str, basis: str, reference: tuple[float, ...]) -> None:
        self.channel, self.basis, self.reference = channel, basis, reference
        self.rate = LiveRate(reference[0]) if basis == 'rate' else None

    def push(self, t_s: float, b_reference: np.ndarray, values: Mapping[str, float]) -> FloatArray:
        x = np.array([values.get(self.channel, np.nan)], dtype=float)
        if self.rate is not None:
            return self.rate.push(t_s, x)
        return basis_columns(self.basis, x, self.reference)[0]

    def reset(self) -> None:
        if self.rate is not None:
            self.rate.reset()


class RecordedSignal(Effect):
    """The effect of one :class:`Declaration`."""

    physics = (
        "A signal the vehicle records on its own topics (a fin's angle, a load's current, a "
        'switched load), declared as TOPIC#FIELD:BASIS: each basis function of it times a '
        '3-vector per sensor (nT per unit of the function).'
    )
    file_factor = NT_PER_T
    separated_by = 'its own time course: the recorded signal, not the attitude'

    def __init__(self, declaration: Declaration) -> None:
        self.declaration = declaration
        self.name = declaration.effect_name
        self.file_unit = {
            'linear': 'nT per signal unit',
            'harmonic': 'nT',
            'onoff': 'nT',
            'rate': 'nT per signal unit per s',
        }[declaration.basis]

    def inputs(self, available: tuple[str, ...]) -> tuple[str, ...]:
        channel = self.declaration.channel
        return (channel,) if channel in available else ()

    def missing(self, available: tuple[str, ...]) -> str:
        if self.inputs(available):
            return ''
        d = self.declaration
        return f'{d.field} of {d.topic} (declared in vehicle_signals)'

    def labels(self, inputs: tuple[str, ...]) -> tuple[str, ...]:
        d = self.declaration
        where = f'{d.topic}#{d.field}'
        return {
            'harmonic': (f'cos {where}', f'sin {where}'),
            'onoff': (f'{where} on',),
            'rate': (f'd/dt {where}',),
        }.get(d.basis, (where,))

    def reference(self, channels: Channels, inputs: tuple[str, ...]) -> tuple[float, ...]:
        if self.declaration.basis == 'rate':
            return (window_for(channels.t_s),)
        if self.declaration.basis != 'onoff':
            return ()
        x = np.asarray(channels.series[self.declaration.channel], dtype=float)
        x = x[np.isfinite(x)]
        return (0.5 * float(x.min() + x.max()),) if len(x) else (0.0,)

    def regressors(
        self, channels: Channels, inputs: tuple[str, ...], reference: tuple[float, ...]
    ) -> FloatArray:
        x = channels.series[self.declaration.channel]
        if self.declaration.basis == 'rate':
            return causal_rate(channels.t_s, np.asarray(x, dtype=float)[:, None], reference[0])
        return basis_columns(self.declaration.basis, x, reference)

    def history_s(self, reference: tuple[float, ...]) -> float:
        return reference[0] if self.declaration.basis == 'rate' else 0.0

    def live(self, inputs: tuple[str, ...], reference: tuple[float, ...]) -> LiveRegressor:
        return _Live(self.declaration.channel, self.declaration.basis, reference)
