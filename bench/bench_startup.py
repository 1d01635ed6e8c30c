"""Start-up cost of each on-vehicle node (issue 33): from the process start to the node
being active (autostart: configured and activated by itself), and its resident memory then.

    .venv/bin/python bench/bench_startup.py [--repeat 3] [--json FILE]

Each node runs alone as ``python -m tetra_gradiometer node NAME`` (the driver in ``sim``
mode) on its own ROS domain, localhost discovery; this process asks its
``~/get_state`` every 20 ms (lifecycle_msgs/GetState) and reads the child's ``VmRSS``
from /proc once it answers ``active``. The import of the node's module alone is timed in a
fresh interpreter too (the part the package controls). Medians over ``--repeat`` runs.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NODES = ('tensor', 'calibrator', 'compensator', 'target', 'driver')


def import_time(node: str) -> float:
    code = ('import time; t = time.perf_counter(); '
            f'import tetra_gradiometer.nodes.{node}; print(time.perf_counter() - t)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    return float(out.stdout.strip())


def active_time(node: str, domain: int) -> tuple[float, float]:
    """(seconds to active, VmRSS MB) of one node process."""
    import rclpy
    from lifecycle_msgs.srv import GetState
    from rclpy.executors import SingleThreadedExecutor

    env = dict(os.environ, PYTHONPATH=str(REPO), ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    command = [sys.executable, '-m', 'tetra_gradiometer', 'node', node]
    if node == 'driver':
        command += ['--ros-args', '-p', 'mode:=sim']
    context = rclpy.Context()
    os.environ.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    rclpy.init(context=context)
    probe = rclpy.create_node('startup_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    client = probe.create_client(GetState, f'/tetra/{node}/get_state')
    started = time.perf_counter()
    child = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while time.perf_counter() - started < 60:
            if client.service_is_ready():
                future = client.call_async(GetState.Request())
                executor.spin_until_future_complete(future, timeout_sec=0.5)
                if future.done() and future.result().current_state.label == 'active':
                    elapsed = time.perf_counter() - started
                    rss = _rss_mb(child.pid)
                    return elapsed, rss
            else:
                executor.spin_once(timeout_sec=0.02)
        raise SystemExit(f'{node} did not become active within 60 s')
    finally:
        child.terminate()
        child.wait(timeout=20)
        executor.shutdown()
        probe.destroy_node()
        rclpy.shutdown(context=context)


def _rss_mb(pid: int) -> float:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--json', default=None)
    args = parser.parse_args()
    rows = []
    for i, node in enumerate(NODES):
        runs = [active_time(node, 60 + 5 * i + r) for r in range(args.repeat)]
        imports = [import_time(node) for _ in range(args.repeat)]
        row = {'node': node, 'import_s': statistics.median(imports),
               'to_active_s': statistics.median(r[0] for r in runs),
               'rss_mb': statistics.median(r[1] for r in runs)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    print('\n| node | import of its module, s | process start -> active, s | resident memory, MB |')
    print('|---|---|---|---|')
    for r in rows:
        print(f'| {r["node"]} | {r["import_s"]:.2f} | {r["to_active_s"]:.2f} | {r["rss_mb"]:.0f} |')
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
