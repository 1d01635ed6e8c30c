"""The survey's files for GIS and geophysics software (the contract of ``survey --out DIR``):

* ``survey.nc`` -- netCDF-4 (h5netcdf), CF-1.8: dimensions ``y``, ``x`` (cell centres, m,
  in the CRS); data variables ``gxx`` .. ``gzz`` (world frame E, N, U: ``gij = dB_i/dx_j``,
  nT/m), ``i0`` (nT/m), ``i1`` (nT2 m-2), ``i2`` (nT3 m-3), ``nss`` (nT/m), each with
  ``<name>_sigma`` (1-sigma, same unit, ``ancillary_variables`` links them) and ``mask``
  (1 where gridded, 0 where farther than ``max_distance_m`` from every sample); every
  variable has ``grid_mapping = "spatial_ref"``, whose ``crs_wkt`` is the CRS's WKT
  (rioxarray's convention, which QGIS and GDAL read); masked cells are NaN (``_FillValue``);
  global attributes name the calibration, its effects, the software version, the CRS, the
  georeference, the cell and mask distance;
* ``geotiff/<variable>.tif`` -- one single-band float32 GeoTIFF per data variable (sigmas and
  mask included), north up, nodata NaN (rioxarray);
* ``targets.geojson`` -- RFC 7946 FeatureCollection: per target a Point (longitude, latitude,
  ellipsoidal height, WGS 84) with ``depth_m`` (below the odom origin, the sea surface),
  ``moment_Am2``, ``position_sigma_m`` (E, N, U of odom), ``passes`` and the rest of its
  ``targets.json`` record; and per target its horizontal 3-sigma ellipse as a Polygon
  (``"kind": "sigma_ellipse"``);
* ``targets.csv`` -- one row per target (the same numbers);
* ``track.geojson`` -- the track as a LineString (one per leg and the connecting pieces,
  thinned to 1 point per second) with its times.
"""

from __future__ import annotations

import csv
import io
import json
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._optional import require
from ..core.types import FloatArray
from ..core.units import NT_PER_T
from .geo import Georeference

__all__ = [
    'ELLIPSE_SIGMAS',
    'UNITS',
    'targets_csv',
    'targets_geojson',
    'track_geojson',
    'write_geotiffs',
    'write_netcdf',
]

#: Unit and SI -> file factor per gridded quantity.
UNITS = {
    **{
        name: ('nT m-1', NT_PER_T)
        for name in ('gxx', 'gxy', 'gxz', 'gyx', 'gyy', 'gyz', 'gzx', 'gzy', 'gzz', 'i0', 'nss')
    },
    'i1': ('nT2 m-2', NT_PER_T**2),
    'i2': ('nT3 m-3', NT_PER_T**3),
}
LONG_NAMES = {
    'i0': 'tensor invariant I0 (trace of the symmetric part)',
    'i1': 'tensor invariant I1 (sum of principal minors)',
    'i2': 'tensor invariant I2 (determinant)',
    'nss': 'normalized source strength',
}
AXES = 'ENU'
#: Ellipses drawn at this many sigma.
ELLIPSE_SIGMAS = 3.0


def _long_name(name: str) -> str:
    if name in LONG_NAMES:
        return LONG_NAMES[name]
    i, j = 'xyz'.index(name[1]), 'xyz'.index(name[2])
    return f'magnetic gradient tensor dB_{AXES[i]}/d{AXES[j]} (geodetic ENU)'


