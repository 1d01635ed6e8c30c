"""The package's one error hierarchy: every domain error is a :class:`TetraError`.

The command line prints a ``TetraError`` as one ``error:`` line and exits 1; any other
exception is a bug and keeps its traceback. Imports nothing, so ``core/`` may use it.
Each subclass also derives from ``ValueError`` so callers that catch ``ValueError`` (numpy
style) keep working.
"""
from __future__ import annotations

__all__ = ['OutputError', 'TetraError']


class TetraError(Exception):
    """Base of every error the user can cause (bad input, bad data, refused output)."""


class OutputError(TetraError, ValueError):
    """An output path is refused: it exists and is not a previous output of the same kind,
    it is or contains an input, or it lies inside a rosbag2 folder. Nothing was written."""
