"""Calibration files: the compensation parameters ``k``, ``b`` as YAML, written atomically.

Format (version 1)::

    tetra_gradiometer_calibration: 1
    method: known_gradient_lstsq_general
    symmetric_k: false
    created_utc: '2026-11-22T10:00:00Z'
    sensor_positions: [12 floats, m]
    k_soft: [[[...]]]     # K_21, K_31, K_41 (3 x 3 x 3), dimensionless
    b_hard_T: [[...]]     # B_21^h, B_31^h, B_41^h (3 x 3), tesla
    diagnostics: {...}    # rank, condition number, residual (nT/m), ...
    sensor_noise_T: 5.0e-11           # optional: per-axis sensor noise estimated by the fit
    covariance: [[...]]               # optional: (P, P) covariance of the parameter vector
                                      # (P = 27 with symmetric_k, else 36; SI units of
                                      # InterferenceParameters.to_vector; with terms, 36
                                      # plus 9 per term regressor: full_vector)
    terms:                            # optional: the vehicle effects fitted with k, b
      - effect: vehicle_current       # core/effects registry name
        inputs: [current:/battery_state]   # the channels it reads
        labels: [I[/battery_state]_A]      # one per regressor
        unit: nT/A                    # of the coefficients
        coefficients: [[[...]]]       # [pair 2-1, 3-1, 4-1][axis x, y, z][regressor]
        reference: []                 # values fixed at the fit (thermal_drift: T_ref degC;
                                      # eddy_current: the differentiation window, s)
        channel_noise: [0.01]         # RMS noise of each regressor, its unit
        evidence: {...}               # the selection's held-out test of the term
        window: {mean: [...], covariance: [[...]]}   # optional: the regressors' mean and
                                      # covariance (SI) over the fitted samples (compensate
                                      # --allow-missing-channels holds and widens with them)

The two optional keys give the compensated tensor its uncertainty
(:mod:`~tetra_gradiometer.core.uncertainty`); files without them (older ones, or methods that
give no covariance) still load, and so do files without ``terms`` (the paper's model).
"""

from __future__ import annotations

import datetime as _dt
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..core import Calibration, InterferenceParameters, TensorCalibration, TetraGeometry
from ..core.effects import Term, term_from_dict, term_to_dict
from ..core.model import n_parameters
from ..core.plausibility import check_parameters, check_positions_match
from ..core.units import T_PER_NT
from ..errors import CalibrationFileError, InputError
from ._yaml import dumps, loads
from .outputs import CALIBRATION, atomic_write_text

FORMAT_VERSION = 1


