"""Issue 15 live: the ``tensor`` node fed by the ``driver`` replaying an async bag (sensors on
their own clocks, offsets up to 4 ms, jitter, lost messages), against the offline path as the
reference (``MagneticBag.read_sets`` resampled to sensor 1's stamps, then eq. 7 by
``core.difference_tensor``): the same sets at the same stamps, none missing and none extra,
every tensor within 1 % of the noise floor (at rate 0 in this process, each tensor handed
back to the driver's pacing); and, replayed in real time over real DDS, the latency the
live resampler adds (waiting for the sample of every sensor at or after the instant) is
within one sample period of the latest sensor (its median; after a lost message the wait is
up to one period longer, and a loaded machine adds its own spikes).

Latency is measured on publication wall times (the DDS source timestamps of the messages,
so the test process's own scheduling does not count): tensor published minus sensor 1's
sample published at the same instant (the added latency), split into the wait for the
completing sample (the last-published of every sensor's first sample at or after the
instant) and the node's processing of that message.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest
from ros_helpers import ros_graph, wait_for

from tetra_gradiometer import core
from tetra_gradiometer.core.units import NS_PER_S
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.recording import write_mission_bag

NT = 1e-9
START_NS = 1_767_225_600 * NS_PER_S
DURATION_S = 12.0
RATE_HZ = 50.0
PERIOD_NS = int(NS_PER_S / RATE_HZ)
#: Not the default regular tetrahedron: a node that ignored ``sensor_positions`` would fail.
GEOMETRY = core.TetraGeometry(
    np.array([[0.0, 0.0, 0.0], [0.55, 0.02, 0.05], [0.1, 0.62, -0.03], [0.2, 0.15, 0.45]]))
CLOCKS = core.SensorClocks(offset_s=[0.0, 0.5e-3, 2.1e-3, 4.0e-3], jitter_s=0.2e-3,
                           loss_fraction=0.005)
NOISE_T = 0.1 * NT
PLAYBACK = 'tetra/driver: playback'
#: Longer than the reliable writer's heartbeat period (Fast DDS default 3 s), s.
REPAIR_S = 6.0


class Replay:
    """A simulated async mission in a bag, its offline tensors and per-sensor stamps."""

    def __init__(self, path, seed: int) -> None:
        rng = np.random.default_rng(seed)
        scenario = core.Scenario(
            geometry=GEOMETRY,
            earth_field_enu=np.array([0.0, 20000.0, -45000.0]) * NT,
            segments=(core.TrimManoeuvre(DURATION_S, center=(0.0, 0.0, -50.0)),),
            sample_rate_hz=RATE_HZ,
            interference=core.random_interference(rng, reference_clean=True),
            noise_t=NOISE_T,
            clocks=CLOCKS,
        )
        mission = core.simulate(scenario, np.random.default_rng(seed))
        self.path = write_mission_bag(path, mission, start_ns=START_NS, progress=False)
        #: Each sensor's header stamps as written, ns.
        self.sensor_stamps = [START_NS + np.round(s.t * NS_PER_S).astype(np.int64)
                              for s in mission.streams]
        with MagneticBag(self.path) as bag:
            self.stamps, fields = bag.read_sets()
            self.counters = bag.counters
        self.tensors = core.difference_tensor(fields, GEOMETRY)
        self.floor = core.noise_floor(NOISE_T, GEOMETRY)

    def unresolvable_at_end(self) -> int:
        """Sensor 1 instants after some sensor's last sample: no later sample ever completes
        them, offline or live."""
        horizon = min(int(s[-1]) for s in self.sensor_stamps)
        return int(np.sum(self.sensor_stamps[0] > horizon))

    def completing(self, instant: int) -> list[tuple[int, int]]:
        """(sensor, stamp) of every sensor's first sample at or after ``instant``."""
        result = []
        for sensor, stamps in enumerate(self.sensor_stamps):
            index = int(np.searchsorted(stamps, instant, side='left'))
            result.append((sensor, int(stamps[index])))
        return result


@pytest.fixture(scope='module')
def replay(tmp_path_factory) -> Replay:
    return Replay(tmp_path_factory.mktemp('async') / 'bag', seed=15)


class PublishTimes:
    """Subscriptions of the test process recording the DDS source timestamp (publication wall
    time, ns) of every magnetometer message and every ``gradient/raw`` tensor, by stamp."""

    def __init__(self, probe) -> None:
        from sensor_msgs.msg import MagneticField

        from tetra_gradiometer.io import conversions as cv
        from tetra_gradiometer.io import gradient_tensor as gt
        from tetra_gradiometer.nodes.common import derived_qos, sensor_qos

        self.lock = threading.Lock()
        self.mags: list[dict[int, int]] = [{} for _ in range(4)]
        self.tensors: dict[int, int] = {}
        for sensor, topic in enumerate(cv.MAG_TOPICS):
            probe.create_subscription(
                MagneticField, topic,
                lambda msg, info, s=sensor: self._note(self.mags[s], msg, info), sensor_qos(1000))
        probe.create_subscription(gt.rclpy_class(), 'gradient/raw',
                                  lambda msg, info: self._note(self.tensors, msg, info),
                                  derived_qos())

    def _note(self, table: dict[int, int], msg, info) -> None:
        from tetra_gradiometer.io import conversions as cv

        with self.lock:
            table[cv.stamp_to_ns(msg.header.stamp)] = int(info['source_timestamp'])


