"""io/geo.py: the odom -> geodetic transform against pyproj's ECEF and textbook ENU, the
NavSatFix fit against a known transform (with fix noise: its residual), and the reading of
a NavSatFix topic from a rosbag2 bag (NO_FIX skipped)."""
import math

import numpy as np
import pytest

from tetra_gradiometer.errors import BagError, InputError
from tetra_gradiometer.io.bag import BagWriter, typestore
from tetra_gradiometer.io.geo import (
    FIX_RESIDUAL_WARN_M,
    MAX_FIX_RESIDUAL_M,
    Fixes,
    Georeference,
    fit_fixes,
    parse_origin,
    read_fixes,
    utm_epsg,
)

pyproj = pytest.importorskip('pyproj')


def textbook_to_lonlat(origin, enu):
    """ENU at ``origin`` -> ECEF (rotation by hand) -> WGS 84 (pyproj's EPSG:4978 -> 4979)."""
    lat, lon = math.radians(origin[0]), math.radians(origin[1])
    rotation = np.array([
        [-math.sin(lon), -math.sin(lat) * math.cos(lon), math.cos(lat) * math.cos(lon)],
        [math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat) * math.sin(lon)],
        [0.0, math.cos(lat), math.sin(lat)],
    ])
    to_ecef = pyproj.Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    centre = np.array(to_ecef.transform(origin[1], origin[0], origin[2]))
    ecef = centre + enu @ rotation.T
    return np.column_stack(to_ecef.transform(*ecef.T, direction='INVERSE'))


def test_origin_places_odom_as_enu_there_exactly_and_back():
    origin = (-33.9, 151.3, 12.0)
    points = np.array([[0.0, 0.0, 0.0], [1500.0, -800.0, -60.0], [-20.0, 3000.0, 5.0]])
    georeference = Georeference(origin)
    lonlat = georeference.to_lonlat(points)
    expected = textbook_to_lonlat(origin, points)
    np.testing.assert_allclose(lonlat[:, :2], expected[:, :2], atol=1e-9)  # 0.1 mm
    np.testing.assert_allclose(lonlat[:, 2], expected[:, 2], atol=1e-4)
    np.testing.assert_allclose(georeference.from_lonlat(lonlat), points, atol=1e-6)
    assert georeference.default_crs() == 'EPSG:32756'  # Sydney: UTM 56 south


def test_utm_zone_is_pyprojs():
    for lat, lon in ((43.2, 5.3), (-10.0, -70.1), (60.0, 179.9), (0.1, -179.9)):
        info = pyproj.database.query_utm_crs_info(
            datum_name='WGS 84', area_of_interest=pyproj.aoi.AreaOfInterest(lon, lat, lon, lat))
        assert utm_epsg(lat, lon) in {f'EPSG:{i.code}' for i in info}


def test_the_fit_recovers_a_known_transform_and_reports_the_fix_noise():
    truth = Georeference((43.2, 5.3, 0.0), math.radians(23.0), (120.0, -45.0, 1.5))
    rng = np.random.default_rng(3)
    odom = np.column_stack([rng.uniform(-800, 800, 200), rng.uniform(-300, 300, 200), np.zeros(200)])
    enu_truth = truth.to_enu(odom) + np.column_stack([rng.normal(0, 0.5, (200, 2)), np.zeros(200)])
    noisy = truth.to_lonlat(truth.from_enu(enu_truth))
    fixes = Fixes(np.arange(200), noisy[:, 1], noisy[:, 0], noisy[:, 2])
    fitted = fit_fixes(fixes, odom, '/fix')
    assert math.degrees(abs(fitted.yaw_rad - truth.yaw_rad)) < 0.01
    assert fitted.residual_m == pytest.approx(0.5 * math.sqrt(2), rel=0.15)
    error = fitted.to_enu(odom) - Georeference(fitted.origin).from_lonlat(truth.to_lonlat(odom))
    # horizontally the fit's error (0.5 m noise, 200 fixes); vertically only the tilt between
    # two tangent planes 120 m apart (the fit's at the fixes' mean): 1e-5 rad over 800 m
    assert np.abs(error[:, :2]).max() < 0.3 and np.abs(error[:, 2]).max() < 0.03
    assert '200 fixes' in fitted.describe() and 'residual' in fitted.describe()


def test_the_fit_refuses_too_few_or_collocated_fixes():
    fixes = Fixes(np.arange(2), np.array([43.0, 43.0]), np.array([5.0, 5.0]), np.zeros(2))
    with pytest.raises(InputError, match='need 3'):
        fit_fixes(fixes, np.zeros((2, 3)), '/fix')
    fixes = Fixes(np.arange(3), np.full(3, 43.0), np.full(3, 5.0), np.zeros(3))
    with pytest.raises(InputError, match='within 1 m'):
        fit_fixes(fixes, np.zeros((3, 3)), '/fix')