def dataset(grids: Any, crs: str, attrs: Mapping[str, Any]) -> Any:
    """The gridded quantities as an xarray Dataset (module docstring), CRS attached."""
    xr = require('xarray', 'writing the survey grids')
    require('rioxarray', 'writing the survey grids')
    variables: dict[str, Any] = {}
    for name, (unit, factor) in UNITS.items():
        common = {'units': unit, 'grid_mapping': 'spatial_ref'}
        variables[name] = (
            ('y', 'x'),
            (grids.values[name] * factor).astype(np.float32),
            {**common, 'long_name': _long_name(name), 'ancillary_variables': f'{name}_sigma'},
        )
        variables[f'{name}_sigma'] = (
            ('y', 'x'),
            (grids.sigmas[name] * factor).astype(np.float32),
            {**common, 'long_name': f'1-sigma of {_long_name(name)}'},
        )
    variables['mask'] = (
        ('y', 'x'),
        grids.mask.astype(np.int8),
        {
            'long_name': 'cell within max_distance_m of a sample',
            'flag_values': np.array([0, 1], np.int8),
            'flag_meanings': 'masked gridded',
            'grid_mapping': 'spatial_ref',
        },
    )
    coords = {
        'x': (
            'x',
            grids.x,
            {
                'units': 'm',
                'standard_name': 'projection_x_coordinate',
                'long_name': 'x (easting) of the cell centre',
                'axis': 'X',
            },
        ),
        'y': (
            'y',
            grids.y,
            {
                'units': 'm',
                'standard_name': 'projection_y_coordinate',
                'long_name': 'y (northing) of the cell centre',
                'axis': 'Y',
            },
        ),
    }
    ds = xr.Dataset(variables, coords=coords, attrs=dict(attrs))
    ds = ds.rio.write_crs(crs, grid_mapping_name='spatial_ref').rio.write_coordinate_system()
    for name in ds.data_vars:  # rioxarray keeps it in .encoding, which write_netcdf replaces
        ds[name].encoding.pop('grid_mapping', None)
        ds[name].attrs['grid_mapping'] = 'spatial_ref'
    ds['spatial_ref'].attrs['long_name'] = f'coordinate reference system {crs}'
    return ds


def write_netcdf(ds: Any, path: Path) -> None:
    """``survey.nc`` (h5netcdf engine; float NaN as the fill value, coordinates without one)."""
    encoding: dict[str, dict[str, Any]] = {
        name: {'_FillValue': np.float32(np.nan), 'compression': 'gzip', 'compression_opts': 4}
        for name in ds.data_vars
        if name not in ('mask', 'spatial_ref')
    }
    encoding['mask'] = {'_FillValue': None, 'compression': 'gzip', 'compression_opts': 4}
    encoding['spatial_ref'] = {'dtype': 'int32'}  # CF: no 64-bit integers
    encoding['x'] = {'_FillValue': None}
    encoding['y'] = {'_FillValue': None}
    ds.to_netcdf(path, engine='h5netcdf', encoding=encoding)


def write_geotiffs(ds: Any, folder: Path) -> list[Path]:
    """``folder/<variable>.tif`` per data variable (north up: rows from the north)."""
    folder.mkdir()
    out = []
    flipped = ds.isel(y=slice(None, None, -1))
    for name in ds.data_vars:
        if name == 'spatial_ref':
            continue
        array = flipped[name]
        if name == 'mask':
            array = array.astype(np.uint8)
        else:
            array = array.rio.write_nodata(np.nan, encoded=False)
        path = folder / f'{name}.tif'
        with warnings.catch_warnings():  # rioxarray 0.19 multiplies affine's matrices with *
            warnings.filterwarnings(
                'ignore', category=PendingDeprecationWarning, module='rioxarray'
            )
            array.rio.to_raster(path, compress='DEFLATE')
        out.append(path)
    return out


def _ellipse_ring(
    georeference: Georeference, position: FloatArray, covariance_xy: FloatArray, n: int = 36
) -> list[list[float]]:
    """The horizontal ``ELLIPSE_SIGMAS`` ellipse as a closed lon/lat ring (counter-clockwise,
    RFC 7946's exterior ring)."""
    values, vectors = np.linalg.eigh(covariance_xy)
    angles = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    unit = np.column_stack([np.cos(angles), np.sin(angles)])
    offsets = ELLIPSE_SIGMAS * (unit * np.sqrt(np.maximum(values, 0.0))) @ vectors.T
    points = np.column_stack(
        [position[0] + offsets[:, 0], position[1] + offsets[:, 1], np.full(n, position[2])]
    )
    lonlat = georeference.to_lonlat(points)[:, :2]
    if np.linalg.det(vectors) < 0:
        lonlat = lonlat[::-1]
    ring = [[float(a), float(b)] for a, b in lonlat]
    return [*ring, ring[0]]


