"""One ``~/calibrate`` call's options (``tetra_gradiometer_msgs/srv/Calibrate``): the samples
it fits, whether it keeps a calibration that fails its checks, the effects it fits. They
apply to that call only; the calibrator's ``force`` and ``effects`` parameters are the
defaults (a request's ``force`` true overrides ``force`` false, not the reverse).

ROS-free (the request is read by its field names), so it is tested without a graph.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.units import NS_PER_S, T_PER_NT
from ..errors import InputError
from ..pipelines.effects_choice import EffectsChoice
from ..pipelines.window_check import CheckedCalibration

#: How ``~/calibrate`` names a passing part of the samples (times from the first one, s).
SUB_WINDOW = 'the samples {0:.0f}-{1:.0f} s after the first'


@dataclass(frozen=True)
class CalibrateCall:
    """The options of one call.

    Attributes
    ----------
    window_s : (first, last) sample stamps fitted, s (ROS time), inclusive; None: every
        sample collected
    force : keep a calibration whose window check or trim assessment fails
    effects : the effects choice (``auto``, ``none`` or effect names)
    """

    window_s: tuple[float, float] | None
    force: bool
    effects: str

    @classmethod
    def parse(cls, request: Any, parameter: Callable[[str], Any]) -> CalibrateCall:
        """The options of ``request`` (``window_s``, ``force``, ``effects``) over the node's
        ``force`` and ``effects`` parameters (``parameter``: the node's ``get_parameter``).

        Raises
        ------
        InputError
            A window that is not two finite stamps with first <= last, or an effects choice
            that names no effect (:meth:`EffectsChoice.parse`)."""
        first, last = (float(v) for v in request.window_s)
        window = None
        if (first, last) != (0.0, 0.0):
            if not (math.isfinite(first) and math.isfinite(last) and 0.0 <= first <= last):
                raise InputError(
                    f'window_s [{first:g}, {last:g}]: must be [first, last] sample stamps, s, '
                    'with 0 <= first <= last ([0, 0]: every sample collected)'
                )
            window = (first, last)
        choice = request.effects.strip() or parameter('effects').value
        try:
            EffectsChoice.parse(choice)
        except InputError as error:
            raise InputError(f'effects {str(error).removeprefix("--effects ")}') from None
        return cls(window, bool(request.force) or bool(parameter('force').value), choice)

    def select(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(n,) bool: the samples of ``stamps_ns`` (ns) inside the window."""
        if self.window_s is None:
            return np.ones(len(stamps_ns), dtype=bool)
        first, last = (round(v * NS_PER_S) for v in self.window_s)
        return (stamps_ns >= first) & (stamps_ns <= last)

    def describe(self, n: int) -> str:
        """The fitted samples, for the reply and the refusals: ``the 300 samples since
        ~/start`` or ``the 120 samples stamped 12.000-24.000 s``."""
        if self.window_s is None:
            return f'the {n} samples since ~/start'
        return f'the {n} samples stamped {self.window_s[0]:.3f}-{self.window_s[1]:.3f} s'


def kept(response: Any, checked: CheckedCalibration, stopped: str, path: Path) -> str:
    """The reply to a call whose calibration was written to ``path`` and published, with the
    fit's figures put into the Calibrate ``response``; ``stopped`` says why a GA stopped
    early ('' when it did not)."""
    s = checked.calibration.summary()
    response.residual_t_per_m = s['residual_rms_nT_per_m'] * T_PER_NT
    if checked.check is not None:
        response.residual_over_floor = checked.check.consistency.ratio
    response.rank, response.calibration_file = int(s['rank']), str(path)
    check = '' if checked.check is None else f'; {checked.check.text(SUB_WINDOW)}'
    regional = f'; regional gradient (ENU, nT/m) {g}' if (g := checked.regional_text()) else ''
    notes = ''.join(f'; {note}' for note in checked.notes)
    return (
        f'{s["method"]}: {s["n_samples"]} samples, {s["n_parameters"]} parameters, rank '
        f'{s["rank"]}, condition number {s["condition_number"]:.3g}, attitude coverage '
        f'{s["attitude_coverage_condition"]:.3g}, fit residual '
        f'{s["residual_rms_nT_per_m"]:.3g} nT/m{regional}{check}{stopped}'
        f'{notes}; written to {path}'
    )
