"""cli/survey.py end to end: simulate (trim, then three lines over two dipoles, noise,
interference) -> calibrate on the trim -> survey --origin. Checked against the simulator's
truth and independent libraries: the gridded world-frame tensor against the same grid of
the true tensor (within 3 sigma in >= 95 % of cells), the mask against scipy's KD-tree,
the GeoJSON targets against targets.json through pyproj's ECEF (and back, 1 mm), the
netCDF against the IOOS compliance checker (CF-1.8), the GeoTIFFs through rasterio
(report.html in a browser: test/reports/test_survey_report.py)."""
import json
import shutil
import subprocess

import numpy as np
import pytest
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core.targets import DetectorSettings, legs
from tetra_gradiometer.io.recording import read_recording
from tetra_gradiometer.io.targets import read_targets
from tetra_gradiometer.pipelines.survey_grid import COMPONENTS, GridSettings, grid_track

from .test_compensate import cli

ORIGIN = (43.2, 5.3, 0.0)  # off Marseille: UTM zone 31N
TRUTH = [
    {'position_m': [-40.0, -6.0, -45.0], 'moment_Am2': [15000.0, 5000.0, -8000.0]},
    {'position_m': [35.0, 9.0, -44.0], 'moment_Am2': [-20000.0, 30000.0, -25000.0]},
]


def survey_mission() -> dict:
    lines = []
    for i, y in enumerate((-16.0, 0.0, 16.0)):
        a, b = (-120.0, 120.0) if i % 2 == 0 else (120.0, -120.0)
        lines.append({'line': {'start_m': [a, y, -25.0], 'end_m': [b, y, -25.0], 'speed_m_s': 2.0}})
    return {
        'seed': 11, 'sample_rate_hz': 10, 'noise_nT': 0.05, 'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]}, 'dipoles': TRUTH,
        'interference': {'random': {'k_scale': 0.005, 'b_scale_nT': 150, 'reference_clean': False}},
        'segments': [{'trim': {'duration_s': 120, 'center_m': [400.0, 400.0, -25.0]}}, *lines],
    }


@pytest.fixture(scope='module')
def surveyed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('survey')
    (tmp / 'mission.yaml').write_text(yaml.safe_dump(survey_mission()))
    cli('simulate', '--scenario', tmp / 'mission.yaml', '--out', tmp / 'mission')
    params = tmp / 'mission.params.yaml'
    cli('calibrate', tmp / 'mission', '--params', params, '--window', '0:119.95', '--out', tmp / 'calib.yaml')
    out = cli('survey', tmp / 'mission', '--params', params, '--calibration', tmp / 'calib.yaml',
              '--out', tmp / 'survey', '--origin', ','.join(map(str, ORIGIN)))
    return tmp, out


@pytest.fixture(scope='module')
def grids(surveyed):
    xr = pytest.importorskip('xarray')
    tmp, _ = surveyed
    with xr.open_dataset(tmp / 'survey' / 'survey.nc', engine='h5netcdf') as ds:
        return ds.load()


def _gridded_truth(tmp):
    """The gridded samples (the straight legs') placed in UTM 31N with pyproj's own
    topocentric inverse (the odom frame is ENU at ORIGIN), and the simulator's true eq. 7
    tensor there (body) rotated to ENU with the recorded attitude."""
    pyproj = pytest.importorskip('pyproj')
    recording = read_recording(tmp / 'mission')
    truth = np.load(tmp / 'mission.truth.npz')
    index = np.searchsorted(truth['stamps_ns'], recording.stamps_ns)
    assert np.array_equal(truth['stamps_ns'][index], recording.stamps_ns)
    rotations = Rotation.from_quat(recording.orientation_xyzw).as_matrix()
    world = np.einsum('nij,njk,nlk->nil', rotations, truth['g_true'][index], rotations)
    track_legs = legs(recording.t_s, recording.position_m, rotations, DetectorSettings())
    assert len(track_legs) == 3
    on_legs = np.concatenate([np.arange(a, b) for a, b in track_legs])
    to_geodetic = pyproj.Transformer.from_pipeline(
        f'+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={ORIGIN[0]} '
        f'+lon_0={ORIGIN[1]} +h_0={ORIGIN[2]} +step +inv +proj=cart +ellps=WGS84')
    lon, lat, _ = to_geodetic.transform(*recording.position_m[on_legs].T)
    x, y = pyproj.Transformer.from_crs('EPSG:4326', 'EPSG:32631', always_xy=True).transform(lon, lat)
    return np.column_stack([x, y]), world[on_legs]


