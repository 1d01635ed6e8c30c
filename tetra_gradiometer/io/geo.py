"""Placing the survey on the Earth: the odom frame -> geodetic (WGS 84) transform, and
positions in any projected CRS (pyproj, imported where used: offline only).

The odom frame is a local ENU frame (REP 105). Its transform to the Earth is a rotation
about the vertical (``yaw_rad``, odom axes -> true east/north) and an offset in the local
geodetic ENU frame tangent at ``origin`` (lat, lon, h on WGS 84): a point ``p`` of the odom
frame is ``R(yaw) p + offset_m`` in that tangent frame, which PROJ's ``topocentric``
conversion maps exactly to geocentric and then geodetic coordinates (no flat-Earth
approximation: the tangent plane's drop below the ellipsoid, 8 cm at 1 km, is kept).

Two sources (:class:`Georeference`):

* ``--origin LAT,LON[,ALT]``: the odom frame's origin is at that point and its axes are
  east, north, up there (``yaw_rad`` 0, ``offset_m`` 0);
* a ``sensor_msgs/NavSatFix`` topic in the bag (:func:`fit_fixes`): the fixes with a fix
  (status >= 0) paired with the odom position at their stamps, the tangent point at their
  mean, and the rotation and translation in the horizontal plane fitted by least squares
  (Kabsch, no scale: odometry is metric); the vertical offset is the mean of ``alt - z``.
  Its residual (RMS horizontal distance, m) is reported.

World-frame tensors are in the local geodetic ENU frame (true north) of the tangent point,
not in the projected grid's axes: the two differ by the meridian convergence (reported as
``convergence_deg``, a fraction of a degree to 3 degrees in a UTM zone).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._optional import require
from ..core.types import FloatArray
from ..errors import BagError, InputError

__all__ = [
    'NAVSATFIX',
    'Fixes',
    'Georeference',
    'fit_fixes',
    'origin_earth_check',
    'parse_origin',
    'read_fixes',
    'utm_epsg',
]

NAVSATFIX = 'sensor_msgs/msg/NavSatFix'
WGS84_LONLAT = 'EPSG:4326'
#: Fewest fixes :func:`fit_fixes` accepts (a rotation and a translation: 3 unknowns).
MIN_FIXES = 3
#: Fixes that follow the odometry worse than this, m RMS, are said to (GNSS at the surface
#: agrees to a few metres; dead reckoning between surfacings drifts by tens).
FIX_RESIDUAL_WARN_M = 25.0
#: Worse than this, m RMS, or than this share of the track's RMS spread, they are not this
#: track's (another vehicle's fixes, another frame): refused.
MAX_FIX_RESIDUAL_M = 500.0
MAX_FIX_RESIDUAL_SHARE = 0.25


def _pyproj() -> Any:
    return require('pyproj', 'georeferencing the survey')


def parse_origin(text: str) -> tuple[float, float, float]:
    """``'LAT,LON[,ALT]'`` (degrees, degrees, m above the WGS 84 ellipsoid; ALT default 0)."""
    try:
        values = [float(v) for v in text.split(',')]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise InputError(f'--origin {text!r}: give LAT,LON or LAT,LON,ALT in degrees and m')
    lat, lon = values[0], values[1]
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise InputError(
            f'--origin {text!r}: latitude must be in [-90, 90], longitude in [-180, 180]'
        )
    return lat, lon, values[2] if len(values) == 3 else 0.0


#: A declared Earth field further than this from the IGRF field at the survey's place is
#: named (IGRF's main field leaves crustal anomalies of up to a few uT; a place 1000 km off
#: moves it by 5-10 uT).
MAX_EARTH_FIELD_OFFSET_T = 10e-6


def igrf_at(origin: tuple[float, float, float], when_ns: int) -> FloatArray:
    """IGRF (3,) T ENU at ``origin`` (lat, lon, h) and ``when_ns`` (ns since the epoch)."""
    import datetime as dt

    from .scenario import igrf_field_enu

    when = dt.datetime.fromtimestamp(when_ns * 1e-9, tz=dt.UTC).replace(tzinfo=None)
    return igrf_field_enu(origin[0], origin[1], when, origin[2])


def origin_earth_check(
    origin: tuple[float, float, float], earth_field_enu: FloatArray, when_ns: int
) -> tuple[str | None, bool]:
    """The placement ``origin`` (lat, lon, h) against the params file's ``earth_field_enu``
    (3,) T: IGRF at that place and at ``when_ns`` (the bag's start) should be within
    :data:`MAX_EARTH_FIELD_OFFSET_T`. Returns (None, False) when it is; else the line, and
    whether the origin given as LON,LAT explains it (the field at the swapped place within
    half the offset, and the bound): then the placement is surely wrong."""
    lat, lon, h = origin
    declared = np.asarray(earth_field_enu, dtype=float)
    offset = float(np.linalg.norm(igrf_at(origin, when_ns) - declared))
    if offset <= MAX_EARTH_FIELD_OFFSET_T:
        return None, False
    swapped = np.inf
    if -90.0 <= lon <= 90.0:
        swapped = float(np.linalg.norm(igrf_at((lon, lat, h), when_ns) - declared))
    if swapped <= min(0.5 * offset, MAX_EARTH_FIELD_OFFSET_T):
        return (
            f'--origin {lat:g},{lon:g} looks given as LON,LAT: the IGRF field there differs from '
            f'earth_field_enu by {offset * 1e6:.0f} uT, at {lon:g},{lat:g} by '
            f'{swapped * 1e6:.1f} uT; give LAT,LON'
        ), True
    return (
        f"the IGRF field at --origin {lat:g},{lon:g} differs from the params file's "
        f'earth_field_enu by {offset * 1e6:.0f} uT (more than {MAX_EARTH_FIELD_OFFSET_T * 1e6:g} '
        "uT): the origin or earth_field_enu is not this survey's"
    ), False


def utm_epsg(lat_deg: float, lon_deg: float) -> str:
    """The WGS 84 UTM zone's EPSG code at a point (``EPSG:326ZZ`` north, ``EPSG:327ZZ``
    south; the standard 6-degree zones, without the Norway and Svalbard exceptions)."""
    zone = min(int((lon_deg + 180.0) // 6.0) + 1, 60)
    return f'EPSG:{32600 + zone if lat_deg >= 0 else 32700 + zone}'


@dataclass(frozen=True)
class Georeference:
    """The odom -> geodetic transform (module docstring).

    Attributes
    ----------
    origin : (lat_deg, lon_deg, h_m), the tangent point on WGS 84
    yaw_rad : rotation of the odom axes into east/north, counter-clockwise seen from above
    offset_m : (3,) the odom origin in the tangent ENU frame, m
    source : where it came from ('--origin' or the NavSatFix topic)
    residual_m : RMS horizontal misfit of the fixes, m (NaN for '--origin')
    n_fixes : fixes used (0 for '--origin')
    n_unlocked : fixes left out as unlocked (NO_FIX, non-finite, or 0, 0)
    """

    origin: tuple[float, float, float]
    yaw_rad: float = 0.0
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str = '--origin'
    residual_m: float = float('nan')
    n_fixes: int = 0
    n_unlocked: int = 0

    @property
    def rotation(self) -> FloatArray:
        """(3, 3) odom vectors -> tangent ENU vectors (a rotation about up)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def _topocentric(self) -> Any:
        lat, lon, h = self.origin
        pipeline = (
            '+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 '
            f'+lat_0={lat!r} +lon_0={lon!r} +h_0={h!r} +step +inv +proj=cart +ellps=WGS84'
        )
        return _pyproj().Transformer.from_pipeline(pipeline)

    def to_enu(self, points_m: FloatArray) -> FloatArray:
        """Odom points (N, 3) m -> the tangent ENU frame (N, 3) m."""
        return np.asarray(points_m, float) @ self.rotation.T + np.asarray(self.offset_m)

    def from_enu(self, enu_m: FloatArray) -> FloatArray:
        """The inverse of :meth:`to_enu`."""
        return (np.asarray(enu_m, float) - np.asarray(self.offset_m)) @ self.rotation

    def to_lonlat(self, points_m: FloatArray) -> FloatArray:
        """Odom points (N, 3) m -> (N, 3): longitude, latitude (degrees), height (m, WGS 84)."""
        enu = self.to_enu(points_m)
        lon, lat, h = self._topocentric().transform(enu[:, 0], enu[:, 1], enu[:, 2])
        return np.column_stack([lon, lat, h])

    def from_lonlat(self, lonlath: FloatArray) -> FloatArray:
        """The inverse of :meth:`to_lonlat`: (N, 3) lon, lat, h -> odom points (N, 3) m."""
        values = np.asarray(lonlath, float)
        transformer = self._topocentric()
        e, n, u = transformer.transform(
            values[:, 0], values[:, 1], values[:, 2], direction='INVERSE'
        )
        return self.from_enu(np.column_stack([e, n, u]))

    def to_crs(self, points_m: FloatArray, crs: str) -> FloatArray:
        """Odom points (N, 3) m -> (N, 2) x, y in ``crs`` (any pyproj CRS string)."""
        lonlat = self.to_lonlat(points_m)
        pyproj = _pyproj()
        transformer = pyproj.Transformer.from_crs(WGS84_LONLAT, crs, always_xy=True)
        x, y = transformer.transform(lonlat[:, 0], lonlat[:, 1])
        return np.column_stack([x, y])

    def default_crs(self) -> str:
        """The UTM zone of the tangent point."""
        return utm_epsg(self.origin[0], self.origin[1])

    def convergence_deg(self, crs: str) -> float:
        """The angle from true north to the CRS's grid north at the tangent point, degrees
        (pyproj's meridian convergence; 0 for a geographic CRS)."""
        pyproj = _pyproj()
        lat, lon, _ = self.origin
        factors = pyproj.Proj(pyproj.CRS.from_user_input(crs)).get_factors(lon, lat)
        return float(factors.meridian_convergence)

    def describe(self) -> str:
        """One line for the command and the files' metadata."""
        lat, lon, h = self.origin
        text = f'odom placed by {self.source} at {lat:.7f}, {lon:.7f}, {h:.2f} m'
        if self.n_fixes:
            text += (
                f' ({self.n_fixes} fixes, yaw {math.degrees(self.yaw_rad):.3f} deg, '
                f'residual {self.residual_m:.3f} m RMS'
                + (f'; {self.n_unlocked} unlocked fixes left out' if self.n_unlocked else '')
                + ')'
            )
        if self.residual_m > FIX_RESIDUAL_WARN_M:
            text += (
                f'; warning: the fixes follow the odometry to {self.residual_m:.0f} m RMS, not '
                'the few metres of GNSS: dead-reckoning drift between fixes, or fixes taken '
                'under water; products are placed no better'
            )
        return text


