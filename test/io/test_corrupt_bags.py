"""Issue 13, a corrupt message costs that message, not the run: bags written with BagWriter
(sqlite3 and mcap) whose bytes are then damaged on purpose. Every good set must still come
back with the values written, the damage must be recorded (topic, log time, reason), and
more damage than ``max_skipped_fraction`` must fail with a BagError."""
import os
import sqlite3
import struct
import subprocess
import sys
from binascii import crc32
from pathlib import Path

import numpy as np
import pytest

from tetra_gradiometer.core.timebase import TimeBase

from tetra_gradiometer.core import TetraGeometry
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.nodes import replay
from tetra_gradiometer.io.bag import BagError, BagWriter, MagneticBag, decode_magnetic_field, typestore
from tetra_gradiometer.io.bag_skips import SkippedMessage
from tetra_gradiometer.io.params import params_document

REPO = Path(__file__).resolve().parents[2]
START = 1_767_225_600 * 10**9 + 123_456_789
PERIOD = 10_000_000  # 100 Hz


def _fields(n, seed=7):
    return np.random.default_rng(seed).normal(0.0, 5e-5, (n, 4, 3))


def _write(path, storage, stamps, fields, damage=None):
    """Sets at ``stamps`` (header = log time); ``damage[(set index, sensor)] = f(raw) -> bytes``."""
    damage = damage or {}
    with BagWriter(path, storage=storage) as writer:
        for i, stamp in enumerate(stamps):
            for sensor in range(4):
                raw = cv.magnetic_field_cdr(fields[i, sensor], int(stamp), cv.MAG_FRAMES[sensor])
                if (i, sensor) in damage:
                    raw = damage[(i, sensor)](raw)
                writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, raw, int(stamp))


def _read(path, **options):
    """Sets paired by stamp unless told (so a lost message costs exactly its set)."""
    options.setdefault('timebase', TimeBase(sync='nearest'))
    fraction = options.pop('max_skipped_fraction', 0.01)
    with MagneticBag(path, max_skipped_fraction=fraction) as bag:
        chunks = list(bag.iter_sets(**options))
        return (np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]),
                list(bag.skipped), bag.skipped_summary())


def _with_u32(offset, value):
    return lambda raw: raw[:offset] + struct.pack('<I', value) + raw[offset + 4:]


DAMAGES = {
    'cut short': (lambda raw: raw[:50], 'payload cut short'),
    'absurd string length': (_with_u32(12, 0x7FFFFFF0), 'frame_id length 2147483632 beyond the payload'),
    'unknown encapsulation': (lambda raw: b'\x00\x07' + raw[2:], 'unknown CDR encapsulation 0x0007'),
    'nanosec >= 1e9': (_with_u32(8, 10**9), 'nanosec 1000000000 >= 1e9'),
    'no payload at all': (lambda raw: b'', 'cut short'),
}


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
@pytest.mark.parametrize('case', sorted(DAMAGES))
def test_a_malformed_message_costs_only_its_set(tmp_path, storage, case):
    n, bad_set = 1000, 400
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n)
    damage, reason = DAMAGES[case]
    _write(tmp_path / 'bag', storage, stamps, fields, {(bad_set, 1): damage})
    keep = np.arange(n) != bad_set
    for fast in (True, False):
        got_stamps, got_fields, skipped, line = _read(tmp_path / 'bag', fast=fast, chunk_size=300)
        assert np.array_equal(got_stamps, stamps[keep])
        assert np.array_equal(got_fields, fields[keep])
        assert [(s.topic, s.log_time_ns, s.count) for s in skipped] == [('/tetra/mag2', stamps[bad_set], 1)]
        if fast:  # the fast decoder's own words; rosbags words the generic path's reasons
            assert reason in skipped[0].reason, skipped[0].reason
        assert line.startswith('skipped 1 undecodable message (/tetra/mag2 at log time 4.000 s: ')
    # Resampling (the default) interpolates sensor 2 across its lost message: no set lost.
    got_stamps, got_fields, _, _ = _read(tmp_path / 'bag', chunk_size=300, timebase=TimeBase())
    assert np.array_equal(got_stamps, stamps)
    assert np.array_equal(got_fields[keep], fields[keep])