@dataclass
class Played:
    """What one live replay gave."""

    tensors: dict[int, np.ndarray]  # gradient/raw by stamp, T/m
    times: PublishTimes
    logs: str  # the driver's final playback status and the nodes' output


def _play(replay: Replay, **driver_params) -> Played:
    """Run tensor + driver (replaying ``replay``) and collect ``gradient/raw`` by stamp until
    the driver has finished and no tensor came for a second."""
    with ros_graph() as (graph, probe, _):
        times = PublishTimes(probe)
        graph.start('tensor', sensor_positions=GEOMETRY.positions.reshape(-1).tolist(),
                    diagnostics_period_s=0.2)
        graph.start('driver', mode='replay', bag=str(replay.path), start_paused=True,
                    min_subscribers=2, diagnostics_period_s=0.2, **driver_params)
        for topic in ('mag1', 'mag2', 'mag3', 'mag4'):  # the tensor node's and ours
            wait_for(lambda t=topic: probe.count_subscribers(f'/tetra/{t}') >= 2
                     and probe.count_publishers(f'/tetra/{t}') >= 2, 30, f'{topic} matched', graph)
        # The tensor node's publisher (and the test feeder's, silent).
        wait_for(lambda: probe.count_publishers('/tetra/gradient/raw') >= 2, 30, 'tensor node',
                 graph)
        with probe.lock:
            probe.collecting = True
        reply = probe.call('driver/resume')
        assert reply.success, reply.message

        deadline = time.monotonic() + 90.0
        last_count, last_change = -1, time.monotonic()
        while time.monotonic() < deadline:
            count = probe.counts['gradient/raw']
            if count != last_count:
                last_count, last_change = count, time.monotonic()
            finished = probe.status(PLAYBACK).get('state') == 'finished'
            # A message the loaded test process did not take in time is repaired by the
            # reliable writer after its next heartbeat (Fast DDS: every 3 s), not at once:
            # once finished, wait for every set or for longer than that heartbeat period.
            quiet = time.monotonic() - last_change
            if finished and (count >= len(replay.stamps) and quiet > 0.3 or quiet > REPAIR_S):
                break
            time.sleep(0.05)
        else:
            raise AssertionError(
                f'replay did not finish ({probe.status(PLAYBACK)})\n{graph.logs()}')
        with probe.lock:
            live = dict(probe.tensors['gradient/raw'])
        logs = f'{PLAYBACK}: {probe.status(PLAYBACK)}\n{graph.logs()}'
    return Played(live, times, logs)


def _assert_offline_tensors(live: dict[int, np.ndarray], replay: Replay, logs: str) -> float:
    """Same stamps as the offline path, each tensor within 1 % of the noise floor; return the
    largest difference over the noise floor."""
    expected = replay.stamps.tolist()
    missing = sorted(set(expected) - set(live))
    extra = sorted(set(live) - set(expected))
    assert not missing and not extra, (
        f'{len(missing)} offline sets missing live (first {missing[:5]}), {len(extra)} extra '
        f'(first {extra[:5]})\n{logs}')
    tensors = np.array([live[s] for s in expected])
    worst = float(np.max(np.abs(tensors - replay.tensors))) / replay.floor
    assert worst <= 0.01, f'max |live - offline| = {worst:.3g} x noise floor'
    return worst


def test_the_offline_reference_holds_every_sensor_1_instant_it_can_resolve(replay):
    """The reference itself: every sensor 1 stamp is a set, except the instants counted as
    skipped (before two samples of every sensor at the stream starts, or across a lost message
    longer than the gap limit) and those after some sensor's last sample (none live either)."""
    counters = replay.counters
    skipped = counters.skipped_start + counters.skipped_gap + counters.evicted
    assert skipped <= 4, counters.text()
    resolvable = len(replay.sensor_stamps[0]) - replay.unresolvable_at_end()
    assert len(replay.stamps) == resolvable - skipped
    assert set(replay.stamps.tolist()) <= set(replay.sensor_stamps[0].tolist())
    assert len(replay.stamps) >= 0.98 * DURATION_S * RATE_HZ


