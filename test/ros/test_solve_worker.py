"""nodes/solve_worker.py without a graph: one work at a time, the caller blocked until its
result, a cancel the work sees, a refused run after shutdown."""
from __future__ import annotations

import threading
import time

from tetra_gradiometer.nodes.solve_worker import SolveWorker


def test_one_work_at_a_time_cancellable_and_timed():
    started, release = threading.Event(), threading.Event()
    seen_stop: list[bool] = []
    worker = SolveWorker('test_solve')

    def work() -> tuple[bool, str]:
        started.set()
        release.wait(5)
        seen_stop.append(worker.should_stop())
        return True, 'done'

    results: list = []
    caller = threading.Thread(target=lambda: results.append(worker.run(work)))
    caller.start()
    assert started.wait(5)
    assert worker.run(lambda: (True, 'second')) is None  # busy: answered at once
    assert worker.running_s is not None and worker.running_s >= 0.0
    assert worker.cancel()
    time.sleep(0.05)
    release.set()
    caller.join(5)
    assert results == [(True, 'done')] and seen_stop == [True]
    assert worker.running_s is None and worker.last_s >= 0.05
    assert not worker.cancel()  # nothing running
    assert worker.run(lambda: (True, 'again')) == (True, 'again')  # the cancel flag is cleared
    worker.shutdown()
    assert worker.run(lambda: (True, 'late')) == (False, 'shutting down')
