"""io/bag.py: the fast paths (CDR decode/encode with numpy, batch matching) against the
generic ones (rosbags' serializer/deserializer, the message-by-message StampMatcher); the
contract check."""
import numpy as np
import pytest

from tetra_gradiometer.core.timebase import TimeBase

from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.errors import InputError
from tetra_gradiometer.io import matching
from tetra_gradiometer.io.bag import (BagError, BagWriter, MagneticBag, _UnsupportedEncoding, decode_magnetic_field,
                                      typestore)

START = 1_767_225_600 * 10**9


@pytest.fixture(scope='module')
def store():
    return typestore()


@pytest.mark.parametrize('frame', ['tetra_mag1', *('abcdefghijklmnop'[:n] for n in range(16))])
def test_encoder_is_byte_identical_to_rosbags(store, frame):
    types = cv.rosbags_types(store)
    field = np.array([1.25e-5, -2.5e-5, 4.75e-5])
    for stamp in (0, START + 123_456_789, 2**31 * 10**9 - 1):
        msg = cv.magnetic_field_msg(types, field, stamp, frame)
        assert cv.magnetic_field_cdr(field, stamp, frame) == bytes(store.serialize_cdr(msg, cv.MAGNETIC_FIELD))


@pytest.mark.parametrize('little_endian', [True, False])
def test_decoder_reads_rosbags_cdr_in_both_byte_orders(store, little_endian):
    types = cv.rosbags_types(store)
    rng = np.random.default_rng(3)
    fields = rng.normal(0.0, 5e-5, (7, 3))
    stamps = START + rng.integers(0, 10**12, 7)
    frames = ['tetra_mag1'] * 7
    for uniform in (True, False):
        if not uniform:  # differing frame_id lengths: the per-message path and every padding
            frames = ['', 'a', 'ab', 'abc', 'abcd', 'abcde', 'abcdefghi']
        raws = [bytes(store.serialize_cdr(cv.magnetic_field_msg(types, f, int(s), fr), cv.MAGNETIC_FIELD,
                                          little_endian=little_endian))
                for f, s, fr in zip(fields, stamps, frames)]
        got_stamps, got_fields = decode_magnetic_field(raws)
        # Truth: rosbags' own deserializer.
        msgs = [store.deserialize_cdr(r, cv.MAGNETIC_FIELD) for r in raws]
        assert got_stamps.tolist() == [cv.stamp_to_ns(m.header.stamp) for m in msgs] == stamps.tolist()
        assert np.array_equal(got_fields, fields)


def test_decoder_refuses_what_it_does_not_know():
    with pytest.raises(_UnsupportedEncoding):
        decode_magnetic_field([b'\x00\x07\x00\x00' + bytes(120)])  # XCDR2 encapsulation
    with pytest.raises(_UnsupportedEncoding):
        decode_magnetic_field([b'\x00\x01\x00\x00' + bytes(20), b'\x00\x01\x00\x00' + bytes(30)])  # truncated


def _irregular_streams(rng):
    """Four streams at 100 Hz with the things a real bag has: a clean synchronised stretch,
    a dropped message, jitter within and beyond tolerance, a repeated stamp."""
    n = 3000
    base = START + np.arange(n, dtype=np.int64) * 10_000_000
    streams = []
    for sensor in range(4):
        stamps = base.copy()
        keep = np.ones(n, bool)
        if sensor == 2:
            keep[1500] = False                                 # one message lost
        if sensor == 3:
            stamps[2000:2100] += rng.integers(-800_000, 800_000, 100)   # jitter within 2 ms
            stamps[2200] += 4_000_000                          # beyond tolerance
            stamps[2500] = stamps[2499]                        # repeated stamp, another reading
        streams.append((stamps[keep], rng.normal(0.0, 5e-5, (keep.sum(), 3))))
    return streams


def _write_streams(path, streams, storage):
    with BagWriter(path, storage=storage) as writer:
        events = sorted((int(s), sensor, i) for sensor, (stamps, _) in enumerate(streams)
                        for i, s in enumerate(stamps))
        for stamp, sensor, i in events:
            writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD,
                             cv.magnetic_field_cdr(streams[sensor][1][i], stamp, cv.MAG_FRAMES[sensor]), stamp)


def _read(path, **options):
    with MagneticBag(path) as bag:
        chunks = list(bag.iter_sets(**options))
        counters = bag.counters
    return np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]), counters


