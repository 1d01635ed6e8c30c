"""Benchmark of the ROS chain mag1..4 -> tensor -> compensator -> gradient/compensated.

The tensor and compensator nodes run as separate processes (``python -m tetra_gradiometer
node ...``, default parameters, a calibration loaded so eq. 19 is applied). This script
plays the driver: it publishes sets of four MagneticField messages at a fixed rate, each
stamped with the wall-clock time of publication, and receives ``gradient/compensated``;
latency = receipt time - header stamp (driver stamp to compensated output, including the
last DDS hop). For each rate it reports sets sent/received, drops and p50/p99/max latency;
the maximum sustained rate is the highest rate with no drop.

    .venv/bin/python bench/bench_chain.py [--rates 100 200 300 400] [--seconds 5]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'test' / 'ros'))

from ros_helpers import NodeProcess, unique_domain, wait_for  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--rates', type=float, nargs='+', default=[100, 200, 300, 400, 500])
    parser.add_argument('--seconds', type=float, default=5.0, help='duration of each rate step')
    args = parser.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import JointState, MagneticField

    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer import core
    from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration
    from tetra_gradiometer.nodes.common import derived_qos

    domain = unique_domain()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    geometry = core.TetraGeometry.regular(0.5)
    rng = np.random.default_rng(1)
    vehicle = core.random_interference(rng, reference_clean=False)
    folder = Path(tempfile.mkdtemp(prefix='tg_bench_'))
    calibration = folder / 'calibration.yaml'
    # With a noise figure and a covariance, so the compensator also computes gradient/sigma and
    # runs its health monitor (issue 12): the throughput target holds with both.
    covariance = np.diag(np.r_[np.full(27, 1e-12), np.full(9, 1e-22)])
    save_calibration(calibration, CalibrationFile(vehicle.effective_parameters(), 'bench', False, geometry.to_flat(),
                                                  sensor_noise_t=1e-10, covariance=covariance))
    fields = vehicle.apply(np.tile([0.0, 2e-5, -4.5e-5], (1, 4, 1)), np.array([[0.0, 2e-5, -4.5e-5]]))[0]

    processes = [NodeProcess('tensor', domain, {'sensor_queue_depth': 200}),
                 NodeProcess('compensator', domain, {'calibration_file': str(calibration)})]
    rclpy.init(domain_id=domain)
    node = Node('bench', namespace='/tetra')
    types = cv.rclpy_types()
    mags = [node.create_publisher(MagneticField, t, 200) for t in cv.MAG_TOPICS]
    received: dict[int, int] = {}
    lock = threading.Lock()

    def on_compensated(msg: JointState) -> None:
        now = time.time_ns()
        with lock:
            received[cv.stamp_to_ns(msg.header.stamp)] = now

    node.create_subscription(JointState, 'gradient/compensated', on_compensated, derived_qos())
    executor = SingleThreadedExecutor()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    executor.add_node(node)
    spinner.start()
    results = []
    try:
        for publisher in mags:
            wait_for(lambda: publisher.get_subscription_count() >= 1, 30, 'the tensor node')
        wait_for(lambda: node.count_publishers('/tetra/gradient/compensated') >= 1, 30, 'the compensator')
        time.sleep(1.0)
        print(f'bench: ROS_DOMAIN_ID {domain}; tensor + compensator as separate processes; '
              f'{os.cpu_count()} CPUs (shared), load average {os.getloadavg()[0]:.2f}', flush=True)
        print(f'{"rate/s":>8} {"sent":>6} {"recv":>6} {"drops":>6} {"p50 ms":>8} {"p99 ms":>8} {"max ms":>8}')
        for rate in args.rates:
            with lock:
                received.clear()
            sent: list[int] = []
            period = 1.0 / rate
            start = time.monotonic()
            n = int(rate * args.seconds)
            for i in range(n):
                delay = start + i * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                stamp = time.time_ns()
                for s in range(4):
                    mags[s].publish(cv.magnetic_field_msg(types, fields[s], stamp, cv.MAG_FRAMES[s]))
                sent.append(stamp)
            achieved = n / (time.monotonic() - start)
            time.sleep(1.0)
            with lock:
                latencies = np.array([received[s] - s for s in sent if s in received]) * 1e-6
            drops = n - len(latencies)
            p50, p99, worst = (np.percentile(latencies, [50, 99]).tolist() + [latencies.max()]
                               if len(latencies) else [float('nan')] * 3)
            results.append((rate, achieved, n, len(latencies), drops, p50, p99, worst))
            print(f'{rate:8.0f} {n:6d} {len(latencies):6d} {drops:6d} {p50:8.2f} {p99:8.2f} {worst:8.2f}'
                  + ('' if achieved > 0.98 * rate else f'  (publisher reached only {achieved:.0f}/s)'), flush=True)
        clean = [r for r in results if r[4] == 0 and r[1] > 0.98 * r[0]]
        fast = [r for r in clean if r[6] < 10.0]
        best = max(clean, key=lambda r: r[0]) if clean else None
        best_fast = max(fast, key=lambda r: r[0]) if fast else None
        print(f'RESULT max_rate_no_drops={best[0] if best else 0:.0f}/s '
              f'(p50 {best[5] if best else float("nan"):.2f} ms, p99 {best[6] if best else float("nan"):.2f} ms); '
              f'max_rate_no_drops_p99_under_10ms={best_fast[0] if best_fast else 0:.0f}/s; '
              f'load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs')
    finally:
        executor.shutdown(timeout_sec=2)
        if spinner.is_alive():
            spinner.join(timeout=5)
        node.destroy_node()
        rclpy.try_shutdown()
        for process in processes:
            process.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
