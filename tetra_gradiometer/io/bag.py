"""rosbag2 files (sqlite3 or mcap) following the data contract, via the rosbags library.

Reading streams: :meth:`MagneticBag.iter_sets` yields matched sample sets in chunks, so
memory stays bounded however long the bag. Writing goes to a private temporary folder moved
into place on success, and never replaces anything but a previous bag of ours
(:func:`~tetra_gradiometer.io.outputs.atomic_output`).

Fast paths (the generic ones stay, and a test checks both agree):

* ``sensor_msgs/MagneticField`` is decoded straight from its CDR bytes with numpy
  (:func:`~.bag_decode.decode_checked`): encapsulation header, ``int32 sec``, ``uint32 nanosec``,
  ``frame_id`` (uint32 length incl. NUL, bytes), padding to 8 (counted from the end of the
  4-byte encapsulation header), 3 float64, 9 float64 covariance. Little- and big-endian
  plain CDR (XCDR1) are handled, as by rosbags' deserializer.
* The channels of :meth:`MagneticBag.read_series` (temperature, currents, the ``/odom`` pose)
  are unpacked from their CDR bytes too (:func:`~.bag_decode.decode_channel`).
* Sets are formed a batch at a time by :class:`~tetra_gradiometer.core.timebase.Resampler`
  (the default: each sensor resampled to sensor 1's stamps, vectorised), or, with
  ``TimeBase(sync='nearest')``, by pairing stamps: when the next stamps of the four sensors
  are identical and increasing (a synchronised driver), the batch is emitted with array
  operations; otherwise it goes message by message through
  :class:`~tetra_gradiometer.io.matching.StampMatcher`.
* :meth:`BagWriter.write_fields` and :meth:`BagWriter.write_tensors` encode MagneticField
  and GradientTensor directly (``conversions.magnetic_field_cdr``,
  ``gradient_tensor.GradientTensorCdr``: the nodes' writers), byte-identical to rosbags'.

Damage: a message that does not decode (cut short, absurd frame_id length,
unknown encapsulation, header nanosec >= 1e9) and an unreadable storage chunk
(:mod:`.bag_skips`) are skipped and recorded in :attr:`MagneticBag.skipped`; a read fails
only when more than ``max_skipped_fraction`` (default 1 %) of a topic's messages are lost.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Generator, Iterable, Iterator, Mapping
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ..core.conventions import frame_id_hints
from ..core.streams import StreamChecker, StreamReport
from ..core.timebase import DEFAULT_TIMEBASE, ClockEstimate, ResampleCounters, TimeBase
from ..core.units import S_PER_NS
from ..errors import BagError, InputError
from . import conversions as cv
from . import gradient_tensor as gt
from . import interfaces
from .bag_decode import (  # noqa: F401  (decode_magnetic_field, _UnsupportedEncoding: re-exported)
    _UnsupportedEncoding,
    checked_stamp_ns,
    decode_channel,
    decode_checked,
    decode_magnetic_field,
    skip_reason,
)
from .bag_skips import MAX_SKIPPED_FRACTION, SkippedMessage, guarded_messages, summary
from .matching import MatchCounters, set_former
from .outputs import BAG, atomic_output, check_output
from .progress import progress_bar
from .topics import BagSource, checked_remap, namespaced

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: What formed the sets counted: stamp pairing or resampling (both have ``sets``, ``text()``
#: and ``as_dict()``).
SetCounters = MatchCounters | ResampleCounters

STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}
#: Sensors whose message rates differ by more than this factor are resampled to a grid at
#: the slowest one's rate (the default time base only).
MIXED_RATES = 1.8
#: The rates are told from each sensor's first this many messages.
RATE_MESSAGES = 64


def typestore() -> Any:
    """The ROS 2 Jazzy typestore, with our interfaces when found (:mod:`.interfaces`)."""
    return interfaces.register(get_typestore(Stores.ROS2_JAZZY), missing_ok=True)


@dataclass(frozen=True)
class Series:
    """An optional topic read whole: ``stamps_ns`` (n,), ``values`` (n, k)."""

    stamps_ns: np.ndarray
    values: np.ndarray


class MagneticBag:
    """Reader of a recorded run. Use as a context manager.

    Parameters
    ----------
    path : path of the rosbag2 folder, or a :class:`~.topics.BagSource` (the folder and the
        topic names the user gave for it: checked against the bag)
    max_skipped_fraction : largest fraction of a topic's messages (the magnetometers
        together in :meth:`iter_sets`) that may be skipped as undecodable or unreadable
        before a read raises :class:`BagError`; default 0.01 (1 %)
    remap : the bag's topic -> the contract's (``conversions.parse_remap``), for a bag recorded
        under other names (e.g. a vehicle namespace: ``/auv1/tetra/mag1`` -> ``/tetra/mag1``);
        every name in it must be recorded. Without either, a contract topic recorded only
        under another namespace is read from there (``topics.namespaced``).

    Attributes
    ----------
    skipped : list of SkippedMessage
        What the reads so far skipped (each message or chunk once), in reading order.
    counters : MatchCounters or ResampleCounters
        The set former's counts of the last :meth:`iter_sets` (``text()``, ``as_dict()``).
    clocks : tuple of ClockEstimate, or None
        Each sensor's clock offset, jitter and rate against the reference instants, from the
        last :meth:`iter_sets` (None when pairing stamps).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        max_skipped_fraction: float = MAX_SKIPPED_FRACTION,
        remap: Mapping[str, str] | None = None,
    ) -> None:
        self.path_given = path
        self.path = Path(path)
        self.remap = dict(remap or {})
        self.assumed: dict[str, str] = {}
        self.rates_note = ''
        self.frames_note: str | None = None  # the magnetometers' frame_ids, once read
        self.unread: dict[str, str] = {}  # optional topics of another type: why not read
        if not self.path.exists():
            raise BagError(f'bag not found: {self.path}')
        if not 0.0 <= max_skipped_fraction <= 1.0:
            raise InputError(
                f'max_skipped_fraction must lie in [0, 1], got {max_skipped_fraction}'
            )
        self.max_skipped_fraction = max_skipped_fraction
        self._reader: AnyReader | None = None
        self.counters: SetCounters = MatchCounters()
        self.streams = StreamReport()
        self.clocks: tuple[ClockEstimate, ...] | None = None
        self.skipped: list[SkippedMessage] = []
        self._seen: set[SkippedMessage] = set()

    def __enter__(self) -> MagneticBag:
        try:
            self._reader = AnyReader([self.path], default_typestore=typestore())
            self._reader.open()
        except Exception as error:  # rosbags raises its own error classes per storage
            raise BagError(f'cannot open bag {self.path}: {error}') from None
        recorded = {c.topic: c.msgtype for c in self.reader.connections}
        if isinstance(self.path_given, BagSource) and self.path_given.names_topics:
            self.remap = self.path_given.remap(recorded)
        elif self.remap:
            self.remap = checked_remap(self.path, self.remap, recorded)
        else:
            self.remap = self.assumed = namespaced(recorded)
        return self

    def _for_rates(self, timebase: TimeBase) -> TimeBase:
        """The default time base, or with sensors at rates more than :data:`MIXED_RATES`
        apart a grid at the slowest one's rate (sets at the fastest sensor's stamps would
        interpolate the slow ones between samples far apart, a misfit no model explains);
        :attr:`rates_note` says so. A time base asked for is kept. The magnetometers'
        frame_ids are read here too, once (:attr:`frames_note`)."""
        if self.frames_note is None:
            self.frames_note = frame_id_hints(self._frame_ids())
        if timebase != DEFAULT_TIMEBASE:
            return timebase
        rates = self._rates()
        if rates is None or rates.max() <= MIXED_RATES * rates.min():
            return timebase
        slowest = float(f'{rates.min():.3g}')
        self.rates_note = (
            'sensors at different rates ('
            + ', '.join(f'{i + 1}: {r:.3g} Hz' for i, r in enumerate(rates))
            + f"): resampled to a {slowest:g} Hz grid, the slowest sensor's rate"
        )
        return dataclasses.replace(timebase, reference_rate_hz=slowest)

    def _rates(self) -> np.ndarray | None:
        """Each magnetometer's rate, Hz, from the median interval of its first log times
        (not its count over the bag: a sensor that stops halfway is no slower), or None when
        a sensor has too few messages to tell."""
        connections = [c for t in cv.BAG_MAG_TOPICS for c in self._connections(t)]
        sensor = {c.id: cv.BAG_MAG_TOPICS.index(self.topic_of(c.topic)) for c in connections}
        times: list[list[int]] = [[] for _ in range(4)]
        for read, (connection, t, _) in enumerate(self.reader.messages(connections)):
            times[sensor[connection.id]].append(t)
            if min(len(ts) for ts in times) > RATE_MESSAGES or read > 40 * RATE_MESSAGES:
                break
        if min(len(ts) for ts in times) < 3:
            return None
        periods = np.array([np.median(np.diff(ts)) for ts in times]) * S_PER_NS
        return None if not np.all(periods > 0) else 1.0 / periods

    def _frame_ids(self) -> list[str]:
        """Each magnetometer's ``frame_id``, from its first message that decodes, or ''."""
        frames = [''] * 4
        for sensor, topic in enumerate(cv.BAG_MAG_TOPICS):
            for connection, _, raw in self.reader.messages(self._connections(topic)):
                with contextlib.suppress(Exception):  # a damaged message: the read counts it
                    msg: Any = self.reader.deserialize(raw, connection.msgtype)
                    frames[sensor] = str(msg.header.frame_id)
                    break
        return frames

    def assumed_text(self) -> str:
        """'' or the line saying which recorded topics were read as the contract's."""
        if not self.assumed:
            return ''
        pairs = ', '.join(f'{recorded} as {topic}' for recorded, topic in self.assumed.items())
        return f'topics read under another namespace: {pairs}'

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def reader(self) -> AnyReader:
        if self._reader is None:
            raise RuntimeError('MagneticBag must be used inside "with"')
        return self._reader

    @property
    def skipped_messages(self) -> int:
        """Messages the reads so far skipped as undecodable or unreadable."""
        return sum(record.count for record in self.skipped)

    def skipped_summary(self) -> str:
        """The reader's line for the CLI ('' when nothing to say): the topics read under
        another namespace (:meth:`assumed_text`), then 'skipped 3 undecodable
        messages (/tetra/mag2 at log time 12.3 s: payload cut short; ...)', log times from
        the bag's start, at most three shown."""
        start = self._reader.start_time if self._reader is not None else 0
        lines = (
            self.assumed_text(),
            self.rates_note,
            self.frames_note or '',
            *self.unread.values(),
            summary(self.skipped, start),
        )
        return '; '.join(line for line in lines if line)

    def record_skip(self, record: SkippedMessage) -> int:
        """Record ``record`` (once); return the messages it loses."""
        if record not in self._seen:
            self._seen.add(record)
            self.skipped.append(record)
        return record.count

    def _check_skipped(self, lost: int, total: int, what: str) -> None:
        if total and lost > self.max_skipped_fraction * total:
            raise BagError(
                f'{self.path}: {lost} of {total} {what} messages skipped as undecodable or '
                f'unreadable ({lost / total:.2%}, more than max_skipped_fraction '
                f'{self.max_skipped_fraction:.2%}): {self.skipped_summary()}'
            )

    def topic_of(self, recorded: str) -> str:
        """The contract topic a recorded topic name stands for (``remap``)."""
        return self.remap.get(recorded, recorded)

    def _connections(self, topic: str) -> list:
        return [c for c in self.reader.connections if self.topic_of(c.topic) == topic]

    def has_topic(self, topic: str) -> bool:
        return bool(self._connections(topic))

    def topics(self) -> tuple[str, ...]:
        """Every (remapped) topic the bag records, sorted."""
        return tuple(sorted({self.topic_of(c.topic) for c in self.reader.connections}))

    def topics_of_type(self, msgtype: str) -> tuple[str, ...]:
        """The (remapped) topics whose messages are of ``msgtype``, sorted."""
        return tuple(
            sorted(
                {self.topic_of(c.topic) for c in self.reader.connections if c.msgtype == msgtype}
            )
        )

    def check_contract(self) -> int:
        """Raise :class:`BagError` for a missing magnetometer topic or an empty bag; return
        the number of magnetometer messages."""
        missing = [t for t in cv.BAG_MAG_TOPICS if not self.has_topic(t)]
        if missing:
            present = sorted({c.topic for c in self.reader.connections})
            hint = f'; remapped: {self.remap}' if self.remap else ' (a topic map: remap)'
            raise BagError(f'{self.path}: missing topic(s) {missing} (present: {present}){hint}')
        for topic in cv.BAG_MAG_TOPICS:
            wrong = [c.msgtype for c in self._connections(topic) if c.msgtype != cv.MAGNETIC_FIELD]
            if wrong:
                raise BagError(
                    f'{self.path}: {topic} has type {wrong[0]}, expected {cv.MAGNETIC_FIELD}'
                )
        count = sum(c.msgcount for t in cv.BAG_MAG_TOPICS for c in self._connections(t))
        if count == 0:
            raise BagError(f'{self.path}: the magnetometer topics hold no messages (empty bag)')
        return count

    def iter_sets(
        self,
        *,
        timebase: TimeBase = DEFAULT_TIMEBASE,
        chunk_size: int = 20_000,
        window_s: tuple[float, float] | None = None,
        progress: bool | None = None,
        fast: bool = True,
        earth_field_t: float | None = None,
    ) -> Generator[tuple[IntArray, FloatArray], None, None]:
        """Sample sets in chunks: ``(stamps_ns (n,) int64, fields (n, 4, 3) tesla)``, formed
        as ``timebase`` says (default: resampled to sensor 1's stamps).

        ``window_s`` keeps sets whose stamp, in seconds from the first set's stamp, lies in
        ``[t0, t1]``. The streams are checked before sets are formed (core/streams.py;
        ``earth_field_t``: the expected ``|B|``, T). After the loop, ``self.counters`` holds the
        set former's counts (``.streams``: the streams' faults), ``self.clocks`` the clocks.
        ``fast=False``: the generic path (rosbags, message by message), the same sets. An
        undecodable message or unreadable chunk is skipped and recorded in :attr:`skipped`.

        Raises BagError: the contract broken (:meth:`check_contract`), no set formed, more than
        ``max_skipped_fraction`` of the magnetometer messages skipped, or a stream that cannot
        be used (``StreamError``: zero stamps, another epoch, a unit).
        """
        total = self.check_contract()
        if chunk_size < 1:
            raise InputError(f'chunk_size must be >= 1, got {chunk_size}')
        timebase = self._for_rates(timebase)
        form = set_former(timebase)
        self.counters, self.clocks = form.counters, None
        checker = StreamChecker(earth_field_t, str(self.path), timebase.reference_rate_hz)
        index = {
            c.id: cv.BAG_MAG_TOPICS.index(self.topic_of(c.topic))
            for c in self.reader.connections
            if self.topic_of(c.topic) in cv.BAG_MAG_TOPICS
        }
        connections = [c for c in self.reader.connections if c.id in index]
        first: list[int] = []
        bar = progress_bar(total, progress, 'reading magnetometers')
        raws: list[list[tuple[Any, int, bytes]]] = [[] for _ in range(4)]
        count = 0
        lost = [0]  # magnetometer messages skipped in this read

        def on_skip(record: SkippedMessage) -> None:
            n = self.record_skip(record)  # recorded whatever the topic ('': a storage range)
            lost[0] += n if self.topic_of(record.topic) in cv.BAG_MAG_TOPICS else 0

        def flush(final: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
            batches = self._checked(raws, fast, on_skip, checker, final)
            raws[:] = [[] for _ in range(4)]
            self._check_skipped(lost[0], total, 'magnetometer')
            stamps, fields = form.add(batches, final=final, fast=fast)  # final: form.finish()
            if len(stamps) and not first:
                first.append(int(stamps[0]))
            if window_s is not None and len(stamps):
                t = (stamps - first[0]) * S_PER_NS
                keep = (t >= window_s[0]) & (t <= window_s[1])
                stamps, fields = stamps[keep], fields[keep]
            for start in range(0, len(stamps), chunk_size):
                yield stamps[start : start + chunk_size], fields[start : start + chunk_size]

        try:
            for item in guarded_messages(self.reader, connections, on_skip):
                raws[index[item[0].id]].append(item)
                count += 1
                if count >= 4 * chunk_size:
                    bar.update(count)
                    count = 0
                    yield from flush(final=False)
            bar.update(count)
            yield from flush(final=True)
        finally:  # also when the caller stops early (generator closed)
            bar.close()
            self.clocks = form.clocks()
            self.streams = form.counters.streams = checker.finish()
        if form.counters.sets == 0:
            raise BagError(
                f'{self.path}: no sample set could be formed ({timebase.text}): '
                f'{form.counters.text()}'
            )

    def _checked(
        self,
        raws: list[list[tuple[Any, int, bytes]]],
        fast: bool,
        on_skip: Callable[[SkippedMessage], None],
        checker: StreamChecker,
        final: bool,
    ) -> list[tuple[IntArray, FloatArray]]:
        """Each sensor's items decoded and checked (core/streams): ``(stamps, fields)``."""
        decoded = [self._decode(raws[sensor], fast, on_skip) for sensor in range(4)]
        stamps, fields, logs = (list(c) for c in zip(*decoded, strict=True))
        return list(zip(*checker.check(stamps, fields, logs, final=final), strict=True))

    def _decode(
        self,
        items: list[tuple[Any, int, bytes]],
        fast: bool,
        on_skip: Callable[[SkippedMessage], None],
    ) -> tuple[IntArray, FloatArray, IntArray]:
        """One sensor's ``(connection, log_ns, raw)`` items -> stamps, fields, log times;
        the malformed ones go to ``on_skip``."""
        _, logs, raws = zip(*items, strict=True) if items else ((), (), ())  # one pass, in C
        if fast:
            stamps, values, bad = decode_checked(list(raws))
        else:
            stamps, values, bad = self._deserialize(items)
        good = np.ones(len(items), bool)
        for i, reason in bad:
            on_skip(SkippedMessage(items[i][0].topic, items[i][1], reason))
            good[i] = False
        return stamps, values, np.array(logs, dtype=np.int64).reshape(-1)[good]

    def _deserialize(
        self, items: list[tuple[Any, int, bytes]]
    ) -> tuple[IntArray, FloatArray, list[tuple[int, str]]]:
        """As :func:`decode_checked` for ``(connection, log_ns, raw)`` items, through rosbags."""
        stamps, values, bad = [], [], []
        for i, (connection, _, raw) in enumerate(items):
            try:
                msg: Any = self.reader.deserialize(raw, connection.msgtype)
                stamp = checked_stamp_ns(msg.header.stamp)
                value = cv.magnetic_field_vector(msg)
            except Exception as error:  # rosbags' SerdeError, or whatever garbage raises
                bad.append((i, skip_reason(error)))
                continue
            stamps.append(stamp)
            values.append(value)
        return (
            np.array(stamps, dtype=np.int64),
            np.array(values, dtype=float).reshape(-1, 3),
            bad,
        )

    def read_sets(self, **options: Any) -> tuple[np.ndarray, np.ndarray]:
        """All matched sets at once (see :meth:`iter_sets` for the options)."""
        chunks = list(self.iter_sets(**options))
        return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])

    def read_series(self, topic: str) -> Series | None:
        """``/odom`` (the pose: ``conversions.odometry_pose``), ``/tetra/temperature`` (degC) or
        a BatteryState topic (``/battery_state``, a thruster's: current, A) by header stamp;
        None when the topic is absent, or of another type (an optional channel: skipped, and
        :attr:`unread` says so)."""
        connections = self._connections(topic)
        if not connections:
            return None
        extract = {
            cv.ODOMETRY: cv.odometry_pose,
            cv.TEMPERATURE: lambda m: np.array([m.temperature]),
            cv.BATTERY_STATE: lambda m: np.array([m.current]),
        }.get(connections[0].msgtype)
        if extract is None:
            expected = {cv.ODOM_TOPIC: cv.ODOMETRY, cv.TEMPERATURE_TOPIC: cv.TEMPERATURE}
            self.unread[topic] = (
                f'{topic} holds {connections[0].msgtype}, not '
                f'{expected.get(topic, cv.BATTERY_STATE)}: not read'
            )
            return None
        stamps: list[int] = []
        values: list[Any] = []  # tuples (fast) or arrays (rosbags), rows of one length
        lost = [0]

        def on_skip(record: SkippedMessage) -> None:
            n = self.record_skip(record)
            lost[0] += n if self.topic_of(record.topic) == topic else 0

        for connection, log_ns, raw in guarded_messages(self.reader, connections, on_skip):
            try:  # every type of ``extract`` has a bag_decode.CHANNEL_LAYOUTS entry
                try:
                    stamp, decoded = decode_channel(raw, connection.msgtype)
                    stamps.append(stamp)
                    values.append(decoded)
                    continue
                except _UnsupportedEncoding:
                    pass  # rosbags' deserializer names the fault below
                msg: Any = self.reader.deserialize(raw, connection.msgtype)
                stamp = checked_stamp_ns(msg.header.stamp)
                value = extract(msg)
            except Exception as error:  # as in _deserialize
                on_skip(SkippedMessage(topic, log_ns, skip_reason(error)))
                continue
            stamps.append(stamp)
            values.append(value)
        self._check_skipped(lost[0], sum(c.msgcount for c in connections), topic)
        if not stamps:
            return None
        order = np.argsort(stamps, kind='stable')
        return Series(
            np.asarray(stamps, dtype=np.int64)[order], np.asarray(values, dtype=float)[order]
        )


