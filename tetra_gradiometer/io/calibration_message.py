"""The calibration as a ``tetra_gradiometer_msgs/Calibration`` message (the ``calibration``
topic), for rclpy and rosbags alike: no message package is imported here.

:func:`calibration_fields` gives the message's fields (all but ``header``) from a calibration
file's text, signature included: ``document`` is the whole text, so the message carries
everything the file holds, and the other fields summarize it (method, terms, the parameter
vector and its covariance, the fit's figures, the provenance, the signature).
:func:`calibration_from_message` reads a message back into the
:class:`~tetra_gradiometer.io.calibration.CalibrationFile` the compensator loads, from
``document``, and refuses a message whose summary fields disagree with its document (as it
refuses a corrupt calibration file).

Provenance: ``source`` is the diagnostics' ``source`` (the calibrator's node name) or else
``bag`` (``calibrate``'s bag); ``window_s`` is the diagnostics' ``samples_window_s`` (the
first and last fitted samples' stamps, s: the calibrator's and ``calibrate``'s) or else
``window_found.window_s`` (seconds into ``calibrate``'s bag), else ``[0, 0]``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import yaml

from ..core.effects import effect
from ..core.model import SYMMETRIC_ENTRIES
from ..core.units import T_PER_NT
from ..errors import CalibrationFileError
from ._yaml import dumps, loads
from .calibration import CalibrationFile

AXES = 'xyz'
PAIRS = ('21', '31', '41')
#: The summary fields, in the order a disagreement is reported.
SUMMARY_FIELDS = (
    *('method', 'symmetric_k', 'sensor_positions', 'terms', 'parameter_names', 'parameters'),
    *('covariance', 'sensor_noise_t', 'residual_t_per_m', 'rank', 'created_utc', 'source'),
    *('window_s', 'signature'),
)


def parameter_names(calibration: CalibrationFile) -> list[str]:
    """One name per element of :func:`parameter_vector`: ``K_21[xy]``, ``B_31[z]``,
    ``vehicle_current[41][x][I[/battery_state]_A]``."""
    if calibration.symmetric_k:
        entries = [AXES[r] + AXES[c] for r, c in SYMMETRIC_ENTRIES]
    else:
        entries = [r + c for r in AXES for c in AXES]
    names = [f'K_{pair}[{entry}]' for pair in PAIRS for entry in entries]
    names += [f'B_{pair}[{axis}]' for pair in PAIRS for axis in AXES]
    for term in calibration.parameters.terms:
        labels = effect(term.effect).labels(term.inputs)
        names += [
            f'{term.effect}[{pair}][{axis}][{label}]'
            for pair in PAIRS
            for axis in AXES
            for label in labels
        ]
    return names


def parameter_vector(calibration: CalibrationFile) -> np.ndarray:
    """(P,) the parameters in the layout of the file's covariance, SI: 27 or 36 for ``k``,
    ``b``, then 9 per term regressor (terms need the general ``k``)."""
    parameters = calibration.parameters
    if parameters.terms:
        return parameters.full_vector()
    return parameters.to_vector(symmetric=calibration.symmetric_k)


def _provenance(diagnostics: dict[str, Any]) -> tuple[str, list[float]]:
    """(source, window_s): see the module docstring."""
    source = str(diagnostics.get('source') or diagnostics.get('bag') or '')
    found = diagnostics.get('window_found')
    window = diagnostics.get('samples_window_s') or (
        found.get('window_s') if isinstance(found, dict) else None
    )
    return source, [float(v) for v in (window or (0.0, 0.0))]


def _signature(text: str, source: str) -> Any:
    try:
        return (loads(text) or {}).get('signature')
    except (yaml.YAMLError, AttributeError):
        raise CalibrationFileError(f'{source} is not a tetra_gradiometer calibration') from None


def calibration_fields(text: str, source: str = 'the calibration') -> dict[str, Any]:
    """The Calibration message's fields but ``header`` (plain lists, floats, ints, strings)
    from a calibration file's ``text`` (its YAML, signed or not).

    Raises
    ------
    CalibrationFileError
        ``text`` is not a calibration (:meth:`CalibrationFile.from_yaml`)."""
    return _fields(CalibrationFile.from_yaml(text, source=source), text, source)


def _fields(calibration: CalibrationFile, text: str, source: str) -> dict[str, Any]:
    diagnostics = calibration.diagnostics
    signature = _signature(text, source)
    residual_nt = diagnostics.get('residual_rms_nT_per_m')
    covariance = calibration.covariance
    origin, window = _provenance(diagnostics)
    return {
        'method': calibration.method,
        'symmetric_k': bool(calibration.symmetric_k),
        'sensor_positions': [float(v) for v in calibration.sensor_positions],
        'terms': [term.effect for term in calibration.parameters.terms],
        'parameter_names': parameter_names(calibration),
        'parameters': parameter_vector(calibration).tolist(),
        'covariance': [] if covariance is None else np.ravel(covariance).tolist(),
        'sensor_noise_t': np.nan if calibration.sensor_noise_t is None
        else float(calibration.sensor_noise_t),
        'residual_t_per_m': np.nan if residual_nt is None else float(residual_nt) * T_PER_NT,
        'rank': int(diagnostics.get('rank', 0)),
        'created_utc': calibration.created_utc,
        'source': origin,
        'window_s': window,
        'signature': '' if signature is None else dumps(signature),
        'document': text,
    }


def _same(name: str, value: Any, expected: Any) -> bool:
    if name == 'signature':  # compared parsed: its YAML layout is the publisher's
        try:
            return loads(value or '""') == loads(expected or '""')
        except yaml.YAMLError:
            return False
    if isinstance(expected, str):
        return bool(value == expected)
    if isinstance(expected, list) and expected and isinstance(expected[0], str):
        return list(value) == expected
    value, expected = np.asarray(value, dtype=float), np.asarray(expected, dtype=float)
    return value.shape == expected.shape and bool(np.array_equal(value, expected, equal_nan=True))


def calibration_from_message(msg: Any, source: str) -> CalibrationFile:
    """The calibration a Calibration message ``msg`` (rclpy's or rosbags') carries, read
    from its ``document``.

    Raises
    ------
    CalibrationFileError
        The document is not a calibration, or a summary field disagrees with it (naming
        the first that does)."""
    calibration = CalibrationFile.from_yaml(msg.document, source=source)
    expected = _fields(calibration, msg.document, source)
    for name in SUMMARY_FIELDS:
        if not _same(name, getattr(msg, name), expected[name]):
            raise CalibrationFileError(
                f'{source}: the field {name} disagrees with the document it summarizes '
                '(a corrupt or altered calibration message)'
            )
    return calibration
