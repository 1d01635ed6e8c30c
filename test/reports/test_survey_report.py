"""The survey's report.html from the shipped sample bags (calibrate on bags/trim, survey
bags/survey placed at 43.2 N, 5.3 E), read as a client's browser shows it: headless
Chromium's rendered text holds the title, the vehicle, the bag, the calibration, the CRS
and a target row at the scenario's dipole (bags/survey.yaml) placed on WGS 84 and UTM by
pyproj's own transforms; its screenshot is a page with the maps and the target markers
drawn, which an empty page and a page with broken images are not."""
import re
import shutil
import subprocess
from datetime import UTC, datetime
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import yaml

from tetra_gradiometer.__main__ import main

REPO = Path(__file__).resolve().parents[2]
ORIGIN = (43.2, 5.3, 0.0)
VEHICLE = 'AUV Sample-1'
MAGENTA = (255, 0, 255)  # the targets' colour (reports/survey_maps.TARGET_COLOUR)

CHROMIUM_FLAGS = ('--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking',
                  '--disable-component-update', '--disable-sync', '--no-first-run',
                  '--enable-logging=stderr', '--v=0', '--hide-scrollbars')


def chromium(tmp, page, *args):
    """Headless Chromium (Debian's package, installed by `make setup`) on a file, in a new
    profile; its stderr carries the page's console messages as 'CONSOLE' lines."""
    binary = shutil.which('chromium') or shutil.which('chromium-browser')
    assert binary, 'headless Chromium is missing: `make setup` installs it (apt-get install chromium)'
    profile = tmp / f'profile-{len(list(tmp.glob("profile-*")))}'
    return subprocess.run([binary, *CHROMIUM_FLAGS, f'--user-data-dir={profile}', *args, page.as_uri()],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope='module')
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('report')
    params = REPO / 'config' / 'tetra_gradiometer.yaml'
    assert main(['calibrate', str(REPO / 'bags' / 'trim'), '--params', str(params),
                 '--out', str(tmp / 'cal.yaml')]) == 0
    assert main(['survey', str(REPO / 'bags' / 'survey'), '--params', str(params),
                 '--calibration', str(tmp / 'cal.yaml'), '--origin', ','.join(map(str, ORIGIN)),
                 '--vehicle', VEHICLE, '--out', str(tmp / 'survey')]) == 0
    return tmp / 'survey' / 'report.html'


class _Page(HTMLParser):
    """The rendered DOM's text and its tables' rows (cell texts)."""

    def __init__(self):
        super().__init__()
        self.text, self.rows, self._cell = [], [], None

    def handle_starttag(self, tag, attrs):
        if tag == 'tr':
            self.rows.append([])
        elif tag in ('td', 'th'):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ('td', 'th') and self._cell is not None:
            self.rows[-1].append(''.join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)


def _truth():
    """The scenario's dipole: latitude, longitude, easting, northing (EPSG:32631), depth
    and |moment|, placed by pyproj (the odom frame is ENU at ORIGIN)."""
    pyproj = pytest.importorskip('pyproj')
    dipole = yaml.safe_load((REPO / 'bags' / 'survey.yaml').read_text())['dipoles'][0]
    to_geodetic = pyproj.Transformer.from_pipeline(
        f'+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 +lat_0={ORIGIN[0]} '
        f'+lon_0={ORIGIN[1]} +h_0={ORIGIN[2]} +step +inv +proj=cart +ellps=WGS84')
    lon, lat, _ = to_geodetic.transform(*dipole['position_m'])
    east, north = pyproj.Transformer.from_crs('EPSG:4326', 'EPSG:32631', always_xy=True).transform(lon, lat)
    return lat, lon, east, north, -dipole['position_m'][2], np.linalg.norm(dipole['moment_Am2'])


def _number(cell):
    return float(cell.replace(',', ''))


