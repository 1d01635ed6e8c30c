"""rosbag2 files (sqlite3 or mcap) following the data contract, via the rosbags library.

Reading streams: :meth:`MagneticBag.iter_sets` yields matched sample sets in chunks, so
memory stays bounded however long the bag. Writing goes to a temporary folder renamed into
place on success (:func:`~tetra_gradiometer.io.atomic.atomic_output_path`).
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .. import conversions as cv
from ..matching import StampMatcher
from .atomic import atomic_output_path

STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}


class BagError(ValueError):
    """A bag is missing, empty, or does not follow the data contract."""


def typestore() -> Any:
    """The ROS 2 Jazzy typestore (message definitions for reading and writing)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class Series:
    """An optional topic read whole: ``stamps_ns`` (n,), ``values`` (n, k)."""

    stamps_ns: np.ndarray
    values: np.ndarray


class MagneticBag:
    """Reader of a recorded run. Use as a context manager.

    Parameters
    ----------
    path : path of the rosbag2 folder
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f'bag not found: {self.path}')
        self._reader: AnyReader | None = None
        self.counters = None

    def __enter__(self) -> MagneticBag:
        try:
            self._reader = AnyReader([self.path], default_typestore=typestore())
            self._reader.open()
        except Exception as error:  # rosbags raises its own error classes per storage
            raise BagError(f'cannot open bag {self.path}: {error}') from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    @property
    def reader(self) -> AnyReader:
        if self._reader is None:
            raise RuntimeError('MagneticBag must be used inside "with"')
        return self._reader

    def _connections(self, topic: str) -> list:
        return [c for c in self.reader.connections if c.topic == topic]

    def has_topic(self, topic: str) -> bool:
        return bool(self._connections(topic))

    def check_contract(self) -> int:
        """Raise :class:`BagError` for a missing magnetometer topic or an empty bag; return
        the number of magnetometer messages."""
        missing = [t for t in cv.BAG_MAG_TOPICS if not self.has_topic(t)]
        if missing:
            present = sorted({c.topic for c in self.reader.connections})
            raise BagError(f'{self.path}: missing topic(s) {missing} (present: {present})')
        for topic in cv.BAG_MAG_TOPICS:
            wrong = [c.msgtype for c in self._connections(topic) if c.msgtype != cv.MAGNETIC_FIELD]
            if wrong:
                raise BagError(f'{self.path}: {topic} has type {wrong[0]}, expected {cv.MAGNETIC_FIELD}')
        count = sum(c.msgcount for t in cv.BAG_MAG_TOPICS for c in self._connections(t))
        if count == 0:
            raise BagError(f'{self.path}: the magnetometer topics hold no messages (empty bag)')
        return count

    def iter_sets(self, *, tolerance_s: float = 2e-3, chunk_size: int = 20_000,
                  window_s: tuple[float, float] | None = None,
                  progress: bool | None = None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Matched sets in chunks: ``(stamps_ns (n,) int64, fields (n, 4, 3) tesla)``.

        ``window_s`` keeps sets whose stamp, in seconds from the first set's stamp, lies in
        ``[t0, t1]``. After the loop, ``self.counters`` holds the matcher's counts.

        Raises
        ------
        BagError
            Contract violations (see :meth:`check_contract`), or no set could be matched.
        """
        total = self.check_contract()
        matcher = StampMatcher(int(round(tolerance_s * 1e9)))
        self.counters = matcher.counters
        index = {c.id: cv.BAG_MAG_TOPICS.index(c.topic) for c in self.reader.connections
                 if c.topic in cv.BAG_MAG_TOPICS}
        connections = [c for c in self.reader.connections if c.id in index]
        stamps: list[int] = []
        fields: list[np.ndarray] = []
        first: int | None = None
        bar = _progress(total, progress, 'reading magnetometers')
        for connection, _, raw in self.reader.messages(connections=connections):
            msg = self.reader.deserialize(raw, connection.msgtype)
            bar.update()
            for stamp, values in matcher.add(index[connection.id], cv.stamp_to_ns(msg.header.stamp),
                                             cv.magnetic_field_vector(msg)):
                first = stamp if first is None else first
                if window_s is not None and not window_s[0] <= (stamp - first) * 1e-9 <= window_s[1]:
                    continue
                stamps.append(stamp)
                fields.append(values)
                if len(stamps) >= chunk_size:
                    yield np.array(stamps, dtype=np.int64), np.array(fields)
                    stamps, fields = [], []
        bar.close()
        if stamps:
            yield np.array(stamps, dtype=np.int64), np.array(fields)
        if matcher.counters.matched == 0:
            raise BagError(f'{self.path}: no sample set could be matched by header stamp within '
                           f'{tolerance_s * 1e3:g} ms ({matcher.counters.dropped_messages} messages unmatched)')

    def read_sets(self, **options: Any) -> tuple[np.ndarray, np.ndarray]:
        """All matched sets at once (see :meth:`iter_sets` for the options)."""
        chunks = list(self.iter_sets(**options))
        return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])

    def read_series(self, topic: str) -> Series | None:
        """``/odom`` (orientation x, y, z, w), ``/tetra/temperature`` (degC) or
        ``/battery_state`` (current, A) by header stamp; None when the topic is absent."""
        connections = self._connections(topic)
        if not connections:
            return None
        extract = {cv.ODOMETRY: cv.odometry_orientation,
                   cv.TEMPERATURE: lambda m: np.array([m.temperature]),
                   cv.BATTERY_STATE: lambda m: np.array([m.current])}.get(connections[0].msgtype)
        if extract is None:
            raise BagError(f'{self.path}: {topic} has unsupported type {connections[0].msgtype}')
        stamps, values = [], []
        for connection, _, raw in self.reader.messages(connections=connections):
            msg = self.reader.deserialize(raw, connection.msgtype)
            stamps.append(cv.stamp_to_ns(msg.header.stamp))
            values.append(extract(msg))
        if not stamps:
            return None
        order = np.argsort(stamps, kind='stable')
        return Series(np.asarray(stamps, dtype=np.int64)[order], np.asarray(values, dtype=float)[order])


