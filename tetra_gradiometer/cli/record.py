"""``python -m tetra_gradiometer record --out BAG --duration S``: record the sim driver's
topics (``/tetra/mag1..4``, ``/tetra/gradient/truth``, ``/tetra/odom``) over ROS 2 into a
rosbag2 folder (io/bag.py BagWriter, messages rebuilt with conversions.rosbags_types), under
the bag contract's names (README, "Topics": the odometry as ``/odom``).

A driver node (sim mode, ``--scenario``, ``--rate`` times real time) and a recorder node run
in this process; ``--duration`` is seconds of *sample* time (so a recording is the same
whatever the rate). The bag is written to a temporary folder and renamed into place only
when complete; the command fails if any message was lost.
"""

from __future__ import annotations

import argparse
import os
import queue
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import MagneticField

from ..errors import InputError
from ..io import conversions as cv
from ..io import gradient_tensor as gt
from ..nodes.common import NAMESPACE, derived_qos, sensor_qos
from ._args import MAX_RATE, MAX_SEED, int_range, positive_float
from .node import PARAMS_HELP

#: ``--duration``: one day of sample time at most (the bag is written as it comes).
MAX_DURATION_S = 86_400.0

if TYPE_CHECKING:
    from ..nodes.driver import DriverNode


class Recorder(Node):
    """Queues every driver message it receives, rebuilt as a rosbags message, with its header
    stamp; the thread that owns the BagWriter drains ``queue`` (sqlite3 objects stay in the
    thread that made them)."""

    def __init__(self, types: cv.MessageTypes, **kwargs) -> None:
        kwargs.setdefault('namespace', NAMESPACE)
        super().__init__('recorder', **kwargs)
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self._types = types
        self.counts: dict[str, int] = {}
        for sensor, topic in enumerate(cv.MAG_TOPICS):
            self.create_subscription(
                MagneticField,
                topic,
                partial(self._mag, cv.BAG_MAG_TOPICS[sensor]),
                sensor_qos(1000),
            )
        self.create_subscription(
            gt.rclpy_class(), 'gradient/truth', self._truth, derived_qos(1000)
        )
        self.create_subscription(Odometry, cv.ODOM_NODE_TOPIC, self._odom, derived_qos(1000))

    def _write(self, topic: str, msg: Any, stamp: int) -> None:
        self.queue.put((topic, msg, stamp))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _mag(self, topic: str, msg: MagneticField) -> None:
        stamp = cv.stamp_to_ns(msg.header.stamp)
        self._write(
            topic,
            cv.magnetic_field_msg(
                self._types, cv.magnetic_field_vector(msg), stamp, msg.header.frame_id
            ),
            stamp,
        )

    def _truth(self, msg: Any) -> None:
        tensor = gt.tensor_set_from_msg(msg)
        self._write(
            f'{NAMESPACE}/gradient/truth',
            gt.gradient_tensor_msg(self._types, tensor),
            tensor.stamp_ns,
        )

    def _odom(self, msg: Odometry) -> None:
        stamp = cv.stamp_to_ns(msg.header.stamp)
        p = msg.pose.pose.position
        self._write(
            cv.ODOM_TOPIC,
            cv.odometry_msg(
                self._types,
                np.array([p.x, p.y, p.z]),
                cv.odometry_orientation(msg),
                stamp,
                frame_id=msg.header.frame_id,
                child_frame_id=msg.child_frame_id,
            ),
            stamp,
        )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--out', required=True, help='rosbag2 folder to write')
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous bag of ours at --out (anything else there is refused)',
    )
    parser.add_argument(
        '--duration',
        type=positive_float(MAX_DURATION_S, 's'),
        required=True,
        help=f'seconds of sample time to record, 0 < s <= {MAX_DURATION_S:g}',
    )
    parser.add_argument('--scenario', default='', help='scenario YAML (default: the built-in one)')
    parser.add_argument(
        '--seed',
        type=int_range(-1, MAX_SEED),
        default=-1,
        help="noise seed, 0 <= n < 2^31; -1 (default): the scenario's",
    )
    parser.add_argument(
        '--rate',
        type=positive_float(MAX_RATE),
        default=10.0,
        help=f'driver speed, x real time, 0 < x <= {MAX_RATE:g} (default %(default)s)',
    )
    parser.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3')
    parser.add_argument('--params', default='', help=PARAMS_HELP)


