"""A fleet of bags, one bag at a time: what ``batch`` runs as one task per bag.

A fleet is a folder whose subfolders ``NAME/`` are rosbag2 folders, each with its params
YAML beside it as ``NAME.yaml`` (:func:`find_bags`). :func:`process_bag` is the task:
importable by a Dask worker, it takes a :class:`BagJob` (plain paths, picklable), never
raises for a bag's fault, and returns the bag's row of ``summary.csv`` (:data:`COLUMNS`).
It calls the library functions the single-bag commands call, with their defaults, so the
figures are theirs:

1. *params*: ``NAME.yaml`` as ``calibrate --params`` reads it; a scenario file instead (as
   ``bags/*.yaml`` are) gives the sensor positions and Earth field the way ``simulate``
   writes ``BAG.params.yaml``, and that params file is written as ``params.yaml``;
2. *calibrate* the window (:func:`~tetra_gradiometer.pipelines.trim.calibrate_assessed`) into
   ``calibration.yaml``; a window the calibration refuses (``AssumptionError``: the fit's
   assumption or the attitude excitation fails; ``IdentifiabilityError``: the window
   cannot identify the parameters) makes the row ``refused`` and skips step 3;
3. *compensate* the whole bag (:func:`~.bag_compensation.compensate_bag`) into
   ``compensated.csv``;
4. *discrepancy* analysis of the whole bag (:func:`~.bag_discrepancy.analyze_bag`) into the
   report folder ``discrepancy/``;
5. *survey*, when asked (``batch --survey-origin`` or ``--survey-navsat-topic``): the
   ``survey`` command's products (:func:`~.pipelines.survey.survey_bag`) into ``survey/``,
   after a calibration that was not refused.

A ``TetraError`` in a step makes the row ``failed`` with ``STEP: message`` as its reason and
ends the bag; any other exception is a bug: also ``failed``, its traceback in ``error.txt``.
Everything goes into a private temporary folder that becomes ``OUT/NAME/`` in one move
(:func:`~.outputs.atomic_output`, kind ``BATCH_BAG``), ``row.json`` last: a bag folder that
exists is complete. :func:`done_row` is the rerun's test: a previous ``ok`` or ``refused``
row made from the same inputs (bag files' sizes and times, params bytes, window).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import socket
import time
import traceback
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from ..core import TetraGeometry
from ..core.units import NT_PER_T
from ..errors import AssumptionError, IdentifiabilityError, InputError, ParamsError, TetraError
from ..io._yaml import loads, read_yaml
from ..io.calibration import load_calibration, save_calibration
from ..io.outputs import BATCH_BAG, BATCH_SUMMARY, atomic_output, atomic_write_text
from ..io.params import earth_field_from_params, geometry_from_params, load_params, params_document
from ..io.scenario import load_scenario
from ..pipelines.calibration import window_text
from ..pipelines.compensation import (
    TensorStatistics,
    compensate_bag,
    health_recorder,
    load_compensation,
)
from ..pipelines.discrepancy import analyze_bag
from ..pipelines.tracking import tracked_stream
from ..pipelines.trim import calibrate_assessed
from ..pipelines.window_search import find_window
from ..reports.discrepancy import write_report

__all__ = [
    'COLUMNS',
    'STATUSES',
    'SUMMARY_FILE',
    'BagJob',
    'FleetBag',
    'done_row',
    'find_bags',
    'make_job',
    'process_bag',
    'summary_text',
    'task_error_row',
    'write_summary',
]

#: The row's statuses: all steps ran; the calibration refused its window (the discrepancy
#: analysis ran); the bag could not be processed.
STATUSES = ('ok', 'refused', 'failed')
#: A rerun skips a bag whose previous row has one of these (made from the same inputs).
DONE_STATUSES = ('ok', 'refused')
#: Columns of ``summary.csv``, in order (docs/offline.md, *batch*, defines each).
COLUMNS = (
    'bag',
    'status',
    'reason',
    'residual_nT_per_m',
    'noise_floor_nT_per_m',
    'effects',
    'runtime_s',
    'window',
    'sets_in_window',
    'sensor_noise_nT',
    'coverage_condition',
    'window_check_ratio',
    'sets_compensated',
    'raw_rms_nT_per_m',
    'compensated_rms_nT_per_m',
    'checks',
    'gap_initial_nT',
    'gap_final_nT',
    'discrepancy_noise_floor_nT',
    'adequate',
    'params',
    'outputs',
    'worker',
    'finished_utc',
)
SUMMARY_FILE = 'summary.csv'
ROW_FILE = 'row.json'
ERROR_FILE = 'error.txt'
PARAMS_FILE = 'params.yaml'
CALIBRATION_FILE = 'calibration.yaml'
CSV_FILE = 'compensated.csv'
REPORT_FOLDER = 'discrepancy'
SURVEY_FOLDER = 'survey'
_ROW_FORMAT = 'tetra_gradiometer_batch_row'

Row = dict[str, Any]


@dataclass(frozen=True)
class FleetBag:
    """One bag of a fleet: ``name`` (its folder's), the rosbag2 folder, its params YAML."""

    name: str
    bag: Path
    params: Path


@dataclass(frozen=True)
class BagJob:
    """One task of ``batch``: a bag, where its outputs go, how to process it.

    Attributes
    ----------
    bag : FleetBag
        Absolute paths, the same on every worker.
    out_dir : Path
        ``OUT/NAME``, written as a whole (kind ``batch bag folder``).
    window : (t0, t1) seconds from the first matched set, or None (the whole bag)
        The calibration window (``calibrate --window``).
    fingerprint : dict
        The inputs as they were when the job was made (:func:`make_job`), kept in
        ``row.json`` for :func:`done_row`.
    plots : bool
        Write the discrepancy report's plots.
    survey : (origin (lat, lon, h) or None, NavSatFix topic or None), or None
        Also write the survey products, placed by the origin or the topic (step 5).
    """

    bag: FleetBag
    out_dir: Path
    window: tuple[float, float] | None = None
    fingerprint: dict[str, Any] = field(default_factory=dict)
    plots: bool = True
    survey: tuple[tuple[float, float, float] | None, str | None] | None = None


def find_bags(
    folder: str | os.PathLike[str], *, exclude: Iterable[str | os.PathLike[str]] = ()
) -> list[FleetBag]:
    """The bags of a fleet folder, by name: every subfolder (not hidden, not in ``exclude``)
    that holds ``metadata.yaml`` or has a ``NAME.yaml`` beside it. Paths are absolute.

    Raises
    ------
    InputError
        ``folder`` is not a folder, is itself a rosbag2 folder, or holds no bag.
    """
    root = Path(folder).absolute()
    if not root.is_dir():
        raise InputError(f'{folder} is not a folder (batch takes the folder that holds the bags)')
    if (root / 'metadata.yaml').is_file():
        raise InputError(
            f'{folder} is a rosbag2 folder: batch takes the folder that holds the bags '
            '(use calibrate, compensate and discrepancy for one bag)'
        )
    skip = {Path(p).absolute() for p in exclude}
    bags = [
        FleetBag(entry.name, entry, entry.with_name(entry.name + '.yaml'))
        for entry in sorted(root.iterdir())
        if entry.is_dir()
        and not entry.name.startswith('.')
        and entry not in skip
        and (
            (entry / 'metadata.yaml').is_file() or entry.with_name(entry.name + '.yaml').is_file()
        )
    ]
    if not bags:
        raise InputError(
            f'{folder} holds no bag (a subfolder NAME/ with metadata.yaml, its params as '
            'NAME.yaml beside it)'
        )
    return bags


def _fingerprint(bag: FleetBag, window: tuple[float, float] | None) -> dict[str, Any]:
    """What a previous row must have been made from to stand: the bag's files (size, mtime),
    the params file's SHA-256 (None when unreadable) and the window."""
    files = {}
    if bag.bag.is_dir():
        for path in sorted(bag.bag.iterdir()):
            if path.is_file():
                stat = path.stat()
                files[path.name] = [stat.st_size, stat.st_mtime_ns]
    try:
        params: str | None = hashlib.sha256(bag.params.read_bytes()).hexdigest()
    except OSError:
        params = None
    return {
        'bag_files': files,
        'params_sha256': params,
        'window': None if window is None else [float(window[0]), float(window[1])],
    }


def make_job(
    bag: FleetBag,
    out: str | os.PathLike[str],
    window: tuple[float, float] | None,
    *,
    plots: bool = True,
    survey: tuple[tuple[float, float, float] | None, str | None] | None = None,
) -> BagJob:
    """The job of ``bag`` with its outputs in ``out/NAME`` and its inputs' fingerprint now."""
    out_dir = Path(out).absolute() / bag.name
    fingerprint = _fingerprint(bag, window)
    if survey is not None:  # a survey asked for: a previous row without it is not done
        fingerprint['survey'] = [None if survey[0] is None else list(survey[0]), survey[1]]
    return BagJob(bag, out_dir, window, fingerprint, plots, survey)


def done_row(job: BagJob) -> Row | None:
    """The previous row of ``job``'s bag when it is done (``ok`` or ``refused``) and was made
    from the same inputs (fingerprint), else None (never run, failed, or inputs changed)."""
    if not BATCH_BAG.holds(job.out_dir):
        return None
    try:
        document = json.loads((job.out_dir / ROW_FILE).read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return None
    if not isinstance(document, dict) or document.get(_ROW_FORMAT) != 1:
        return None
    row = document.get('row')
    same = document.get('fingerprint') == json.loads(json.dumps(job.fingerprint))
    if not same or not isinstance(row, dict) or row.get('status') not in DONE_STATUSES:
        return None
    return row


# --------------------------------------------------------------------------- the task


def process_bag(job: BagJob) -> Row:
    """Calibrate, compensate and analyse one bag into ``job.out_dir``: the Dask task.

    Parameters
    ----------
    job : BagJob
        The bag, its params, where its outputs go, the calibration window.

    Returns
    -------
    dict
        The bag's row of ``summary.csv`` (keys of :data:`COLUMNS`; a step that did not run
        leaves its keys out), also written to ``OUT/NAME/row.json`` when the folder could be.

    Never raises for the bag's fault: a ``TetraError`` or a bug in a step is a ``failed``
    row (module docstring: statuses, steps, outputs).
    """
    started = time.perf_counter()
    row: Row = {
        'bag': job.bag.name,
        'status': 'ok',
        'reason': '',
        'window': window_text(job.window),
        'params': str(job.bag.params),
        'outputs': str(job.out_dir),
        'worker': f'{socket.gethostname()}:{os.getpid()}',
    }
    try:
        with atomic_output(
            job.out_dir,
            BATCH_BAG,
            force=True,
            inputs=(job.bag.bag, job.bag.params),
            command='batch',
        ) as tmp:
            tmp.mkdir()
            _run_steps(job, tmp, row)
            _finish(row, started)
            document = {_ROW_FORMAT: 1, 'fingerprint': job.fingerprint, 'row': row}
            text = json.dumps(document, indent=1, default=_json_scalar)
            (tmp / ROW_FILE).write_text(text + '\n', encoding='utf-8')
    except TetraError as error:  # the bag's folder could not be written (or moved into place)
        _fail(row, f'output: {error}')
        _finish(row, started)
    return row


def task_error_row(job: BagJob, error: BaseException) -> Row:
    """The row of a task that did not return: the cluster lost it (a worker died each time
    it ran it: ``KilledWorker``), or it could not run there (a worker without this
    package)."""
    return {
        'bag': job.bag.name,
        'status': 'failed',
        'reason': f'the task did not complete on the cluster: {type(error).__name__}: '
        f'{_one_line(str(error))}',
        'window': window_text(job.window),
        'params': str(job.bag.params),
        'outputs': str(job.out_dir),
        'finished_utc': _utc_now(),
    }


def _run_steps(job: BagJob, tmp: Path, row: Row) -> None:
    """The four steps of the module docstring, each filling its part of ``row``; a failing
    step ends the bag (``failed``: a ``TetraError``'s message, or a bug's traceback)."""
    step = 'params'
    try:
        geometry, earth = _site(job, tmp, row)
        step = 'calibrate'
        calibration = _calibrate(job, tmp, row, geometry, earth)
        if calibration is not None:
            step = 'compensate'
            _compensate(job, tmp, row, geometry, calibration)
        step = 'discrepancy'
        _discrepancy(job, tmp, row, geometry, earth)
        if calibration is not None and job.survey is not None:
            step = 'survey'
            _survey(job, tmp, geometry, calibration)
    except TetraError as error:
        _fail(row, f'{step}: {error}')
    except Exception as error:  # a bug: the batch goes on, the row says so and where to look
        (tmp / ERROR_FILE).write_text(
            f'batch: bug in step {step} of {job.bag.bag}\n{traceback.format_exc()}',
            encoding='utf-8',
        )
        _fail(
            row,
            f'bug in {step}: {type(error).__name__}: {_one_line(str(error))} '
            f'(traceback in {job.out_dir / ERROR_FILE})',
        )


def _site(job: BagJob, tmp: Path, row: Row) -> tuple[TetraGeometry, np.ndarray | None]:
    """Geometry and Earth field from ``NAME.yaml``: a params file, or a scenario file whose
    params (as ``simulate`` writes them) go to ``params.yaml`` and into the row."""
    source = job.bag.params
    try:
        params = load_params(source)
    except ParamsError:
        document = read_yaml(source, 'params', ParamsError)
        if not (isinstance(document, dict) and 'segments' in document):
            raise  # not a scenario either: the params file's own error
        scenario, _ = load_scenario(source)
        text = params_document(
            {
                'sensor_positions': scenario.geometry.to_flat(),
                'earth_field_enu': [float(v) for v in scenario.earth_field_enu],
            }
        )
        (tmp / PARAMS_FILE).write_text(
            f'# Written by "python -m tetra_gradiometer batch" from the scenario {source}\n'
            + text,
            encoding='utf-8',
        )
        params = loads(text)['/**']['ros__parameters']  # as calibrate reads it
        row['params'] = str(job.out_dir / PARAMS_FILE)
    return geometry_from_params(params, str(source)), earth_field_from_params(params, str(source))


def _calibrate(
    job: BagJob, tmp: Path, row: Row, geometry: TetraGeometry, earth: np.ndarray | None
) -> Path | None:
    """``calibrate`` with its defaults on the window (without one, as ``calibrate``: the
    window found in the bag, :func:`~tetra_gradiometer.pipelines.window_search.find_window`);
    the calibration file, or None when the calibration refuses the window (the row is then
    ``refused``)."""
    try:
        if job.window is None:
            result = find_window(job.bag.bag, geometry, earth, progress=False).result
            row['window'] = result.window
        else:
            result, _ = calibrate_assessed(
                job.bag.bag, geometry, earth, window=job.window, progress=False
            )
    except (AssumptionError, IdentifiabilityError) as error:
        row['status'] = 'refused'
        row['reason'] = f'calibrate: {_one_line(str(error))}'
        return None
    summary = result.calibration.summary()
    check = None if result.check is None else result.check.consistency
    row.update(
        residual_nT_per_m=summary.get('residual_rms_nT_per_m'),
        # The noise measured on the window itself, independent of the fit (the fit's own
        # sensor-noise estimate comes from its residual: their ratio would always be 1).
        noise_floor_nT_per_m=None if check is None else check.noise_rms * NT_PER_T,
        sets_in_window=result.sets_in_window,
        sensor_noise_nT=summary.get('sensor_noise_nT'),
        coverage_condition=result.coverage_condition,
        window_check_ratio=None if check is None else check.ratio,
    )
    path = tmp / CALIBRATION_FILE
    save_calibration(path, result.record, inputs=(job.bag.bag, job.bag.params))
    return path


def _compensate(
    job: BagJob, tmp: Path, row: Row, geometry: TetraGeometry, calibration: Path
) -> None:
    """``compensate --csv`` with its defaults, and the RMS of the raw and written tensors."""
    compensation = load_compensation(calibration, geometry, target=str(job.bag.params))
    statistics = TensorStatistics()
    health = health_recorder(geometry, compensation)
    tracking, _ = tracked_stream(
        job.bag.bag,
        geometry,
        compensation.parameters,
        compensation.sensor_noise_t,
        health,
        fitted=compensation.fitted,
    )
    counts = compensate_bag(
        job.bag.bag,
        geometry,
        compensation,
        health=health,
        tracking=tracking,
        statistics=statistics,
        csv=tmp / CSV_FILE,
        progress=False,
        inputs=(job.bag.bag, job.bag.params, calibration),
    )
    verdict = None if health is None else health.document()
    alarms = f'health: {verdict["verdict"]}' if verdict and verdict['alarms'] else ''
    checks = (alarms, counts.extrapolated, counts.conventions, *compensation.forced)
    row.update(
        sets_compensated=counts.n_sets,
        raw_rms_nT_per_m=statistics.raw_rms * NT_PER_T,
        compensated_rms_nT_per_m=statistics.rms * NT_PER_T,
        checks=' | '.join(check for check in checks if check) or 'ok',
    )


def _discrepancy(
    job: BagJob, tmp: Path, row: Row, geometry: TetraGeometry, earth: np.ndarray | None
) -> None:
    """``discrepancy`` with its defaults on the whole bag: the report folder and its
    findings."""
    report, _ = analyze_bag(job.bag.bag, geometry, earth, progress=False)
    write_report(
        report, tmp / REPORT_FOLDER, plots=job.plots, inputs=(job.bag.bag, job.bag.params)
    )
    row.update(
        effects=';'.join(report.named_effects) or 'none',
        gap_initial_nT=report.gap_initial_nT,
        gap_final_nT=report.gap_final_nT,
        discrepancy_noise_floor_nT=report.noise_floor_nT,
        adequate=bool(report.adequate),
    )


def _survey(job: BagJob, tmp: Path, geometry: TetraGeometry, calibration: Path) -> None:
    """``survey`` with its defaults into ``survey/`` (step 5)."""
    from ..pipelines.survey import survey_bag
    from ..reports.survey import write_survey

    assert job.survey is not None
    origin, topic = job.survey
    compensation = load_compensation(calibration, geometry, target=str(job.bag.params))
    result = survey_bag(
        job.bag.bag, geometry, compensation, origin=origin, navsat_topic=topic, progress=False
    )
    metadata = {
        'calibration': str(job.out_dir / CALIBRATION_FILE),
        'bag': str(job.bag.bag),
        'params': str(job.bag.params),
        'sensor_noise': compensation.noise_source,
        'command': 'batch (its survey step, with the defaults)',
    }
    write_survey(
        result,
        tmp / SURVEY_FOLDER,
        metadata=metadata,
        inputs=(job.bag.bag,),
        calibration=load_calibration(calibration),
    )


def _json_scalar(value: Any) -> Any:
    """numpy scalars as Python numbers in ``row.json``."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'{type(value).__name__} is not JSON serializable')


def _fail(row: Row, reason: str) -> None:
    row['status'] = 'failed'
    row['reason'] = _one_line(reason)


def _finish(row: Row, started: float) -> None:
    row['runtime_s'] = round(time.perf_counter() - started, 3)
    row['finished_utc'] = _utc_now()


def _one_line(text: str) -> str:
    return ' '.join(text.split())


def _utc_now() -> str:
    return datetime.now(UTC).strftime('%Y-%m-%dT%H:%M:%SZ')


# --------------------------------------------------------------------------- the summary


def _cell(value: Any) -> str:
    """A CSV cell: '' for missing, yes/no for booleans, floats exactly (``repr``)."""
    if value is None:
        return ''
    if isinstance(value, bool | np.bool_):
        return 'yes' if value else 'no'
    if isinstance(value, float | np.floating):
        return repr(float(value))
    return str(value)


def summary_text(rows: Iterable[Row]) -> str:
    """``summary.csv``: the header :data:`COLUMNS`, then one line per row, by bag name."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator='\n')
    writer.writerow(COLUMNS)
    for row in sorted(rows, key=lambda r: str(r['bag'])):
        writer.writerow([_cell(row.get(column)) for column in COLUMNS])
    return buffer.getvalue()


def write_summary(out: str | os.PathLike[str], rows: Iterable[Row]) -> Path:
    """Write ``out/summary.csv`` atomically (replacing the previous one, never anything
    else)."""
    return atomic_write_text(
        Path(out) / SUMMARY_FILE, summary_text(rows), BATCH_SUMMARY, force=True
    )
