"""The ``locate`` output folder: ``targets.json`` (the compensated tensor's targets, the
contract of :mod:`.targets`), ``targets_raw.json`` (when asked for: the same search on the
uncompensated tensor, for comparison), ``map.png`` (track, detections, targets with their 3-sigma
horizontal error ellipses, and the detection statistic against its threshold) and
``report.md`` (both target tables side by side). Written as one atomic folder.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.units import NT_PER_T
from ..io.outputs import TARGETS, atomic_output
from ..io.targets import dumps, targets_document
from ..pipelines.targets import BagTargets, Search

if TYPE_CHECKING:
    from matplotlib.axes import Axes

#: Error ellipses drawn at this many sigma.
ELLIPSE_SIGMAS = 3.0
FILE_NAMES = {'compensated': 'targets.json', 'raw': 'targets_raw.json'}


def documents(result: BagTargets) -> dict[str, dict[str, Any]]:
    """File name -> ``targets.json`` document, per search."""
    out = {}
    for search in (result.main, result.comparison):
        if search is None:
            continue
        out[FILE_NAMES[search.tensor]] = targets_document(
            search.targets,
            tensor=search.tensor,
            t0_stamp_s=result.t0_stamp_s,
            false_alarms_per_hour=_rate(search),
            detections=len(search.detected.detections),
        )
    return out


def _rate(search: Search) -> float:
    return search.detected.settings.false_alarms_per_hour


def write_locate_report(
    result: BagTargets,
    out: str | os.PathLike[str],
    *,
    plots: bool = True,
    force: bool = False,
    inputs: Iterable[str | os.PathLike[str]] = (),
) -> Path:
    """Write the folder ``out`` (module docstring) atomically; returns its path."""
    with atomic_output(out, TARGETS, force=force, inputs=inputs, command='locate') as tmp:
        tmp.mkdir()
        for name, document in documents(result).items():
            (tmp / name).write_text(dumps(document), encoding='utf-8')
        (tmp / 'report.md').write_text(report_markdown(result), encoding='utf-8')
        if plots:
            _plot_map(tmp / 'map.png', result)
    return Path(out)


def report_markdown(result: BagTargets) -> str:
    """Both searches' targets as Markdown tables."""
    lines = ['# Targets', '']
    for search in (result.main, result.comparison):
        if search is None:
            continue
        detected = search.detected
        lines += [
            f'## {search.tensor.capitalize()} tensor ({FILE_NAMES[search.tensor]})',
            '',
            f'{len(detected.detections)} detections at {_rate(search):g} '
            f'false alarms per hour (noise {np.mean(detected.sigma) * NT_PER_T:.3g} nT/m per '
            f'component, {detected.noise.dof:.1f} independent samples per window), '
            f'{len(search.targets)} targets.',
            '',
            '| # | position (m, odom) | sigma (m) | moment (A m^2) | sigma (A m^2) | seen (s) '
            '| fit RMS (nT/m) | chi2 | dipolar | fitted with |',
            '|---|---|---|---|---|---|---|---|---|---|',
        ]
        for i, target in enumerate(search.targets, 1):
            fit = target.fit
            lines.append(
                f'| {i} | {_vector(fit.position, ".2f")} | {_vector(fit.position_sigma, ".2g")} '
                f'| {_vector(fit.moment, ".4g")} | {_vector(fit.moment_sigma, ".2g")} '
                f'| {target.first_seen_s:.1f}-{target.last_seen_s:.1f} '
                f'| {fit.rms * NT_PER_T:.3g} | {fit.chi2_reduced:.2f} '
                f'| {"yes" if target.dipolar else "no"} '
                f'| {", ".join(f"#{j + 1}" for j in target.fitted_with) or "-"} |'
            )
        lines.append('')
    if any(result.input_counts.values()):
        counts = ', '.join(f'{k} {v}' for k, v in result.input_counts.items() if v)
        lines += [f'Input not used: {counts}.', '']
    if result.held_summary:
        lines += [f'**{result.held_summary[0].upper()}{result.held_summary[1:]}.**', '']
    return '\n'.join(lines)


def _vector(values: np.ndarray, spec: str) -> str:
    return '[' + ', '.join(format(float(v), spec) for v in values) + ']'


def _plot_map(path: Path, result: BagTargets) -> None:
    from matplotlib.figure import Figure

    searches = [s for s in (result.main, result.comparison) if s is not None]
    fig = Figure(figsize=(6.5 * len(searches), 10.0))
    axes = fig.subplots(2, len(searches), squeeze=False, height_ratios=[2.2, 1.0])
    for column, search in enumerate(searches):
        _map_panel(axes[0, column], search)
        _statistic_panel(axes[1, column], search)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)


def _map_panel(ax: Axes, search: Search) -> None:
    from matplotlib.patches import Ellipse

    xy = search.survey.positions[:, :2]
    # The searched legs only: a transit or a trim kilometres away would shrink the survey
    # to a dot.
    for i, (start, stop) in enumerate(search.detected.legs):
        ax.plot(
            *xy[start:stop].T,
            color='0.6',
            lw=0.6,
            label='track (searched legs)' if i == 0 else None,
        )
    for i, detection in enumerate(search.detected.detections):
        span = xy[detection.start : detection.stop]
        ax.plot(span[:, 0], span[:, 1], color='tab:orange', lw=1.5,
                label='detections (peak: dot)' if i == 0 else None)  # fmt: skip
        ax.plot(*xy[detection.peak], '.', color='tab:orange', ms=6)
    for i, target in enumerate(search.targets):
        fit = target.fit
        values, vectors = np.linalg.eigh(fit.covariance[:2, :2])
        angle = float(np.degrees(np.arctan2(vectors[1, 1], vectors[0, 1])))
        width, height = 2 * ELLIPSE_SIGMAS * np.sqrt(np.maximum(values[::-1], 0.0))
        ax.add_patch(Ellipse(tuple(fit.position[:2]), width, height, angle=angle,
                             fill=False, color='tab:red'))  # fmt: skip
        ax.plot(*fit.position[:2], 'x' if target.dipolar else 's', color='tab:red', ms=8,
                label='targets (x dipolar)' if i == 0 else None)  # fmt: skip
        text = (
            f'{i + 1}: z {fit.position[2]:.1f}±{fit.position_sigma[2]:.2g} m\n'
            f'|m| {np.linalg.norm(fit.moment):.3g} A m²'
        )
        where = (float(fit.position[0]), float(fit.position[1]))
        ax.annotate(text, where, xytext=(6, 6), textcoords='offset points', fontsize=8)
    ax.set_aspect('equal', adjustable='datalim')
    ax.set_xlabel('x east (m, odom)')
    ax.set_ylabel('y north (m, odom)')
    ax.set_title(f'{search.tensor} tensor: {len(search.targets)} targets '
                 f'({ELLIPSE_SIGMAS:g}-sigma ellipses)')  # fmt: skip
    ax.legend(loc='best', fontsize=8)


def _statistic_panel(ax: Axes, search: Search) -> None:
    detected = search.detected
    t = search.survey.t_s
    ax.semilogy(t, np.maximum(detected.statistic, 1e-3), lw=0.6, label='statistic (window mean)')
    label = f'threshold ({_rate(search):g} false alarms/h)'
    ax.axhline(detected.threshold, color='tab:red', lw=0.8, label=label)
    ax.set_xlabel('time from the first sample (s)')
    ax.set_ylabel('q (noise units squared)')
    ax.legend(loc='upper right', fontsize=8)
