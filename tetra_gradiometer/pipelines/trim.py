"""The trim guidance around a calibration from a bag: what ``calibrate`` (and ``batch``, per
bag) does before it writes.

:func:`assess_window` adds the trim guidance of :mod:`tetra_gradiometer.core.guidance` on the
sets the solve used: attitude coverage from the bag's ``/odom`` when it holds one, the Earth
field from the params file (else estimated from ``/odom``). :func:`calibrate_assessed` is the
calibration (:func:`~.calibration.calibrate_bag`), its assessment and the refusal of a window
whose attitudes do not excite the parameters.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core import TetraGeometry, difference_tensor
from ..core.guidance import TrimAssessment, assess, trim_statistics
from ..core.units import NT_PER_T, S_PER_NS
from ..io import conversions as cv
from ..io.bag import MagneticBag
from ..io.recording import odometry_at
from .calibration import BagCalibration, calibrate_bag
from .window_check import excitation_refusal, forced, orientation_at

__all__ = [
    'WindowAssessment',
    'assess_window',
    'calibrate_assessed',
    'check_excitation',
    'odom_earth_field',
]

FloatArray = npt.NDArray[np.float64]


#: Sensor noise the assessment assumes if the window were too short to estimate its own, T.
DEFAULT_SENSOR_NOISE_T = 0.1e-9


@dataclass(frozen=True)
class WindowAssessment:
    """The trim guidance of a calibration window (``assessment`` None when it is impossible).

    Attributes
    ----------
    assessment : TrimAssessment or None
        On the sets the solve used; None without an Earth field (see ``notes``).
    earth_field_enu : ndarray, shape (3,), or None
        The site's field used, tesla, ENU.
    notes : tuple of str
        Where the Earth field and the attitude came from, or why there is no assessment.
    """

    assessment: TrimAssessment | None
    earth_field_enu: FloatArray | None
    notes: tuple[str, ...]


def odom_earth_field(orientation: FloatArray, b_reference: FloatArray) -> FloatArray | None:
    """The Earth field in ENU as the mean of ``R B_1'`` over the sets with an attitude (sensor
    1's own interference, a few hundred nT, biases it: negligible for the guidance)."""
    from scipy.spatial.transform import Rotation

    known = np.all(np.isfinite(orientation), axis=1)
    if not known.any():
        return None
    return Rotation.from_quat(orientation[known]).apply(b_reference[known]).mean(axis=0)


def assess_window(
    result: BagCalibration,
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    earth_field_enu: FloatArray | None = None,
) -> WindowAssessment:
    """The trim guidance (:func:`tetra_gradiometer.core.guidance.assess`) of the sets a
    calibration used: coverage by attitude from the bag's ``/odom`` when present, the Earth
    field ``earth_field_enu`` (the params file's) or else estimated from ``/odom``; the model
    assessed is the known-gradient solve of the method's parameter count.

    Raises
    ------
    BagError
        ``/odom`` is present but unreadable past the bag reader's skip limit.
    """
    stamps, fields = result.stamps_ns, result.fields
    notes: list[str] = []
    orientation = result.orientation_xyzw  # read for the joint fit: every set has one
    if orientation is None:  # not read, or some sets lack one: the coverage takes the rest
        with MagneticBag(bag_path) as bag:  # checked (io/recording.odometry_at)
            odometry = odometry_at(bag, stamps, fields[:, 0], 'calibrate', earth_field_enu)
        if odometry.orientation_xyzw is not None and odometry.check is not None:
            check = odometry.check
            orientation = orientation_at(
                check.stamps_ns, check.pose[:, cv.POSE_ORIENTATION], stamps
            )
    if orientation is None:
        notes.append(f'no usable {cv.ODOM_TOPIC}: coverage is of the body-frame field direction')
    earth = earth_field_enu
    if earth is not None:
        notes.append('Earth field from the params file (earth_field_enu)')
    elif orientation is not None:
        earth = odom_earth_field(orientation, fields[:, 0])
        if earth is not None:
            b_nt = ', '.join(f'{v * NT_PER_T:.0f}' for v in earth)
            notes.append(f"Earth field estimated from {cv.ODOM_TOPIC} and B_1': [{b_nt}] nT ENU")
    if earth is None:
        notes.append(
            'no trim assessment: the params file has no earth_field_enu and the bag no '
            f'{cv.ODOM_TOPIC} to estimate it from'
        )
        return WindowAssessment(None, None, tuple(notes))
    statistics = trim_statistics(
        fields[:, 0],
        difference_tensor(fields, geometry),
        geometry,
        orientation_xyzw=orientation,
    )
    span_s = (stamps[-1] - stamps[0]) * S_PER_NS if len(stamps) > 1 else 0.0
    noise_nt = result.calibration.details.get('sensor_noise_nT')
    assessment = assess(
        statistics,
        geometry,
        earth,
        sample_rate_hz=(len(stamps) - 1) / span_s if span_s > 0 else 1.0,
        sensor_noise_t=noise_nt / NT_PER_T if noise_nt else DEFAULT_SENSOR_NOISE_T,
        symmetric=result.calibration.n_parameters == 27,
        noise_given='the fit with its terms' if result.record.parameters.terms else '',
    )
    return WindowAssessment(assessment, np.asarray(earth, dtype=float), tuple(notes))


def check_excitation(
    result: BagCalibration, window: WindowAssessment, force: bool = False
) -> BagCalibration:
    """Refuse a calibration whose window's attitudes do not excite its parameters, or with
    ``force`` keep it with the warning in its notes (and its file's).

    Raises
    ------
    AssumptionError
        The trim assessment predicts a compensated survey sigma above
        :data:`~.window_check.MAX_PREDICTED_RATIO` noise floors, and not ``force``.
    """
    refusal = None
    if window.assessment is not None:
        refusal = excitation_refusal(window.assessment, result.window)
    for warning in forced([refusal], force):
        result = result.with_note(warning)
    return result


def calibrate_assessed(
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    earth_field_enu: FloatArray | None = None,
    *,
    force: bool = False,
    **options: Any,
) -> tuple[BagCalibration, WindowAssessment]:
    """The ``calibrate`` command's work before it writes: :func:`calibrate_bag` (``options``
    are its keywords; ``force`` keeps a window that fails a check, with the warning), the trim
    assessment of the sets used (:func:`assess_window`, ``earth_field_enu`` the params
    file's) and :func:`check_excitation`.

    Raises
    ------
    AssumptionError : the window breaks the fit's assumption or does not excite the
        parameters (not ``force``)
    BagError, IdentifiabilityError, InputError, CalibrationFileError : as
        :func:`calibrate_bag`
    """
    result = calibrate_bag(
        bag_path, geometry, force=force, earth_field_enu=earth_field_enu, **options
    )
    window = assess_window(result, bag_path, geometry, earth_field_enu)
    return check_excitation(result, window, force), window