def test_a_bad_message_does_not_cost_its_batch(tmp_path):
    """One batch holds 4 x 20 000 messages: a single bad one must not send the others away."""
    n = 6000
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 1)
    bad = {(10, 0): DAMAGES['cut short'][0], (2500, 3): DAMAGES['nanosec >= 1e9'][0],
           (5999, 2): DAMAGES['absurd string length'][0]}
    _write(tmp_path / 'bag', 'mcap', stamps, fields, bad)
    got_stamps, got_fields, skipped, _ = _read(tmp_path / 'bag')
    keep = ~np.isin(np.arange(n), [10, 2500, 5999])
    assert np.array_equal(got_stamps, stamps[keep]) and np.array_equal(got_fields, fields[keep])
    assert sorted((s.log_time_ns, s.topic) for s in skipped) == [
        (stamps[10], '/tetra/mag1'), (stamps[2500], '/tetra/mag4'), (stamps[5999], '/tetra/mag3')]


@pytest.mark.parametrize('fast', [True, False])
def test_more_than_the_allowed_fraction_fails(tmp_path, fast):
    n = 1000  # 4000 messages: 1 % is 40
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n)
    cut = DAMAGES['cut short'][0]
    _write(tmp_path / 'bag', 'sqlite3', stamps, fields, {(i, 0): cut for i in range(100, 148)})
    with pytest.raises(BagError, match=r'48 of 4000 magnetometer messages skipped .*\(1\.20%, more than '
                                       r'max_skipped_fraction 1\.00%\): skipped 48 undecodable'):
        _read(tmp_path / 'bag', fast=fast)
    got_stamps, _, skipped, _ = _read(tmp_path / 'bag', fast=fast, max_skipped_fraction=0.02)
    assert len(got_stamps) == n - 48 and len(skipped) == 48


# --------------------------------------------------------------------------- storage damage


def _mcap_chunks(path):
    """The chunk index of a bag's .mcap file (rosbags' own parser)."""
    from rosbags.rosbag2.storage_mcap import McapReader
    (mcap,) = Path(path).glob('*.mcap')
    reader = McapReader(mcap)
    reader.open()
    try:
        return mcap, list(reader.chunks)
    finally:
        reader.close()


def _expected_after_chunk_loss(stamps, chunk):
    return (stamps < chunk.message_start_time) | (stamps > chunk.message_end_time)


def _check_chunk_lost(path, stamps, fields, chunk, reason):
    got_stamps, got_fields, skipped, line = _read(path, max_skipped_fraction=0.5)
    keep = _expected_after_chunk_loss(stamps, chunk)
    assert 0 < (~keep).sum() < len(stamps) // 2
    assert np.array_equal(got_stamps, stamps[keep]) and np.array_equal(got_fields, fields[keep])
    assert {s.topic for s in skipped} == set(cv.BAG_MAG_TOPICS)
    for s in skipped:
        assert (s.log_time_ns, s.end_log_time_ns) == (chunk.message_start_time, chunk.message_end_time)
        assert reason in s.reason
    assert sum(s.count for s in skipped) == sum(chunk.channel_count.values())
    assert line.startswith(f'skipped {sum(s.count for s in skipped)} undecodable messages (/tetra/mag')
    with pytest.raises(BagError, match='more than max_skipped_fraction 1.00%'):
        _read(path)  # the default policy: a whole chunk of a small bag is too much


@pytest.fixture()
def three_chunk_bag(tmp_path):
    n = 4000  # 16 000 messages, ~2.7 MB: three chunks of rosbags' 1 MiB
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 3)
    _write(tmp_path / 'bag', 'mcap', stamps, fields)
    mcap, chunks = _mcap_chunks(tmp_path / 'bag')
    assert len(chunks) == 3
    return tmp_path / 'bag', mcap, chunks, stamps, fields


def test_a_chunk_with_a_bad_checksum_is_skipped(three_chunk_bag):
    path, mcap, chunks, stamps, fields = three_chunk_bag
    chunk = chunks[1]
    data = bytearray(mcap.read_bytes())
    records = chunk.chunk_start_offset + 9 + 40 + len(chunk.compression)  # rosbags' msgsrc layout
    crc_at = chunk.chunk_start_offset + 9 + 24
    data[crc_at:crc_at + 4] = struct.pack('<I', crc32(data[records:records + chunk.uncompressed_size]))
    data[records + 5000] ^= 0xFF  # a flipped byte inside the chunk's message records
    mcap.write_bytes(bytes(data))
    _check_chunk_lost(path, stamps, fields, chunk, 'Chunk checksum mismatch')