def test_the_page_is_one_self_contained_file_without_script(report):
    html = report.read_text()
    assert '<script' not in html
    references = re.findall(r'\b(?:src|href)\s*=\s*"([^"]*)"', html)
    assert references and all(r.startswith('data:image/png;base64,') for r in references), references
    assert 100_000 < len(html.encode()) < 1_500_000  # two inlined maps, no library


def test_the_rendered_page_states_the_survey_the_crs_and_the_target_at_the_truth(report, tmp_path):
    # the console detector works: a page with an error shows it
    bad = tmp_path / 'bad.html'
    bad.write_text('<html><body><script>console.error("boom"); missing();</script></body></html>')
    assert 'CONSOLE' in chromium(tmp_path, bad, '--dump-dom').stderr
    dom = chromium(tmp_path, report, '--dump-dom')
    assert not [line for line in dom.stderr.splitlines() if 'CONSOLE' in line]
    page = _Page()
    page.feed(dom.stdout)
    text = ' '.join(' '.join(page.text).split())
    start_ns = yaml.safe_load((REPO / 'bags' / 'survey' / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['starting_time']['nanoseconds_since_epoch']
    started = datetime.fromtimestamp(start_ns / 1e9, UTC).strftime('%Y-%m-%d %H:%M')
    for expected in ('Magnetic gradient tensor survey', VEHICLE, 'bags/trim', f'bags/survey, {started[:10]}',
                     f'{started}:', 'known_gradient_lstsq_general', 'EPSG:32631 (WGS 84 / UTM zone 31N)',
                     f'python -m tetra_gradiometer survey {REPO / "bags" / "survey"}'):
        assert expected in text, expected
    header = next(row for row in page.rows if row and row[0] == 'id')
    targets = [row for row in page.rows if len(row) == len(header) and row[0].isdigit()]
    assert len(targets) == 1, targets
    row = dict(zip(header, targets[0], strict=True))
    lat, lon, east, north, depth, moment = _truth()
    assert abs(_number(row['latitude, °']) - lat) < 3e-7  # 3 cm
    assert abs(_number(row['longitude, °']) - lon) < 4e-7
    assert abs(_number(row['easting, m']) - east) < 0.1
    assert abs(_number(row['northing, m']) - north) < 0.1
    assert abs(_number(row['depth, m']) - depth) < 0.02
    assert abs(_number(row['|moment|, A m²']) / moment - 1) < 1e-3
    sigmas = [_number(v) for v in row['position 1σ x / y / z, m'].split('/')]
    assert len(sigmas) == 3 and all(0 < s < 0.05 for s in sigmas)


def _screenshot(tmp, page):
    """The page rendered 1200 px wide and tall enough for the maps, as an (H, W, 3) array."""
    from PIL import Image

    shot = tmp / f'{page.stem}.png'
    chromium(tmp, page, '--window-size=1200,4200', f'--screenshot={shot}')
    return np.asarray(Image.open(shot).convert('RGB')).astype(int)


def _drawn(pixels):
    """(share of the page that is not background, target-coloured pixels)."""
    background = np.median(pixels.reshape(-1, 3), axis=0)
    inked = np.abs(pixels - background).max(axis=2) > 40
    magenta = np.abs(pixels - MAGENTA).max(axis=2) <= 30
    return inked.mean(), int(magenta.sum())


@pytest.mark.slow
def test_the_screenshot_is_a_page_with_its_maps_and_targets_drawn(report, tmp_path):
    inked, targets = _drawn(_screenshot(tmp_path, report))
    # text, tables and two maps: the target disc on the overview and on the nine panels
    assert inked > 0.03, inked
    assert targets > 10 * 40, targets
    # the checks fail on an empty page and on the same page with its images broken
    empty = tmp_path / 'empty.html'
    empty.write_text('<!DOCTYPE html><html><body></body></html>')
    assert _drawn(_screenshot(tmp_path, empty))[0] < 0.001
    broken = tmp_path / 'broken.html'
    broken.write_text(re.sub(r'base64,[^"]{200}', 'base64,AAAA', report.read_text()))
    assert _drawn(_screenshot(tmp_path, broken))[1] == 0