@dataclass(frozen=True)
class CalibrationFile:
    """What a calibration file holds."""

    parameters: InterferenceParameters
    method: str
    symmetric_k: bool
    sensor_positions: list[float]
    diagnostics: dict[str, Any] = field(default_factory=dict)
    created_utc: str = ''
    sensor_noise_t: float | None = None
    covariance: np.ndarray | None = None

    @classmethod
    def from_calibration(
        cls, calibration: Calibration, geometry: TetraGeometry
    ) -> CalibrationFile:
        """The file of a ``k, b`` calibration (:class:`TensorCalibration`); other results
        (Pei & Yeo's per-sensor maps) and implausible ``k``, ``b`` (outside the bounds of
        :mod:`~tetra_gradiometer.core.plausibility`) raise :class:`CalibrationFileError`."""
        if not isinstance(calibration, TensorCalibration):
            raise CalibrationFileError(
                f'{calibration.method} gives no k, b: it cannot be written as a calibration file'
            )
        parameters = calibration.parameters
        try:
            check_parameters(parameters.k_soft, parameters.b_hard, f'the {calibration.method} fit')
        except InputError as error:
            raise CalibrationFileError(
                f'{error}; not written (were the samples a trim manoeuvre in a uniform field?)'
            ) from None
        summary = calibration.summary()
        noise_nt = summary.get('sensor_noise_nT')
        return cls(
            parameters=calibration.parameters,
            method=calibration.method,
            symmetric_k=calibration.symmetric,
            sensor_positions=geometry.to_flat(),
            diagnostics={k: v for k, v in summary.items() if np.isscalar(v)},
            created_utc=_dt.datetime.now(_dt.UTC).strftime('%Y-%m-%dT%H:%M:%SZ'),
            sensor_noise_t=None if noise_nt is None else float(noise_nt) * T_PER_NT,
            covariance=calibration.covariance,
        )

    def forced_warnings(self) -> tuple[str, ...]:
        """The checks this calibration was kept over (``--force``), from its notes: every use
        of it says them."""
        notes = self.diagnostics.get('notes') or []
        return tuple(str(note) for note in notes if str(note).startswith('WARNING ('))

    def to_yaml(self) -> str:
        document = {
            'tetra_gradiometer_calibration': FORMAT_VERSION,
            'method': self.method,
            'symmetric_k': bool(self.symmetric_k),
            'created_utc': self.created_utc,
            'sensor_positions': [float(v) for v in self.sensor_positions],
            'k_soft': self.parameters.k_soft.tolist(),
            'b_hard_T': self.parameters.b_hard.tolist(),
            'diagnostics': {
                k: (float(v) if isinstance(v, (float, np.floating)) else v)
                for k, v in self.diagnostics.items()
            },
        }
        if self.sensor_noise_t is not None:
            document['sensor_noise_T'] = float(self.sensor_noise_t)
        if self.covariance is not None:
            document['covariance'] = np.asarray(self.covariance, dtype=float).tolist()
        if self.parameters.terms:
            document['terms'] = [term_to_dict(term) for term in self.parameters.terms]
        return dumps(document)

    @classmethod
    def from_yaml(cls, text: str, source: str = 'calibration') -> CalibrationFile:
        """Parse and check a calibration: ``k``, ``b`` finite and within the physical
        bounds of :mod:`~tetra_gradiometer.core.plausibility` (else
        :class:`CalibrationFileError` naming the element)."""
        try:
            document = loads(text)
        except yaml.YAMLError as error:
            raise CalibrationFileError(f'{source} is not valid YAML: {error}') from None
        if (
            not isinstance(document, dict)
            or document.get('tetra_gradiometer_calibration') != FORMAT_VERSION
        ):
            raise CalibrationFileError(
                f'{source} is not a tetra_gradiometer calibration (version {FORMAT_VERSION})'
            )
        _check_keys(document, source)
        try:
            check_parameters(document['k_soft'], document['b_hard_T'], source)
            terms = _terms(document.get('terms'), source)
            parameters = InterferenceParameters(document['k_soft'], document['b_hard_T'], terms)
            symmetric_k = bool(document['symmetric_k'])
            if terms and symmetric_k:
                raise InputError(f'{source}: terms need the general k (symmetric_k: false)')
            return cls(
                parameters=parameters,
                method=str(document['method']),
                symmetric_k=symmetric_k,
                sensor_positions=[float(v) for v in document['sensor_positions']],
                diagnostics=dict(document.get('diagnostics') or {}),
                created_utc=str(document.get('created_utc', '')),
                sensor_noise_t=_noise(document.get('sensor_noise_T'), source),
                covariance=_covariance(
                    document.get('covariance'), parameters, symmetric_k, source
                ),
            )
        except InputError as error:  # named by check_parameters / the shape checks
            raise CalibrationFileError(str(error)) from None
        except (KeyError, TypeError, ValueError) as error:
            raise CalibrationFileError(f'{source} is malformed: {error}') from None


#: Every top-level key a calibration file may hold (``signature``: nodes/authentication).
KEYS = (
    'tetra_gradiometer_calibration',
    'method',
    'symmetric_k',
    'created_utc',
    'sensor_positions',
    'k_soft',
    'b_hard_T',
    'diagnostics',
    'sensor_noise_T',
    'covariance',
    'terms',
    'signature',
)
#: A calibration is refused unread above this size (the largest, with every term and its
#: covariance, is a few MB).
MAX_FILE_BYTES = 32 * 2**20


def _check_keys(document: dict[Any, Any], source: str) -> None:
    """Refuse unknown keys, naming each and the known key it most resembles: a misspelt
    optional key (``sensor_noise_t``) would otherwise be ignored without a word."""
    import difflib

    unknown = [str(key) for key in document if key not in KEYS]
    if not unknown:
        return
    named = []
    for key in unknown:
        close = difflib.get_close_matches(key, KEYS, n=1, cutoff=0.6)
        named.append(f'{key!r}' + (f' (did you mean {close[0]!r}?)' if close else ''))
    raise CalibrationFileError(
        f'{source}: unknown key{"s" * (len(unknown) > 1)} {", ".join(named)}; a calibration '
        f'holds only {", ".join(KEYS)}'
    )