def test_replayed_as_fast_as_the_chain_takes_it_the_tensors_are_the_offline_ones(monkeypatch, replay):
    """``rate: 0`` in this process (test/ros/in_process.py): the driver's messages handed to
    the tensor node in the order it published them, each tensor handed back to the driver
    (its rate-0 pacing), the driver ticked until it has played the bag."""
    from rclpy.serialization import serialize_message

    from in_process import deserialized, last_status, node_in_process
    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    mags = {f'/tetra/mag{s + 1}': s for s in range(4)}
    with node_in_process(DriverNode, monkeypatch, mode='replay', bag=str(replay.path), rate=0.0) as (driver, played), \
            node_in_process(TensorNode, monkeypatch, sensor_positions=GEOMETRY.positions.reshape(-1).tolist()) \
            as (tensor, published):
        taken, returned = 0, 0
        for _ in range(100_000):
            driver._tick()
            while taken < len(played) or returned < len(published):  # what each gave the other
                for topic, message in played[taken:]:
                    if topic in mags:
                        tensor._on_mag(mags[topic], message if isinstance(message, bytes) else serialize_message(message))
                taken = len(played)
                for topic, message in published[returned:]:
                    if topic == '/tetra/gradient/raw':  # its pacing: may publish the next sets
                        driver._on_ack(deserialized([(topic, message)], topic, gt.rclpy_class())[0])
                returned = len(published)
            if driver.state == 'finished':
                break
        assert driver.state == 'finished' and driver.ack_timeouts == 0
        tensor._publish_diagnostics()
        sensors = [last_status(published, f'tetra/tensor: mag{s}') for s in range(1, 5)]
        live = {t.stamp_ns: t.g for t in map(gt.tensor_set_from_msg,
                                             deserialized(published, '/tetra/gradient/raw', gt.rclpy_class()))}
    worst = _assert_offline_tensors(live, replay, '')
    # The node's clock estimates on /diagnostics: the simulated offsets (as offline).
    offsets_ms = [float(status['clock_offset_ms']) for status in sensors]
    np.testing.assert_allclose(offsets_ms, CLOCKS.offset_s * 1e3, rtol=0, atol=0.05)
    print(f'\nrate 0: {len(live)} sets, max |live - offline| {worst:.2e} x noise '
          f'floor; clock offsets {np.round(offsets_ms, 3)} ms')


@pytest.mark.slow
def test_replayed_in_real_time_the_tensors_are_the_offline_ones_within_one_period(replay):
    """``rate: 1``: the same tensors, and the added latency (tensor published minus sensor 1's
    sample published at that instant) is within one sample period of the latest sensor: the
    resampler waits for each sensor's first sample at or after the instant (here the 4 ms
    offset of sensor 4; one period more after a lost message), then publishes at once.
    Asserted on medians (wall-clock spikes of a loaded CI machine are not the node's)."""
    played = _play(replay, rate=1.0)
    live, times = played.tensors, played.times
    worst = _assert_offline_tensors(live, replay, played.logs)

    added, waited, processing, allowed = [], [], [], []
    with times.lock:
        for stamp in replay.stamps.tolist():
            completing = replay.completing(stamp)
            published = [times.mags[s].get(t) for s, t in completing]
            if stamp not in times.tensors or None in published or stamp not in times.mags[0]:
                continue  # a best-effort copy to this test process was lost: not timed
            tensor, last = times.tensors[stamp], max(published)
            added.append(tensor - times.mags[0][stamp])
            waited.append(last - times.mags[0][stamp])
            processing.append(tensor - last)
            # In sample time: the latest sensor's first sample at or after the instant.
            allowed.append(max(t for _, t in completing) - stamp)
    added_ms, waited_ms, processing_ms = (np.array(x) * 1e-6 for x in (added, waited, processing))
    allowed_ms = np.array(allowed) * 1e-6
    period_ms = PERIOD_NS * 1e-6
    assert len(added) >= 0.9 * len(replay.stamps), f'{len(added)} of {len(replay.stamps)} timed'
    # Sample time: the wait is within one period of the latest sensor (up to two after a
    # lost message: then the next sample is one period later).
    assert np.median(allowed_ms) <= period_ms and np.max(allowed_ms) <= 2 * period_ms + 1.0
    # Wall time: the node publishes as soon as the completing sample is in (median well
    # below a period), so the added latency is the wait plus that: within one period.
    assert np.median(processing_ms) < 0.5 * period_ms, np.percentile(processing_ms, [50, 90])
    assert np.median(added_ms) <= period_ms, np.percentile(added_ms, [50, 90])
    print(f'\nrate 1: {len(live)} sets, max |live - offline| {worst:.2e} x noise floor; '
          f'{len(added)} timed: added latency median {np.median(added_ms):.2f} ms, '
          f'p90 {np.percentile(added_ms, 90):.2f} ms, max {np.max(added_ms):.2f} ms '
          f'(period {period_ms:g} ms; wait for the completing sample: sample time median '
          f'{np.median(allowed_ms):.2f} ms, max {np.max(allowed_ms):.2f} ms; wall median '
          f'{np.median(waited_ms):.2f} ms); processing median {np.median(processing_ms):.2f} ms, '
          f'p90 {np.percentile(processing_ms, 90):.2f} ms, max {np.max(processing_ms):.2f} ms')