@dataclass(frozen=True)
class Fixes:
    """A NavSatFix topic's fixes: stamps (N,) ns, lat, lon (N,) degrees, alt (N,) m;
    ``unlocked`` the messages left out (NO_FIX, non-finite or at 0, 0)."""

    stamps_ns: np.ndarray
    lat_deg: FloatArray
    lon_deg: FloatArray
    alt_m: FloatArray
    unlocked: int = 0


def read_fixes(bag_path: str | os.PathLike[str], topic: str) -> Fixes:
    """The fixes of ``topic`` in the bag, by header stamp: status >= 0, finite lat/lon, and
    not exactly 0, 0 (a receiver's value before its first fix); the rest counted.

    Raises
    ------
    BagError
        The topic is absent, not a NavSatFix, or holds no fix.
    """
    from .bag import MagneticBag

    stamps, rows, unlocked = [], [], 0
    with MagneticBag(bag_path) as bag:
        reader = bag.reader
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise BagError(f'{bag_path}: no {topic} (the NavSatFix topic) in the bag')
        if connections[0].msgtype != NAVSATFIX:
            raise BagError(f'{bag_path}: {topic} is a {connections[0].msgtype}, not a {NAVSATFIX}')
        for connection, _, raw in reader.messages(connections=connections):
            msg: Any = reader.deserialize(raw, connection.msgtype)
            row = (msg.latitude, msg.longitude, msg.altitude)
            locked = msg.status.status >= 0 and all(math.isfinite(v) for v in row[:2])
            if not locked or row[:2] == (0.0, 0.0):
                unlocked += 1
                continue
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            rows.append(row)
    if not rows:
        raise BagError(
            f'{bag_path}: {topic} holds no fix ({unlocked} messages, every one NO_FIX, '
            'non-finite or at 0, 0)'
        )
    values = np.asarray(rows, float)
    stamps_ns = np.asarray(stamps, np.int64)
    return Fixes(stamps_ns, values[:, 0], values[:, 1], values[:, 2], unlocked)


