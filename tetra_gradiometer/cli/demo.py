"""``python -m tetra_gradiometer demo --out DIR``: the main job, end to end over ROS 2.

Brings the four nodes up in this process (sim mode, built-in scenario, the driver paced by
the tensor node, or at ``--rate`` times real time, holding between the trim and the
survey), then, as an operator would:
``calibrator/start``, play the trim manoeuvre, ``calibrator/stop``, ``calibrator/calibrate``;
waits for the compensator to take the latched calibration; plays the survey pass over the
dipole while collecting ``gradient/raw``, ``gradient/compensated`` and ``gradient/truth``.
Prints progress and the calibration summary (with the error of the identified parameters
against the simulator's exact ones), saves ``DIR/norms.png`` (Frobenius norms, nT/m) and
ends with one ``RESULT`` line computed from the collected topics.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.identification import CALIBRATION_METHODS, DEFAULT_METHOD
from ..core.units import NT_PER_T, S_PER_NS
from ..io.outputs import DEMO, atomic_output, check_output
from ._args import MAX_RATE, finite_float
from .node import PARAMS_HELP

if TYPE_CHECKING:
    from ..io.calibration import CalibrationFile
    from ._probe import Probe

#: The /diagnostics statuses the demo follows.
COMPENSATION = 'tetra/compensator: compensation'
PLAYBACK = 'tetra/driver: playback'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--out', default='out/demo', help='output folder (default %(default)s)')
    parser.add_argument(
        '--force',
        action='store_true',
        help='replace a previous demo folder at --out (anything else there is refused)',
    )
    parser.add_argument(
        '--rate',
        type=finite_float(0.0, MAX_RATE),
        default=0.0,
        help=f'driver speed, multiple of real time, 0 <= x <= {MAX_RATE:g}; 0 (the default): as '
        'fast as the tensor node takes the sets, paced by it, so none is lost on a loaded machine',
    )
    parser.add_argument(
        '--method',
        default=DEFAULT_METHOD,
        choices=CALIBRATION_METHODS,
        help="the calibrator node's method (default %(default)s)",
    )
    parser.add_argument('--params', default='', help=PARAMS_HELP)


def _say(text: str) -> None:
    print(text, flush=True)


def run(args: argparse.Namespace) -> int:
    inputs = (args.params,) if args.params else ()
    check_output(args.out, DEMO, force=args.force, inputs=inputs)  # refuse before starting ROS
    with atomic_output(args.out, DEMO, force=args.force, inputs=inputs, command='demo') as folder:
        folder.mkdir()
        return _fly(args, folder, Path(args.out))


def _fly(args: argparse.Namespace, out: Path, final: Path) -> int:
    """The demo, writing into ``out`` (the temporary folder that becomes ``final``)."""
    from rclpy.executors import SingleThreadedExecutor

    from ..nodes.process import stop_graph
    from ._probe import Probe, init_local_ros

    calibration_file = (out / 'calibration.yaml').resolve()
    domain = init_local_ros(args.params)  # Ctrl-C: KeyboardInterrupt, clean stop
    nodes: list[Any] = []
    # One thread: in rclpy the MultiThreadedExecutor lost ~25 % of the sets at 200 sets/s in
    # one process (GIL and task overhead); the single-threaded one lost none.
    executor = SingleThreadedExecutor()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    started = time.monotonic()
    try:
        nodes = _graph(args.method, args.rate, calibration_file)
        driver = nodes[-1]
        probe = Probe('demo')
        nodes.append(probe)
        for node in nodes:
            executor.add_node(node)
        spinner.start()
        _say(
            f'demo: ROS_DOMAIN_ID {domain}; sim '
            + (f'at {args.rate:g}x real time; ' if args.rate else 'paced by the tensor node; ')
            + f'{driver.info["samples"]} samples ({driver.info["segments"]})'
        )
        if not _calibrate(probe, calibration_file):
            return 1
        published, (stamps, g_raw, g_comp, g_true) = _survey(probe)
        if len(stamps) < 10:
            _say(f'demo: only {len(stamps)} survey samples arrived')
            return 1
        metrics = _report(probe, published, stamps, g_raw, g_comp, g_true, out)
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
        stop_graph([executor], spinner, nodes)


def _graph(method: str, rate: float, calibration_file: Path) -> list[Any]:
    """tensor, calibrator, compensator and the sim driver (paused, holding between segments)."""
    from rclpy.parameter import Parameter

    from ..nodes.calibrator import CalibratorNode
    from ..nodes.compensator import CompensatorNode
    from ..nodes.driver import DriverNode
    from ..nodes.tensor import TensorNode

    cal = [Parameter('calibration_file', value=str(calibration_file))]
    nodes: list[Any] = []
    try:
        nodes.append(TensorNode())
        nodes.append(CalibratorNode(parameter_overrides=cal + [Parameter('method', value=method)]))
        nodes.append(CompensatorNode(parameter_overrides=cal))
        driver = [
            Parameter('mode', value='sim'),
            Parameter('rate', value=rate),
            Parameter('start_paused', value=True),
            Parameter('hold_between_segments', value=True),
            Parameter('min_subscribers', value=1),
        ]
        nodes.append(DriverNode(parameter_overrides=driver))
    except BaseException:
        for node in nodes:
            node.destroy_node()
        raise
    return nodes


def _compensating(probe: Probe) -> str | None:
    """The compensator's ``compensating`` diagnostic value ('True', 'False') or None."""
    return probe.status(COMPENSATION).get('compensating')