def test_a_chunk_with_broken_records_is_skipped(three_chunk_bag):
    path, mcap, chunks, stamps, fields = three_chunk_bag
    chunk = chunks[1]
    data = bytearray(mcap.read_bytes())
    records = chunk.chunk_start_offset + 9 + 40 + len(chunk.compression)
    data[records + 1:records + 9] = struct.pack('<Q', 2**40)  # first record's length: absurd
    mcap.write_bytes(bytes(data))
    _check_chunk_lost(path, stamps, fields, chunk, 'unreadable storage chunk')


def test_a_corrupt_compressed_chunk_is_skipped(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
    n = 12000  # zstd chunks of 1 MiB uncompressed: three of them
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 4)
    writer = Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connections = [writer.add_connection(t, cv.MAGNETIC_FIELD, typestore=typestore())
                       for t in cv.BAG_MAG_TOPICS]
        for i, stamp in enumerate(stamps):
            for sensor in range(4):
                writer.write(connections[sensor], int(stamp),
                             cv.magnetic_field_cdr(fields[i, sensor], int(stamp), cv.MAG_FRAMES[sensor]))
    mcap, chunks = _mcap_chunks(tmp_path / 'bag')
    assert len(chunks) >= 3 and chunks[1].compression == 'zstd'
    chunk = chunks[1]
    data = bytearray(mcap.read_bytes())
    compressed = chunk.chunk_start_offset + 9 + 40 + len(chunk.compression)
    for k in range(0, chunk.compressed_size, 997):
        data[compressed + k] ^= 0x5A
    mcap.write_bytes(bytes(data))
    _check_chunk_lost(tmp_path / 'bag', stamps, fields, chunk, 'unreadable storage chunk')


@pytest.mark.parametrize('value', ['text, not a blob', b'', b'\x00\x01'])
def test_a_malformed_sqlite_row_is_skipped(tmp_path, value):
    n = 500
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 5)
    _write(tmp_path / 'bag', 'sqlite3', stamps, fields)
    (db3,) = (tmp_path / 'bag').glob('*.db3')
    with sqlite3.connect(db3) as db:
        (topic_id,) = db.execute('SELECT id FROM topics WHERE name = ?', ('/tetra/mag3',)).fetchone()
        db.execute('UPDATE messages SET data = ? WHERE topic_id = ? AND timestamp = ?',
                   (value, topic_id, int(stamps[123])))
    db.close()
    for fast in (True, False):
        got_stamps, got_fields, skipped, _ = _read(tmp_path / 'bag', fast=fast)
        keep = np.arange(n) != 123
        assert np.array_equal(got_stamps, stamps[keep]) and np.array_equal(got_fields, fields[keep])
        assert [(s.topic, s.log_time_ns) for s in skipped] == [('/tetra/mag3', stamps[123])]


