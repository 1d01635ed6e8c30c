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

Stopping (``run_node``, ``spin_node``): SIGINT and SIGTERM only set a flag
(:class:`StopRequest`; rclpy's own handlers are not installed), from the start of the
process: the console scripts (``main_driver`` ...) and ``python -m tetra_gradiometer node``
install it before the node's module is imported (a second of numpy, scipy and rclpy, during
which a signal was lost when the process inherited SIGINT ignored, a script's background
job: the node then came up and spun for good). The spin loop sees the flag within
:data:`STOP_POLL_S` (a flag set during start-up: as soon as the node is built), then the
node's work stops, running callbacks finish, what they sent gets :data:`DELIVERY_S` to
arrive, the node and the context go, in that order, and the process exits 0. Further
signals are ignored from then on, and a watchdog ends the process (status 1, every thread's
traceback on stderr) if that stop has not finished :data:`STOP_DEADLINE_S` after it began
(docs/ros.md, test/ros/test_shutdown.py). A crash in C code (SIGSEGV, SIGABRT) prints every
thread's Python stack on stderr first (``faulthandler``). Once the node and the context are
gone, ``run_node`` ends the process at once (``os._exit``): the C++ libraries' own teardown at
exit, which crashed now and then, never runs.
"""

from __future__ import annotations

import faulthandler
import gc
import importlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, NoReturn

from ..errors import TetraError


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
    from .common import (
        command_line_parameters,
        dropped_command_line_value,
        misnamed_section,
        unknown_overrides,
    )

    misnamed = misnamed_section(node, args)
    if misnamed:
        return misnamed
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


#: Longest wait of one spin call: bounds the reaction to a stop request or a shutdown, s.
STOP_POLL_S = 0.1
#: The lifecycle service whose refusals raise out of rclpy (the others only answer).
LIFECYCLE_SERVICES = ('/change_state',)
#: Time the stop of ``spin_node`` may take before its watchdog ends the process, s: a hung
#: stop's traceback before ``ros2 launch`` kills the process (SIGTERM at 5 s, ignored by
#: then, SIGKILL at 10 s). A stop slowed by a starved machine is not a hang: a calibrator
#: stopped while 18 nodes start beside it on two cores can pass 2.5 s in the participant's
#: release, which takes 0.04 s of CPU.
STOP_DEADLINE_S = 8.0
#: Time the replies and messages of the last callbacks get to reach their readers before the
#: node's endpoints go, s: destroyed at once, a ~/calibrate reply sent by the stop itself was
#: lost in 3 of 12 stops on a loaded machine (none of 12 with this wait).
DELIVERY_S = 0.3


class StopRequest:
    """The first SIGINT or SIGTERM, once :meth:`install` has made them set it.

    The handler only stores the signal's number: it takes no lock and raises nothing, so it
    is safe wherever the main thread is when Python runs it (inside a callback, a lock's
    ``with``, rclpy's teardown), unlike rclpy's handler, which raises KeyboardInterrupt
    there for SIGINT and shuts the context down under the running callbacks."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def install(self) -> StopRequest:
        signal.signal(signal.SIGINT, self._handle)
        signal.signal(signal.SIGTERM, self._handle)
        # A crash in C (SIGSEGV, SIGABRT ...) prints every thread's Python stack on stderr:
        # the node's log says where it died, not only launch's "exit code -11".
        faulthandler.enable()
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum

    def is_set(self) -> bool:
        return self.signum is not None


#: The process's stop request: installed by :func:`run_node` before the node's imports,
#: again (the same handler) by :func:`spin_node`.
_STOP = StopRequest()


def run_node(name: str, args: list[str] | None = None) -> NoReturn:
    """Run node ``name`` (``driver``, ``tensor``, ``calibrator``, ``compensator``,
    ``target``) in this process, then end the process with the exit status of its
    ``main(args)``. SIGINT and SIGTERM are first made to request the stop
    (:class:`StopRequest`), then the node's module is imported. This module imports nothing
    heavy, so only the interpreter's own start precedes the handler."""
    _STOP.install()
    module = importlib.import_module(f'{__package__}.{name}')
    status = int(module.main(args) or 0)
    # The node, its endpoints and rclpy's context are gone (spin_node), the ROS log closed.
    # What the interpreter's exit would still run is the teardown of the C++ libraries
    # loaded (Fast DDS's singletons and threads), whose destructors at exit segfault now and
    # then: exit -11 after a clean stop, past faulthandler's reach (rmw_fastrtps#761 has
    # the same, quick_exit its workaround). The process ends here, with the node's status.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


# The console scripts (setup.py; ``ros2 run``, the launch file).
def main_driver() -> int:
    return run_node('driver')


def main_tensor() -> int:
    return run_node('tensor')


def main_calibrator() -> int:
    return run_node('calibrator')


def main_compensator() -> int:
    return run_node('compensator')


def main_target() -> int:
    return run_node('target')


def events_executor() -> Any:
    """rclpy's EventsExecutor (rclpy.experimental), the executor of the single-threaded nodes:
    rclpy's SingleThreadedExecutor rebuilds its wait set in Python for every callback, which
    capped the chain near 400 sets/s (bench/bench_chain.py, README); this one queues the
    middleware's events in C++. No guard conditions (no node of ours creates one). Spin it
    with :func:`spin`."""
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


def spin(
    executor: Any, context: Any = None, stop: threading.Event | StopRequest | None = None
) -> None:
    """Spin ``executor`` until ``context`` (default: rclpy's) shuts down (rclpy's SIGINT
    handler, an external shutdown), ``stop`` is set (:func:`stop_on_signals`,
    :class:`StopRequest`) or Ctrl-C raises. The events executor is spun in a loop of
    ``spin_until_future_complete`` on a future that never completes, with a timeout: its own
    ``spin()`` in rclpy 7.1.6 busy-waits without dispatching and ignores SIGINT, and
    ``spin_once`` returns to Python after every callback (a tenth of the tensor node's time at
    1000 sets/s went to that loop). An rclpy executor is spun by its ``spin()`` without
    ``stop``, else by ``spin_once`` calls of at most :data:`STOP_POLL_S`."""
    import rclpy
    from rclpy.executors import Executor, ExternalShutdownException
    from rclpy.task import Future

    if isinstance(executor, Executor) and stop is None:
        executor.spin()
        return
    context = context or rclpy.get_default_context()
    never = Future()  # dispatch events until the timeout, not one per Python loop
    if isinstance(stop, threading.Event):
        # Busy without a pause (a replay at rate 0), the events executor keeps dispatching
        # past its timeout: the future done stops it at once.
        done = threading.Thread(target=lambda: stop.wait() and never.set_result(None))
        done.daemon = True
        done.start()
    try:
        while context.ok() and not (stop and stop.is_set()):
            try:
                if isinstance(executor, Executor):
                    executor.spin_once(timeout_sec=STOP_POLL_S)
                else:
                    executor.spin_until_future_complete(never, timeout_sec=STOP_POLL_S)
            except RuntimeError as error:  # rclpy's RCLError
                if 'lifecycle' not in str(error):
                    raise
                # A lifecycle request that is no transition from the node's state: refused by
                # rcl_lifecycle (its WARN names both), raised out of rclpy's service callback.
                rclpy.logging.get_logger('lifecycle').warning(f'request refused: {error}')
                _serve_waiting_lifecycle_requests(executor)
    except ExternalShutdownException:  # the context shut down while waiting: done
        pass


def _serve_waiting_lifecycle_requests(executor: Any) -> None:
    """Serve the lifecycle requests already waiting in the middleware, after one raised.

    The events executor drops the rest of a batch of service events when a callback raises:
    the requests that came with the refused one stay in the middleware unserved, and every
    later event of that service takes the oldest of them, so a valid transition asked after
    a burst of invalid ones went unanswered and undone (measured: 3 of 8 graphs). Taken here
    as rclpy's own executors take them (``service_take_request``, the service's callback,
    ``send_response``), each refusal logged as above."""
    import rclpy

    for node in executor.get_nodes():
        for service in node.services:
            if not service.srv_name.endswith(LIFECYCLE_SERVICES):
                continue
            while True:
                with service.handle:
                    taken = service.handle.service_take_request(service.srv_type.Request)
                request, header = taken if taken is not None else (None, None)
                if header is None:
                    break
                try:
                    response = service.callback(request, service.srv_type.Response())
                except RuntimeError as error:
                    if 'lifecycle' not in str(error):
                        raise
                    rclpy.logging.get_logger('lifecycle').warning(f'request refused: {error}')
                    continue
                service.send_response(response, header)


def spin_node(
    factory: Callable[[], Any], name: str, args: list[str] | None, threads: int = 1
) -> int:
    """The ``main()`` of every node (the ros2/demos pattern): init, build the node, spin until
    SIGINT or SIGTERM (or an external shutdown), then :func:`_stop_node`: stop its long work
    (``stop_work()``: nodes/managed.py), wait for its running callbacks, destroy the node,
    ``rclpy.try_shutdown()``, free the participant (:func:`_release_ros`); 0.

    Signals only request that stop (:class:`StopRequest`, installed by :func:`run_node`
    before the imports, else here: a signal during start-up stops the node once built).
    rclpy's handlers are not installed: on SIGINT theirs raises KeyboardInterrupt wherever
    the main thread is, so a second Ctrl-C landed in this teardown or in the interpreter's
    exit (exit -2 or 130, an abort inside the events executor's C++), and they shut the
    context down under running callbacks (a publish failing: exit 1).

    ``threads`` > 1 spins a MultiThreadedExecutor of that many threads (the calibrator: its
    callback groups let diagnostics and ``~/cancel`` run while a solve runs); else the
    single-threaded one.

    Returns 1, after one ``cannot start:`` log line and no traceback, when the ROS arguments
    cannot be parsed, a parameter is refused (range, type, validator: ``ParamsError``; rclpy's
    ``ParameterException``), an override names an undeclared parameter
    (:func:`unknown_overrides`) or the node's constructor raises a ``TetraError``; else 0.
    """
    stop = _STOP.install()  # already, when started by run_node
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    logger = rclpy.logging.get_logger(name)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as error:  # rclpy's RCLError: unparsable arguments or params file
        logger.error(f'cannot start: {_rcl_reason(error)}')
        return 1
    try:
        return _build_and_spin(factory, logger, args, threads, stop)
    finally:
        _release_ros()


def _build_and_spin(
    factory: Callable[[], Any], logger: Any, args: list[str] | None, threads: int,
    stop: StopRequest,
) -> int:
    """:func:`spin_node` from the node's construction to its stop; the node and the executor
    are unreachable once it returns."""
    from rclpy.exceptions import ParameterException
    from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor

    try:
        node = factory()
    except (TetraError, ParameterException) as error:
        logger.error(f'cannot start: {error}')
        return 1
    refusal = _start_refusal(node, args)
    if refusal:
        logger.error(f'cannot start: {refusal}')
        node.destroy_node()
        return 1
    executor: Executor = (
        MultiThreadedExecutor(num_threads=threads) if threads > 1 else events_executor()
    )
    executor.add_node(node)
    # numpy imports numpy.ma on the first np.median: 30-70 ms inside a callback, the sets of
    # that moment held up behind it (the chain's worst latency, bench/bench_chain.py). Now.
    import numpy.ma  # noqa: F401
    # The objects of start-up (rclpy, numpy, scipy, the node) will live as long as the
    # process: moved out of the collector's reach, a full collection no longer walks them
    # (a pause of several ms in the middle of the message stream: bench/bench_chain.py p99).
    gc.collect()
    gc.freeze()
    try:
        spin(executor, stop=stop)
    except ExternalShutdownException:
        pass
    finally:
        _stop_node(node, executor)
    return 0


def _stop_node(node: Any, executor: Any) -> None:
    """The end of :func:`spin_node`, the executor no longer spinning: from here SIGINT and
    SIGTERM are ignored (the stop is under way; ignored, not Python-handled, they cannot end
    the interpreter's own exit either), and a watchdog ends the process with status 1 and
    every thread's traceback if all this and the exit take over :data:`STOP_DEADLINE_S`.
    What the last callbacks sent gets :data:`DELIVERY_S` before the node is destroyed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    faulthandler.dump_traceback_later(STOP_DEADLINE_S, exit=True)
    node.stop_work()  # a callback waiting on that work (~/calibrate) returns now
    _finish_callbacks(executor)
    time.sleep(DELIVERY_S)
    executor.shutdown(timeout_sec=STOP_DEADLINE_S)
    node.destroy_node()


def _release_ros() -> None:
    """Shut rclpy down and free what it would leave to the exit, the node's last references
    gone. rclpy 7.1.6's LifecycleNode never destroys its state machine, which holds the
    node's handle, which holds the context's; with the node's objects in ``gc.freeze``'s
    permanent generation nothing freed them, and the participant (its threads, its
    shared-memory segments) went in Fast DDS's own destructors at the C exit, past
    faulthandler's reach (gdb: ``rcl_context_fini`` was never called). Collected here, the
    state machine, the node and the participant go in order, while the interpreter is whole."""
    import rclpy

    rclpy.try_shutdown()
    gc.unfreeze()
    gc.collect()
    rclpy.get_default_context().destroy()


def _finish_callbacks(executor: Any) -> None:
    """Wait for the callbacks a MultiThreadedExecutor is running and end its threads. rclpy
    7.1.6's ``Executor.shutdown`` does not wait for them (it sets its shutdown flag, then
    waits only if the flag is unset), so the node was destroyed and the context shut down
    under them (a ``~/calibrate`` reply lost), and its pool's threads were left for the
    interpreter's exit to join. Nothing new is dispatched: only the spin loop does that."""
    from concurrent.futures import ThreadPoolExecutor

    pool = getattr(executor, '_executor', None)  # MultiThreadedExecutor's thread pool
    if isinstance(pool, ThreadPoolExecutor):
        pool.shutdown(wait=True, cancel_futures=True)


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
