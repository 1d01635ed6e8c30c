"""``targets.json``: located targets, the record of ``locate`` and of the target node.

::

    {"targets": [{"position_m": [x, y, z], "position_sigma_m": [sx, sy, sz],
                  "moment_Am2": [mx, my, mz], "moment_sigma_Am2": [...],
                  "first_seen_s": t0, "last_seen_s": t1, "fit_rms_nT_per_m": r,
                  "chi2_reduced": c, "dipolar": true, "passes": k, "samples": n,
                  "fitted_with": [j, ...]}, ...],
     "frame": "odom", "tensor": "compensated", "t0_stamp_s": s,
     "false_alarms_per_hour": f, "detections": d}

Positions in the ``/odom`` frame (ENU, m), moments in A m^2, sigmas 1-sigma from the fit's
covariance; ``first_seen_s`` / ``last_seen_s`` are seconds from the first tensor sample,
whose absolute header stamp (Unix seconds) is ``t0_stamp_s``. ``fit_rms_nT_per_m`` is the
fit's RMS residual per tensor component; ``dipolar`` false flags a target a point dipole
does not explain (a close pair, an extended object): its position is then only indicative.
``fitted_with`` lists the (0-based) indices of the targets fitted jointly with this one
(their tensors overlap along the track: a close pair or group, with correlated estimates).
``tensor`` says which tensor was searched (``compensated`` or ``raw``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..core.targets import Target
from ..core.units import NT_PER_T
from ..errors import InputError

#: The record's required keys per target (the contract; more may follow).
TARGET_KEYS = (
    'position_m',
    'position_sigma_m',
    'moment_Am2',
    'moment_sigma_Am2',
    'first_seen_s',
    'last_seen_s',
    'fit_rms_nT_per_m',
)
FRAME = 'odom'


def target_record(target: Target, t0_s: float = 0.0) -> dict[str, Any]:
    """One target as its ``targets.json`` entry; ``t0_s``: the time ``first_seen_s`` and
    ``last_seen_s`` are counted from (same clock as the target's)."""
    fit = target.fit
    return {
        'position_m': [float(v) for v in fit.position],
        'position_sigma_m': [float(v) for v in fit.position_sigma],
        'moment_Am2': [float(v) for v in fit.moment],
        'moment_sigma_Am2': [float(v) for v in fit.moment_sigma],
        'first_seen_s': float(target.first_seen_s - t0_s),
        'last_seen_s': float(target.last_seen_s - t0_s),
        'fit_rms_nT_per_m': float(fit.rms * NT_PER_T),
        'chi2_reduced': float(fit.chi2_reduced),
        'dipolar': bool(target.dipolar),
        'passes': len(target.detections),
        'samples': int(fit.n_samples),
        'fitted_with': [int(j) for j in target.fitted_with],
    }


def targets_document(
    targets: Iterable[Target],
    *,
    tensor: str,
    t0_stamp_s: float,
    false_alarms_per_hour: float,
    detections: int,
    t0_s: float = 0.0,
) -> dict[str, Any]:
    """The whole ``targets.json`` document (module docstring)."""
    return {
        'targets': [target_record(t, t0_s) for t in targets],
        'frame': FRAME,
        'tensor': tensor,
        't0_stamp_s': float(t0_stamp_s),
        'false_alarms_per_hour': float(false_alarms_per_hour),
        'detections': int(detections),
    }


def dumps(document: Mapping[str, Any]) -> str:
    """The document as JSON text (no NaN: strict JSON, as every reader expects)."""
    return json.dumps(document, indent=2, allow_nan=False) + '\n'


def read_targets(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A ``targets.json`` document, checked against the contract.

    Raises
    ------
    InputError
        Unreadable, not JSON, or an entry without a contract key or with a non-finite value.
    """
    path = Path(path)
    try:
        document = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, ValueError) as error:
        raise InputError(f'{path}: not a readable targets.json ({error})') from error
    if not isinstance(document, dict) or not isinstance(document.get('targets'), list):
        raise InputError(f'{path}: no "targets" list')
    if document.get('frame') != FRAME:
        raise InputError(f'{path}: frame {document.get("frame")!r}, expected {FRAME!r}')
    for i, entry in enumerate(document['targets']):
        missing = [key for key in TARGET_KEYS if key not in entry]
        if missing:
            raise InputError(f'{path}: targets[{i}] lacks {", ".join(missing)}')
        for key in TARGET_KEYS:
            values = entry[key] if isinstance(entry[key], list) else [entry[key]]
            if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
                raise InputError(f'{path}: targets[{i}].{key} is not finite: {entry[key]!r}')
    return document
