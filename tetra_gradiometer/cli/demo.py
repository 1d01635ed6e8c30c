"""``python -m tetra_gradiometer demo --out DIR``: the main job, end to end over ROS 2.

Brings the four nodes up in this process (sim mode, built-in scenario, driver at ``--rate``
times real time, holding between the trim and the survey), then, as an operator would:
``calibrator/start``, play the trim manoeuvre, ``calibrator/stop``, ``calibrator/calibrate``;
waits for the compensator to take the latched calibration; plays the survey pass over the
dipole while collecting ``gradient/raw``, ``gradient/compensated`` and ``gradient/truth``.
Prints progress and the calibration summary (with the error of the identified parameters
against the simulator's exact ones), saves ``DIR/norms.png`` (Frobenius norms, nT/m) and
ends with one ``RESULT`` line computed from the collected topics.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..core.identification import CALIBRATION_METHODS, DEFAULT_METHOD
from ..core.units import NT_PER_T, S_PER_NS
from ..io.outputs import DEMO, atomic_output, check_output
from .node import PARAMS_HELP, ros_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--out', default='out/demo', help='output folder (default %(default)s)')
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous demo folder at --out (anything else there is refused)',
    )
    parser.add_argument(
        '--rate',
        type=float,
        default=20.0,
        help='driver speed, multiple of real time (default %(default)s)',
    )
    parser.add_argument(
        '--method',
        default=DEFAULT_METHOD,
        choices=CALIBRATION_METHODS,
        help='the calibrator node\'s method (default %(default)s)',
    )
    parser.add_argument('--params', default='', help=PARAMS_HELP)


def _say(text: str) -> None:
    print(text, flush=True)


def _domain() -> int:
    """This run's ROS_DOMAIN_ID: the environment's, else one derived from the pid (1..100)."""
    value = os.environ.get('ROS_DOMAIN_ID')
    return int(value) if value else 1 + os.getpid() % 100


def run(args: argparse.Namespace) -> int:
    inputs = (args.params,) if args.params else ()
    check_output(args.out, DEMO, force=args.force, inputs=inputs)  # refuse before starting ROS
    with atomic_output(args.out, DEMO, force=args.force, inputs=inputs, command='demo') as folder:
        folder.mkdir()
        return _fly(args, folder, Path(args.out))


def _fly(args: argparse.Namespace, out: Path, final: Path) -> int:
    """The demo, writing into ``out`` (the temporary folder that becomes ``final``)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    from ..core import summarize
    from ..io.calibration import load_calibration
    from ..nodes.calibrator import CalibratorNode
    from ..nodes.common import interrupt_on_signals, stop_graph
    from ..nodes.compensator import CompensatorNode
    from ..nodes.driver import DriverNode
    from ..nodes.tensor import TensorNode
    from ._probe import Probe

    calibration_file = (out / 'calibration.yaml').resolve()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    domain = _domain()
    interrupt_on_signals()
    rclpy.init(
        args=ros_arguments(args.params, ['--log-level', 'warn']),
        domain_id=domain,
        signal_handler_options=SignalHandlerOptions.NO,
    )  # Ctrl-C: KeyboardInterrupt, clean stop
    cal = [Parameter('calibration_file', value=str(calibration_file))]
    nodes: list = []
    # One thread: in rclpy the MultiThreadedExecutor lost ~25 % of the sets at 200 sets/s in
    # one process (GIL and task overhead); the single-threaded one lost none.
    executor = SingleThreadedExecutor()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    started = time.monotonic()
    try:
        nodes = [
            TensorNode(),
            CalibratorNode(parameter_overrides=cal + [Parameter('method', value=args.method)]),
            CompensatorNode(parameter_overrides=cal),
            DriverNode(
                parameter_overrides=[
                    Parameter('mode', value='sim'),
                    Parameter('rate', value=args.rate),
                    Parameter('start_paused', value=True),
                    Parameter('hold_between_segments', value=True),
                    Parameter('min_subscribers', value=1),
                ]
            ),
        ]
        probe = Probe('demo')
        nodes.append(probe)
        for node in nodes:
            executor.add_node(node)
        spinner.start()
        driver = 'driver'
        _say(
            f'demo: ROS_DOMAIN_ID {domain}; sim at {args.rate:g}x real time; '
            f'{nodes[3].info["samples"]} samples ({nodes[3].info["segments"]})'
        )
        probe.wait_for(
            lambda: probe.status('tetra/compensator: compensation').get('compensating') == 'False',
            20,
            'the compensator (uncompensated before any calibration)',
        )
        _say(
            'demo: compensator up, uncompensated (no calibration yet): '
            + probe.status('tetra/compensator: compensation')['message'][:100]
        )

        _say('demo: calibrator/start; trim manoeuvre 3 km from the target ...')
        _expect(probe.call('calibrator/start'))
        _expect(probe.call(f'{driver}/resume'))
        _progress(
            probe, lambda: probe.status('tetra/driver: playback').get('state') == 'holding', 'trim'
        )
        _say(f'demo: calibrator/stop: {_expect(probe.call("calibrator/stop"))}')
        reply = probe.call('calibrator/calibrate', timeout_s=120)
        if not reply.success:
            _say(f'demo: calibration failed: {reply.message}')
            return 1
        _say(f'demo: calibrator/calibrate: {reply.message}')
        probe.wait_for(
            lambda: probe.status('tetra/compensator: compensation').get('compensating') == 'True',
            20,
            'the compensator to take the calibration',
        )
        _summarise_calibration(load_calibration(calibration_file))

        _say('demo: survey pass over the dipole ...')
        with probe.lock:
            probe.collecting = True
        _expect(probe.call(f'{driver}/resume'))
        _progress(
            probe,
            lambda: probe.status('tetra/driver: playback').get('state') == 'finished',
            'survey',
        )
        _settle(probe)
        stamps, g_raw, g_comp, g_true = probe.paired()
        if len(stamps) < 10:
            _say(f'demo: only {len(stamps)} survey samples arrived')
            return 1
        tensor_diag = probe.status('tetra/tensor: matching')
        _say(
            f'demo: survey: {len(stamps)} samples compensated; tensor node: {tensor_diag.get("message")}, '
            f'invalid sets {tensor_diag.get("sets_dropped_invalid")}, unmatched messages '
            f'{tensor_diag.get("messages_dropped_unmatched")}'
        )
        metrics = summarize(g_raw, g_comp, g_true)
        _say(f'demo: compensator running compensated_percent topic: {probe.percent:.4f} %')
        _plot(out / 'norms.png', stamps, g_raw, g_comp, g_true, metrics)
        _say(
            f'demo: plot {final / "norms.png"}; calibration {final / "calibration.yaml"}; '
            f'{time.monotonic() - started:.1f} s'
        )
        print(
            f'RESULT compensated_percent={metrics["compensated_percent"]:.4f} '
            f'rms_residual_nT_per_m={metrics["rms_residual_nT_per_m"]:.4f} '
            f'improvement_ratio={metrics["improvement_ratio"]:.2f}',
            flush=True,
        )
        return 0
    except TimeoutError as error:
        print(f'error: {error}', file=sys.stderr)
        return 1
    finally:
        stop_graph(executor, spinner, nodes)


