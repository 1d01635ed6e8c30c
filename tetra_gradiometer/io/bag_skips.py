"""Reading a rosbag2 bag past its damage: a corrupt message or storage chunk costs that
message or chunk, not the run.

:func:`guarded_messages` yields ``(connection, log_ns, raw)`` like rosbags'
``AnyReader.messages`` and reports what it could not read as :class:`SkippedMessage`
records instead of raising:

* **MCAP** (indexed, the rosbag2 default): rosbags' ``McapReader.messages`` merges one
  generator per chunk (``storage_mcap.msgsrc``: a sentinel at the chunk's first log time,
  then the chunk read, checked and decompressed whole) with ``heapq.merge``; one bad chunk
  (CRC, decompression, record layout) raises through the merge and ends the run. We run
  the same merge over the same ``msgsrc`` generators, each wrapped so that a chunk that
  fails is recorded (per topic: its message count from the chunk index and its log-time
  range) and yields nothing; the other chunks go on in log-time order, and a chunk is still
  decompressed only when the merge reaches its start time (bounded memory).
* **sqlite3** (and MCAP without chunk index): rosbags' query ``ORDER BY timestamp`` is
  re-entered through the storage's documented ``messages(connections, start)`` after an
  error: first exactly where it stopped (``start`` = last log time, passing over the
  messages already yielded at that time); if that fails again without progress, from a
  start that doubles its distance past the damage (1 ns, 2 ns, 4 ns, ...), and the
  log-time range passed over is recorded. Rows whose content is malformed (NULL data or
  log time) reach the caller, whose per-message decode skips them.
* Message-compressed bags (rosbag2 ``compression_mode: message``): a message whose zstd
  frame does not decompress is skipped.

It relies on rosbags 0.11 internals (``Reader.storage.storages``, ``McapReader.chunks``,
``msgsrc``); if they are missing, it falls back to ``AnyReader.messages`` (no recovery:
a storage error then ends the read as before).
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ..core.units import S_PER_NS

#: Above this fraction of a topic's messages skipped, a read fails (:class:`BagError`).
MAX_SKIPPED_FRACTION = 0.01

#: Skipped records shown in :func:`summary`.
SHOWN = 3


@dataclass(frozen=True)
class SkippedMessage:
    """A message (or a run of them: a storage chunk) that could not be read.

    Attributes
    ----------
    topic : the message's topic ('' when the storage cannot tell)
    log_time_ns : its log time, ns (a chunk: its first log time; None when unknown)
    reason : short text, e.g. 'payload cut short'
    count : messages lost (1 for a message; a chunk's count on ``topic``, 0 if unknown)
    end_log_time_ns : a chunk's last log time, ns (None for a single message)
    """

    topic: str
    log_time_ns: int | None
    reason: str
    count: int = 1
    end_log_time_ns: int | None = None


def summary(skipped: Collection[SkippedMessage], start_ns: int, shown: int = SHOWN) -> str:
    """One line for the CLI: 'skipped N undecodable messages (TOPIC at log time T s: REASON;
    ...)', times relative to ``start_ns``, at most ``shown`` records; '' when nothing was
    skipped. A storage range of unknown size (sqlite3) is counted apart: '... and 1
    unreadable storage range'."""
    if not skipped:
        return ''
    total = sum(s.count for s in skipped)
    parts = []
    for s in list(skipped)[:shown]:
        where = s.topic or 'unknown topic'
        if s.count != 1:
            where += f' ({s.count} messages)' if s.count else ' (unknown number of messages)'
        if s.log_time_ns is None:
            when = 'unknown log time'
        else:
            when = f'log time {(s.log_time_ns - start_ns) * S_PER_NS:.3f} s'
            if s.end_log_time_ns is not None:
                when += f' to {(s.end_log_time_ns - start_ns) * S_PER_NS:.3f} s'
        parts.append(f'{where} at {when}: {s.reason}')
    more = f'; and {len(skipped) - shown} more' if len(skipped) > shown else ''
    noun = 'message' if total == 1 else 'messages'
    ranges = sum(1 for s in skipped if not s.count)
    head = f'skipped {total} undecodable {noun}'
    if ranges:
        head += f' and {ranges} unreadable storage range{"s" if ranges > 1 else ""}'
    return f'{head} ({"; ".join(parts)}{more})'