def fit_fixes(fixes: Fixes, odom_m: FloatArray, source: str) -> Georeference:
    """The transform (module docstring) from fixes and the odom positions (N, 3) m at their
    stamps: tangent point at the fixes' mean, 2D Kabsch rotation and translation.

    Raises
    ------
    InputError
        Fewer than :data:`MIN_FIXES` fixes, fixes all at one place (no rotation), or fixes
        that miss the track by more than :data:`MAX_FIX_RESIDUAL_M` RMS or a quarter of its
        spread (the odometry's x and y swapped named when that fits: NED positions).
    """
    odom = np.asarray(odom_m, float)
    if len(odom) < MIN_FIXES:
        raise InputError(f'{source}: {len(odom)} fix(es) on the track, need {MIN_FIXES}')
    origin = (float(np.mean(fixes.lat_deg)), float(np.mean(fixes.lon_deg)), 0.0)
    tangent = Georeference(origin)
    geodetic = np.column_stack([fixes.lon_deg, fixes.lat_deg, fixes.alt_m])
    enu = tangent.from_lonlat(geodetic)  # yaw 0, offset 0: the tangent frame itself
    if np.sqrt(np.sum(np.square(odom[:, :2] - odom[:, :2].mean(axis=0)), axis=1)).max() < 1.0:
        raise InputError(f'{source}: the fixes lie within 1 m of each other: no heading to fit')
    yaw, horizontal, residual = _plane_fit(odom[:, :2], enu[:, :2])
    swapped = _plane_fit(odom[:, 1::-1], enu[:, :2])[2] if residual > FIX_RESIDUAL_WARN_M else 0
    # a misfit near the track's own size is no placement: the fit only centred it
    spread = float(np.sqrt(np.mean(np.sum(np.square(odom[:, :2] - odom[:, :2].mean(0)), axis=1))))
    limit = min(MAX_FIX_RESIDUAL_M, max(FIX_RESIDUAL_WARN_M, MAX_FIX_RESIDUAL_SHARE * spread))
    if residual > max(4.0 * swapped, FIX_RESIDUAL_WARN_M) or residual > limit:
        cause = (
            f'with its x and y swapped the track fits them to {swapped:.1f} m: the /odom '
            'positions look NED (x north, y east; REP 103 is ENU)'
            if 4.0 * swapped < residual
            else "the fixes are not this track's (another vehicle's or another time's), or the "
            'odometry is in another frame'
        )
        raise InputError(
            f'{source}: the {len(odom)} fixes miss the /odom track by {residual:.0f} m RMS '
            f'(GNSS: a few metres): {cause}'
        )
    vertical = float(np.mean(enu[:, 2] - odom[:, 2]))
    offset = (float(horizontal[0]), float(horizontal[1]), vertical)
    return Georeference(origin, yaw, offset, source, residual, len(odom), fixes.unlocked)


def _plane_fit(a: FloatArray, b: FloatArray) -> tuple[float, FloatArray, float]:
    """The rotation about up (yaw, rad) and translation (2,) m taking points ``a`` (N, 2)
    onto ``b`` (N, 2) in least squares (2D Kabsch), and the RMS misfit, m."""
    a_mean, b_mean = a.mean(axis=0), b.mean(axis=0)
    cross = (a - a_mean).T @ (b - b_mean)
    yaw = math.atan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
    rotation = Georeference((0.0, 0.0, 0.0), yaw).rotation[:2, :2]
    horizontal = b_mean - rotation @ a_mean
    misfit = b - (a @ rotation.T + horizontal)
    return yaw, horizontal, float(np.sqrt(np.mean(np.sum(misfit**2, axis=1))))
