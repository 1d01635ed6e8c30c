"""Starting and stopping nodes and in-process graphs: ``spin_node`` (every node's ``main()``),
the executor of the single-threaded nodes (rclpy's EventsExecutor, :func:`events_executor`,
:func:`spin`), and for the commands in ``cli/`` that run a graph in one process,
``interrupt_on_signals``, ``stop_on_signals`` (bringup: the events executor) and
``stop_graph``.

Start-up refusals (``spin_node``): a parameter value outside its declared range, of the
wrong type (also an integer for a double parameter, as ROS refuses it: write ``10.0``) or
refused by its validator, an override naming a parameter the node does not declare (see
:func:`~tetra_gradiometer.nodes.common.unknown_overrides`), unparsable ROS arguments, and any
``TetraError`` of the node's constructor end the process with exit status 1 and one log line,
never a traceback.
"""

from __future__ import annotations

import gc
import threading
from collections.abc import Callable
from typing import Any

from ..errors import TetraError
from .common import command_line_parameters, dropped_command_line_value, unknown_overrides


def interrupt_on_signals() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread (also when the shell
    started us with SIGINT ignored), for processes that stop their executors themselves
    instead of letting rclpy's handler invalidate the context under running callbacks."""
    import signal

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (also when the shell started us with SIGINT
    ignored), for :func:`spin` of the events executor: a KeyboardInterrupt raised inside one
    of its callbacks would be logged as the callback's failure instead of stopping it."""
    import signal

    stop = threading.Event()

    def request_stop(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    return stop


def _start_refusal(node: Any, args: list[str] | None) -> str | None:
    """Why the overrides of a constructed node are refused (an undeclared name, a ``-p``
    value rcl dropped), or None."""
    rules = command_line_parameters(args, node.get_name())
    unknown = unknown_overrides(node, rules)
    if unknown:
        declared = ', '.join(node.list_parameters([], 0).names)
        word = 'parameter' if len(unknown) == 1 else 'parameters'
        return f'unknown {word} {", ".join(map(repr, unknown))} (declared: {declared})'
    return dropped_command_line_value(node, rules)


def _rcl_reason(error: Exception) -> str:
    """rcl's message without its source locations (``, at /project/src/...``)."""
    return str(error).split(', at /')[0]


_EVENTS_WAIT_S = 0.5  # longest wait of one spin call: bounds the reaction to a shutdown


def events_executor() -> Any:
    """rclpy's EventsExecutor (rclpy.experimental), the executor of the single-threaded nodes:
    rclpy's SingleThreadedExecutor rebuilds its wait set in Python for every callback, which
    capped the chain near 400 sets/s (bench/bench_chain.py, README); this one queues the
    middleware's events in C++. No guard conditions (no node of ours creates one). Spin it
    with :func:`spin`."""
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


def spin(executor: Any, context: Any = None, stop: threading.Event | None = None) -> None:
    """Spin ``executor`` until ``context`` (default: rclpy's) shuts down (rclpy's SIGINT
    handler, an external shutdown), ``stop`` is set (:func:`stop_on_signals`) or Ctrl-C
    raises. The events executor is spun in a loop of ``spin_until_future_complete`` on a
    future that never completes, with a timeout: its own ``spin()`` in rclpy 7.1.6
    busy-waits without dispatching and ignores SIGINT, and ``spin_once`` returns to Python
    after every callback (a tenth of the tensor node's time at 1000 sets/s went to that
    loop)."""
    import rclpy
    from rclpy.executors import Executor, ExternalShutdownException
    from rclpy.task import Future

    if isinstance(executor, Executor):
        executor.spin()
        return
    context = context or rclpy.get_default_context()
    never = Future()  # dispatch events until the timeout, not one per Python loop
    try:
        while context.ok() and not (stop and stop.is_set()):
            executor.spin_until_future_complete(never, timeout_sec=_EVENTS_WAIT_S)
    except ExternalShutdownException:  # the context shut down while waiting: done
        pass


def spin_node(
    factory: Callable[[], Any], name: str, args: list[str] | None, threads: int = 1
) -> int:
    """The ``main()`` of every node (the ros2/demos pattern): init, build the node, spin until
    Ctrl-C or an external shutdown, then stop its long work (``stop_work()``:
    nodes/managed.py), the executor, the node and ``rclpy.try_shutdown()``.

    ``threads`` > 1 spins a MultiThreadedExecutor of that many threads (the calibrator: its
    callback groups let diagnostics and ``~/cancel`` run while a solve runs); else the
    single-threaded one.

    Returns 1, after one ``cannot start:`` log line and no traceback, when the ROS arguments
    cannot be parsed, a parameter is refused (range, type, validator: ``ParamsError``; rclpy's
    ``ParameterException``), an override names an undeclared parameter
    (:func:`unknown_overrides`) or the node's constructor raises a ``TetraError``; else 0.
    """
    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import (
        Executor,
        ExternalShutdownException,
        MultiThreadedExecutor,
    )

    logger = rclpy.logging.get_logger(name)
    try:
        rclpy.init(args=args)
    except RuntimeError as error:  # rclpy's RCLError: unparsable arguments or params file
        logger.error(f'cannot start: {_rcl_reason(error)}')
        return 1
    try:
        node = factory()
    except (TetraError, ParameterException) as error:
        logger.error(f'cannot start: {error}')
        rclpy.try_shutdown()
        return 1
    refusal = _start_refusal(node, args)
    if refusal:
        logger.error(f'cannot start: {refusal}')
        node.destroy_node()
        rclpy.try_shutdown()
        return 1
    executor: Executor = (
        MultiThreadedExecutor(num_threads=threads) if threads > 1 else events_executor()
    )
    executor.add_node(node)
    # The objects of start-up (rclpy, numpy, scipy, the node) will live as long as the
    # process: moved out of the collector's reach, a full collection no longer walks them
    # (a pause of several ms in the middle of the message stream: bench/bench_chain.py p99).
    gc.collect()
    gc.freeze()
    try:
        spin(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.stop_work()
        executor.shutdown(timeout_sec=5)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def stop_graph(executors: list[Any], spinner: Any, nodes: list[Any]) -> None:
    """Stop an in-process graph (demo, record, bringup): the executors (running callbacks
    finish), then the spin thread, then the nodes and the context, in that order (joining the
    thread first avoids a crash at exit)."""
    import rclpy

    for executor in executors:
        executor.shutdown(timeout_sec=2)
    if spinner.is_alive():
        spinner.join(timeout=5)
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()
