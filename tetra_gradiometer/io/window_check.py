"""What ``calibrate`` adds around a known-gradient solve on a bag window (issue 15): the
attitude from ``/odom`` so that a regional gradient is estimated jointly, and the test of
the fit's own assumption (a constant gradient over the window) with its verdict, the part
of the window that fails and a sub-window that would pass.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core import TetraGeometry, difference_tensor
from ..core.identification import (
    FitConsistency,
    Options,
    TensorCalibration,
    calibration_residual,
    fit_consistency,
    identify,
)
from ..core.units import NT_PER_T, S_PER_NS
from ..errors import AssumptionError, IdentifiabilityError
from . import conversions as cv
from .bag import MagneticBag
from .recording import interp_orientation

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Methods that assume a known (zero, or jointly fitted regional) gradient over the window.
KNOWN_GRADIENT_METHODS = ('known_gradient_lstsq', 'known_gradient_lstsq_general')
#: An ``/odom`` message further than this from a set leaves that set's attitude unknown, s
#: (the joint regional gradient and the trim guidance alike).
MAX_ODOM_GAP_S = 0.5
#: Shortest sub-window worth pointing to, s.
MIN_SUB_WINDOW_S = 30.0


def odom_orientation(
    bag_path: str | os.PathLike[str], stamps_ns: IntArray
) -> tuple[FloatArray | None, str]:
    """``/odom``'s orientation slerped onto ``stamps_ns`` (n, 4), or None, with a note why.

    None when the bag has no ``/odom`` or some set lies further than ``MAX_ODOM_GAP_S`` from
    every ``/odom`` message (the joint solve needs every attitude).
    """
    with MagneticBag(bag_path) as bag:
        series = bag.read_series(cv.ODOM_TOPIC)
    if series is None or len(series.stamps_ns) < 2:
        return None, (
            f'no {cv.ODOM_TOPIC} in the bag: a regional gradient cannot be told from the '
            'interference without the attitude, and is assumed zero'
        )
    odom = series.stamps_ns
    index = np.clip(np.searchsorted(odom, stamps_ns), 1, len(odom) - 1)
    gap = np.minimum(np.abs(odom[index] - stamps_ns), np.abs(stamps_ns - odom[index - 1]))
    if np.any(gap * S_PER_NS > MAX_ODOM_GAP_S):
        return None, (
            f'{cv.ODOM_TOPIC} misses {int(np.sum(gap * S_PER_NS > MAX_ODOM_GAP_S))} sets of the '
            f'window by more than {MAX_ODOM_GAP_S:g} s: the regional gradient is assumed zero'
        )
    note = f'regional gradient estimated jointly (attitude from {cv.ODOM_TOPIC})'
    return interp_orientation(odom, series.values, stamps_ns), note


@dataclass(frozen=True)
class WindowCheck:
    """The fit's test of its own assumption on the window.

    Attributes
    ----------
    consistency : FitConsistency
    first_ns : stamp of the bag's first set (window times are counted from it), ns
    passing_window : (t0, t1) s from the bag's first set: a sub-window that passes when
        refitted, or None
    """

    consistency: FitConsistency
    first_ns: int
    passing_window: tuple[float, float] | None

    @property
    def passed(self) -> bool:
        return self.consistency.passed

    def text(self) -> str:
        """One line: the verdict with the figures, the failing part, the passing window."""
        c = self.consistency
        line = (
            f'fit residual {c.residual_rms * NT_PER_T:.3g} nT/m is {c.ratio:.2f}x the noise '
            f'{c.noise_rms * NT_PER_T:.3g} nT/m (limit {c.threshold_ratio:.2f}x, F test at '
            f'alpha {c.alpha:g} of residual <= {c.tolerance:g} x noise)'
        )
        failing = c.failing_spans()
        if failing:
            line += '; fails in ' + ', '.join(f'{a:.0f}-{b:.0f} s' for a, b in failing[:3])
        if not self.passed:
            line += (
                f'; --window {self.passing_window[0]:.0f}:{self.passing_window[1]:.0f} would pass'
                if self.passing_window
                else '; no sub-window passes'
            )
        return line

    def to_dict(self) -> dict[str, Any]:
        return {
            **self.consistency.to_dict(),
            'passing_window_s': None if self.passing_window is None else list(self.passing_window),
        }


def check_window(
    calibration: TensorCalibration,
    method: str,
    stamps_ns: IntArray,
    fields: FloatArray,
    geometry: TetraGeometry,
    options: Options,
    first_ns: int,
) -> WindowCheck:
    """Test the fit on its window; when it fails, refit the longest passing run of blocks
    and point to it if that passes. Times are seconds from ``first_ns``."""
    orientation = options.orientation_xyzw
    consistency = _consistency(calibration, stamps_ns, fields, geometry, orientation, first_ns)
    passing = None
    span = None if consistency.passed else consistency.longest_passing_span()
    if span is not None and span[1] - span[0] >= MIN_SUB_WINDOW_S:
        t = (stamps_ns - first_ns) * S_PER_NS
        keep = (t >= span[0]) & (t <= span[1])
        sub = dataclasses.replace(
            options, orientation_xyzw=None if orientation is None else orientation[keep]
        )
        try:
            g_sub = difference_tensor(fields[keep], geometry)
            refit = identify(method, g_sub, fields[keep, 0], geometry, sub)
        except IdentifiabilityError:
            refit = None
        if isinstance(refit, TensorCalibration):
            again = _consistency(
                refit, stamps_ns[keep], fields[keep], geometry, sub.orientation_xyzw, first_ns
            )
            passing = span if again.passed else None
    return WindowCheck(consistency, first_ns, passing)


def _consistency(
    calibration: TensorCalibration,
    stamps_ns: IntArray,
    fields: FloatArray,
    geometry: TetraGeometry,
    orientation: FloatArray | None,
    first_ns: int,
) -> FitConsistency:
    g_measured = difference_tensor(fields, geometry)
    residual = calibration_residual(
        calibration, g_measured, fields[:, 0], geometry, orientation_xyzw=orientation
    )
    regional = calibration.regional_gradient_enu is not None
    n_parameters = calibration.n_parameters + (5 if regional else 0)
    t_s = (stamps_ns - first_ns) * S_PER_NS
    return fit_consistency(residual, t_s, geometry, n_parameters)


def refuse(check: WindowCheck, window: str) -> AssumptionError:
    """The error ``calibrate`` raises on a failed check (without ``--force``)."""
    return AssumptionError(
        f'the window ({window}) is not consistent with a constant gradient (a target, a '
        f'spatially varying field or a bad stretch): {check.text()}; no calibration written '
        '(--force writes it anyway, with this warning in the file)'
    )