def _settle(probe, quiet_s: float = 1.0, timeout_s: float = 30.0) -> None:
    """Wait until no tensor has arrived for ``quiet_s`` (the graph has drained)."""
    deadline = time.monotonic() + timeout_s
    last, since = dict(probe.counts), time.monotonic()
    while time.monotonic() - since < quiet_s and time.monotonic() < deadline:
        time.sleep(0.1)
        if probe.counts != last:
            last, since = dict(probe.counts), time.monotonic()


def _expect(reply) -> str:
    if not reply.success:
        raise TimeoutError(f'service refused: {reply.message}')
    return reply.message


def _progress(probe, done, label: str, timeout_s: float = 600.0) -> None:
    deadline = time.monotonic() + timeout_s
    last = 0.0
    while not done():
        if time.monotonic() > deadline:
            raise TimeoutError(f'the {label} did not finish within {timeout_s:g} s')
        if time.monotonic() - last > 2.0:
            last = time.monotonic()
            _say(f'demo:   {label}: {probe.counts["gradient/raw"]} tensors so far')
        time.sleep(0.05)


def _summarise_calibration(calibration) -> None:
    """Print the file's diagnostics and its error against the simulator's exact parameters."""
    from ..io.scenario import load_scenario_or_default

    scenario, _ = load_scenario_or_default()
    exact = scenario.interference.effective_parameters()
    d = calibration.diagnostics
    k_err = np.abs(calibration.parameters.k_soft - exact.k_soft).max()
    b_err = np.abs(calibration.parameters.b_hard - exact.b_hard).max() * NT_PER_T
    _say(
        f'demo: calibration {calibration.method}: {d.get("n_samples")} samples, {d.get("n_parameters")} '
        f'parameters, rank {d.get("rank")}, fit residual {d.get("residual_rms_nT_per_m", float("nan")):.3g} nT/m, '
        f'estimated sensor noise {d.get("sensor_noise_nT", float("nan")):.3g} nT'
    )
    _say(
        f'demo: against the simulator: max |k error| {k_err:.2e} (largest |k| '
        f'{np.abs(exact.k_soft).max():.2e}), max |b error| {b_err:.3g} nT (largest |b| '
        f'{np.abs(exact.b_hard).max() * NT_PER_T:.3g} nT)'
    )


def _plot(
    path: Path,
    stamps: np.ndarray,
    g_raw: np.ndarray,
    g_comp: np.ndarray,
    g_true: np.ndarray,
    metrics: dict,
) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    t = (stamps - stamps[0]) * S_PER_NS
    norm = {
        name: np.linalg.norm(g, axis=(1, 2)) * NT_PER_T
        for name, g in (('raw', g_raw), ('compensated', g_comp), ('true', g_true))
    }
    fig, (top, bottom) = plt.subplots(
        2, 1, figsize=(9, 6.5), sharex=True, gridspec_kw={'height_ratios': [2, 1]}
    )
    top.plot(t, norm['raw'], color='tab:red', lw=1.2, label='raw $G_m$ (eq. 7)')
    top.plot(t, norm['true'], color='black', lw=2.5, alpha=0.5, label='true (simulator)')
    top.plot(
        t, norm['compensated'], color='tab:blue', lw=1.0, ls='--', label='compensated (eq. 19)'
    )
    top.set_ylabel('Frobenius norm (nT/m)')
    top.set_title(
        f'Survey pass over a dipole: {metrics["compensated_percent"]:.3f} % compensated (eq. 24), '
        f'RMS residual {metrics["rms_residual_nT_per_m"]:.2f} nT/m',
        fontsize=10,
    )
    top.legend(loc='upper left')
    top.grid(alpha=0.3)
    bottom.plot(t, norm['raw'] - norm['true'], color='tab:red', lw=1, label='raw - true')
    bottom.plot(
        t, norm['compensated'] - norm['true'], color='tab:blue', lw=1, label='compensated - true'
    )
    bottom.set_ylabel('norm error (nT/m)')
    bottom.set_xlabel('time along the survey line (s)')
    bottom.set_yscale('symlog', linthresh=1.0)
    bottom.legend(loc='upper left')
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=110)
    plt.close(fig)
