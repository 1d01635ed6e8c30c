"""A declared signal's values from a bag: a number message read straight from its CDR equals
what rosbags' deserializer reads, a NaN is skipped and counted, and a field inside a message
with a header is placed by its stamp, also on a topic the bag takes for a contract one (its
only Temperature topic).

Truth: the values written into the bag."""
from __future__ import annotations

import math

import numpy as np

from tetra_gradiometer.io.bag import BagWriter, MagneticBag
from tetra_gradiometer.io.signals import read_signal

START_NS = 1_767_225_600 * 10**9


def test_numbers_and_fields_read_as_written(tmp_path):
    rng = np.random.default_rng(3)
    values = rng.normal(0.0, 1e3, 200)
    values[17] = math.nan
    with BagWriter(tmp_path / 'bag') as writer:
        Float64, Float32 = writer.types['std_msgs/msg/Float64'], writer.types['std_msgs/msg/Float32']
        Temperature = writer.types['sensor_msgs/msg/Temperature']
        Header, Time = writer.types['std_msgs/msg/Header'], writer.types['builtin_interfaces/msg/Time']
        for i, value in enumerate(values):
            log = START_NS + i * 10**8
            writer.write('/board/a', Float64(data=float(value)), log)
            writer.write('/board/b', Float32(data=np.float32(value)), log)
            stamp = log - 5 * 10**7  # measured 50 ms before it was logged
            header = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id='')
            writer.write('/pump/temperature', Temperature(header=header, temperature=float(value), variance=0.0), log)
    log = START_NS + np.arange(200) * 10**8
    good = np.isfinite(values)
    with MagneticBag(tmp_path / 'bag') as bag:
        a, b = read_signal(bag, '/board/a', 'data'), read_signal(bag, '/board/b', 'data')
        t = read_signal(bag, '/pump/temperature', 'temperature')
        skipped = [record.topic for record in bag.skipped]
    assert sorted(skipped) == ["/board/a", "/board/b", "/pump/temperature"], skipped  # each NaN, counted
    np.testing.assert_array_equal(a.stamps_ns, log[good])
    np.testing.assert_array_equal(a.values[:, 0], values[good])
    np.testing.assert_array_equal(b.values[:, 0], values[good].astype(np.float32))
    np.testing.assert_array_equal(t.stamps_ns, log[good] - 5 * 10**7)
    np.testing.assert_array_equal(t.values[:, 0], values[good])