def test_gridded_components_match_the_grid_of_the_true_tensor_within_3_sigma(surveyed, grids):
    tmp, _ = surveyed
    xy, world = _gridded_truth(tmp)
    zeros = np.zeros_like(world)
    settings = GridSettings(grids.attrs['cell_m'], grids.attrs['max_distance_m'])
    truth = grid_track(xy, world, zeros, zeros, legs=[], array_size_m=0.8, settings=settings)
    np.testing.assert_allclose(truth.x, grids.x, atol=1e-6)
    np.testing.assert_allclose(truth.y, grids.y, atol=1e-6)
    gridded = grids['mask'].values == 1
    assert gridded.sum() > 500
    for name in COMPONENTS:
        measured = grids[name].values[gridded]  # nT/m
        sigma = grids[f'{name}_sigma'].values[gridded]
        expected = truth.values[name][gridded] * 1e9
        assert np.all(np.isfinite(measured)) and np.all(sigma > 0)
        within = np.abs(measured - expected) <= 3 * sigma
        assert within.mean() >= 0.95, (name, within.mean())
        # and the sigma is not inflated: the normalized errors spread like a unit normal
        assert 0.5 < np.std((measured - expected) / sigma) < 1.5, name
    # the anomaly is there: the true grid spans far more than the sigma
    assert np.nanmax(np.abs(truth.values['gzz'])) * 1e9 > 100 * np.nanmedian(grids['gzz_sigma'].values)


def test_cells_far_from_every_sample_are_masked_never_extrapolated(surveyed, grids):
    tmp, _ = surveyed
    track = json.loads((tmp / 'survey' / 'track.geojson').read_text())
    assert track['type'] == 'FeatureCollection' and track['features']
    assert all(f['geometry']['type'] == 'LineString' for f in track['features'])
    xy, _ = _gridded_truth(tmp)
    gx, gy = np.meshgrid(grids.x.values, grids.y.values)
    distance, _ = cKDTree(xy).query(np.column_stack([gx.ravel(), gy.ravel()]))
    near = (distance <= grids.attrs['max_distance_m']).reshape(gx.shape)
    np.testing.assert_array_equal(grids['mask'].values == 1, near)
    assert np.all(np.isnan(grids['gzz'].values[~near])) and np.all(np.isfinite(grids['gzz'].values[near]))
    assert near.sum() > 500
    # a mask distance under half the line spacing (16 m): the cells between lines go
    _, world = _gridded_truth(tmp)
    zeros = np.zeros_like(world)
    tight = grid_track(xy, world, zeros, zeros, legs=[], array_size_m=0.8,
                       settings=GridSettings(grids.attrs['cell_m'], 5.0))
    gx, gy = np.meshgrid(tight.x, tight.y)
    distance, _ = cKDTree(xy).query(np.column_stack([gx.ravel(), gy.ravel()]))
    near = (distance <= 5.0).reshape(gx.shape)
    np.testing.assert_array_equal(tight.mask, near)
    assert 0.2 < near.mean() < 0.9
    assert np.all(np.isnan(tight.values['gzz'][~near])) and np.all(np.isnan(tight.sigmas['nss'][~near]))


def _ecef_enu(origin):
    """The ENU -> ECEF rotation at ``origin`` (textbook) and the origin in ECEF (pyproj)."""
    pyproj = pytest.importorskip('pyproj')
    lat, lon = np.radians(origin[0]), np.radians(origin[1])
    rotation = np.array([
        [-np.sin(lon), -np.sin(lat) * np.cos(lon), np.cos(lat) * np.cos(lon)],
        [np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat) * np.sin(lon)],
        [0.0, np.cos(lat), np.sin(lat)],
    ])
    to_ecef = pyproj.Transformer.from_crs('EPSG:4979', 'EPSG:4978', always_xy=True)
    centre = np.array(to_ecef.transform(origin[1], origin[0], origin[2]))
    return rotation, centre, to_ecef


