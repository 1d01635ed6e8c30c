"""The ``survey`` output folder (written as one atomic folder) and its ``report.html``.

Files (the contract; formats in :mod:`~tetra_gradiometer.io.survey_files`)::

    survey.nc           every grid, its 1-sigma and the mask (CF-1.8)
    geotiff/<var>.tif   one GeoTIFF per grid
    targets.json        the targets in the odom frame (the contract of ``locate``)
    targets.geojson     the targets in WGS 84 (points, 3-sigma ellipses)
    targets.csv         the same, one row per target
    track.geojson       the track
    report.html         the interactive report (self-contained: plotly's JS inlined, no
                        tile server, no network)
    survey.json         what was done: georeference, CRS, cell, mask distance, timings,
                        health alarms, lost and refused spans, per-leg residuals

``report.html`` shows the track over the gridded maps (a selector picks the quantity),
the targets with their 3-sigma ellipses and tooltips (position, depth, moment, sigma,
passes), the health alarms and the lost or refused spans along the track, and the per-leg
residual of the non-field part against its noise floor.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterable, Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from .._optional import require
from ..io import survey_files as files
from ..io.outputs import SURVEY, atomic_output
from ..io.targets import dumps, target_record, targets_document
from ..pipelines.survey import SurveyResult
from ..pipelines.survey_grid import COMPONENTS, DERIVED

__all__ = ['TARGET_COLOUR', 'report_html', 'write_survey']

#: The package's version for the files' metadata (the package is loaded: this module is in
#: it; read from there rather than imported upwards).
__version__ = str(getattr(sys.modules[__name__.split('.')[0]], '__version__', 'unknown'))

#: The targets' marker colour in report.html (no colour scale of the maps contains it).
TARGET_COLOUR = '#ff00ff'
#: Heatmaps in the report are thinned to at most this many cells a side (the files keep all).
REPORT_CELLS = 300
#: Track points drawn in the report, at most.
REPORT_TRACK_POINTS = 4000
SPAN_COLOURS = {'lost': '#ff8c00', 'refused': '#d62728'}


def write_survey(
    result: SurveyResult,
    out: str | os.PathLike[str],
    *,
    metadata: Mapping[str, Any],
    force: bool = False,
    inputs: Iterable[str | os.PathLike[str]] = (),
) -> Path:
    """Write the folder ``out`` (module docstring) atomically; ``metadata``: the global
    attributes of ``survey.nc`` beside those of the result (calibration, effects...)."""
    records = [target_record(t) for t in result.targets]
    lonlat = (
        result.georeference.to_lonlat(np.array([r['position_m'] for r in records]))
        if records
        else np.zeros((0, 3))
    )
    covariances = [t.fit.covariance[:2, :2] for t in result.targets]
    with atomic_output(out, SURVEY, force=force, inputs=inputs, command='survey') as tmp:
        tmp.mkdir()
        ds = files.dataset(result.grids, result.crs, _attributes(result, metadata))
        files.write_netcdf(ds, tmp / 'survey.nc')
        files.write_geotiffs(ds, tmp / 'geotiff')
        document = targets_document(
            result.targets,
            tensor='compensated',
            t0_stamp_s=result.t0_stamp_s,
            false_alarms_per_hour=result.false_alarms_per_hour,
            detections=result.detections,
        )
        (tmp / 'targets.json').write_text(dumps(document), encoding='utf-8')
        geojson = files.targets_geojson(records, covariances, result.georeference)
        (tmp / 'targets.geojson').write_text(files.dumps(geojson), encoding='utf-8')
        (tmp / 'targets.csv').write_text(files.targets_csv(records, lonlat), encoding='utf-8')
        track = files.track_geojson(result.track.t_s, result.track.lonlat, result.track.legs)
        (tmp / 'track.geojson').write_text(files.dumps(track), encoding='utf-8')
        (tmp / 'survey.json').write_text(
            json.dumps(summary(result, metadata), indent=1) + '\n', encoding='utf-8'
        )
        (tmp / 'report.html').write_text(report_html(result, records), encoding='utf-8')
    return Path(out)


def _attributes(result: SurveyResult, metadata: Mapping[str, Any]) -> dict[str, Any]:
    grids = result.grids
    return {
        'Conventions': 'CF-1.8',
        'title': 'Magnetic gradient tensor survey grids (world frame E, N, U)',
        'institution': 'tetra_gradiometer',
        'source': f'tetra_gradiometer {__version__} survey',
        'history': f'tetra_gradiometer {__version__} survey',
        'references': (
            'Yu et al. 2014; Pedersen & Rasmussen 1990 (invariants); Beiki et al. 2012 (nss)'
        ),
        'comment': (
            'tensor components in the geodetic ENU frame (true north) at the georeference '
            f'tangent point; grid axes in {result.crs} (meridian convergence '
            f'{result.georeference.convergence_deg(result.crs):.4f} deg); blocks of '
            f'cell_m averaged, then the mean of the {grids.neighbours} nearest blocks (verde)'
        ),
        'crs': result.crs,
        'georeference': result.georeference.describe(),
        'cell_m': grids.cell_m,
        'max_distance_m': grids.max_distance_m,
        'line_spacing_m': grids.line_spacing_m if np.isfinite(grids.line_spacing_m) else -1.0,
        'software_version': __version__,
        **{k: str(v) for k, v in metadata.items()},
    }


def summary(result: SurveyResult, metadata: Mapping[str, Any]) -> dict[str, Any]:
    """``survey.json``: what was done and found (module docstring)."""
    geo = result.georeference
    return {
        'crs': result.crs,
        'georeference': {
            'origin_lat_lon_h': list(geo.origin),
            'yaw_deg': float(np.degrees(geo.yaw_rad)),
            'offset_m': list(geo.offset_m),
            'source': geo.source,
            'residual_m': geo.residual_m if np.isfinite(geo.residual_m) else None,
            'fixes': geo.n_fixes,
        },
        'grid': {
            'cell_m': result.grids.cell_m,
            'max_distance_m': result.grids.max_distance_m,
            'neighbours': result.grids.neighbours,
            'blocks': result.grids.blocks,
            'cells': int(result.grids.mask.size),
            'cells_gridded': int(result.grids.mask.sum()),
        },
        'targets': len(result.targets),
        'alarms': result.health['alarms'],
        'health_verdict': result.health['verdict'],
        'spans': [asdict(s) for s in result.spans],
        'legs': [asdict(leg) for leg in result.leg_residuals],
        'input_counts': result.input_counts,
        'timings_s': result.timings_s,
        **{k: str(v) for k, v in metadata.items()},
    }


def _thinned(values: np.ndarray, step: int) -> list[Any]:
    """A 2D grid every ``step`` cells, NaN as None (JSON null: a gap in the heatmap)."""
    part = values[::step, ::step] * 1.0
    return [[None if not np.isfinite(v) else round(float(v), 6) for v in row] for row in part]


def _gridded_box(result: SurveyResult) -> tuple[slice, slice]:
    """Rows and columns of the grid that hold gridded cells (the report's view)."""
    rows = np.flatnonzero(result.grids.mask.any(axis=1))
    columns = np.flatnonzero(result.grids.mask.any(axis=0))
    if not len(rows):
        return slice(None), slice(None)
    return slice(rows[0], rows[-1] + 1), slice(columns[0], columns[-1] + 1)


def _map_traces(result: SurveyResult) -> list[dict[str, Any]]:
    """One heatmap per quantity (the first visible) over the gridded cells, file units."""
    grids = result.grids
    rows, columns = _gridded_box(result)
    shape = grids.mask[rows, columns].shape
    step = max(1, int(np.ceil(max(shape) / REPORT_CELLS)))
    traces = []
    for n, name in enumerate(('nss', *COMPONENTS, *DERIVED[:3])):
        unit, factor = files.UNITS[name]
        traces.append(
            {
                'type': 'heatmap',
                'x': grids.x[columns][::step].tolist(),
                'y': grids.y[rows][::step].tolist(),
                'z': _thinned(grids.values[name][rows, columns] * factor, step),
                'colorscale': 'Viridis' if name == 'nss' else 'RdBu',
                'reversescale': name != 'nss',
                'zmid': None if name == 'nss' else 0.0,
                'colorbar': {'title': {'text': unit}, 'x': 0.62},
                'name': name,
                'visible': n == 0,
                'hovertemplate': f'{name} %{{z:.4g}} {unit}<extra></extra>',
            }
        )
    return traces


def _track_traces(result: SurveyResult) -> list[dict[str, Any]]:
    """The track, its lost/refused spans and the health alarms along it."""
    track = result.track
    step = max(1, len(track.t_s) // REPORT_TRACK_POINTS)
    x, y = track.xy_m[:, 0], track.xy_m[:, 1]
    traces: list[dict[str, Any]] = [
        {
            'type': 'scatter',
            'mode': 'lines',
            'x': x[::step].tolist(),
            'y': y[::step].tolist(),
            'line': {'color': 'black', 'width': 1},
            'name': 'track',
            'hoverinfo': 'skip',
        }
    ]
    for span in result.spans:
        inside = (track.t_s >= span.start_s) & (track.t_s <= span.stop_s)
        xs = np.interp([span.start_s, span.stop_s], track.t_s, x)
        ys = np.interp([span.start_s, span.stop_s], track.t_s, y)
        if inside.sum() > 2:
            xs, ys = x[inside], y[inside]
        traces.append(
            {
                'type': 'scatter',
                'mode': 'lines+markers',
                'x': list(map(float, xs)),
                'y': list(map(float, ys)),
                'line': {'color': SPAN_COLOURS[span.kind], 'width': 4},
                'name': f'{span.kind} {span.start_s:.1f}-{span.stop_s:.1f} s',
                'showlegend': False,
                'hovertemplate': (
                    f'{span.kind}: {span.start_s:.1f} to {span.stop_s:.1f} s<extra></extra>'
                ),
            }
        )
    alarms = result.health['alarms']
    if alarms:
        times = [a['t_s'] for a in alarms]
        traces.append(
            {
                'type': 'scatter',
                'mode': 'markers',
                'x': np.interp(times, track.t_s, x).tolist(),
                'y': np.interp(times, track.t_s, y).tolist(),
                'name': 'health alarm',
                'marker': {'symbol': 'x', 'size': 12, 'color': '#d62728'},
                'text': [f'{a["kind"]} at {a["t_s"]:.1f} s' for a in alarms],
                'hoverinfo': 'text',
            }
        )
    return traces


def _target_traces(result: SurveyResult, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Targets (markers with tooltips) and their 3-sigma ellipses, in the CRS."""
    if not records:
        return []
    geo, crs = result.georeference, result.crs
    positions = np.array([r['position_m'] for r in records])
    xy = geo.to_crs(positions, crs)
    traces = []
    for target in result.targets:
        values, vectors = np.linalg.eigh(target.fit.covariance[:2, :2])
        angles = np.linspace(0, 2 * np.pi, 49)
        ring = (
            files.ELLIPSE_SIGMAS
            * (np.column_stack([np.cos(angles), np.sin(angles)]) * np.sqrt(np.maximum(values, 0)))
            @ vectors.T
        )
        points = np.column_stack([target.fit.position[:2] + ring, np.zeros(len(ring))])
        outline = geo.to_crs(points, crs)
        traces.append(
            {
                'type': 'scatter',
                'mode': 'lines',
                'x': outline[:, 0].tolist(),
                'y': outline[:, 1].tolist(),
                'line': {'color': TARGET_COLOUR, 'width': 2},
                'showlegend': False,
                'hoverinfo': 'skip',
            }
        )
    text = [
        f'target {i}<br>x, y {xy[i, 0]:.1f}, {xy[i, 1]:.1f} m ({crs})<br>'
        f'depth {-r["position_m"][2]:.2f} m<br>moment '
        + ', '.join(f'{v:.0f}' for v in r['moment_Am2'])
        + ' A m²<br>σ '
        + ', '.join(f'{v:.3f}' for v in r['position_sigma_m'])
        + f' m<br>passes {r["passes"]}'
        for i, r in enumerate(records)
    ]
    traces.append(
        {
            'type': 'scatter',
            'mode': 'markers',
            'x': xy[:, 0].tolist(),
            'y': xy[:, 1].tolist(),
            'name': 'targets',
            'text': text,
            'hoverinfo': 'text',
            'marker': {
                'color': TARGET_COLOUR,
                'size': 16,
                'symbol': 'circle',
                'line': {'color': 'black', 'width': 1},
            },
        }
    )
    return traces


def _legs_traces(result: SurveyResult) -> list[dict[str, Any]]:
    legs = result.leg_residuals
    index = list(range(len(legs)))
    return [
        {
            'type': 'bar',
            'x': index,
            'y': [leg.residual_nT_per_m for leg in legs],
            'name': 'residual (non-field part)',
            'xaxis': 'x2',
            'yaxis': 'y2',
            'marker': {'color': '#1f77b4'},
        },
        {
            'type': 'scatter',
            'mode': 'markers+lines',
            'x': index,
            'y': [leg.floor_nT_per_m for leg in legs],
            'name': 'noise floor (1-sigma)',
            'xaxis': 'x2',
            'yaxis': 'y2',
            'line': {'color': 'black', 'dash': 'dot'},
        },
    ]


def report_html(result: SurveyResult, records: list[dict[str, Any]]) -> str:
    """The self-contained report (module docstring)."""
    go = require('plotly.graph_objects', 'the survey report')
    pio = require('plotly.io', 'the survey report')
    maps = _map_traces(result)
    rest = _track_traces(result) + _target_traces(result, records)
    n_maps = len(maps)
    buttons = [
        {
            'label': trace['name'],
            'method': 'restyle',
            'args': [{'visible': [k == n for k in range(n_maps)] + [True] * (len(rest) + 2)}],
        }
        for n, trace in enumerate(maps)
    ]
    figure = go.Figure(data=maps + rest + _legs_traces(result))
    geo = result.georeference
    rows, columns = _gridded_box(result)
    margin = 2 * result.grids.cell_m
    x_range = [result.grids.x[columns][0] - margin, result.grids.x[columns][-1] + margin]
    y_range = [result.grids.y[rows][0] - margin, result.grids.y[rows][-1] + margin]
    figure.update_layout(
        title={
            'text': f'Survey: {len(result.targets)} targets, cell {result.grids.cell_m:.2f} m, '
            f'{result.crs}; {geo.describe()}',
            'font': {'size': 13},
            'x': 0.16,
            'xanchor': 'left',
        },
        xaxis={'domain': [0.0, 0.6], 'title': {'text': f'x (m, {result.crs})'}, 'range': x_range},
        yaxis={'title': {'text': 'y (m)'}, 'scaleanchor': 'x', 'scaleratio': 1, 'range': y_range},
        xaxis2={'domain': [0.72, 1.0], 'anchor': 'y2', 'title': {'text': 'leg'}},
        yaxis2={'anchor': 'x2', 'title': {'text': 'nT/m'}},
        updatemenus=[
            {
                'buttons': buttons,
                'direction': 'down',
                'x': 0.0,
                'y': 1.12,
                'xanchor': 'left',
                'showactive': True,
            }
        ],
        legend={'x': 0.72, 'y': 1.0},
        height=800,
        plot_bgcolor='white',
    )
    return str(
        pio.to_html(figure, include_plotlyjs=True, full_html=True, config={'responsive': True})
    )


def residual_table(result: SurveyResult) -> str:
    """The per-leg check as text lines (for the command's output)."""
    return '\n'.join(
        f'leg {i}: {leg.start_s:.0f}-{leg.stop_s:.0f} s, residual {leg.residual_nT_per_m:.3f} '
        f'nT/m vs floor {leg.floor_nT_per_m:.3f} nT/m'
        for i, leg in enumerate(result.leg_residuals)
    )