class BagWriter:
    """Write a rosbag2 folder atomically. Use as a context manager.

    Parameters
    ----------
    path : target folder (must not be inside another bag)
    storage : 'sqlite3' or 'mcap'
    """

    def __init__(self, path: str | os.PathLike, *, storage: str = 'sqlite3') -> None:
        if storage not in STORAGES:
            raise BagError(f'storage must be one of {sorted(STORAGES)}, got {storage!r}')
        self.path = Path(path)
        self.storage = storage
        self.store = typestore()
        self.types = cv.rosbags_types(self.store)
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        # The bag is written as <tmp>/<name> so its storage file carries the final name;
        # the folder <tmp> is then renamed into place.
        self._atomic = atomic_output_path(self.path)
        self._tmp = self._atomic.__enter__()
        self._tmp.mkdir()
        self._writer = Writer(self._tmp / self.path.name, version=9, storage_plugin=STORAGES[self.storage])
        self._writer.open()
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            self._writer.close()
            if exc_type is None:
                holder = self._tmp.with_name(self._tmp.name + '.holder')
                os.replace(self._tmp, holder)
                os.replace(holder / self.path.name, self._tmp)
                holder.rmdir()
        finally:
            self._atomic.__exit__(exc_type, exc, tb)

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Write one message, logged at ``stamp_ns``."""
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, msg.__msgtype__, typestore=self.store)
            self._connections[topic] = connection
        self._writer.write(connection, int(stamp_ns), self.store.serialize_cdr(msg, msg.__msgtype__))

    def write_fields(self, stamps_ns: np.ndarray, fields: np.ndarray) -> None:
        """``/tetra/mag1..4`` from fields (N, 4, 3) tesla."""
        for stamp, sample in zip(stamps_ns, fields):
            for sensor, (topic, frame) in enumerate(zip(cv.BAG_MAG_TOPICS, cv.MAG_FRAMES)):
                self.write(topic, cv.magnetic_field_msg(self.types, sample[sensor], int(stamp), frame), stamp)

    def write_tensors(self, topic: str, stamps_ns: np.ndarray, tensors: np.ndarray) -> None:
        """A tensor topic from tensors (N, 3, 3) T/m."""
        for stamp, g in zip(stamps_ns, tensors):
            self.write(topic, cv.tensor_msg(self.types, g, int(stamp)), stamp)


def _progress(total: int, enabled: bool | None, description: str) -> Any:
    """A tqdm bar on long input; silent when not a terminal unless asked for."""
    from tqdm import tqdm
    show = sys.stderr.isatty() if enabled is None else enabled
    return tqdm(total=total, desc=description, unit='msg', disable=not show or total < 50_000,
                mininterval=0.5, file=sys.stderr)