def test_targets_geojson_is_targets_json_through_pyproj_and_back_within_1_mm(surveyed):
    tmp, _ = surveyed
    document = read_targets(tmp / 'survey' / 'targets.json')
    assert len(document['targets']) == len(TRUTH)
    geojson = json.loads((tmp / 'survey' / 'targets.geojson').read_text())
    assert geojson['type'] == 'FeatureCollection'
    points = [f for f in geojson['features'] if f['geometry']['type'] == 'Point']
    ellipses = [f for f in geojson['features'] if f['geometry']['type'] == 'Polygon']
    assert len(points) == len(ellipses) == len(TRUTH)
    rotation, centre, to_ecef = _ecef_enu(ORIGIN)
    for target, feature in zip(document['targets'], points, strict=True):
        properties = feature['properties']
        for key in ('depth_m', 'moment_Am2', 'position_sigma_m', 'passes'):
            assert key in properties
        assert properties['depth_m'] == pytest.approx(-target['position_m'][2])
        assert properties['moment_Am2'] == target['moment_Am2']
        lon, lat, h = feature['geometry']['coordinates']
        # forward: targets.json's odom (ENU at ORIGIN) -> ECEF -> WGS 84, all by pyproj
        ecef = centre + rotation @ np.array(target['position_m'])
        expected = to_ecef.transform(*ecef, direction='INVERSE')
        back = rotation.T @ (np.array(to_ecef.transform(lon, lat, h)) - centre)
        np.testing.assert_allclose(back, target['position_m'], atol=1e-3)  # back: 1 mm
        metres_per_degree = 111_320.0
        assert abs(lat - expected[1]) * metres_per_degree < 1e-3
        assert abs(lon - expected[0]) * metres_per_degree * np.cos(np.radians(lat)) < 1e-3
        assert abs(h - expected[2]) < 1e-3
    # the ellipse rings are closed and lie around their target (3 sigma < 1 m here)
    for ellipse, point in zip(ellipses, points, strict=True):
        ring = np.array(ellipse['geometry']['coordinates'][0])
        assert np.array_equal(ring[0], ring[-1])
        assert np.abs(ring - point['geometry']['coordinates'][:2]).max() < 1e-4
    rows = (tmp / 'survey' / 'targets.csv').read_text().splitlines()
    assert rows[0].startswith('id,lon_deg,lat_deg') and len(rows) == 1 + len(TRUTH)


def test_netcdf_passes_the_cf_checker_and_holds_the_contract(surveyed, grids):
    tmp, _ = surveyed
    checker = shutil.which('compliance-checker') or str(
        __import__('pathlib').Path(__import__('sys').executable).with_name('compliance-checker'))
    report = tmp / 'cf.json'
    subprocess.run([checker, '--test', 'cf:1.8', '--format', 'json', '--output', str(report),
                    str(tmp / 'survey' / 'survey.nc')], capture_output=True, text=True, timeout=120)
    result = json.loads(report.read_text())['cf:1.8']
    messages = [m for key in ('high_priorities', 'medium_priorities') for m in result[key] for m in m['msgs']]
    assert result['high_count'] == 0 and result['medium_count'] == 0, messages
    assert grids['gzz'].dims == ('y', 'x')
    for name in (*COMPONENTS, 'i0', 'i1', 'i2', 'nss'):
        assert grids[name].attrs['units'] and grids[f'{name}_sigma'].attrs['units'] == grids[name].attrs['units']
        # xarray moves grid_mapping into .encoding when it decodes the file
        mapping = grids[name].encoding.get('grid_mapping', grids[name].attrs.get('grid_mapping'))
        assert mapping == 'spatial_ref'
    assert grids['gzz'].attrs['units'] == 'nT m-1'
    pyproj = pytest.importorskip('pyproj')
    assert pyproj.CRS.from_wkt(grids['spatial_ref'].attrs['crs_wkt']).to_epsg() == 32631
    assert grids.attrs['Conventions'] == 'CF-1.8' and 'calibration' in grids.attrs


def test_geotiffs_open_in_place_with_the_crs_and_the_grid(surveyed, grids):
    rasterio = pytest.importorskip('rasterio')
    tmp, _ = surveyed
    folder = tmp / 'survey' / 'geotiff'
    names = {p.stem for p in folder.glob('*.tif')}
    assert {'gzz', 'gzz_sigma', 'nss', 'i1', 'mask'} <= names
    with rasterio.open(folder / 'gzz.tif') as tif:
        assert tif.crs.to_epsg() == 32631
        band = tif.read(1)
        cell = grids.attrs['cell_m']
        assert tif.transform.a == pytest.approx(cell) and tif.transform.e == pytest.approx(-cell)
        assert tif.transform.c == pytest.approx(float(grids.x[0]) - cell / 2)
        assert tif.transform.f == pytest.approx(float(grids.y[-1]) + cell / 2)
    np.testing.assert_array_equal(np.isnan(band), np.isnan(grids['gzz'].values[::-1]))
    np.testing.assert_allclose(band, grids['gzz'].values[::-1], equal_nan=True)


