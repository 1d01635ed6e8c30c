"""The survey's ``report.html``: one self-contained page a client can be sent.

No script, no request: the maps are PNG images inlined as data URIs
(:mod:`.survey_maps`), the style is in the page. Sections, in order: what was surveyed
(date, vehicle, bag, placement, CRS, grid), a summary, the targets (latitude, longitude,
easting and northing, depth, moment, position 1-sigma), the maps, the survey's quality
checks (per-leg residual against the noise floor, lost and refused spans, health alarms,
sets dropped), the calibration (method, terms, trim checks) and how the page was made
(software version, command line, timings, the folder's files). Reported units: nT, nT/m,
m, A m², degrees.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import itertools
import platform
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from .._optional import require
from ..core.units import NT_PER_T
from ..io.calibration import CalibrationFile
from ..pipelines.survey import SurveyResult
from .survey_maps import MAP_QUANTITIES, overview_png, quantities_png

__all__ = ['TITLE', 'report_html']

TITLE = 'Magnetic gradient tensor survey'

STYLE = """
body { font: 14px/1.45 system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif;
       color: #1a1a1a; margin: 0; background: #f4f5f7; }
main { max-width: 1080px; margin: 0 auto; padding: 24px 32px 48px; background: white; }
h1 { font-size: 26px; margin: 0 0 2px; }
h2 { font-size: 19px; margin: 28px 0 8px; padding-bottom: 4px; border-bottom: 2px solid #1f4e79; }
.subtitle { color: #555; margin: 0 0 16px; }
table { border-collapse: collapse; margin: 6px 0 10px; }
th, td { border: 1px solid #d0d4da; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #eef1f5; font-weight: 600; }
td.n { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
table.facts th { width: 190px; }
.summary { display: flex; flex-wrap: wrap; gap: 10px; margin: 10px 0; }
.summary div { flex: 1 1 150px; border: 1px solid #d0d4da; border-radius: 4px; padding: 8px 12px; }
.summary b { display: block; font-size: 22px; }
.note { color: #555; font-size: 13px; }
img { max-width: 100%; height: auto; display: block; margin: 6px 0; }
code { font-size: 12.5px; background: #f2f2f2; padding: 1px 3px; word-break: break-all; }
@media print { body { background: white; } main { padding: 0; } h2 { break-after: avoid; } }
"""

#: The folder's files, one line each (the contract: :mod:`.survey`).
FOLDER = (
    ('survey.nc', 'every grid, its 1-sigma and the mask (CF-1.8 netCDF)'),
    ('geotiff/<quantity>.tif', 'one GeoTIFF per grid'),
    ('targets.csv', 'the targets, one row each (the table above)'),
    ('targets.geojson', 'the targets and their 3-sigma ellipses in WGS 84'),
    ('targets.json', 'the targets in the odometry frame'),
    ('track.geojson', 'the track in WGS 84'),
    ('survey.json', 'what was done, as data'),
)


def _e(value: Any) -> str:
    return html.escape(str(value))


def _table(header: Sequence[str], rows: Iterable[Sequence[Any]], numeric: int = 0) -> str:
    """An HTML table; columns from ``numeric`` on are right-aligned numbers."""
    head = ''.join(f'<th>{_e(h)}</th>' for h in header)
    body = ''.join(
        '<tr>'
        + ''.join(
            f'<td class="n">{_e(c)}</td>' if k >= numeric > 0 else f'<td>{_e(c)}</td>'
            for k, c in enumerate(row)
        )
        + '</tr>'
        for row in rows
    )
    return f'<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _facts(rows: Iterable[tuple[str, Any]]) -> str:
    body = ''.join(f'<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>' for k, v in rows)
    return f'<table class="facts">{body}</table>'


def _utc(stamp_s: float) -> str:
    return dt.datetime.fromtimestamp(stamp_s, dt.UTC).strftime('%Y-%m-%d %H:%M:%S UTC')


def _image(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode('ascii')
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{data}">'


def crs_name(crs: str) -> str:
    """``EPSG:32631 (WGS 84 / UTM zone 31N)``: the code and pyproj's name for it."""
    pyproj = require('pyproj', 'the survey report')
    return f'{crs} ({pyproj.CRS.from_user_input(crs).name})'


def _array_text(calibration: CalibrationFile | None) -> str:
    if calibration is None:
        return ''
    positions = np.reshape(calibration.sensor_positions, (-1, 3))
    baseline = max(np.linalg.norm(a - b) for a, b in itertools.combinations(positions, 2))
    return f'{len(positions)} three-axis magnetometers, longest baseline {baseline:.2f} m'


def _survey_facts(
    result: SurveyResult, metadata: Mapping[str, Any], calibration: CalibrationFile | None
) -> str:
    track, grids = result.track, result.grids
    duration = float(track.t_s[-1]) if len(track.t_s) else 0.0
    vehicle = metadata.get('vehicle') or 'not named (survey --vehicle NAME)'
    array = _array_text(calibration)
    spacing = grids.line_spacing_m
    return _facts(
        [
            ('Survey date', f'{_utc(result.t0_stamp_s)} to {_utc(result.t0_stamp_s + duration)}'),
            ('Vehicle', f'{vehicle}; {array}' if array else vehicle),
            (
                'Recording (bag)',
                f'{metadata.get("bag", "")}: {len(track.t_s)} tensor sets, {duration:.1f} s',
            ),
            ('Vehicle parameters', metadata.get('params', 'not given')),
            ('Calibration', metadata.get('calibration', 'not given')),
            ('Placement', result.georeference.describe()),
            (
                'Coordinates',
                f'{crs_name(result.crs)}; grid north '
                f'{result.georeference.convergence_deg(result.crs):+.3f}° from true north',
            ),
            (
                'Grid',
                f'{grids.cell_m:.2f} m cells, {int(grids.mask.sum())} of '
                f'{grids.mask.size} gridded (masked beyond {grids.max_distance_m:.1f} m of the '
                'track, never extrapolated); line spacing '
                + (f'{spacing:.1f} m' if np.isfinite(spacing) else 'none (one line)'),
            ),
        ]
    )


def _summary(result: SurveyResult) -> str:
    legs = result.leg_residuals
    worst = max((leg.residual_nT_per_m / leg.floor_nT_per_m for leg in legs), default=np.nan)
    lost = sum(s.stop_s - s.start_s for s in result.spans)
    boxes = [
        ('targets located', str(len(result.targets))),
        ('straight legs', str(len(legs))),
        ('worst leg residual', f'{worst:.2f} × floor' if np.isfinite(worst) else 'no leg'),
        ('lost or refused', f'{len(result.spans)} spans, {lost:.1f} s'),
        ('calibration health', str(result.health['verdict'])),
    ]
    cells = ''.join(f'<div><b>{_e(v)}</b>{_e(k)}</div>' for k, v in boxes)
    return f'<div class="summary">{cells}</div>'


def _targets(result: SurveyResult, records: list[dict[str, Any]]) -> str:
    if not records:
        return '<p>No target was located.</p>'
    positions = np.array([r['position_m'] for r in records])
    lonlat = result.georeference.to_lonlat(positions)
    xy = result.georeference.to_crs(positions, result.crs)
    rows = [
        (
            i,
            f'{lonlat[i, 1]:.7f}',
            f'{lonlat[i, 0]:.7f}',
            f'{xy[i, 0]:,.1f}',
            f'{xy[i, 1]:,.1f}',
            f'{-r["position_m"][2]:.2f}',
            ' / '.join(f'{s:.3f}' for s in r['position_sigma_m']),
            f'{np.linalg.norm(r["moment_Am2"]):,.0f}',
            ' / '.join(f'{m:,.0f}' for m in r['moment_Am2']),
            r['passes'],
            f'{r["fit_rms_nT_per_m"]:.3f}',
        )
        for i, r in enumerate(records)
    ]
    header = (
        'id',
        'latitude, °',
        'longitude, °',
        'easting, m',
        'northing, m',
        'depth, m',
        'position 1σ x / y / z, m',
        '|moment|, A m²',
        'moment x / y / z, A m²',
        'passes',
        'fit RMS, nT/m',
    )
    return _table(header, rows, numeric=1) + (
        '<p class="note">Latitude and longitude on WGS 84; easting and northing in '
        f"{_e(crs_name(result.crs))}; depth below the placement origin's height; x, y, z "
        "are the odometry frame's axes (east, north, up when the placement yaw is 0); "
        'each target is a magnetic dipole fitted to the compensated tensor along the track '
        f'(the same rows are in <code>targets.csv</code>).</p>'
    )


def _maps(result: SurveyResult, records: list[dict[str, Any]]) -> str:
    names = ', '.join(title for title, _ in MAP_QUANTITIES.values())
    return (
        '<h3>Track and gridded area</h3>'
        + _image(overview_png(result, records), 'the track, the gridded area and the targets')
        + '<h3>Gridded quantities</h3>'
        + _image(quantities_png(result, records), 'the gridded tensor and its invariants')
        + f'<p class="note">{_e(names)}; the tensor in the geodetic east, north, up frame, '
        f'gridded in {_e(crs_name(result.crs))} at true scale; blank cells are farther than '
        f'{result.grids.max_distance_m:.1f} m from the track. Magenta discs: the targets, '
        'with their 3-sigma horizontal ellipses. GeoTIFFs of every grid and its 1-sigma are '
        'in the folder.</p>'
    )


LEG_HEADER = (
    'leg',
    'from, s',
    'to, s',
    'residual, nT/m',
    'noise floor (1σ), nT/m',
    'residual / floor',
)
#: What the per-leg check measures, under its table.
LEG_NOTE = (
    'Residual: the RMS of the part of the compensated tensor that no magnetic field has (its '
    'trace and antisymmetric part); noise floor: the RMS of its 1-sigma from the sensor noise '
    "and the calibration's covariance. It rises above the floor where the gradient is strong "
    '(near a target) with no fault: the gradient changes across the array, and the '
    'differences of the four sensors read that as a non-field part. Times are seconds from '
    'the first tensor set.'
)


def _legs(result: SurveyResult) -> str:
    """The per-leg residual against the noise floor, nT/m."""
    rows = [
        (
            i,
            f'{leg.start_s:.1f}',
            f'{leg.stop_s:.1f}',
            f'{leg.residual_nT_per_m:.3f}',
            f'{leg.floor_nT_per_m:.3f}',
            f'{leg.residual_nT_per_m / leg.floor_nT_per_m:.2f}',
        )
        for i, leg in enumerate(result.leg_residuals)
    ]
    table = _table(LEG_HEADER, rows, numeric=1) if rows else '<p>No straight leg was found.</p>'
    return f'{table}<p class="note">{_e(LEG_NOTE)}</p>'


def _spans(result: SurveyResult) -> str:
    """The lost and refused spans, s."""
    rows = [
        (s.kind, f'{s.start_s:.1f}', f'{s.stop_s:.1f}', f'{s.stop_s - s.start_s:.1f}')
        for s in result.spans
    ]
    if not rows:
        return '<p>None: no gap of more than three sample periods, no set refused.</p>'
    return _table(('kind', 'from, s', 'to, s', 'length, s'), rows, numeric=1)


def _quality(result: SurveyResult) -> str:
    alarms = [(f'{a["t_s"]:.1f}', a['kind']) for a in result.health['alarms']]
    counts = [(k.replace('_', ' '), v) for k, v in result.input_counts.items()]
    return (
        f'<h3>Residual per straight leg</h3>{_legs(result)}'
        f'<h3>Lost and refused spans</h3>{_spans(result)}'
        f'<h3>Calibration health along the survey</h3><p>{_e(result.health["verdict"])}.</p>'
        + (_table(('at, s', 'alarm'), alarms) if alarms else '')
        + '<h3>Input</h3>'
        + _table(('sets or messages', 'count'), counts, numeric=1)
    )


def _calibration(calibration: CalibrationFile | None, metadata: Mapping[str, Any]) -> str:
    if calibration is None:
        return f'<p>{_e(metadata.get("calibration", "not given"))}</p>'
    d = calibration.diagnostics
    check = d.get('window_check') or {}
    noise = calibration.sensor_noise_t
    rows = [
        ('File', f'{metadata.get("calibration", "")} (made {calibration.created_utc})'),
        ('Method', calibration.method),
        (
            'Terms',
            ', '.join(t.effect for t in calibration.parameters.terms)
            or 'none (soft and hard iron only)',
        ),
        (
            'Trim recording',
            f'{d.get("bag", "not recorded")}, window {d.get("window_s", "?")}, '
            f'{d.get("n_samples", "?")} sets',
        ),
        (
            'Trim residual',
            check.get('text') or f'{d.get("residual_rms_nT_per_m", np.nan):.3f} nT/m',
        ),
        ('Sensor noise', f'{noise * NT_PER_T:.4f} nT per axis' if noise else 'not estimated'),
        ('Noise behind the 1-sigma', metadata.get('sensor_noise', 'not recorded')),
        (
            'Conditioning',
            f'condition number {d.get("condition_number", np.nan):.1f}; attitude '
            f'coverage {d.get("attitude_coverage_condition", np.nan):.1f}',
        ),
    ]
    predicted = (d.get('window_found') or {}).get('predicted_ratio')
    if predicted is not None:
        rows.append(('Predicted survey accuracy', f'{predicted:.3f} × the noise floor'))
    rows += [('Kept over a failed check', note) for note in calibration.forced_warnings()]
    return _facts(rows)


def _provenance(result: SurveyResult, metadata: Mapping[str, Any], version: str) -> str:
    timings = ', '.join(f'{k} {v:.1f} s' for k, v in result.timings_s.items())
    command = metadata.get('command', 'not recorded')
    facts = _facts(
        [
            (
                'Software',
                f'tetra_gradiometer {version}, Python {platform.python_version()}, '
                f'numpy {np.__version__}',
            ),
            ('Command', command),
            ('Report written', dt.datetime.now(dt.UTC).strftime('%Y-%m-%d %H:%M:%S UTC')),
            ('Timings', timings),
        ]
    )
    files = ''.join(f'<li><code>{_e(n)}</code>: {_e(t)}</li>' for n, t in FOLDER)
    return facts + f'<p>The folder beside this page holds:</p><ul>{files}</ul>'


def report_html(
    result: SurveyResult,
    records: list[dict[str, Any]],
    metadata: Mapping[str, Any],
    *,
    calibration: CalibrationFile | None = None,
    version: str = 'unknown',
) -> str:
    """The page (module docstring); ``records``: the targets as ``targets.json`` entries;
    ``metadata``: ``bag``, ``calibration``, ``params``, ``vehicle``, ``command`` (any may
    be missing); ``calibration``: the loaded calibration file, for its checks."""
    bag = str(metadata.get('bag', ''))
    sections = [
        f'<h1>{TITLE}</h1><p class="subtitle">{_e(bag)}, {_utc(result.t0_stamp_s)[:10]}</p>',
        _survey_facts(result, metadata, calibration),
        _summary(result),
        '<h2>Targets</h2>' + _targets(result, records),
        '<h2>Maps</h2>' + _maps(result, records),
        '<h2>Survey quality</h2>' + _quality(result),
        '<h2>Calibration</h2>' + _calibration(calibration, metadata),
        '<h2>How this report was made</h2>' + _provenance(result, metadata, version),
    ]
    return (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f'<title>{TITLE}: {_e(bag)}</title><style>{STYLE}</style></head>'
        f'<body><main>{"".join(sections)}</main></body></html>\n'
    )
