"""Benchmark of the ROS chain mag1..4 -> tensor -> compensator -> gradient/compensated.

The tensor and compensator nodes run as separate processes (``python -m tetra_gradiometer
node ...``, default parameters but the tensor node's ``sync``, a calibration loaded so eq. 19
is applied). This script plays the driver: it publishes sets of four MagneticField messages
at a fixed rate and receives ``gradient/compensated``. Synchronous sets (the default, all
offsets 0): the four messages of a set carry one stamp, the wall-clock time of publication.
With ``--offsets-ms`` (sensors on their own clocks), each sensor's message is published
at its own instant, the set's reference instant + that sensor's offset, and stamped with the
wall-clock time of its own publication (sensors with equal offsets share a stamp).
Latency = receipt time - sensor 1's stamp (the reference instant, the set's stamp carried
to ``gradient/compensated``), driver to compensated output including the last DDS hop
and, with offsets, the wait for the latest sensor. For each rate it reports sets
sent/received, drops and p50/p99/max latency; the maximum sustained rate is the highest rate
with no drop (the queues are deep: an overloaded chain shows a growing p50 before drops).
Each rate step begins with 2 sets that are published but not counted: after
the pause between steps (and at the start) the resampler needs two earlier samples of every
sensor before it interpolates, so with offsets those sets are skipped by design.

    .venv/bin/python bench/bench_chain.py [--rates 100 200 300 400] [--seconds 5]
        [--sync interpolate|nearest] [--offsets-ms 0 0.5 2.1 4.0] [--busy 2] [--json FILE]

The ``diag`` column is the tensor node's worst ``/diagnostics`` level during the step, and
below it what its WARN and ERROR statuses said: a chain that loses sets must say so.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'test' / 'ros'))

from ros_helpers import NodeProcess, unique_domain, wait_for  # noqa: E402

#: Sets published at the start of each rate step and not counted (see the docstring).
LEAD_IN_SETS = 2


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--rates', type=float, nargs='+', default=[100, 200, 300, 400, 500])
    parser.add_argument('--seconds', type=float, default=5.0, help='duration of each rate step')
    parser.add_argument('--sync', choices=('interpolate', 'nearest'), default='interpolate',
                        help="the tensor node's parameter sync")
    parser.add_argument('--queue-depth', type=int, default=200,
                        help="the tensor node's sensor_queue_depth")
    parser.add_argument('--busy', type=int, default=0,
                        help='processes spinning on the CPUs beside the chain (a busy machine)')
    parser.add_argument('--json', default=None,
                        help='write the rows here (bench/results/chain.json: the README table)')
    parser.add_argument('--trace', default=None,
                        help="write each counted set's stamp (ns) and latency (ms) here (.npz, "
                             'one array per rate): where the tail lies in time')
    parser.add_argument('--offsets-ms', type=float, nargs=4, default=[0.0] * 4,
                        metavar=('O1', 'O2', 'O3', 'O4'),
                        help="each sensor's publication instant after the reference instant, ms")
    return parser.parse_args()


def write_calibration(folder: Path) -> tuple[Path, np.ndarray]:
    """A calibration file in ``folder`` and the four fields (4, 3) T the driver publishes."""
    from tetra_gradiometer import core
    from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration

    geometry = core.TetraGeometry.regular(0.5)
    rng = np.random.default_rng(1)
    vehicle = core.random_interference(rng, reference_clean=False)
    calibration = folder / 'calibration.yaml'
    # With a noise figure and a covariance, so the compensator also computes g_sigma and
    # runs its health monitor (issue 12): the throughput target holds with both.
    covariance = np.diag(np.r_[np.full(27, 1e-12), np.full(9, 1e-22)])
    save_calibration(calibration, CalibrationFile(
        vehicle.effective_parameters(), 'bench', False, geometry.to_flat(),
        sensor_noise_t=1e-10, covariance=covariance))
    earth = np.array([[0.0, 2e-5, -4.5e-5]])
    fields = vehicle.apply(np.tile(earth, (1, 4, 1)), earth)[0]
    return calibration, fields


Event = tuple[float, int, tuple[int, ...]]


def schedule(rate: float, n: int, offsets_ms: list[float]) -> list[Event]:
    """Publication events ``(seconds from the step start, set index, sensors)`` in time order;
    sensors with equal offsets publish together (all four when synchronous)."""
    groups: dict[float, tuple[int, ...]] = {}
    for s, offset in enumerate(offsets_ms):
        groups[offset] = groups.get(offset, ()) + (s,)
    first = min(offsets_ms)
    events = [(i / rate + (offset - first) * 1e-3, i, sensors)
              for i in range(n) for offset, sensors in groups.items()]
    return sorted(events, key=lambda e: (e[0], e[1]))


class Driver:
    """The bench node: four magnetometer publishers and the ``gradient/compensated`` receipts."""

    def __init__(self, fields: np.ndarray) -> None:
        from rclpy.node import Node
        from sensor_msgs.msg import MagneticField

        from tetra_gradiometer.io import conversions as cv
        from tetra_gradiometer.io import gradient_tensor as gt
        from tetra_gradiometer.nodes.common import derived_qos

        self.cv, self.fields = cv, fields
        self.node = Node('bench', namespace='/tetra')
        self.mags = [self.node.create_publisher(MagneticField, t, 200) for t in cv.MAG_TOPICS]
        self.received: dict[int, int] = {}
        self.trace: dict[float, np.ndarray] = {}  # rate -> (stamp ns, latency ms) per set
        self.lock = threading.Lock()
        self.node.create_subscription(gt.rclpy_class(), 'gradient/compensated', self._on_compensated,
                                      derived_qos(), raw=True)
        from diagnostic_msgs.msg import DiagnosticArray

        self.statuses: dict[str, tuple[int, str]] = {}  # the tensor node's, worst of the step
        self.collecting = False
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)

    def _on_diagnostics(self, msg: Any) -> None:
        with self.lock:
            if not self.collecting:
                return
            for status in msg.status:
                if status.name.startswith('tetra/tensor: '):
                    level = status.level[0] if isinstance(status.level, bytes) else status.level
                    if level >= self.statuses.get(status.name, (-1, ''))[0]:
                        self.statuses[status.name] = (level, status.message)

    def _on_compensated(self, data: bytes) -> None:
        now = time.time_ns()
        with self.lock:
            self.received[self.cv.stamp_from_cdr(data)] = now

    def wait_for_chain(self) -> None:
        for publisher in self.mags:
            wait_for(lambda p=publisher: p.get_subscription_count() >= 1, 30, 'the tensor node')
        wait_for(lambda: self.node.count_publishers('/tetra/gradient/compensated') >= 1, 30,
                 'the compensator')

    def publish(self, sensors: tuple[int, ...]) -> int:
        """Publish the readings of ``sensors`` now, stamped now; return the stamp (ns).
        Serialized by io/conversions' CDR writer (the tensor node's path for its outputs), so
        the bench driver takes as little of the two CPUs as a C++ driver would."""
        cv, stamp = self.cv, time.time_ns()
        for s in sensors:
            self.mags[s].publish(cv.magnetic_field_cdr(self.fields[s], stamp, cv.MAG_FRAMES[s]))
        return stamp

    def run_step(self, rate: float, seconds: float, offsets_ms: list[float]) -> tuple:
        """One rate step: ``(rate, achieved, sent, received, drops, p50, p99, max)``, ms."""
        with self.lock:
            self.received.clear()
            self.statuses.clear()
            self.collecting = True
        n = int(rate * seconds)
        reference: dict[int, int] = {}  # set index -> sensor 1's stamp
        events = schedule(rate, LEAD_IN_SETS + n, offsets_ms)
        start = time.monotonic()
        for at, i, sensors in events:
            delay = start + at - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            stamp = self.publish(sensors)
            if 0 in sensors:
                reference[i] = stamp
        achieved = n / max(time.monotonic() - start - LEAD_IN_SETS / rate, 1e-9)
        time.sleep(0.8)  # the last sets, and the diagnostics that saw them (every 1 s)
        with self.lock:
            self.collecting = False  # the silence after the step is not the step's
        time.sleep(0.7)
        sent = [reference[i] for i in range(LEAD_IN_SETS, LEAD_IN_SETS + n)]
        with self.lock:
            latencies = np.array([self.received[s] - s for s in sent if s in self.received]) * 1e-6
        drops = n - len(latencies)
        p50, p99, worst = (np.percentile(latencies, [50, 99]).tolist() + [latencies.max()]
                           if len(latencies) else [float('nan')] * 3)
        self.trace[rate] = np.array([(s, (self.received[s] - s) * 1e-6)
                                     for s in sent if s in self.received]).reshape(-1, 2)
        return rate, achieved, n, len(latencies), drops, p50, p99, worst


def gc_pauses() -> list[float]:
    """This process's garbage collections from now on: their durations (s), appended."""
    pauses: list[float] = []
    started = [0.0]

    def note(phase: str, info: dict) -> None:
        if phase == 'start':
            started[0] = time.perf_counter()
        else:
            pauses.append(time.perf_counter() - started[0])

    gc.callbacks.append(note)
    return pauses


