"""Packages only the offline tools need, imported where they are used.

A vehicle computer installs with rosdep, which knows ``numpy``, ``scipy``, ``yaml`` and the
ROS packages but not ``rosbags``, ``ppigrf``, ``dask`` or the survey's ``verde``,
``xarray``, ``h5netcdf``, ``rioxarray``, ``pyproj`` (package.xml). The
on-vehicle nodes never import these; a path that does (the driver's replay, a scenario's
IGRF field, ``batch``, ``survey``) calls :func:`require` first, so a missing package is
one ``error:`` line naming the package and the pip command, not a traceback.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import DependencyError

#: Offline-only packages: import name -> pip requirement (requirements.txt pins the versions).
PIP_ONLY = {
    'rosbags': 'rosbags==0.11.9',
    'ppigrf': 'ppigrf==2.1.0',
    'dask': 'dask[distributed]==2026.8.0',
    'distributed': 'dask[distributed]==2026.8.0',
    # the survey command's gridding, grids, files and coordinates
    'verde': 'verde==1.9.0',
    'xarray': 'xarray==2026.9.0',
    'h5netcdf': 'h5netcdf==1.8.2',
    'rioxarray': 'rioxarray==0.19.0',
    'rasterio': 'rasterio==1.4.4',
    'pyproj': 'pyproj==3.7.2',
}


def require(module: str, purpose: str) -> ModuleType:
    """``module`` imported, or a :class:`DependencyError` saying that ``purpose`` needs it.

    Only a missing top-level package is turned into the error: an import error inside an
    installed package is a bug and keeps its traceback.
    """
    top = module.split('.')[0]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as error:
        if (error.name or '').split('.')[0] != top:
            raise
        pin = PIP_ONLY.get(top, top)
        raise DependencyError(
            f'{purpose} needs the Python package {top!r}, which a rosdep install does not '
            f'provide: python3 -m pip install "{pin}"'
        ) from None
