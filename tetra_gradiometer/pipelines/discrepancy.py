"""The discrepancy analysis of a bag: read the recorded run and search the effects library.

:func:`analyze_bag` is the work of the ``discrepancy`` command (and of ``batch``, per bag)
between loading the params file and writing the report folder
(:func:`tetra_gradiometer.reports.discrepancy.write_report`): the bag read whole
(:func:`~tetra_gradiometer.io.recording.read_recording`), analysed by
:func:`tetra_gradiometer.core.discrepancy.analyze`, and the report's ``data`` completed with
what never reached the analysis (implausible sets, undecodable messages). The analysis
runs on one BLAS thread (see :func:`analyze_bag`).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import numpy.typing as npt
from threadpoolctl import threadpool_limits

from ..core import TetraGeometry
from ..core.discrepancy import RecordedRun, Report, Settings, analyze
from ..core.effects import SIGNAL_PREFIX
from ..core.timebase import DEFAULT_TIMEBASE, TimeBase
from ..io.recording import Recording, read_recording

__all__ = ['analyze_bag']


def analyze_bag(
    bag_path: str | os.PathLike[str],
    geometry: TetraGeometry,
    earth_field_enu: npt.NDArray[np.float64] | None = None,
    *,
    settings: Settings | None = None,
    window: tuple[float, float] | None = None,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    progress: bool | None = None,
) -> tuple[Report, Recording]:
    """The discrepancy report of the bag, and the recording it was made from.

    Parameters
    ----------
    bag_path : path of the rosbag2 folder
    geometry : TetraGeometry of the array that recorded the bag
    earth_field_enu : (3,) tesla, ENU (the params file's ``earth_field_enu``), or None
    settings : the search's settings (None: ``Settings()``, the command's defaults)
    window : (t0, t1) seconds from the first sample to analyse, or None for the whole run
    timebase : how the four streams become sets (default: resampled to sensor 1's stamps)
    progress : tqdm bar on stderr while reading (None: only on a terminal, long bags)

    Raises
    ------
    BagError
        The bag breaks the data contract, or every set has an implausible reading.
    """
    recording = read_recording(
        bag_path,
        timebase=timebase,
        progress=progress,
        earth_field_enu=earth_field_enu,
        discover=settings is None or settings.candidates is None,
    )
    run = RecordedRun(
        recording.t_s,
        recording.fields,
        recording.orientation_xyzw,
        recording.temperature_c,
        recording.current_a,
        recording.missing,
        recording.extra_currents,
        recording.position_m,
        recording.signals,
    )
    # One BLAS thread: the analysis is many small solves and products, where a second
    # thread only spins; on the shared 2-core machine (load 3-9) the clean 1,000 s survey
    # took 86 s wall / 43 s CPU with OpenBLAS's two threads, 24 s / 14 s with one
    # (bench/bench_discrepancy_survey.py). threadpoolctl: the maintained way to set it at
    # run time (the environment variables act only before numpy loads).
    with threadpool_limits(limits=1, user_api='blas'):
        report = analyze(run, geometry, earth_field_enu, settings=settings, window_s=window)
    declared = [
        n.removeprefix(SIGNAL_PREFIX) for n in report.named_effects if n.startswith(SIGNAL_PREFIX)
    ]
    signals = {
        'vehicle_signals': declared,  # the params file's declaration of what was named
        'signals_read': [n.removeprefix(SIGNAL_PREFIX) for n in recording.signals],
        'signals_left_out': list(recording.signal_notes),
    }
    report = dataclasses.replace(
        report, data={**report.data, **recording.input_counts(), **signals}
    )
    return report, recording