def guarded_messages(
    reader: Any, connections: Iterable[Any], on_skip: Callable[[SkippedMessage], None]
) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages(connections=...)`` of an open ``AnyReader`` over one rosbag2 folder,
    in log-time order per storage file, reporting unreadable storage to ``on_skip``."""
    connections = list(connections)
    try:
        (bag,) = reader.readers
        directory = bag.storage
        storages = list(directory.storages)
        per_message = directory.metadata.compression_mode == 'message'
    except (AttributeError, TypeError, ValueError):  # not rosbags 0.11's layout: no recovery
        yield from reader.messages(connections=connections)
        return
    end_ns = int(reader.end_time)
    for storage in storages:
        by_id = {
            s.id: c
            for s in storage.connections
            for c in connections
            if (c.topic, c.msgtype) == (s.topic, s.msgtype)
        }
        own = [s for s in storage.connections if s.id in by_id]
        if not own:
            continue
        if getattr(storage, 'chunks', None):
            source = _mcap_chunks(storage, own, on_skip)
        else:
            source = _resumed(storage, own, on_skip, end_ns)
        for own_connection, log_ns, data in source:
            connection = by_id[own_connection.id]
            if per_message:
                try:
                    data = _zstd_decompress(data)
                except Exception as error:
                    on_skip(SkippedMessage(connection.topic, log_ns, f'zstd frame: {error}'))
                    continue
            yield connection, log_ns, data


def _zstd_decompress(data: bytes) -> bytes:
    from rosbags.rosbag2.reader import zstd

    return bytes(zstd.decompress(data))


def _mcap_chunks(
    storage: Any, connections: list[Any], on_skip: Callable[[SkippedMessage], None]
) -> Iterator[tuple[Any, int, bytes]]:
    """``McapReader.messages`` with each chunk guarded (see the module docstring)."""
    from rosbags.rosbag2.storage_mcap import msgsrc

    channel_map = {c.id: c for c in connections}

    def guarded(chunk: Any) -> Iterator[Any]:
        source = msgsrc(
            chunk, channel_map, chunk.message_start_time, chunk.message_end_time + 1, storage.bio
        )
        yield next(source)  # the sentinel: the chunk is read when the merge reaches its start
        try:
            messages = list(source)  # msgsrc reads, checks and sorts the chunk before yielding
        except Exception as error:
            for cid, count in chunk.channel_count.items():
                if cid in channel_map:
                    on_skip(
                        SkippedMessage(
                            channel_map[cid].topic,
                            chunk.message_start_time,
                            f'unreadable storage chunk ({error})',
                            count,
                            chunk.message_end_time,
                        )
                    )
            return
        yield from messages

    sources = [
        guarded(chunk)
        for chunk in storage.chunks
        if any(chunk.channel_count.get(cid, 0) for cid in channel_map)
    ]
    for log_ns, offset, connection, data in heapq.merge(*sources):
        if offset:  # 0: a chunk's sentinel
            yield connection, log_ns, data


def _resumed(
    storage: Any,
    connections: list[Any],
    on_skip: Callable[[SkippedMessage], None],
    end_ns: int,
) -> Iterator[tuple[Any, int, bytes]]:
    """``storage.messages(connections, start)``, re-entered after an error (module docstring).

    The clean path costs nothing per message: ``row`` (the last row yielded) is the loop
    variable itself. A resume at ``start`` = its log time passes over the rows up to an
    equal one (same topic and bytes), so a row is yielded once (identical duplicates logged
    at the same time and read just before the damage could be yielded twice)."""
    row: Any = None  # the last row yielded
    start: int | None = None
    damage_from: int | None = None  # log time from which damage is being jumped over
    step = 1
    error: Exception | None = None
    while True:
        before = row
        rows = storage.messages(connections, start)
        try:
            if before is not None and damage_from is None:  # pass over what was yielded
                for candidate in rows:
                    if candidate[1] > before[1]:
                        row = candidate
                        yield row
                        break
                    if candidate[0].id == before[0].id and candidate[2] == before[2]:
                        break
            if damage_from is not None:
                for row in rows:  # the first row past the damage: record the range jumped
                    on_skip(_range_skip(damage_from, row[1], error))
                    damage_from, step = None, 1
                    yield row
                    break
            for row in rows:
                yield row
        except Exception as exc:
            error = exc
        else:
            if damage_from is not None:
                on_skip(_range_skip(damage_from, end_ns, error))
            return
        if row is not before:  # progress since the last attempt: resume right after `row`
            start = row[1]
            continue
        if damage_from is None:  # no progress: jump, doubling the distance each time
            damage_from = row[1] if row is not None else int(storage.metadata.start_time)
        start, step = damage_from + step, step * 2
        if start > end_ns:
            on_skip(_range_skip(damage_from, end_ns, error))
            return


def _range_skip(
    first_ns: int | None, end_ns: int | None, error: Exception | None
) -> SkippedMessage:
    return SkippedMessage('', first_ns, f'unreadable storage ({error})', 0, end_ns)
