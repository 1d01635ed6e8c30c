"""The ``survey`` output folder (written as one atomic folder) and its ``report.html``.

Files (the contract; formats in :mod:`~tetra_gradiometer.io.survey_files`)::

    survey.nc           every grid, its 1-sigma and the mask (CF-1.8)
    geotiff/<var>.tif   one GeoTIFF per grid
    targets.json        the targets in the odom frame (the contract of ``locate``)
    targets.geojson     the targets in WGS 84 (points, 3-sigma ellipses)
    targets.csv         the same, one row per target
    track.geojson       the track
    report.html         the report for the client (:mod:`.survey_page`: one page, maps
                        inlined, no script, no network)
    survey.json         what was done: georeference, CRS, cell, mask distance, timings,
                        health alarms, lost and refused spans, per-leg residuals
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

from ..io import survey_files as files
from ..io.calibration import CalibrationFile
from ..io.outputs import SURVEY, atomic_output
from ..io.targets import dumps, target_record, targets_document
from ..pipelines.survey import SurveyResult
from .survey_page import report_html

__all__ = ['residual_table', 'summary', 'write_survey']

#: The package's version for the files' metadata (the package is loaded: this module is in
#: it; read from there rather than imported upwards).
__version__ = str(getattr(sys.modules[__name__.split('.')[0]], '__version__', 'unknown'))


def write_survey(
    result: SurveyResult,
    out: str | os.PathLike[str],
    *,
    metadata: Mapping[str, Any],
    force: bool = False,
    inputs: Iterable[str | os.PathLike[str]] = (),
    calibration: CalibrationFile | None = None,
) -> Path:
    """Write the folder ``out`` (module docstring) atomically; ``metadata``: the global
    attributes of ``survey.nc`` beside those of the result (calibration, effects, and for
    the report ``bag``, ``params``, ``vehicle``, ``command``); ``calibration``: the loaded
    calibration file, whose checks the report states."""
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
        page = report_html(result, records, metadata, calibration=calibration, version=__version__)
        (tmp / 'report.html').write_text(page, encoding='utf-8')
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


def residual_table(result: SurveyResult) -> str:
    """The per-leg check as text lines (for the command's output)."""
    return '\n'.join(
        f'leg {i}: {leg.start_s:.0f}-{leg.stop_s:.0f} s, residual {leg.residual_nT_per_m:.3f} '
        f'nT/m vs floor {leg.floor_nT_per_m:.3f} nT/m'
        for i, leg in enumerate(result.leg_residuals)
    )
