"""Compensating a bag: stream its matched sets into a tensor CSV and/or a tensor bag.

Each set is differenced into the tensor (eq. 7) and compensated (eq. 19) with the
calibration's ``k``, ``b``; without parameters the raw tensor is written.

CSV (written to a temporary file, renamed into place at the end)::

    stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz,sigma_gxx,sigma_gxy,...,sigma_gzz

one row per matched set (sets with an implausible reading, non-finite or ``|B| > 1e-3 T``, are
dropped and counted); ``stamp_s`` is the **absolute** header stamp of sensor 1 in seconds since
the Unix epoch, printed exactly from the integer nanoseconds (9 decimals); ``gij`` =
``G_ij = dB_i/dx_j`` in **nT/m** (6 decimals), body frame; ``sigma_gij`` its standard uncertainty
(1-sigma, nT/m, 6 decimals) from the sensor noise and the calibration's parameter covariance
(:mod:`~tetra_gradiometer.core.uncertainty`, :func:`load_compensation` says which noise).
Without a sensor-noise figure (the raw tensor without ``--sensor-noise-nt``) the nine
``sigma_`` columns are left out. Compensated without a channel (``allow_missing_channels``: a
channel the calibration's terms read is absent from the bag), the CSV starts with one comment
line, ``# compensated WITHOUT <channel> (<topic>): ...`` (:meth:`.terms.HeldTerms.text`),
before the header: the terms reading it are held at their calibration-window mean and the sigma
columns include their spread over that window. With the calibration tracked (:mod:`.tracking`)
the tensors and sigma are the tracked ones and nine ``db_*`` columns follow.

The output bag holds ``/tetra/gradient/compensated`` (``/tetra/gradient/raw`` for the raw
tensor): ``tetra_gradiometer_msgs/GradientTensor`` as the nodes publish it (``g``, ``g_sigma``
NaN without a noise figure, ``B_1'``; COMPENSATED with the ``created_utc``, or RAW).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import numpy.typing as npt

from ..core import InterferenceParameters, TetraGeometry, compensate, difference_tensor
from ..core.conventions import TensorSample
from ..core.health import HealthConfig
from ..core.plausibility import DroppedSets, plausible_sets
from ..core.timebase import DEFAULT_TIMEBASE, ClockEstimate, TimeBase
from ..core.uncertainty import SigmaModel
from ..core.units import NS_PER_S, NT_PER_T, S_PER_NS, T_PER_NT
from ..errors import BagError, InputError, OutputError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..io.bag import BagWriter, MagneticBag, SetCounters
from ..io.calibration import check_positions, load_calibration
from ..io.outputs import BAG, CSV, atomic_output, check_output
from .health import HealthRecorder
from .terms import StreamRegressors
from .tracking import TrackedStream, learn_after_ns

__all__ = [
    'COMPENSATED_TOPIC',
    'CSV_HEADER',
    'CSV_SIGMA_HEADER',
    'RAW_TOPIC',
    'Compensation',
    'CompensationCounts',
    'TensorStatistics',
    'check_outputs',
    'compensate_bag',
    'format_rows',
    'input_storage',
    'load_compensation',
]

CSV_HEADER = 'stamp_s,' + ','.join(cv.TENSOR_NAMES)
#: The header with the nine 1-sigma columns (nT/m) after the tensor.
CSV_SIGMA_HEADER = CSV_HEADER + ',' + ','.join(f'sigma_{name}' for name in cv.TENSOR_NAMES)
COMPENSATED_TOPIC = f'{cv.NAMESPACE}/gradient/compensated'
RAW_TOPIC = f'{cv.NAMESPACE}/gradient/raw'

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class CompensationCounts:
    """What :func:`compensate_bag` wrote.

    Attributes
    ----------
    n_sets : int
        Sets written (rows of the CSV, messages of the output bag).
    dropped : DroppedSets
        Matched sets dropped as implausible (non-finite, ``|B|`` too large), by reason.
    span_s : float
        Seconds from the first set written to the last.
    topic : str
        The tensor topic of the output bag.
    counters : MatchCounters or ResampleCounters
        The set former's counts.
    clocks : tuple of ClockEstimate, or None
        The sensors' clocks against the reference instants (None when pairing stamps).
    skipped_messages : int
        Messages skipped as undecodable or unreadable (``MagneticBag.skipped``).
    skipped_summary : str
        The reader's line about them ('' when none).
    channel_dropped : int
        Sets dropped because a channel the calibration's terms read was unknown there.
    channel_summary : str
        Which channel and when ('' when none).
    held_summary : str
        Compensated without an absent channel: which, and what was done instead ('' when
        every channel was there).
    extrapolated : str
        The terms' regressors beyond what the calibration window saw ('' when none).
    conventions : str
        The written tensors are not a gradient with the declared positions and reading
        frame: the hypotheses that make them one (core/conventions; '' when they are one,
        or their signal is too weak to tell).
    """

    n_sets: int
    dropped: DroppedSets
    span_s: float
    topic: str
    counters: SetCounters
    clocks: tuple[ClockEstimate, ...] | None = None
    skipped_messages: int = 0
    skipped_summary: str = ''
    channel_dropped: int = 0
    channel_summary: str = ''
    held_summary: str = ''
    extrapolated: str = ''
    conventions: str = ''


@dataclass
class TensorStatistics:
    """Running RMS over all nine components of the raw (eq. 7) and written tensors of
    :func:`compensate_bag` (``batch``'s figures).

    Attributes
    ----------
    n_sets : int
        Sets added.
    raw_square_sum, square_sum : float
        Sums of the squared components, (T/m)^2, of the raw and of the written tensors.
    """

    n_sets: int = 0
    raw_square_sum: float = 0.0
    square_sum: float = 0.0

    def add(self, raw: FloatArray, tensors: FloatArray) -> None:
        """Add a chunk: raw and written tensors, each (n, 3, 3) T/m."""
        self.n_sets += len(raw)
        self.raw_square_sum += float(np.sum(np.square(raw)))
        self.square_sum += float(np.sum(np.square(tensors)))

    @property
    def raw_rms(self) -> float:
        """RMS of the raw tensor's components, T/m (NaN before any set)."""
        return float(np.sqrt(self.raw_square_sum / (9 * self.n_sets))) if self.n_sets else np.nan

    @property
    def rms(self) -> float:
        """RMS of the written tensor's components, T/m (NaN before any set)."""
        return float(np.sqrt(self.square_sum / (9 * self.n_sets))) if self.n_sets else np.nan


def format_rows(
    stamps_ns: IntArray,
    tensors_t_per_m: FloatArray,
    sigmas_t_per_m: FloatArray | None = None,
    extra_si: FloatArray | None = None,
) -> str:
    """CSV rows (with trailing newline) for stamps (n,) ns, tensors (n, 3, 3) T/m and,
    when given, their 1-sigma (n, 3, 3) T/m and more columns (n, m) (T or T/m: nT, nT/m)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps)
    # Sign and magnitude apart: divmod floors, so -1.5 s would print as -2.500000000.
    seconds, nanoseconds = np.divmod(np.abs(stamps), NS_PER_S)
    signs = np.where(stamps < 0, '-', '')
    columns = [tensors_t_per_m.reshape(n, 9)]
    if sigmas_t_per_m is not None:
        columns.append(sigmas_t_per_m.reshape(n, 9))
    if extra_si is not None:
        columns.append(extra_si.reshape(n, -1))
    values = np.concatenate(columns, axis=1) * NT_PER_T
    prefixes = [
        f'{sign}{s}.{ns:09d},'
        for sign, s, ns in zip(signs.tolist(), seconds.tolist(), nanoseconds.tolist(), strict=True)
    ]
    row = ','.join(['%.6f'] * values.shape[1]) + '\n'
    return ''.join(
        prefix + row % tuple(v) for prefix, v in zip(prefixes, values.tolist(), strict=True)
    )


def input_storage(bag: PathLike) -> str:
    """The storage of a rosbag2 folder: ``'mcap'`` or ``'sqlite3'``."""
    return 'mcap' if any(Path(bag).glob('*.mcap')) else 'sqlite3'


def check_outputs(
    csv: PathLike | None,
    out_bag: PathLike | None,
    *,
    force: bool = False,
    inputs: Iterable[PathLike] = (),
) -> None:
    """Refuse, before any work, outputs that are not ours to replace (or are one path)."""
    inputs = tuple(inputs)
    if csv is not None and out_bag is not None and Path(csv).resolve() == Path(out_bag).resolve():
        raise OutputError('--csv and --out-bag name the same path')
    if csv is not None:
        check_output(csv, CSV, force=force, inputs=inputs)
    if out_bag is not None:
        check_output(out_bag, BAG, force=force, inputs=inputs)


@dataclass(frozen=True)
class Compensation:
    """What :func:`compensate_bag` applies, from :func:`load_compensation`.

    Attributes
    ----------
    parameters : InterferenceParameters or None
        ``k``, ``b`` of eq. 19; None for the raw tensor (eq. 7).
    sigma : SigmaModel or None
        The 1-sigma of each written tensor; None: no sigma columns (noise unknown).
    sensor_noise_t : float or None
        The per-axis sensor noise behind ``sigma``, tesla.
    noise_source : str
        Where it came from (for the command's summary line), '' when None.
    with_covariance : bool
        ``sigma`` includes the calibration parameters' covariance.
    covariance : (P, P) ndarray or None
        That covariance (for the health monitor's calibration-error bound): of ``k``, ``b``
        only when the calibration has terms.
    forced : the checks the calibration was kept over (``--force``), each use says them
    calibration_id : the calibration's ``created_utc`` ('' for the raw tensor)
    """

    parameters: InterferenceParameters | None
    sigma: SigmaModel | None = None
    sensor_noise_t: float | None = None
    noise_source: str = ''
    with_covariance: bool = False
    covariance: np.ndarray | None = None
    forced: tuple[str, ...] = ()
    calibration_id: str = ''
    fitted: int | None = None  # the last fitted stamp, ns (learn_after_ns)


def health_recorder(
    geometry: TetraGeometry, compensation: Compensation, config: HealthConfig | None = None
) -> HealthRecorder | None:
    """The health monitor every compensation runs (None for the raw tensor or without a
    sensor noise: nothing to judge the compensated tensor against)."""
    if compensation.parameters is None or compensation.sensor_noise_t is None:
        return None
    return HealthRecorder(
        geometry,
        compensation.parameters,
        compensation.sensor_noise_t,
        compensation.covariance,
        config,
    )


def load_compensation(
    calibration_path: PathLike | None,
    geometry: TetraGeometry,
    *,
    target: str,
    sensor_noise_nt: float | None = None,
) -> Compensation:
    """The calibration file's ``k``, ``b`` (checked against ``geometry``) and the 1-sigma model.

    The sensor noise is ``sensor_noise_nt`` (nT per axis) when given, else the file's
    ``sensor_noise_T`` (the fit's estimate); the file's ``covariance``, when it has one, adds
    the calibration term. ``calibration_path`` None is the raw tensor: its sigma (noise only)
    needs ``sensor_noise_nt``, without it there is none.

    Raises
    ------
    CalibrationFileError
        The file is unreadable, or was made for other sensor positions than ``target``'s.
    InputError
        A calibration without a noise estimate (older files, ``constraint_lstsq``,
        ``paper_ga``) and no ``sensor_noise_nt``: the uncertainty could not be given.
    """
    override = None if sensor_noise_nt is None else float(sensor_noise_nt) * T_PER_NT
    if calibration_path is None:
        if override is None:
            return Compensation(None)
        sigma = SigmaModel.build(geometry, override)
        return Compensation(None, sigma, override, '--sensor-noise-nt')
    calibration = load_calibration(calibration_path)
    check_positions(calibration, geometry, source=str(calibration_path), target=target)
    noise = override if override is not None else calibration.sensor_noise_t
    if noise is None:
        raise InputError(
            f'{calibration_path} ({calibration.method}) has no sensor noise estimate '
            '(sensor_noise_T): give --sensor-noise-nt for the sigma columns'
        )
    sigma = SigmaModel.build(geometry, noise, calibration.parameters, calibration.covariance)
    source = '--sensor-noise-nt' if override is not None else f"{calibration_path}'s estimate"
    covariance = calibration.covariance
    if covariance is not None and calibration.parameters.terms:
        # The health monitor bounds the k, b part of the calibration error (the terms' part
        # is in the 1-sigma, not in its offsets' signatures): the general 36 block.
        covariance = covariance[:36, :36]
    return Compensation(
        calibration.parameters,
        sigma,
        noise,
        source,
        calibration.covariance is not None,
        covariance,
        calibration.forced_warnings(),
        calibration.created_utc,
        learn_after_ns(calibration.diagnostics),
    )


def compensate_bag(
    bag_path: PathLike,
    geometry: TetraGeometry,
    compensation: Compensation,
    *,
    health: HealthRecorder | None = None,
    tracking: TrackedStream | None = None,
    statistics: TensorStatistics | None = None,
    csv: PathLike | None = None,
    out_bag: PathLike | None = None,
    out_storage: str | None = None,
    timebase: TimeBase = DEFAULT_TIMEBASE,
    fast: bool = True,
    progress: bool | None = None,
    force: bool = False,
    inputs: Iterable[PathLike] = (),
    allow_missing_channels: bool = False,
    earth_field_t: float | None = None,
) -> CompensationCounts:
    """Stream the bag's matched sets into the CSV ``csv`` and/or the new bag ``out_bag``.

    Parameters
    ----------
    bag_path : path of the rosbag2 folder to read
    geometry : TetraGeometry of the array that recorded the bag
    compensation : its ``parameters`` (``k``, ``b`` of eq. 19 and the terms, their channels read
        from the bag, a set where one is unknown dropped and counted; None writes the raw
        tensor, eq. 7), ``sigma`` (the CSV's nine ``sigma_`` columns) and ``calibration_id``
    health, statistics : optional; fed every chunk of compensated (and raw) tensors
    tracking : optional; the tracked calibration's tensors, sigma, ``db_*`` CSV columns
    csv, out_bag, out_storage : outputs (one at least, each written atomically); the bag's
        storage (default: the input's)
    timebase : how the streams become sets (default: resampled to sensor 1's stamps);
        ``fast`` False decodes with rosbags and matches message by message (same result)
    progress : tqdm bar on stderr (None: only on a terminal and for long bags)
    force, inputs : as for :func:`~tetra_gradiometer.io.outputs.atomic_output`
    allow_missing_channels : a channel the terms read that the bag lacks is not refused: its
        terms are held (:class:`.terms.HeldTerms`; the CSV's first line and the counts'
        ``held_summary`` say so)
    earth_field_t : |B| of the Earth field, T, for the streams' check (core/streams)

    Raises
    ------
    BagError : the bag breaks the data contract, every set has a non-finite reading, or a
        channel the terms read is not in the bag (unless ``allow_missing_channels``)
    OutputError : an output is not ours to replace
    """
    parameters, sigma = compensation.parameters, compensation.sigma
    inputs, topic = tuple(inputs), RAW_TOPIC if parameters is None else COMPENSATED_TOPIC
    n_sets, first, last, dropped, sample = 0, 0, 0, DroppedSets(), TensorSample()
    monitor = health if tracking is None or tracking.health is None else None  # else it feeds
    with ExitStack() as stack:
        bag = stack.enter_context(MagneticBag(bag_path))
        bag.check_contract()
        terms = _stream_regressors(parameters, bag, bag_path, geometry, allow_missing_channels)
        handle, writer = _open_outputs(
            stack, bag_path, csv, out_bag, out_storage, (sigma, tracking, terms), force, inputs
        )
        sets = bag.iter_sets(
            timebase=timebase, progress=progress, fast=fast, earth_field_t=earth_field_t
        )
        for stamps, fields in sets:
            stamps, fields = _drop_implausible(stamps, fields, dropped)
            stamps, fields, x = _with_regressors(terms, stamps, fields)
            if not len(stamps):
                continue
            raw, tensors = _tensors(fields, geometry, parameters, x)
            sigmas = _sigmas(sigma, fields, x, terms)
            tensors, sigmas, offsets = _tracked(tracking, stamps, fields, tensors, sigmas, bag)
            chunk = (stamps, tensors, sigmas, offsets, fields[:, 0])
            _write(handle, writer, topic, chunk, compensation.calibration_id)
            _feed(monitor, statistics, stamps, fields, raw, tensors, bag.reader.start_time)
            sample.add(tensors)
            first, last = int(stamps[0]) if n_sets == 0 else first, int(stamps[-1])
            n_sets += len(stamps)
        _close_read(n_sets, bag_path, dropped, bag, writer)
    # The raw tensor holds the vehicle's interference, not a gradient: not self-checked.
    counts = _counts(n_sets, dropped, (last - first) * S_PER_NS, topic, bag, terms)
    checked = '' if parameters is None else sample.conventions_text(geometry.positions)
    return dataclasses.replace(counts, conventions=checked)


def _counts(
    n_sets: int,
    dropped: DroppedSets,
    span_s: float,
    topic: str,
    bag: MagneticBag,
    terms: StreamRegressors | None,
) -> CompensationCounts:
    """:func:`compensate_bag`'s counts, from the closed bag and the terms' stream."""
    skipped = bag.skipped_messages, bag.skipped_summary()
    if terms is None:
        return CompensationCounts(
            n_sets, dropped, span_s, topic, bag.counters, bag.clocks, *skipped
        )
    return CompensationCounts(
        n_sets,
        dropped,
        span_s,
        topic,
        bag.counters,
        bag.clocks,
        *skipped,
        sum(terms.unknown.values()),
        terms.text(),
        '' if terms.held is None else terms.held.text(),
        terms.ranges.text(),
    )


def _sigmas(
    sigma: SigmaModel | None,
    fields: FloatArray,
    regressors: FloatArray | None,
    terms: StreamRegressors | None,
) -> FloatArray | None:
    """The chunk's 1-sigma (n, 3, 3) T/m, widened in quadrature by the held terms' spread
    (None without a sigma model)."""
    if sigma is None:
        return None
    sigmas, held = sigma(fields[:, 0, :], regressors), None if terms is None else terms.held
    return sigmas if held is None else np.sqrt(sigmas**2 + held.sigma_t_per_m**2)


def _close_read(
    n_sets: int,
    bag_path: PathLike,
    dropped: DroppedSets,
    bag: MagneticBag,
    writer: BagWriter | None,
) -> None:
    """BagError when no set was written (every matched set had an implausible reading); else
    the streams' faults into the output bag's metadata (``custom_data``)."""
    if n_sets == 0:
        raise BagError(
            f'{Path(bag_path)}: every matched set has an implausible reading ({dropped.text()})'
        )
    if writer is not None and bag.streams.faults:
        writer.set_custom_data(
            'tetra_gradiometer.stream_faults', json.dumps(bag.streams.as_dict())
        )


def _feed(
    health: HealthRecorder | None,
    statistics: TensorStatistics | None,
    stamps: IntArray,
    fields: FloatArray,
    raw: FloatArray,
    tensors: FloatArray,
    bag_start_ns: int,
) -> None:
    """The chunk to the health monitor and the running statistics, when asked for."""
    if health is not None:
        health.add(stamps, fields, tensors, bag_start_ns=bag_start_ns)
    if statistics is not None:
        statistics.add(raw, tensors)


def _stream_regressors(
    parameters: InterferenceParameters | None,
    bag: MagneticBag,
    bag_path: PathLike,
    geometry: TetraGeometry,
    allow_missing_channels: bool,
) -> StreamRegressors | None:
    """The terms' regressors over the bag (None without terms); an absent channel's terms
    held with ``allow_missing_channels``."""
    if parameters is None or not parameters.terms:
        return None
    return StreamRegressors(
        parameters.terms, bag, bag_path, geometry if allow_missing_channels else None
    )


def _with_regressors(
    terms: StreamRegressors | None, stamps: IntArray, fields: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray | None]:
    """The sets whose terms' regressors are known, with them (all sets, None: no terms)."""
    if terms is None or not len(stamps):
        return stamps, fields, None
    x = terms(stamps, fields)
    known = np.all(np.isfinite(x), axis=1)
    return stamps[known], fields[known], x[known]


def _tracked(
    tracking: TrackedStream | None,
    stamps: IntArray,
    fields: FloatArray,
    tensors: FloatArray,
    sigmas: FloatArray | None,
    bag: MagneticBag,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """The chunk tracked: its tensors, 1-sigma and the change removed (n, 9) T (None untracked)."""
    if tracking is None:
        return tensors, sigmas, None
    return tracking.apply(stamps, fields, tensors, sigmas, bag.reader.start_time)


def _open_outputs(
    stack: ExitStack,
    bag_path: PathLike,
    csv: PathLike | None,
    out_bag: PathLike | None,
    out_storage: str | None,
    content: tuple[SigmaModel | None, TrackedStream | None, StreamRegressors | None],
    force: bool,
    inputs: tuple[PathLike, ...],
) -> tuple[TextIO | None, BagWriter | None]:
    """The CSV (a held channel's comment and the header written: the sigma columns with a
    sigma model, the tracker's with a tracker) and the bag writer, each None when not asked
    for; both closed (and moved into place) by ``stack``."""
    sigma, tracking, terms = content
    held = None if terms is None else terms.held
    comment = '' if held is None else f'# {held.text()}\n'
    columns = '' if tracking is None else tracking.csv_columns
    with_sigma = sigma is not None
    handle = writer = None
    if csv is not None:
        tmp = stack.enter_context(atomic_output(csv, CSV, force=force, inputs=inputs))
        handle = stack.enter_context(open(tmp, 'w', encoding='ascii', newline='\n'))
        handle.write(comment + (CSV_SIGMA_HEADER if with_sigma else CSV_HEADER) + columns + '\n')
    if out_bag is not None:
        storage = out_storage or input_storage(bag_path)
        writer = stack.enter_context(
            BagWriter(out_bag, storage=storage, force=force, inputs=inputs, command='compensate')
        )
    return handle, writer


def _drop_implausible(
    stamps: IntArray, fields: FloatArray, dropped: DroppedSets
) -> tuple[IntArray, FloatArray]:
    """The sets whose four readings are plausible; the others are counted into ``dropped``."""
    keep, chunk_dropped = plausible_sets(fields)
    if not chunk_dropped.total:
        return stamps, fields
    dropped.add(chunk_dropped)
    return stamps[keep], fields[keep]


def _tensors(
    fields: FloatArray,
    geometry: TetraGeometry,
    parameters: InterferenceParameters | None,
    regressors: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The raw tensor (eq. 7) and the one written: compensated (eq. 19, with the terms'
    ``regressors``), or the raw one."""
    raw = difference_tensor(fields, geometry)
    if parameters is None:
        return raw, raw
    return raw, compensate(raw, fields[:, 0, :], parameters, geometry, regressors)


def _write(
    handle: TextIO | None,
    writer: BagWriter | None,
    topic: str,
    chunk: tuple[IntArray, FloatArray, FloatArray | None, FloatArray | None, FloatArray],
    calibration: str,
) -> None:
    """A chunk (stamps, tensors, sigma, the tracker's offsets, ``B_1'``) to CSV and bag."""
    stamps, tensors, sigmas, offsets, refs = chunk
    if handle is not None:
        handle.write(format_rows(stamps, tensors, sigmas, offsets))
    if writer is not None:  # RAW on the raw topic, else COMPENSATED by ``calibration``
        values = gt.pack_sets(tensors, sigmas, refs)
        state = gt.RAW if topic == RAW_TOPIC else gt.COMPENSATED
        writer.write_tensors(topic, stamps, values, state, calibration)