def test_a_survey_needs_a_placement_and_never_replaces_a_foreign_folder(surveyed):
    tmp, _ = surveyed
    params = tmp / 'mission.params.yaml'
    args = ('survey', tmp / 'mission', '--params', params, '--calibration', tmp / 'calib.yaml')
    result = cli(*args, '--out', tmp / 'other', check=False)
    assert result.returncode == 2 and '--origin' in result.stderr
    foreign = tmp / 'foreign'
    foreign.mkdir()
    (foreign / 'notes.txt').write_text('mine')
    result = cli(*args, '--out', foreign, '--origin', '43,5', check=False)
    assert result.returncode == 1 and result.stderr.startswith('error:') and 'Traceback' not in result.stderr
    assert (foreign / 'notes.txt').read_text() == 'mine'
    result = cli(*args, '--out', tmp / 'x', '--origin', '95,5', check=False)
    assert result.returncode == 2 and 'latitude' in result.stderr


def test_the_command_reports_the_placement_the_grid_and_the_legs(surveyed):
    _, out = surveyed
    assert 'odom placed by --origin at 43.2000000, 5.3000000' in out.stdout
    assert 'EPSG:32631' in out.stdout and '2 targets' in out.stdout
    assert out.stdout.count('leg ') == 3
    for stage in ('reading the bag', 'gridding', 'locating targets', 'writing the products'):
        assert stage in out.stderr


@pytest.mark.slow
def test_batch_writes_the_same_survey_products_per_bag_when_asked(surveyed, tmp_path, monkeypatch):
    from tetra_gradiometer.cli import fleet
    from tetra_gradiometer.cli.fleet import FleetBag, make_job, process_bag

    # the discrepancy step takes minutes on this bag and is test_batch's; the survey's here
    monkeypatch.setattr(fleet, '_discrepancy', lambda *args: None)
    tmp, _ = surveyed
    bag = FleetBag('mission', tmp / 'mission', tmp / 'mission.params.yaml')
    job = make_job(bag, tmp_path / 'batch', (0.0, 119.95), plots=False, survey=(ORIGIN, None))
    assert job.fingerprint['survey'] == [list(ORIGIN), None]
    row = process_bag(job)
    assert row['status'] == 'ok', row
    folder = tmp_path / 'batch' / 'mission' / 'survey'
    for name in ('survey.nc', 'targets.geojson', 'track.geojson', 'report.html', 'geotiff/gzz.tif'):
        assert (folder / name).is_file(), name
    ours = json.loads((folder / 'targets.geojson').read_text())['features']
    command = json.loads((tmp / 'survey' / 'targets.geojson').read_text())['features']
    assert [f['geometry'] for f in ours] == [f['geometry'] for f in command]


@pytest.mark.slow
def test_an_origin_given_as_lon_lat_is_refused_by_the_earth_field(surveyed, capsys):
    """IGRF at the place given against the params file's Earth field (that of Marseille to
    6 uT): LON,LAT is named and refused before any work; a place on another continent is a
    warning naming both inputs."""
    from tetra_gradiometer.__main__ import main

    tmp, _ = surveyed
    params = tmp / 'mission.params.yaml'
    common = ['survey', str(tmp / 'mission'), '--params', str(params), '--calibration', str(tmp / 'calib.yaml')]
    assert main([*common, '--out', str(tmp / 'swapped'), '--origin', '5.3,43.2']) == 1
    err = capsys.readouterr().err
    assert err.startswith('error: --origin 5.3,43.2 looks given as LON,LAT') and 'give LAT,LON' in err
    assert not (tmp / 'swapped').exists()
    assert main([*common, '--out', str(tmp / 'cape'), '--origin=-33.9,18.4']) == 0
    err = capsys.readouterr().err
    assert 'warning: the IGRF field at --origin -33.9,18.4 differs from' in err
