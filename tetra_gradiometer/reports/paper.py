"""The section 6 reproduction's files: ``results.json``, the figures and the printed table.

The numbers come from :mod:`tetra_gradiometer.core.paper`. Figures are drawn with
matplotlib's object API (:class:`matplotlib.figure.Figure`), so no global backend or pyplot
state is touched.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..core.paper import METHODS, READINGS, Choices, Reading, reproduce_readings, results_json
from ..io.outputs import PAPER, atomic_output, check_output

__all__ = ['COLOURS', 'FIGURES', 'TITLES', 'format_table', 'plot_fig2', 'plot_fig3', 'reproduce']


def reproduce(
    out_dir: str | os.PathLike[str],
    *,
    choices: Choices | None = None,
    plots: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Run both readings, write ``results.json`` (and the figures) into the folder ``out_dir``
    (atomically; a previous paper folder is replaced only with ``force``); return the JSON."""
    check_output(out_dir, PAPER, force=force)  # refuse before the work
    readings = reproduce_readings(choices)
    results = results_json(readings)
    with atomic_output(out_dir, PAPER, force=force, command='paper') as folder:
        folder.mkdir()
        (folder / 'results.json').write_text(
            json.dumps(results, indent=2, allow_nan=False) + '\n', encoding='utf-8'
        )
        if plots:
            for name, reading in readings.items():
                plot_fig2(reading, folder / f'fig2_{name}.png', TITLES[name])
                plot_fig3(reading, folder / f'fig3_{name}.png', TITLES[name])
    return results


TITLES = {'earth_field': 'dipole + 50 000 nT Earth field', 'dipole_only': 'dipole field only'}
FIGURES = tuple(f'fig{n}_{reading}.png' for n in (2, 3) for reading in READINGS)
COLOURS = {
    'paper_ga': 'tab:orange',
    'constraint_lstsq': 'tab:purple',
    'known_gradient_lstsq': 'tab:green',
    'known_gradient_lstsq_general': 'tab:blue',
    'pei_yeo_2009': 'tab:brown',
    'paper_ga_wide_bounds': 'tab:pink',
    'pei_yeo_2009_on_trim': 'tab:olive',
}


def _floor_line(axis: Any, curves: dict[str, Any]) -> None:
    # The Frobenius norm of pure sensor noise on the tensor is ~3x the per-component RMS.
    axis.axhline(
        3 * curves['floor'],
        color='grey',
        lw=1,
        ls=':',
        label=f'noise (Frobenius, 3 x {curves["floor"]:.2f})',
    )


def plot_fig2(reading: Reading, path: Path, title: str) -> None:
    """Analogue of Fig. 2: |G|_F before, after and true along the pass, per method."""
    from matplotlib.figure import Figure

    c = reading.curves
    figure = Figure(figsize=(12, 7.5))
    axes = figure.subplots(2, 2, sharex=True)
    for row, name in enumerate(('paper_ga', 'known_gradient_lstsq_general')):
        m = reading.methods[name]
        left, right = axes[row]
        left.semilogy(c['index'], c['before'], color='tab:red', lw=1.5, label='before (measured)')
        left.semilogy(c['index'], c['after'][name], color=COLOURS[name], lw=1.5, label='after')
        left.semilogy(c['index'], c['true'], color='k', lw=1.2, ls='--', label='true')
        left.set_ylabel('|G|_F  (nT/m)')
        left.set_title(
            f'{name}: {m["compensated_percent"]:.3f} % compensated (eq. 24)', fontsize=10
        )
        right.semilogy(
            c['index'],
            c['error_before'],
            color='tab:red',
            lw=1.0,
            alpha=0.7,
            label='before: |G_m - G_true|_F',
        )
        right.semilogy(c['index'], c['error'][name], color=COLOURS[name], lw=1.2, label='after')
        _floor_line(right, c)
        right.set_ylabel('|G_after - G_true|_F  (nT/m)')
        right.set_title(
            f'{name}: residual RMS {m["rms_residual_nT_per_m"]:.3g} nT/m per component',
            fontsize=10,
        )
        left.legend(fontsize=8, loc='best')
        right.legend(fontsize=8, loc='best')
        for axis in (left, right):
            axis.grid(True, which='both', alpha=0.3)
    for axis in axes[1]:
        axis.set_xlabel('pass point index (30-229 compensated; 2 m spacing)')
    figure.suptitle(f'Fig. 2 analogue, {title}: Frobenius norm along the pass')
    figure.tight_layout()
    figure.savefig(path, format='png', dpi=110)


def plot_fig3(reading: Reading, path: Path, title: str) -> None:
    """Analogue of Fig. 3: the methods compared along the pass."""
    from matplotlib.figure import Figure

    c = reading.curves
    figure = Figure(figsize=(13, 6.5))
    left, right = figure.subplots(1, 2)
    left.semilogy(c['index'], c['before'], color='tab:red', lw=2, label='before (measured)')
    right.semilogy(
        c['index'], c['error_before'], color='tab:red', lw=2, label='before (interference)'
    )
    for name in METHODS:
        m = reading.methods[name]
        label = f'{name} ({m["compensated_percent"]:.1f} %, {m["rms_residual_nT_per_m"]:.3g} nT/m)'
        left.semilogy(c['index'], c['after'][name], color=COLOURS[name], lw=1.2, label=label)
        right.semilogy(c['index'], c['error'][name], color=COLOURS[name], lw=1.2, label=name)
    left.semilogy(c['index'], c['true'], color='k', lw=1.5, ls='--', label='true')
    _floor_line(right, c)
    left.set_ylabel('|G|_F  (nT/m)')
    left.set_title('after compensation (legend: eq. 24 %, residual RMS)', fontsize=10)
    right.set_ylabel('|G_after - G_true|_F  (nT/m)')
    right.set_title('error of each method', fontsize=10)
    for axis in (left, right):
        axis.set_xlabel('pass point index (30-229 compensated; 2 m spacing)')
        axis.grid(True, which='both', alpha=0.3)
        axis.legend(
            fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False
        )
    figure.suptitle(f'Fig. 3 analogue, {title}: methods compared')
    figure.tight_layout()
    figure.savefig(path, format='png', dpi=110)


def format_table(reading: dict[str, Any], title: str) -> str:
    """The methods table of one reading (a results.json reading), as printed by the command."""
    floor = reading['scenario']['noise_floor_nT_per_m']
    identifiability = reading['identifiability']
    uncompensated = reading['scenario']['uncompensated']['rms_interference_nT_per_m']
    rows = [
        f'{title}  (constraint rank {identifiability["constraint_rank"]} of '
        f'{identifiability["n_parameters"]}; noise floor {floor:.3f} nT/m; '
        f'uncompensated RMS {uncompensated:.4g} nT/m)',
        f'  {"method":<46} {"compensated %":>14} {"RMS nT/m":>12} {"improvement":>12} '
        f'{"solve s":>9}',
    ]
    entries = list(reading['methods'].items()) + [
        (f'({name})', v) for name, v in reading['variants'].items()
    ]
    for name, m in entries:
        rows.append(
            f'  {name:<46} {m["compensated_percent"]:>14.3f} {m["rms_residual_nT_per_m"]:>12.4g} '
            f'{m["improvement_ratio"]:>12.4g} {m["solve_seconds"]:>9.4f}'
        )
    return '\n'.join(rows)
