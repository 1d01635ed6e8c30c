"""The package's one error hierarchy: every domain error is a :class:`TetraError`.

The command line prints a ``TetraError`` as one ``error:`` line and exits 1; any other
exception is a bug and keeps its traceback. This module imports nothing, so ``core/`` may
use it. Each subclass also derives from ``ValueError``, so callers that catch
``ValueError`` (numpy and scipy style) keep working.
"""

from __future__ import annotations

__all__ = [
    'BagError',
    'CalibrationFileError',
    'DependencyError',
    'GeometryError',
    'IdentifiabilityError',
    'InputError',
    'MessageError',
    'OutputError',
    'ParamsError',
    'ScenarioError',
    'StreamError',
    'TetraError',
]


class TetraError(Exception):
    """Base of every error the user can cause (bad input, bad data, refused output)."""


class InputError(TetraError, ValueError):
    """An argument has the wrong shape, a non-finite or out-of-range value, or an unknown name."""


class GeometryError(InputError):
    """Sensor positions do not form a usable tetrahedron."""


class IdentifiabilityError(InputError):
    """The data cannot identify the asked parameters (too few samples or field directions)."""


class AssumptionError(InputError):
    """The data break the fit's assumption (e.g. a constant gradient over a calibration
    window): the residual is well above the noise."""


class MessageError(InputError):
    """A ROS message does not hold what the contract says (names, sizes, values)."""


class ParamsError(InputError):
    """A ROS 2 parameter file is missing, unreadable or invalid."""


class CalibrationFileError(InputError):
    """A calibration file (or topic text) is missing, truncated, malformed or for another array."""


class BagError(InputError):
    """A rosbag2 folder is missing, unreadable or does not follow the data contract."""


class StreamError(BagError):
    """A magnetometer stream cannot be used (its stamps or its unit): the message names the
    sensor and the time span (core/streams.py)."""


class ScenarioError(InputError):
    """A scenario file is missing or invalid."""


class DependencyError(TetraError, ImportError):
    """A package only the offline tools need (rosbags, ppigrf, dask) is not installed."""


class OutputError(TetraError, ValueError):
    """An output path is refused: it exists and is not a previous output of the same kind,
    it is, contains or lies inside an input, or it lies inside a rosbag2 folder. Nothing was
    written."""