@pytest.mark.parametrize('storage', ['sqlite3', pytest.param('mcap', marks=pytest.mark.slow)])
@pytest.mark.parametrize('sync', ['interpolate', 'nearest'])
def test_fast_reading_equals_the_generic_path(tmp_path, storage, sync):
    streams = _irregular_streams(np.random.default_rng(11))
    _write_streams(tmp_path / 'bag', streams, storage)
    timebase = TimeBase(sync=sync)
    generic = _read(tmp_path / 'bag', fast=False, chunk_size=20_000, timebase=timebase)
    for chunk_size in (1, 97, 1000, 20_000):
        fast = _read(tmp_path / 'bag', fast=True, chunk_size=chunk_size, timebase=timebase)
        assert np.array_equal(fast[0], generic[0])
        assert np.array_equal(fast[1], generic[1])
        assert fast[2] == generic[2]
    window = _read(tmp_path / 'bag', fast=True, chunk_size=500, window_s=(3.0, 7.5), timebase=timebase)
    window_generic = _read(tmp_path / 'bag', fast=False, window_s=(3.0, 7.5), timebase=timebase)
    assert np.array_equal(window[0], window_generic[0]) and np.array_equal(window[1], window_generic[1])
    # Independent truth for the sets themselves: the clean stretch comes back verbatim.
    stamps, fields, counters = generic
    assert np.array_equal(stamps[:1500], streams[0][0][:1500])
    for sensor in range(4):
        assert np.array_equal(fields[:1500, sensor], streams[sensor][1][:1500])
    # The repeated stamp carries another reading: both are dropped (which one is the sample at
    # that stamp is unknowable), named as a stream fault of sensor 4 at 25.0 s.
    assert counters.out_of_order == 0
    (fault,) = counters.streams.faults
    assert (fault.sensor, fault.kind, fault.messages) == (3, 'duplicate_stamps', 2)
    assert fault.start_s == pytest.approx(24.99, abs=0.011)
    if sync == 'nearest':
        assert counters.dropped_messages > 0
    else:  # the lost message and the jitter are interpolated across: every instant but none
        assert counters.sets == 3000 and counters.skipped == 0
        assert np.array_equal(stamps, streams[0][0])


def test_a_synchronised_bag_takes_the_array_path(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    stamps = START + np.arange(5000, dtype=np.int64) * 10_000_000
    fields = rng.normal(0.0, 5e-5, (5000, 4, 3))
    with BagWriter(tmp_path / 'bag', storage='mcap') as writer:
        writer.write_fields(stamps, fields)
    calls = []
    original = matching.StampMatcher.add
    monkeypatch.setattr(matching.StampMatcher, 'add', lambda self, *a: calls.append(1) or original(self, *a))
    got_stamps, got_fields, counters = _read(tmp_path / 'bag', chunk_size=700, timebase=TimeBase(sync='nearest'))
    assert calls == []
    assert np.array_equal(got_stamps, stamps) and np.array_equal(got_fields, fields)
    assert counters.matched == 5000 and counters.dropped_messages == 0
    # Resampling gives the very same sets (exact stamps take their own samples).
    again = _read(tmp_path / 'bag', chunk_size=700)
    assert np.array_equal(again[0], stamps) and np.array_equal(again[1], fields)


def test_bag_without_magnetometers_is_refused(tmp_path):
    with BagWriter(tmp_path / 'odd') as writer:
        writer.write_tensors('/tetra/gradient/raw', np.array([1, 2]), np.zeros((2, 30)), 0, '')
    with MagneticBag(tmp_path / 'odd') as bag, pytest.raises(BagError, match='missing topic'):
        bag.check_contract()
    with pytest.raises(BagError, match='not found'):
        MagneticBag(tmp_path / 'nothing')


def test_a_bag_recorded_under_a_vehicle_namespace_is_read_through_a_topic_map(tmp_path):
    """A topic map (``FROM:=TO``, as ``ros2 bag play --remap``) reads the bag's own names as
    the contract's: the sets equal the fields written; without it the one topic of each
    contract name under the namespace is read, and the bag says so; replay frames carry the
    contract's keys."""
    from tetra_gradiometer.nodes import replay

    stamps = START + np.arange(200) * 20_000_000
    fields = np.random.default_rng(5).normal(0.0, 3e-5, (200, 4, 3))
    path = tmp_path / 'vehicle'
    recorded = [f'/auv1{topic}' for topic in cv.BAG_MAG_TOPICS]
    with BagWriter(path) as writer:
        for i, stamp in enumerate(stamps.tolist()):
            for sensor, topic in enumerate(recorded):
                writer.write_raw(topic, cv.MAGNETIC_FIELD,
                                 cv.magnetic_field_cdr(fields[i, sensor], stamp, cv.MAG_FRAMES[sensor]), stamp)
    rules = ' '.join(f'{a}:={b}' for a, b in zip(recorded, cv.BAG_MAG_TOPICS))
    for remap in (cv.parse_remap(rules), None):
        with MagneticBag(path, remap=remap) as bag:
            got_stamps, got = bag.read_sets(timebase=TimeBase(sync='nearest'))
            said = bag.skipped_summary()
        np.testing.assert_array_equal(got_stamps, stamps)
        np.testing.assert_array_equal(got, fields)
        assert ('/auv1/tetra/mag4 as /tetra/mag4' in said) == (remap is None), said
    frames = list(replay.iter_frames(path, cv.rosbags_types(typestore()), remap=cv.parse_remap(rules)))
    assert len(frames) == 800 and {f.items[0][:2] for f in frames} == {('mag', s) for s in range(4)}


@pytest.mark.parametrize('rules, message', [
    ('/a/mag1=/tetra/mag1', 'expected'),
    ('a/mag1:=/tetra/mag1', 'expected'),
    ('/a/mag1:=/tetra/mag9', 'not a topic of the bag contract'),
    ('/a/x:=/tetra/mag1 /a/x:=/tetra/mag2', 'twice'),
    ('/a/x:=/tetra/mag1, /a/y:=/tetra/mag1', 'twice'),
])
def test_bad_topic_map_rules_are_refused_with_the_rule(rules, message):
    with pytest.raises(InputError, match=message):
        cv.parse_remap(rules)
    assert cv.parse_remap('') == {}
