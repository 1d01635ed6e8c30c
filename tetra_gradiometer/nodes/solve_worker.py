"""A long computation run off the executor, one at a time, cancellable and timed.

A node's service callback calls :meth:`SolveWorker.run` (in a reentrant callback group): the
work runs in the worker's own thread while the callback waits for its result, so a
MultiThreadedExecutor keeps serving the node's other callbacks (a second call is answered
at once, a cancel sets the flag the work polls through :attr:`SolveWorker.should_stop`).
Used by the calibrator's ``~/calibrate``; ROS-free, so it is tested without a graph.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import CancelledError, ThreadPoolExecutor


class SolveWorker:
    """One worker thread; :meth:`run` blocks its caller until the work is done.

    Parameters
    ----------
    name : thread name prefix
    on_start : called (in the caller's thread) once the work is accepted, before it runs
    """

    def __init__(self, name: str, on_start: Callable[[], None] | None = None) -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._busy = threading.Lock()
        self._cancel = threading.Event()
        self._on_start = on_start
        self._started: float | None = None
        self._last_s = 0.0

    @property
    def running_s(self) -> float | None:
        """Seconds the running work has taken so far; None when idle."""
        started = self._started
        return None if started is None else time.monotonic() - started

    @property
    def last_s(self) -> float:
        """Seconds the last finished work took."""
        return self._last_s

    def should_stop(self) -> bool:
        """True once :meth:`cancel` or :meth:`shutdown` was called during this work."""
        return self._cancel.is_set()

    def run(self, work: Callable[[], tuple[bool, str]]) -> tuple[bool, str] | None:
        """``work()``'s ``(ok, message)``; ``(False, 'shutting down')`` once shut down; None,
        at once, when another work is running."""
        if not self._busy.acquire(blocking=False):
            return None
        try:
            self._cancel.clear()
            self._started = time.monotonic()
            if self._on_start is not None:
                self._on_start()
            try:
                return self._executor.submit(work).result()
            except (RuntimeError, CancelledError):  # shut down before it ran: the node stops
                return False, 'shutting down'
        finally:
            self._last_s = time.monotonic() - (self._started or time.monotonic())
            self._started = None
            self._busy.release()

    def cancel(self) -> bool:
        """Ask the running work to stop; False when none runs."""
        if self._started is None:
            return False
        self._cancel.set()
        return True

    def shutdown(self) -> None:
        """Cancel the running work and wait for it; later :meth:`run` calls are refused, and
        a work accepted but not started is dropped (its :meth:`run` answers "shutting
        down"). The caller bounds the wait (``process.spin_node``'s watchdog): the work
        polls :meth:`should_stop`."""
        self._cancel.set()
        self._executor.shutdown(wait=True, cancel_futures=True)