@pytest.mark.parametrize('text, message', [('43', 'LAT,LON'), ('a,b', 'LAT,LON'), ('91,0', 'latitude'),
                                           ('0,181', 'longitude'), ('1,2,3,4', 'LAT,LON')])
def test_a_bad_origin_is_refused_naming_it(text, message):
    with pytest.raises(InputError, match=message):
        parse_origin(text)
    assert parse_origin('43.5,-5') == (43.5, -5.0, 0.0)


def test_navsatfix_topic_is_read_from_a_bag_without_the_no_fix_ones(tmp_path):
    store = typestore()
    NavSatFix = store.types['sensor_msgs/msg/NavSatFix']
    Status = store.types['sensor_msgs/msg/NavSatStatus']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    with BagWriter(tmp_path / 'bag', storage='mcap') as writer:
        for i in range(6):
            status = -1 if i == 2 else 0
            lat, lon = (0.0, 0.0) if i == 5 else (43.0 + i * 1e-4, 5.0)  # 5: a receiver's 0, 0
            msg = NavSatFix(
                header=Header(stamp=Time(sec=100 + i, nanosec=5), frame_id='gps'),
                status=Status(status=status, service=1), latitude=lat,
                longitude=lon, altitude=0.5, position_covariance=np.zeros(9),
                position_covariance_type=0)
            writer.write('/fix', msg, (100 + i) * 1_000_000_000)
    fixes = read_fixes(tmp_path / 'bag', '/fix')
    np.testing.assert_array_equal(fixes.stamps_ns, [(100 + i) * 1_000_000_000 + 5 for i in (0, 1, 3, 4)])
    np.testing.assert_allclose(fixes.lat_deg, [43.0, 43.0001, 43.0003, 43.0004])
    assert fixes.unlocked == 2
    with pytest.raises(BagError, match='no /gps'):
        read_fixes(tmp_path / 'bag', '/gps')



def _track_fixes(odom_enu, drift=None):
    """Fixes of the odom track (N, 3) placed by a known transform, plus ``drift`` (N, 2) m."""
    truth = Georeference((43.2, 5.3, 0.0), math.radians(-35.0), (60.0, 10.0, 0.0))
    enu = truth.to_enu(odom_enu)
    if drift is not None:
        enu[:, :2] += drift
    lonlat = truth.to_lonlat(truth.from_enu(enu))
    return Fixes(np.arange(len(odom_enu)), lonlat[:, 1], lonlat[:, 0], lonlat[:, 2], unlocked=3)


def _lawnmower(n=120):
    """Three 1 km legs 200 m apart, as a survey's fixes at the surface."""
    t = np.linspace(0.0, 1.0, n // 3)
    legs = [np.column_stack([1000 * (t if k % 2 == 0 else 1 - t), np.full(len(t), 200.0 * k)]) for k in range(3)]
    xy = np.vstack(legs)
    return np.column_stack([xy, np.zeros(len(xy))])


def test_fixes_that_miss_the_track_by_kilometres_are_refused_naming_the_cause():
    odom = _lawnmower()
    fixes = _track_fixes(odom)
    assert fit_fixes(fixes, odom, '/fix').residual_m < 0.01
    ned = odom[:, [1, 0, 2]] * [1, 1, -1]  # the same track published N, E, D
    with pytest.raises(InputError, match=r'miss the /odom track by \d+ m RMS.*look NED'):
        fit_fixes(fixes, ned, '/fix')
    foreign = odom[::-1] * [1.0, 3.0, 1.0]  # another vehicle's track
    with pytest.raises(InputError, match="not this track's"):
        fit_fixes(fixes, foreign, '/fix')


def test_fixes_that_drift_from_dead_reckoning_are_used_and_said_so():
    odom = _lawnmower()
    drift = np.column_stack([np.linspace(0, 150, len(odom)), np.zeros(len(odom))])  # 150 m over the dive
    fitted = fit_fixes(_track_fixes(odom, drift), odom, '/fix')
    assert FIX_RESIDUAL_WARN_M < fitted.residual_m < MAX_FIX_RESIDUAL_M
    line = fitted.describe()
    assert 'warning: the fixes follow the odometry to' in line and '3 unlocked fixes left out' in line
    assert 'warning' not in fit_fixes(_track_fixes(odom, drift / 10), odom, '/fix').describe()
