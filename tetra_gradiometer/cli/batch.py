"""``python -m tetra_gradiometer batch DIR --out OUT [--window T0:T1] [--scheduler ADDR]``.

Every bag of the fleet folder ``DIR`` (a subfolder ``NAME/`` with its params YAML beside it
as ``NAME.yaml``) is calibrated on the window, compensated and analysed for discrepancies,
one Dask task per bag (:func:`tetra_gradiometer.cli.fleet.process_bag`): on a
``dask.distributed.LocalCluster`` of this machine by default (one single-threaded worker
process per core), on a running cluster with ``--scheduler tcp://HOST:PORT``. Each bag's
outputs go to ``OUT/NAME/``; ``OUT/summary.csv`` has one row per bag (``ok``, ``refused`` or
``failed``, the reason and the figures), rewritten as each bag completes. A rerun skips the
bags already done from the same inputs; ``--force`` redoes them. Only this command imports
Dask.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from .._optional import require
from ..errors import InputError
from ..io.outputs import BATCH, BATCH_BAG, output_folder, remove_stale_temporaries
from ..io.progress import progress_bar
from ._args import add_force_argument, add_progress_arguments, int_range, window_arg
from .fleet import (
    STATUSES,
    SUMMARY_FILE,
    BagJob,
    done_row,
    find_bags,
    make_job,
    process_bag,
    task_error_row,
    write_summary,
)
from .survey import origin_arg

#: ``--workers``: LocalCluster worker processes.
MAX_WORKERS = 256
#: Seconds to wait for ``--scheduler`` to answer.
CONNECT_TIMEOUT_S = 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        'folder',
        metavar='DIR',
        help='folder of bags: each subfolder NAME/ a rosbag2 folder with its params YAML '
        '(or scenario) beside it as NAME.yaml',
    )
    parser.add_argument(
        '--out', required=True, help='batch folder: OUT/summary.csv and OUT/NAME/ per bag'
    )
    parser.add_argument(
        '--window',
        type=window_arg,
        default=None,
        metavar='T0:T1',
        help='calibration window of every bag, seconds from its first set (default: found in '
        'each bag, as calibrate does without --window)',
    )
    parser.add_argument(
        '--scheduler',
        default=None,
        metavar='ADDR',
        help='address of a running Dask scheduler, e.g. tcp://HOST:8786 (default: a '
        'LocalCluster on this machine)',
    )
    parser.add_argument(
        '--workers',
        type=int_range(1, MAX_WORKERS),
        default=None,
        help='LocalCluster: worker processes, one thread each (default: the cores, at most '
        'one per bag to run)',
    )
    parser.add_argument(
        '--no-plots', action='store_true', help="write the discrepancy reports' JSON and MD only"
    )
    place = parser.add_mutually_exclusive_group()
    place.add_argument(
        '--survey-origin',
        type=origin_arg,
        default=None,
        metavar='LAT,LON[,ALT]',
        help="also write each bag's survey products (OUT/NAME/survey/), odom ENU at this point",
    )
    place.add_argument(
        '--survey-navsat-topic',
        default=None,
        help="also write each bag's survey products, placed by this NavSatFix topic",
    )
    add_force_argument(
        parser, "the outputs of bags already done (they are redone; OUT's other content stays)"
    )
    add_progress_arguments(parser)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    bags = find_bags(args.folder, exclude=(args.out,))
    inputs = [path for bag in bags for path in (bag.bag, bag.params)]
    out = output_folder(args.out, BATCH, inputs=inputs, command='batch')  # refused: no work
    survey = None
    if args.survey_origin is not None or args.survey_navsat_topic is not None:
        survey = (args.survey_origin, args.survey_navsat_topic)
    jobs = [
        make_job(bag, out, args.window, plots=not args.no_plots, survey=survey) for bag in bags
    ]
    previous = {} if args.force else {job.bag.name: done_row(job) for job in jobs}
    rows = {name: row for name, row in previous.items() if row is not None}
    todo = [job for job in jobs if job.bag.name not in rows]
    write_summary(out, rows.values())
    skipped = f'{len(rows)} done before, skipped (--force redoes them); ' if rows else ''
    print(f'batch: {len(jobs)} bags in {args.folder}: {skipped}{len(todo)} to run')
    where = 'nothing to run'
    if todo:
        try:
            with _client(args.scheduler, args.workers, len(todo)) as (client, where):
                print(f'running on {where}')
                _run_jobs(client, todo, rows, out, args.progress)
        except KeyboardInterrupt:  # SIGINT, SIGTERM: the local workers are gone with the
            for job in todo:  # cluster; what they were writing is removed (their own only)
                remove_stale_temporaries(job.out_dir, BATCH_BAG)
            raise
    counts = {s: sum(r['status'] == s for r in rows.values()) for s in STATUSES}
    print(
        f'batch: {len(rows)} bags: {counts["ok"]} ok, {counts["refused"]} refused, '
        f'{counts["failed"]} failed ({len(todo)} run on {where}, {len(jobs) - len(todo)} '
        f'skipped) in {time.perf_counter() - started:.1f} s; summary: {out / SUMMARY_FILE}'
    )
    return 0


@contextmanager
def _client(scheduler: str | None, workers: int | None, n_jobs: int) -> Iterator[tuple[Any, str]]:
    """A ``distributed.Client`` of ``scheduler``, or of a LocalCluster started (and closed)
    here; with a description of where the tasks run."""
    distributed = require('dask.distributed', 'batch (a fleet on Dask)')
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, ValueError, TypeError) as error:
            raise InputError(f'cannot reach the Dask scheduler at {scheduler}: {error}') from None
        with client:
            n_workers = len(client.scheduler_info().get('workers', {}))
            waiting = '' if n_workers else ': the tasks wait for workers to join'
            yield client, f'the scheduler {scheduler} ({_workers(n_workers)}{waiting})'
        return
    n_workers = workers or max(1, min(os.cpu_count() or 1, n_jobs))
    with (
        LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,  # numpy-heavy tasks: one process per core
            processes=True,
            host='127.0.0.1',  # this machine only; no dashboard (its HTTP port: any free one)
            scheduler_kwargs={'dashboard': False, 'dashboard_address': '127.0.0.1:0'},
            # CRITICAL, not ERROR: a worker's heartbeat racing the scheduler's close logs an
            # ERROR with a traceback on a loaded machine (CommClosedError) though every task is
            # done; a task's own failure reaches its row, never a log.
            silence_logs=logging.CRITICAL,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client, f'a LocalCluster of {_workers(n_workers)}'


def _workers(n: int) -> str:
    return f'{n} worker' + ('' if n == 1 else 's')


def _run_jobs(
    client: Any, jobs: list[BagJob], rows: dict[str, Any], out: Any, progress: bool | None
) -> None:
    """Submit one task per job and, as each completes, add its row, rewrite the summary and
    show it; a task that raised (a lost worker) is a ``failed`` row too."""
    from dask.distributed import as_completed

    run_id = uuid.uuid4().hex[:8]
    futures = {
        client.submit(
            process_bag, job, key=f'tetra-batch-{run_id}-{job.bag.name}', pure=False
        ): job
        for job in jobs
    }
    bar = progress_bar(len(jobs), progress, 'bags', unit='bag', min_total=1)
    try:
        for n_done, future in enumerate(as_completed(futures), start=1):
            job = futures.pop(future)
            try:
                row = future.result()
            except Exception as error:  # the cluster lost the task: the batch goes on
                row = task_error_row(job, error)
            future.release()
            rows[job.bag.name] = row
            write_summary(out, rows.values())
            bar.update(1)
            bar.write(f'[{n_done}/{len(jobs)}] {_row_text(row)}', file=sys.stdout)
    finally:
        bar.close()


def _row_text(row: dict[str, Any]) -> str:
    """One line per completed bag: status, name, the headline figures or the reason."""
    parts = [f'{row["status"]:<7} {row["bag"]}']
    residual, floor = row.get('residual_nT_per_m'), row.get('noise_floor_nT_per_m')
    if residual is not None and floor:
        parts.append(f'residual {residual:.4g} nT/m = {residual / floor:.2f} x noise {floor:.4g}')
    if row.get('effects'):
        parts.append(f'effects: {row["effects"]}')
    if row.get('reason'):
        parts.append(str(row['reason']))
    if row.get('runtime_s') is not None:
        parts.append(f'{row["runtime_s"]:.1f} s')
    return '; '.join(parts)