def targets_geojson(
    records: list[dict[str, Any]],
    covariances_xy: list[FloatArray],
    georeference: Georeference,
) -> dict[str, Any]:
    """The FeatureCollection (module docstring) from ``targets.json`` records and each
    target's horizontal position covariance (2, 2) m^2 (odom x, y)."""
    features: list[dict[str, Any]] = []
    if records:
        positions = np.array([r['position_m'] for r in records], float)
        lonlat = georeference.to_lonlat(positions)
    for i, record in enumerate(records):
        properties = {
            'id': i,
            'depth_m': -float(record['position_m'][2]),
            **{k: v for k, v in record.items()},
        }
        features.append(
            {
                'type': 'Feature',
                'geometry': {'type': 'Point', 'coordinates': [float(v) for v in lonlat[i]]},
                'properties': properties,
            }
        )
        ring = _ellipse_ring(georeference, positions[i], covariances_xy[i])
        features.append(
            {
                'type': 'Feature',
                'geometry': {'type': 'Polygon', 'coordinates': [ring]},
                'properties': {'id': i, 'kind': 'sigma_ellipse', 'sigmas': ELLIPSE_SIGMAS},
            }
        )
    return {'type': 'FeatureCollection', 'features': features}


def targets_csv(records: list[dict[str, Any]], lonlat: FloatArray) -> str:
    """One row per target: lon, lat, height, depth, odom position, sigmas, moment, passes."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator='\n')
    writer.writerow(
        [
            'id',
            'lon_deg',
            'lat_deg',
            'height_m',
            'depth_m',
            'x_m',
            'y_m',
            'z_m',
            'sigma_x_m',
            'sigma_y_m',
            'sigma_z_m',
            'mx_Am2',
            'my_Am2',
            'mz_Am2',
            'passes',
            'dipolar',
            'fit_rms_nT_per_m',
        ]
    )
    for i, r in enumerate(records):
        writer.writerow(
            [
                i,
                *(f'{v:.9f}' for v in lonlat[i][:2]),
                f'{lonlat[i][2]:.3f}',
                f'{-r["position_m"][2]:.3f}',
                *(f'{v:.3f}' for v in r['position_m']),
                *(f'{v:.3f}' for v in r['position_sigma_m']),
                *(f'{v:.1f}' for v in r['moment_Am2']),
                r['passes'],
                r['dipolar'],
                f'{r["fit_rms_nT_per_m"]:.4f}',
            ]
        )
    return out.getvalue()


def track_geojson(t_s: FloatArray, lonlat: FloatArray, legs: list[tuple[int, int]]) -> dict:
    """The track as a FeatureCollection of LineStrings, one per leg (``"leg": i``) and
    per connecting piece (``"leg": null``), thinned to about 1 point per second."""
    pieces: list[tuple[int, int, int | None]] = []
    last = 0
    for i, (start, stop) in enumerate(legs):
        if start > last:
            pieces.append((last, start + 1, None))
        pieces.append((start, stop, i))
        last = stop - 1
    if last < len(t_s) - 1:
        pieces.append((last, len(t_s), None))
    period = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    step = max(1, int(round(1.0 / max(period, 1e-9))))
    features = []
    for start, stop, leg in pieces:
        index = np.unique(np.r_[np.arange(start, stop, step), stop - 1])
        if len(index) < 2:
            continue
        features.append(
            {
                'type': 'Feature',
                'geometry': {
                    'type': 'LineString',
                    'coordinates': [[round(float(v), 9) for v in lonlat[k, :2]] for k in index],
                },
                'properties': {
                    'leg': leg,
                    'start_s': float(t_s[start]),
                    'stop_s': float(t_s[stop - 1]),
                },
            }
        )
    return {'type': 'FeatureCollection', 'features': features}


def dumps(document: Mapping[str, Any]) -> str:
    """JSON text (finite numbers only, as RFC 7946 requires of coordinates)."""
    return json.dumps(document, indent=1, allow_nan=False) + '\n'
