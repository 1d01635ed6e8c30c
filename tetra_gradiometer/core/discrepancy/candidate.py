"""What the discrepancy search tests: a candidate, a named family of terms added to the
per-sensor model ``B_i' = B_i + K_i B^b + B_i^h``, and what its builder may use.

A builder returns, for the current model state, the family's regressor columns as
full-sensor arrays ``(N, 4, 3, p)`` (nT per unit of the parameter), an optional fixed
``offset`` ``(N, 4, 3)`` nT (the exact remainder of a nonlinear family at its current
estimate, so that the linear columns fit the correction), and a label ``(sensor, name)``
per column. Units: nT, s, degC, A.

The candidates are the one registry's effects (:mod:`.effects`) and the search's detectors
of model errors (:mod:`.detectors`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..effects import Effect
from ..model import SensorInterference
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


def required(value: Array | None, what: str) -> Array:
    """``value``, which the candidate's ``requires`` guarantees (the workflow tests it first)."""
    if value is None:
        raise InputError(f'this candidate needs {what}, which the run does not have')
    return value


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
    """A named, physically explained family of terms: one candidate of the search.

    Attributes
    ----------
    name : its one name (report, ``--candidates``, synthetic cases)
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
    effect : the registry's effect it is, or None (a detector)
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
    effect: Effect | None = None


def empty(n: int, p: int) -> Array:
    """Zero columns (n, 4, 3, p)."""
    return np.zeros((n, 4, 3, p))


def registry_columns(ctx: Context, x: Array, label: Callable[[int, int], str]) -> Built:
    """A registry effect's regressors ``x`` (N, m) as per-sensor columns: for each sensor of
    the view, axis ``a`` and regressor ``j`` a column ``x[:, j]`` at (sensor, axis) with the
    label ``label(a, j)`` (the coefficient is in nT per unit of ``x``)."""
    n, m = x.shape
    cols = empty(n, 3 * m * len(ctx.sensors))
    labels: list[tuple[int, str]] = []
    k = 0
    for s in ctx.sensors:
        for a in range(3):
            for j in range(m):
                cols[:, s, a, k] = x[:, j]
                labels.append((s, label(a, j)))
                k += 1
    return cols, None, labels
