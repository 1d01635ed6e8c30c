"""Compensating a bag: stream its matched sets into a tensor CSV and/or a tensor bag.

Each set is differenced into the tensor (eq. 7) and compensated (eq. 19) with the
calibration's ``k``, ``b``; without parameters the raw tensor is written.

CSV (written to a temporary file, renamed into place at the end)::

    stamp_s,gxx,gxy,gxz,gyx,gyy,gyz,gzx,gzy,gzz

one row per matched set (sets with an implausible reading, non-finite or ``|B| > 1e-3 T``,
are dropped and counted);
``stamp_s`` is the **absolute** header stamp of sensor 1 in seconds since the Unix epoch,
printed exactly from the integer nanoseconds (9 decimals); ``gij = G_ij = dB_i/dx_j`` in
**nT/m** (6 decimals), body frame.

The output bag holds ``/tetra/gradient/compensated`` (``/tetra/gradient/raw`` for the raw
tensor): ``sensor_msgs/JointState`` named ``gxx..gzz``, positions in T/m, header stamp = the
set's stamp (``conversions.tensor_msg``).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import numpy.typing as npt

from ..core import InterferenceParameters, TetraGeometry, compensate, difference_tensor
from ..core.plausibility import DroppedSets, plausible_sets
from ..core.units import NS_PER_S, NT_PER_T, S_PER_NS
from ..errors import BagError, OutputError
from . import conversions as cv
from .bag import BagWriter, MagneticBag
from .calibration import check_positions, load_calibration
from .matching import MatchCounters
from .outputs import BAG, CSV, atomic_output, check_output

__all__ = [
    'COMPENSATED_TOPIC',
    'CSV_HEADER',
    'RAW_TOPIC',
    'CompensationCounts',
    'calibration_parameters',
    'check_outputs',
    'compensate_bag',
    'format_rows',
    'input_storage',
]

CSV_HEADER = 'stamp_s,' + ','.join(cv.TENSOR_NAMES)
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
    counters : MatchCounters
        The stamp matcher's counts.
    skipped_messages : int
        Messages skipped as undecodable or unreadable (``MagneticBag.skipped``).
    skipped_summary : str
        The reader's line about them ('' when none).
    """

    n_sets: int
    dropped: DroppedSets
    span_s: float
    topic: str
    counters: MatchCounters
    skipped_messages: int = 0
    skipped_summary: str = ''


def format_rows(stamps_ns: IntArray, tensors_t_per_m: FloatArray) -> str:
    """CSV rows (with trailing newline) for stamps (n,) ns and tensors (n, 3, 3) T/m."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    # Sign and magnitude apart: divmod floors, so -1.5 s would print as -2.500000000.
    seconds, nanoseconds = np.divmod(np.abs(stamps), NS_PER_S)
    signs = np.where(stamps < 0, '-', '')
    values = tensors_t_per_m.reshape(len(stamps), 9) * NT_PER_T
    row = '%s%d.%09d,' + ','.join(['%.6f'] * 9)
    return ''.join(
        row % (sign, s, ns, *v) + '\n'
        for sign, s, ns, v in zip(
            signs.tolist(), seconds.tolist(), nanoseconds.tolist(), values.tolist(), strict=True
        )
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


def calibration_parameters(
    path: PathLike, geometry: TetraGeometry, *, target: str
) -> InterferenceParameters:
    """The ``k``, ``b`` of the calibration file ``path``, checked against ``geometry``.

    Raises
    ------
    CalibrationFileError
        The file is unreadable, or was made for other sensor positions than ``target``'s.
    """
    calibration = load_calibration(path)
    check_positions(calibration, geometry, source=str(path), target=target)
    return calibration.parameters


def compensate_bag(
    bag_path: PathLike,
    geometry: TetraGeometry,
    parameters: InterferenceParameters | None,
    *,
    csv: PathLike | None = None,
    out_bag: PathLike | None = None,
    out_storage: str | None = None,
    tolerance_s: float = 2e-3,
    fast: bool = True,
    progress: bool | None = None,
    force: bool = False,
    inputs: Iterable[PathLike] = (),
) -> CompensationCounts:
    """Stream the bag's matched sets into the CSV ``csv`` and/or the new bag ``out_bag``.

    Parameters
    ----------
    bag_path : path of the rosbag2 folder to read
    geometry : TetraGeometry
        The array that recorded the bag.
    parameters : InterferenceParameters or None
        ``k``, ``b`` of eq. 19; None writes the raw tensor (eq. 7).
    csv, out_bag : outputs (at least one), each written atomically
    out_storage : storage of ``out_bag`` (default: the input's)
    tolerance_s : largest spread of the four header stamps in one set, seconds
    fast : False decodes with rosbags and matches message by message (same result)
    progress : tqdm bar on stderr (None: only on a terminal and for long bags)
    force, inputs : as for :func:`~tetra_gradiometer.io.outputs.atomic_output`

    Raises
    ------
    BagError
        The bag breaks the data contract, or every set has a non-finite reading.
    OutputError
        An output is not ours to replace.
    """
    inputs = tuple(inputs)
    topic = RAW_TOPIC if parameters is None else COMPENSATED_TOPIC
    n_sets = 0
    dropped = DroppedSets()
    first = last = 0
    with ExitStack() as stack:
        bag = stack.enter_context(MagneticBag(bag_path))
        bag.check_contract()
        handle = writer = None
        if csv is not None:
            tmp = stack.enter_context(atomic_output(csv, CSV, force=force, inputs=inputs))
            handle = stack.enter_context(open(tmp, 'w', encoding='ascii', newline='\n'))
            handle.write(CSV_HEADER + '\n')
        if out_bag is not None:
            storage = out_storage or input_storage(bag_path)
            writer = stack.enter_context(
                BagWriter(
                    out_bag, storage=storage, force=force, inputs=inputs, command='compensate'
                )
            )
        sets = bag.iter_sets(tolerance_s=tolerance_s, progress=progress, fast=fast)
        for stamps, fields in sets:
            keep, chunk_dropped = plausible_sets(fields)
            if chunk_dropped.total:  # an implausible reading: drop the set, count it
                dropped.add(chunk_dropped)
                stamps, fields = stamps[keep], fields[keep]
                if not len(stamps):
                    continue
            tensors = _tensors(fields, geometry, parameters)
            _write(handle, writer, topic, stamps, tensors)
            first = int(stamps[0]) if n_sets == 0 else first
            last = int(stamps[-1])
            n_sets += len(stamps)
        if n_sets == 0:
            raise BagError(
                f'{Path(bag_path)}: every matched set has an implausible reading '
                f'({dropped.text()})'
            )
    span_s = (last - first) * S_PER_NS
    skipped = bag.skipped_messages, bag.skipped_summary()
    return CompensationCounts(n_sets, dropped, span_s, topic, bag.counters, *skipped)


def _tensors(
    fields: FloatArray, geometry: TetraGeometry, parameters: InterferenceParameters | None
) -> FloatArray:
    tensors = difference_tensor(fields, geometry)
    if parameters is not None:
        tensors = compensate(tensors, fields[:, 0, :], parameters, geometry)
    return tensors


def _write(
    handle: TextIO | None,
    writer: BagWriter | None,
    topic: str,
    stamps: IntArray,
    tensors: FloatArray,
) -> None:
    if handle is not None:
        handle.write(format_rows(stamps, tensors))
    if writer is not None:
        writer.write_tensors(topic, stamps, tensors)
