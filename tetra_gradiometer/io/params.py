"""ROS 2 parameter files (``/**: ros__parameters:``) as the offline tools read them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..core import TetraGeometry
from ..core.plausibility import MAX_FIELD_T, plausible_readings
from ..errors import InputError, ParamsError
from ._yaml import read_yaml


def load_params(path: str | os.PathLike, node: str = '/**') -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` (default the wildcard ``/**``) in ``path``.

    Falls back to the only node section when ``node`` is absent, so a file written for one
    named node also works.
    """
    path = Path(path)
    document = read_yaml(path, 'params', ParamsError)
    if not isinstance(document, dict) or not document:
        raise ParamsError(
            f'params file {path} has no node sections (expected "/**: ros__parameters:")'
        )
    section = document.get(node)
    if section is None and len(document) == 1:
        section = next(iter(document.values()))
    if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
        raise ParamsError(f'params file {path}: no "{node}: ros__parameters:" mapping')
    return section['ros__parameters']


def geometry_from_params(params: dict[str, Any], source: str = 'params') -> TetraGeometry:
    """The tetrahedron from ``sensor_positions`` (12 floats, metres, sensor 1 first).

    :meth:`TetraGeometry.from_flat` checks the values; its error is relabelled with
    ``source``.

    Raises
    ------
    ParamsError
        ``sensor_positions`` is missing or is not a usable tetrahedron.
    """
    values = params.get('sensor_positions')
    if values is None:
        raise ParamsError(f'{source}: sensor_positions is missing (12 floats, metres, body frame)')
    try:
        return TetraGeometry.from_flat(values)
    except InputError as error:
        raise ParamsError(f'{source}: {error}') from error


def earth_field_from_params(params: dict[str, Any], source: str = 'params') -> np.ndarray | None:
    """``earth_field_enu`` (3 finite floats, tesla, ``|B| <= MAX_FIELD_T``) or None when
    absent."""
    values = params.get('earth_field_enu')
    if values is None:
        return None
    try:
        field = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError):  # text, nested lists of unequal length, mappings
        field = np.full(1, np.nan)
    if field.size != 3 or not np.all(np.isfinite(field)):
        raise ParamsError(
            f'{source}: earth_field_enu must be 3 finite floats (tesla), got {values!r}'
        )
    if not plausible_readings(field):  # the readings' bound (core/plausibility)
        raise ParamsError(
            f'{source}: earth_field_enu must be tesla with |B| <= {MAX_FIELD_T:g} T '
            f'(the Earth field is ~5e-5 T), got {values!r}'
        )
    return field


def params_document(params: dict[str, Any]) -> str:
    """YAML text of a ``/**: ros__parameters:`` file holding ``params``."""
    return yaml.safe_dump({'/**': {'ros__parameters': params}}, sort_keys=False)