class BagWriter:
    """Write a rosbag2 folder atomically. Use as a context manager.

    Parameters
    ----------
    path : target folder; refused as :func:`~tetra_gradiometer.io.outputs.check_output`
        says (an existing folder is replaced only if it is a bag this package wrote, and
        only with ``force``)
    storage : 'sqlite3' or 'mcap'
    force : replace a previous bag written by this package
    inputs : the command's inputs (the bag may not be, contain or lie in one)
    command : the writing command, recorded in the folder's marker file
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        storage: str = 'sqlite3',
        force: bool = False,
        inputs: Iterable[str | os.PathLike] = (),
        command: str = '',
    ) -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        self.path = check_output(path, BAG, force=force, inputs=inputs)
        self.storage = storage
        self.store = typestore()
        self.types = cv.rosbags_types(self.store)
        self._connections: dict[str, Any] = {}
        self._force, self._inputs, self._command = force, tuple(inputs), command
        self._stack = ExitStack()

    def __enter__(self) -> BagWriter:
        with ExitStack() as stack:
            tmp = stack.enter_context(
                atomic_output(
                    self.path, BAG, force=self._force, inputs=self._inputs, command=self._command
                )
            )
            # The storage file is named after the folder, which carries its final name already.
            self._writer = Writer(tmp, version=9, storage_plugin=STORAGES[self.storage])
            self._writer.open()
            stack.callback(self._writer.close)  # runs before the folder is moved into place
            self._stack = stack.pop_all()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self._stack.__exit__(exc_type, exc, tb)

    def _connection(self, topic: str, msgtype: str) -> Any:
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msgtype, typestore=self.store)
            self._connections[topic] = connection
        elif connection.msgtype != msgtype:
            raise BagError(f'{topic} already carries {connection.msgtype}, not {msgtype}')
        return connection

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Write one message, logged at ``stamp_ns``."""
        connection = self._connection(topic, msg.__msgtype__)
        self._writer.write(
            connection, int(stamp_ns), self.store.serialize_cdr(msg, msg.__msgtype__)
        )

    def set_custom_data(self, key: str, value: str) -> None:
        """A key of the bag's ``metadata.yaml`` ``custom_data`` (rosbag2's free-form strings)."""
        self._writer.set_custom_data(key, value)

    def write_raw(self, topic: str, msgtype: str, data: bytes, stamp_ns: int) -> None:
        """Write one already serialized (CDR) message, logged at ``stamp_ns``."""
        self._writer.write(self._connection(topic, msgtype), int(stamp_ns), data)

    def write_fields(self, stamps_ns: np.ndarray, fields: np.ndarray) -> None:
        """``/tetra/mag1..4`` from fields (N, 4, 3) tesla (CDR encoded directly)."""
        fields = np.asarray(fields, dtype=float)
        for stamp, sample in zip(stamps_ns, fields, strict=True):
            self.write_sample(int(stamp), sample)

    def write_sample(self, stamp_ns: int, sample: np.ndarray) -> None:
        """One set of ``/tetra/mag1..4`` at header and log stamp ``stamp_ns``, fields (4, 3) T."""
        for sensor, (topic, frame) in enumerate(
            zip(cv.BAG_MAG_TOPICS, cv.MAG_FRAMES, strict=True)
        ):
            data = cv.magnetic_field_cdr(sample[sensor], stamp_ns, frame)
            self.write_raw(topic, cv.MAGNETIC_FIELD, data, stamp_ns)

    def write_tensors(
        self, topic: str, stamps_ns: np.ndarray, values: np.ndarray, state: int, calibration: str
    ) -> None:
        """A GradientTensor topic from ``values`` (N, 30) (``gradient_tensor.pack_sets``) in
        ``state`` by ``calibration`` (its ``created_utc``; CDR encoded directly)."""
        cdr = gt.GradientTensorCdr(cv.ARRAY_FRAME)
        for t, row in zip(np.asarray(stamps_ns).tolist(), values, strict=True):
            self.write_raw(topic, gt.GRADIENT_TENSOR, cdr.write(t, row, state, calibration), t)