def _calibrate(probe: Probe, calibration_file: Path) -> bool:
    """Trim manoeuvre between ``calibrator/start`` and ``/stop``, then ``calibrator/calibrate``;
    wait for the compensator to take the calibration. False when the calibration is refused."""
    from ..io.calibration import load_calibration

    probe.wait_for(
        lambda: _compensating(probe) == 'False',
        20,
        'the compensator (uncompensated before any calibration)',
    )
    _say(
        'demo: compensator up, uncompensated (no calibration yet): '
        + probe.status(COMPENSATION)['message'][:100]
    )
    _say('demo: calibrator/start; trim manoeuvre 3 km from the target ...')
    _expect(probe.call('calibrator/start'))
    _expect(probe.call('driver/resume'))
    _progress(probe, lambda: probe.status(PLAYBACK).get('state') == 'holding', 'trim')
    _say(f'demo: calibrator/stop: {_expect(probe.call("calibrator/stop"))}')
    reply = probe.call('calibrator/calibrate', timeout_s=120)
    if not reply.success:
        _say(f'demo: calibration failed: {reply.message}')
        return False
    _say(f'demo: calibrator/calibrate: {reply.message}')
    probe.wait_for(
        lambda: _compensating(probe) == 'True', 20, 'the compensator to take the calibration'
    )
    _summarise_calibration(load_calibration(calibration_file))
    return True


def _published(probe: Probe) -> int:
    """The sets the driver has published so far (its playback diagnostics)."""
    return int(probe.status(PLAYBACK).get('sets_published', 0))


def _survey(probe: Probe) -> tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Play the survey pass while the probe collects: the sets the driver published, and the
    stamps (n,) ns and the raw, compensated and true tensors (n, 3, 3) T/m on their common
    stamps."""
    _say('demo: survey pass over the dipole ...')
    with probe.lock:
        probe.collecting = True
    before = _published(probe)
    _expect(probe.call('driver/resume'))
    _progress(probe, lambda: probe.status(PLAYBACK).get('state') == 'finished', 'survey')
    _settle(probe)
    return _published(probe) - before, probe.paired()


def _report(
    probe: Probe,
    published: int,
    stamps: np.ndarray,
    g_raw: np.ndarray,
    g_comp: np.ndarray,
    g_true: np.ndarray,
    out: Path,
) -> dict[str, float]:
    """Print the survey's counts (of the ``published`` sets), save ``out/norms.png``; return
    the eq. 24 metrics."""
    from ..core import summarize

    tensor_diag = probe.status('tetra/tensor: matching')
    _say(
        f'demo: survey: {len(stamps)} of {published} sets compensated; tensor node: '
        f'{tensor_diag.get("message")}, invalid sets {tensor_diag.get("sets_dropped_invalid")}, '
        f'unmatched messages {tensor_diag.get("messages_dropped_unmatched")}'
    )
    if len(stamps) < published:
        # Best-effort transport drops what a starved process does not take in time: the
        # figures below are then those of the sets that arrived.
        _say(
            f'demo: {published - len(stamps)} survey sets lost (a loaded machine at '
            '--rate > 0); at --rate 0 the tensor node paces the driver and none is lost'
        )
    metrics = summarize(g_raw, g_comp, g_true)
    _say(f'demo: compensator running compensated_percent topic: {probe.percent:.4f} %')
    _plot(out / 'norms.png', stamps, g_raw, g_comp, g_true, metrics)
    return metrics


def _settle(probe: Probe, quiet_s: float = 1.0, timeout_s: float = 30.0) -> None:
    """Wait until no tensor has arrived for ``quiet_s`` (the graph has drained)."""
    deadline = time.monotonic() + timeout_s
    last, since = dict(probe.counts), time.monotonic()
    while time.monotonic() - since < quiet_s and time.monotonic() < deadline:
        time.sleep(0.1)
        if probe.counts != last:
            last, since = dict(probe.counts), time.monotonic()


def _expect(reply: Any) -> str:
    if not reply.success:
        raise TimeoutError(f'service refused: {reply.message}')
    return reply.message


def _progress(
    probe: Probe, done: Callable[[], bool], label: str, timeout_s: float = 600.0
) -> None:
    deadline = time.monotonic() + timeout_s
    last = 0.0
    while not done():
        if time.monotonic() > deadline:
            raise TimeoutError(f'the {label} did not finish within {timeout_s:g} s')
        if time.monotonic() - last > 2.0:
            last = time.monotonic()
            _say(f'demo:   {label}: {probe.counts["gradient/raw"]} tensors so far')
        time.sleep(0.05)


def _summarise_calibration(calibration: CalibrationFile) -> None:
    """Print the file's diagnostics and its error against the simulator's exact parameters."""
    from ..io.scenario import load_scenario_or_default

    scenario, _ = load_scenario_or_default()
    exact = scenario.interference.effective_parameters()
    d = calibration.diagnostics
    k_err = np.abs(calibration.parameters.k_soft - exact.k_soft).max()
    b_err = np.abs(calibration.parameters.b_hard - exact.b_hard).max() * NT_PER_T
    residual = d.get('residual_rms_nT_per_m', float('nan'))
    noise = d.get('sensor_noise_nT', float('nan'))
    _say(
        f'demo: calibration {calibration.method}: {d.get("n_samples")} samples, '
        f'{d.get("n_parameters")} parameters, rank {d.get("rank")}, fit residual '
        f'{residual:.3g} nT/m, estimated sensor noise {noise:.3g} nT'
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
    from matplotlib.figure import Figure  # the object API: no pyplot, no global backend

    t = (stamps - stamps[0]) * S_PER_NS
    norm = {
        name: np.linalg.norm(g, axis=(1, 2)) * NT_PER_T
        for name, g in (('raw', g_raw), ('compensated', g_comp), ('true', g_true))
    }
    fig = Figure(figsize=(9, 6.5))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [2, 1]})
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