def test_a_corrupt_sqlite_page_costs_only_its_rows(tmp_path):
    """An overflow-page chain broken mid-file: rosbags opens the bag (its counts do not read
    message data) and the query fails at that row; it is re-entered past the damage."""
    n = 300
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 6)
    with BagWriter(tmp_path / 'bag') as writer:  # /tetra/mag2 messages span overflow pages
        for i, stamp in enumerate(stamps):
            for sensor in range(4):
                frame = cv.MAG_FRAMES[sensor] + ('x' * 10_000 if sensor == 1 else '')
                writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD,
                                 cv.magnetic_field_cdr(fields[i, sensor], int(stamp), frame), int(stamp))
    (db3,) = (tmp_path / 'bag').glob('*.db3')
    with sqlite3.connect(db3) as db:
        page_size = db.execute('PRAGMA page_size').fetchone()[0]
    db.close()
    data = bytearray(db3.read_bytes())
    last = data.find(struct.pack('<3d', *fields[150, 1])) // page_size + 1  # 1-based page number
    pointing = [q for q in range(len(data) // page_size)
                if data[q * page_size:q * page_size + 4] == struct.pack('>I', last)]
    assert len(pointing) == 1  # the overflow page before it in the chain
    data[pointing[0] * page_size:pointing[0] * page_size + 4] = struct.pack('>I', 0x7FFFFFF)
    db3.write_bytes(bytes(data))
    got_stamps, got_fields, skipped, line = _read(tmp_path / 'bag')
    keep = np.arange(n) != 150
    assert np.array_equal(got_stamps, stamps[keep]) and np.array_equal(got_fields, fields[keep])
    assert [(s.topic, s.log_time_ns, s.count) for s in skipped] == [('', stamps[150], 0)]
    assert skipped[0].end_log_time_ns == stamps[151] and 'malformed' in skipped[0].reason
    assert line.startswith('skipped 0 undecodable messages and 1 unreadable storage range (unknown topic')


# --------------------------------------------------------------------------- stamps, replay, CLI


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_negative_and_pre_1970_stamps_round_trip_exactly(tmp_path, storage):
    stamps = np.array([-3 * 10**9 - 1, -2 * 10**9, -999_999_999, -1, 0, 1, 999_999_999, 10**9,
                       -(2**31) * 10**9, (2**31 - 1) * 10**9 + 999_999_999], dtype=np.int64)
    stamps.sort()
    fields = _fields(len(stamps), 8)
    with BagWriter(tmp_path / 'bag', storage=storage) as writer:  # log time: uint64 in MCAP
        for i, stamp in enumerate(stamps):
            for sensor in range(4):
                writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD,
                                 cv.magnetic_field_cdr(fields[i, sensor], int(stamp), cv.MAG_FRAMES[sensor]), START + i)
    for fast in (True, False):
        got_stamps, got_fields, skipped, _ = _read(tmp_path / 'bag', fast=fast)
        assert got_stamps.tolist() == stamps.tolist() and skipped == []
        assert np.array_equal(got_fields, fields)
    raws = [cv.magnetic_field_cdr(fields[0, 0], int(s), 'tetra_mag1') for s in stamps]
    store = typestore()
    truth = [cv.stamp_to_ns(store.deserialize_cdr(r, cv.MAGNETIC_FIELD).header.stamp) for r in raws]
    assert decode_magnetic_field(raws)[0].tolist() == truth == stamps.tolist()


def test_replay_skips_and_counts(tmp_path, caplog):
    n = 50
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 9)
    _write(tmp_path / 'bag', 'mcap', stamps, fields,
           {(7, 2): DAMAGES['cut short'][0], (30, 0): DAMAGES['nanosec >= 1e9'][0]})
    skipped: list[SkippedMessage] = []
    with caplog.at_level('WARNING', logger=replay.__name__):
        frames = list(replay.iter_frames(tmp_path / 'bag', cv.rosbags_types(typestore()), skipped=skipped))
    assert len(frames) == 4 * n - 2
    assert [(s.topic, s.log_time_ns) for s in skipped] == [('/tetra/mag3', stamps[7]), ('/tetra/mag1', stamps[30])]
    mag1 = [f.mag1_stamp for f in frames if f.mag1_stamp is not None]
    assert mag1 == [int(s) for i, s in enumerate(stamps) if i != 30]
    assert 'skipped 2 undecodable messages' in caplog.text


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_compensate_on_a_damaged_bag_exits_0(tmp_path, storage):
    n = 1000
    stamps = START + np.arange(n, dtype=np.int64) * PERIOD
    fields = _fields(n, 10)
    _write(tmp_path / 'bag', storage, stamps, fields,
           {(100, 1): DAMAGES['cut short'][0], (600, 3): DAMAGES['unknown encapsulation'][0]})
    (tmp_path / 'p.yaml').write_text(params_document({'sensor_positions': TetraGeometry.regular().to_flat()}))
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop('TETRA_DEBUG', None)
    result = subprocess.run([sys.executable, '-m', 'tetra_gradiometer', 'compensate', str(tmp_path / 'bag'), '--raw',
                             '--params', str(tmp_path / 'p.yaml'), '--csv', str(tmp_path / 'out.csv'),
                             '--no-progress'], capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr
    assert 'Traceback' not in result.stderr + result.stdout
    rows = (tmp_path / 'out.csv').read_text().splitlines()[1:]
    assert len(rows) == n  # the two lost readings are interpolated across (default --sync)
    assert 'skipped 2 undecodable messages (/tetra/mag2 at log time' in result.stdout, result.stdout
