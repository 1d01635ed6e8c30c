"""Boundary checks shared by the core: shapes and finiteness, with messages that say where."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .types import ArrayLike, FloatArray


def as_array(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Return ``value`` as a finite float64 array of ``shape`` (``None`` = any length).

    Raises
    ------
    ValueError
        Naming ``name``, the expected and actual shape, or the first non-finite index.
    """
    array = np.asarray(value, dtype=float)
    if array.ndim != len(shape) or any(
        want is not None and have != want for have, want in zip(array.shape, shape, strict=True)
    ):
        want = (
            '('
            + ', '.join('N' if s is None else str(s) for s in shape)
            + (',)' if len(shape) == 1 else ')')
        )
        raise InputError(f'{name} must have shape {want}, got {array.shape}')
    if not np.all(np.isfinite(array)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        raise InputError(f'{name} has a non-finite value at index {bad}')
    return array


def frozen_array(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Like :func:`as_array`, but a read-only copy: for frozen dataclasses, so that neither the
    caller nor anyone else can change them afterwards."""
    array = as_array(value, name, shape).copy()
    array.setflags(write=False)
    return array


def as_fields(value: ArrayLike, name: str = 'fields') -> FloatArray:
    """Sensor fields, shape (N, 4, 3), tesla."""
    return as_array(value, name, (None, 4, 3))


def as_tensors(value: ArrayLike, name: str = 'tensors') -> FloatArray:
    """Gradient tensors, shape (N, 3, 3), T/m."""
    return as_array(value, name, (None, 3, 3))


def as_vectors(value: ArrayLike, name: str = 'vectors') -> FloatArray:
    """Vectors, shape (N, 3)."""
    return as_array(value, name, (None, 3))


def same_length(**arrays: np.ndarray) -> int:
    """Return the common first dimension of ``arrays`` or raise naming the mismatch."""
    lengths = {name: len(a) for name, a in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise InputError(f'sample counts differ: {lengths}')
    return next(iter(lengths.values()))


def require_positive(owner: str, **values: float) -> None:
    """Raise InputError naming the first value that is not a positive finite number."""
    for name, value in values.items():
        if not (np.isfinite(value) and value > 0):
            raise InputError(f'{owner}.{name} must be positive, got {value}')