def run(args: argparse.Namespace) -> int:
    from ..io.bag import BagWriter
    from ..io.outputs import BAG, check_output
    from ..nodes.process import stop_graph
    from ._probe import Probe, init_local_ros

    if not args.duration > 0:
        raise InputError(f'--duration must be > 0 s, got {args.duration}')
    inputs = tuple(p for p in (args.scenario, args.params) if p)
    check_output(args.out, BAG, force=args.force, inputs=inputs)  # refuse before starting ROS
    init_local_ros(args.params)
    nodes: list[Node] = []
    executor, spinner = _executor()
    try:
        with BagWriter(
            args.out, storage=args.storage, force=args.force, inputs=inputs, command='record'
        ) as writer:
            driver = _driver(args)
            recorder = Recorder(writer.types)
            operator = Probe('record_operator')
            nodes = [driver, recorder, operator]
            for node in nodes:
                executor.add_node(node)
            spinner.start()
            topics = [*cv.MAG_TOPICS, 'gradient/truth', cv.ODOM_NODE_TOPIC]
            operator.wait_for(
                lambda: all(recorder.count_publishers(t) > 0 for t in topics), 20, 'the driver'
            )
            time.sleep(0.5)
            operator.call('driver/resume')
            _drain(writer, recorder, lambda: driver.state == 'finished')
            executor.shutdown(timeout_sec=2)
            if spinner.is_alive():
                spinner.join(timeout=5)
            while not recorder.queue.empty():  # callbacks may have queued more before the stop
                writer.write(*recorder.queue.get_nowait())
            expected = driver.sets_published
            _check_complete(recorder.counts, expected)
        seconds = expected / driver.info['sample_rate_hz']
        print(
            f'record: {args.out}: {expected} sets ({seconds:g} s) '
            f'of {", ".join(sorted(recorder.counts))} ({args.storage})'
        )
        return 0
    except TimeoutError as error:
        raise OSError(str(error)) from None
    finally:
        stop_graph([executor], spinner, nodes)


def _executor() -> tuple[Any, threading.Thread]:
    """A single-threaded executor and the thread that will spin it."""
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor()
    return executor, threading.Thread(target=executor.spin, daemon=True)


def _driver(args: argparse.Namespace) -> DriverNode:
    """The sim driver, paused, playing ``--duration`` s of ``--scenario`` at ``--rate``."""
    from rclpy.parameter import Parameter

    from ..nodes.driver import DriverNode

    scenario = os.path.abspath(args.scenario) if args.scenario else ''
    return DriverNode(
        parameter_overrides=[
            Parameter('mode', value='sim'),
            Parameter('rate', value=float(args.rate)),
            Parameter('start_paused', value=True),
            Parameter('max_duration_s', value=float(args.duration)),
            Parameter('scenario', value=scenario),
            Parameter('seed', value=int(args.seed)),
        ]
    )


def _drain(writer: Any, recorder: Recorder, finished: Callable[[], bool]) -> None:
    """Write the recorder's queue into the bag until the driver has finished and nothing more
    arrived for 2 s."""
    quiet_since = None
    while True:
        try:
            writer.write(*recorder.queue.get(timeout=0.1))
            quiet_since = None
        except queue.Empty:
            if finished():
                quiet_since = quiet_since or time.monotonic()
                if time.monotonic() - quiet_since > 2.0:
                    return


def _check_complete(counts: dict[str, int], expected: int) -> None:
    """Raise OSError unless every recorded topic got ``expected`` messages."""
    lost = {
        t: expected - counts.get(t, 0)
        for t in [*cv.BAG_MAG_TOPICS, cv.ODOM_TOPIC, f'{NAMESPACE}/gradient/truth']
    }
    if any(lost.values()):
        raise OSError(f'messages were lost while recording: {lost}')