def _noise(value: Any, source: str) -> float | None:
    """The optional ``sensor_noise_T``: finite, >= 0 and at most 1e-6 T."""
    if value is None:
        return None
    noise = float(value)
    if not 0.0 <= noise <= 1e-6:  # also refuses NaN
        raise InputError(f'{source}: sensor_noise_T = {noise:g} T is outside [0, 1e-6] T')
    return noise


def _terms(value: Any, source: str) -> tuple[Term, ...]:
    """The optional ``terms``: a list of :func:`~tetra_gradiometer.core.effects.term_to_dict`
    mappings, each checked; () when absent."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise InputError(f'{source}: terms must be a list, got {type(value).__name__}')
    terms = tuple(term_from_dict(item, f'{source}: terms[{i}]') for i, item in enumerate(value))
    names = [term.effect for term in terms]
    if len(set(names)) != len(names):
        raise InputError(f'{source}: terms name an effect twice: {names}')
    return terms


def _covariance(
    value: Any, parameters: InterferenceParameters, symmetric_k: bool, source: str
) -> np.ndarray | None:
    """The optional ``covariance``: finite, (P, P) for this layout, non-negative diagonal."""
    if value is None:
        return None
    covariance = np.asarray(value, dtype=float)
    size = n_parameters(symmetric=symmetric_k) + 9 * parameters.n_term_regressors
    if covariance.shape != (size, size):
        raise InputError(
            f'{source}: covariance must be {size} x {size} (symmetric_k: {symmetric_k}, '
            f'{parameters.n_term_regressors} term regressors), got shape {covariance.shape}'
        )
    if not np.all(np.isfinite(covariance)) or np.any(np.diag(covariance) < 0):
        raise InputError(f'{source}: covariance must be finite with a non-negative diagonal')
    return covariance


def check_positions(
    calibration: CalibrationFile,
    geometry: TetraGeometry,
    *,
    source: str,
    target: str = 'this array',
) -> None:
    """Raise :class:`CalibrationFileError` when ``calibration`` was made for other sensor
    positions than ``geometry`` (beyond :data:`~tetra_gradiometer.core.plausibility.
    POSITION_MATCH_M`), or its positions are not finite."""
    try:
        check_positions_match(
            calibration.sensor_positions, geometry.positions, source=source, target=target
        )
    except InputError as error:
        raise CalibrationFileError(str(error)) from None


def save_calibration(
    path: str | os.PathLike,
    calibration: CalibrationFile,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    sign: Callable[[str], str] | None = None,
) -> Path:
    """Write atomically (temporary file, then rename); ``sign`` maps the YAML text to the
    signed text (the calibrator's HMAC, ``calibrate --key-file``).

    Refused (:class:`~tetra_gradiometer.errors.OutputError`) when ``path`` exists and is not
    a calibration file, or is a previous one and ``force`` is False, or is one of ``inputs``
    (:func:`~tetra_gradiometer.io.outputs.check_output`).
    """
    text = calibration.to_yaml()
    text = text if sign is None else sign(text)
    return atomic_write_text(path, text, CALIBRATION, force=force, inputs=inputs)


def load_calibration(path: str | os.PathLike) -> CalibrationFile:
    """Read a calibration file, raising :class:`CalibrationFileError` with the reason."""
    path = Path(path)
    try:
        with path.open('rb') as handle:  # one bounded read: a pipe or device ends too
            data = handle.read(MAX_FILE_BYTES + 1)
    except OSError as error:
        raise CalibrationFileError(
            f'cannot read calibration file {path}: {error.strerror}'
        ) from None
    if len(data) > MAX_FILE_BYTES:
        raise CalibrationFileError(
            f'{path} is larger than {MAX_FILE_BYTES // 2**20} MB: too large to be a calibration; '
            'was another file given as the calibration?'
        )
    try:
        text = data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise CalibrationFileError(
            f'{path} is not a calibration: not UTF-8 text (byte {error.start})'
        ) from None
    return CalibrationFile.from_yaml(text, source=str(path))