def session_cpu_s(session: int) -> float:
    """CPU time (user + system, s) of every process of a session (a node process and the
    Python it re-executes: ros_wheels_bootstrapper), from /proc (Linux)."""
    total, tick = 0, os.sysconf('SC_CLK_TCK')
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
        except OSError:  # exited meanwhile
            continue
        if int(fields[3]) == session:  # field 6 of stat: the session id
            total += int(fields[11]) + int(fields[12])  # utime, stime
    return total / tick


def own_cpu_s() -> float:
    """CPU time (s) of this process, all its threads (the bench driver and its DDS)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def print_step(result: tuple, statuses: dict[str, tuple[int, str]]) -> None:
    rate, achieved, n, count, drops, p50, p99, worst = result
    short = '' if achieved > 0.98 * rate else f'  (publisher reached only {achieved:.0f}/s)'
    level = max((lv for lv, _ in statuses.values()), default=-1)
    print(f'{rate:8.0f} {n:6d} {count:6d} {drops:6d} {p50:8.2f} {p99:8.2f} {worst:8.2f} '
          f'{"OK WARN ERROR".split()[level] if level >= 0 else "none":>6}{short}', flush=True)
    for name, (lv, text) in sorted(statuses.items()):
        if lv > 0:  # what the tensor node said of the step (its worst)
            print(f'    {name}: {text}', flush=True)


def print_result(results: list[tuple]) -> None:
    clean = [r for r in results if r[4] == 0 and r[1] > 0.98 * r[0]]
    fast = [r for r in clean if r[6] < 10.0]
    best = max(clean, key=lambda r: r[0]) if clean else None
    best_fast = max(fast, key=lambda r: r[0]) if fast else None
    p50, p99 = (best[5], best[6]) if best else (float('nan'), float('nan'))
    print(f'RESULT max_rate_no_drops={best[0] if best else 0:.0f}/s '
          f'(p50 {p50:.2f} ms, p99 {p99:.2f} ms); '
          f'max_rate_no_drops_p99_under_10ms={best_fast[0] if best_fast else 0:.0f}/s; '
          f'load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs')


def main() -> int:
    args = parse_args()
    import rclpy

    from tetra_gradiometer.nodes.process import events_executor, spin

    domain = unique_domain()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(args.busy)]
    calibration, fields = write_calibration(Path(tempfile.mkdtemp(prefix='tg_bench_')))
    processes = [NodeProcess('tensor', domain, {'sensor_queue_depth': args.queue_depth, 'sync': args.sync}),
                 NodeProcess('compensator', domain, {'calibration_file': str(calibration)})]
    rclpy.init(domain_id=domain)
    driver = Driver(fields)
    executor = events_executor()  # as the nodes (nodes/process.spin_node)
    spinner = threading.Thread(target=spin, args=(executor,), daemon=True)
    executor.add_node(driver.node)
    spinner.start()
    try:
        driver.wait_for_chain()
        time.sleep(1.0)
        # As the nodes do (nodes/process.spin_node): a full collection walking start-up's
        # objects would pause the driver and its receipts, not the chain.
        gc.collect()
        gc.freeze()
        pauses = gc_pauses()
        offsets = ' '.join(f'{o:g}' for o in args.offsets_ms)
        print(f'bench: ROS_DOMAIN_ID {domain}; tensor (sync {args.sync}) + compensator as '
              f'separate processes; sensor offsets {offsets} ms; {os.cpu_count()} CPUs (shared), '
              f'load average {os.getloadavg()[0]:.2f}', flush=True)
        print(f'{"rate/s":>8} {"sent":>6} {"recv":>6} {"drops":>6} {"p50 ms":>8} {"p99 ms":>8} '
              f'{"max ms":>8} {"diag":>6}')
        results, cpu = [], []
        for rate in args.rates:
            before = [session_cpu_s(p.process.pid) for p in processes] + [own_cpu_s()]
            results.append(driver.run_step(rate, args.seconds, args.offsets_ms))
            after = [session_cpu_s(p.process.pid) for p in processes] + [own_cpu_s()]
            cpu.append([(b - a) / results[-1][3] * 1000 for a, b in zip(before, after, strict=True)])
            with driver.lock:
                print_step(results[-1], dict(driver.statuses))
        print_result(results)
        print(f'bench driver: {len(pauses)} garbage collections, longest '
              f'{max(pauses, default=0.0) * 1e3:.2f} ms')
        for (rate, *_), (tensor, compensator, bench) in zip(results, cpu, strict=True):
            print(f'CPU per 1000 sets at {rate:.0f}/s: tensor {tensor:.2f} s, compensator '
                  f'{compensator:.2f} s, bench driver {bench:.2f} s (total '
                  f'{tensor + compensator + bench:.2f} s)')
        if args.trace:
            np.savez(args.trace, **{f'rate_{r:g}': t for r, t in driver.trace.items()})
        if args.json:
            rows = [{'rate': int(r[0]), 'sent': r[2], 'received': r[3], 'p50_ms': round(r[5], 2),
                     'p99_ms': round(r[6], 2), 'max_ms': round(r[7], 2),
                     'cpu_s_per_1000_sets': round(sum(c), 2)}
                    for r, c in zip(results, cpu, strict=True)]
            Path(args.json).write_text(json.dumps(
                {'bench': 'bench/bench_chain.py ' + ' '.join(sys.argv[1:]), 'rows': rows},
                indent=1) + '\n')
    finally:
        for process in busy:
            process.kill()
        executor.shutdown(timeout_sec=2)
        if spinner.is_alive():
            spinner.join(timeout=5)
        driver.node.destroy_node()
        rclpy.try_shutdown()
        for process in processes:
            process.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
