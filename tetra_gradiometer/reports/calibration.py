"""The calibration report of ``calibrate --report DIR``: ``report.json``, ``report.md`` and
four PNG plots (residual over the window, attitude coverage, parameters with their 1-sigma,
predicted survey accuracy), in one folder written atomically
(:func:`~tetra_gradiometer.io.outputs.atomic_output`, kind :data:`CALIBRATION_REPORT`)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core import InterferenceParameters, TetraGeometry
from ..core.effects import term_to_dict
from ..core.guidance import ENOUGH_RATIO, SURVEY_HEADINGS_DEG, SURVEY_SWAY_DEG, TrimAssessment
from ..core.identification import regional_body_tensor
from ..core.model import compensate_fields
from ..core.units import NT_PER_T, S_PER_NS
from ..io.outputs import CALIBRATION_REPORT, atomic_output
from ..pipelines.calibration import BagCalibration
from ..pipelines.trim import WindowAssessment

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ['FIGURES', 'report_document', 'write_calibration_report']

#: Figure key -> file name (the survey and coverage plots need an assessment).
FIGURES = {
    'residual': 'residual.png',
    'parameters': 'parameters.png',
    'coverage': 'coverage.png',
    'survey': 'survey.png',
}
_MAX_POINTS = 4000


def _plain(value: Any) -> Any:
    """JSON-ready: numpy to Python, non-finite floats to None, recursively."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def window_residual(result: BagCalibration, geometry: TetraGeometry) -> tuple[Any, Any]:
    """Seconds from the first set used (n,) and the RMS over the 9 components of each set's
    compensated tensor (n,), T/m: the residual where the true gradient is taken as zero, or
    as the regional gradient fitted with the calibration."""
    candidates = result.terms.candidates
    if candidates:  # the terms' regressors on the sets used (NaN rows: left out)
        regressors = np.concatenate([c.regressors for c in candidates], axis=1)
        compensated = compensate_fields(
            result.fields, result.record.parameters, geometry, regressors
        )
    else:
        compensated = result.calibration.compensate_fields(result.fields, geometry)
    regional = getattr(result.calibration, 'regional_gradient_enu', None)
    if regional is not None and result.orientation_xyzw is not None:
        compensated = compensated - regional_body_tensor(result.orientation_xyzw, regional)
    t = (result.stamps_ns - result.stamps_ns[0]) * S_PER_NS
    rms = np.sqrt(np.mean(compensated.reshape(len(t), 9) ** 2, axis=1))
    known = np.isfinite(rms)
    return t[known], rms[known]


def _parameters(result: BagCalibration, assessment: TrimAssessment | None) -> dict[str, Any]:
    """The parameters, and their 1-sigma: the fit's (known-gradient methods) or, for the
    others, the assessment's prediction for the known-gradient solve of the same sets."""
    parameters = result.record.parameters
    out: dict[str, Any] = {
        'k_soft': parameters.k_soft,
        'b_hard_nT': parameters.b_hard * NT_PER_T,
        'sigma_source': None,
    }
    errors = getattr(result.calibration, 'standard_errors', None)
    source = 'fit'
    if errors is None and assessment is not None:
        errors, source = assessment.parameter_sigma, 'assessment (known-gradient solve)'
    if errors is not None:
        base = len(errors) - 9 * result.record.parameters.n_term_regressors  # k, b first
        sigma = InterferenceParameters.from_vector(errors[:base], symmetric=base == 27)
        out.update(k_soft_sigma=sigma.k_soft, b_hard_sigma_nT=sigma.b_hard * NT_PER_T)
        out['sigma_source'] = source
    return out


def report_document(
    result: BagCalibration, window: WindowAssessment, geometry: TetraGeometry
) -> dict[str, Any]:
    """What ``report.json`` holds (plain types; nT, nT/m, seconds, degrees)."""
    t, residual = window_residual(result, geometry)
    assessment = window.assessment
    return _plain(
        {
            'calibration': result.calibration.summary(),
            'window': {
                'window_s': result.window,
                'sets_in_window': result.sets_in_window,
                'thinned_every': result.thinned_every,
                'sets_used': len(result.stamps_ns),
                'duration_s': float(t[-1]) if len(t) else 0.0,
            },
            'residual': {
                'rms_nT_per_m': float(np.sqrt(np.mean(residual**2))) * NT_PER_T,
                'max_nT_per_m': float(residual.max()) * NT_PER_T,
            },
            'parameters': _parameters(result, assessment),
            'earth_field_enu_nT': None
            if window.earth_field_enu is None
            else window.earth_field_enu * NT_PER_T,
            'assessment': None if assessment is None else assessment.to_dict(),
            'effects': result.terms.diagnostics(),
            'terms': [term_to_dict(term) for term in result.record.parameters.terms],
            'notes': list(window.notes),
        }
    )


# --------------------------------------------------------------------------- plots


def _figure(figsize: tuple[float, float]) -> Figure:
    """A figure of matplotlib's object API: no pyplot, no global backend state."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _plot_residual(
    path: Path, result: BagCalibration, geometry: TetraGeometry, floor: float | None
) -> None:
    t, residual = window_residual(result, geometry)
    step = max(1, int(np.ceil(len(t) / _MAX_POINTS)))
    fig = _figure((7.0, 3.0))
    ax = fig.subplots()
    ax.plot(t[::step], residual[::step] * NT_PER_T, lw=0.6, label='compensated, RMS of 9')
    if floor is not None:
        ax.axhline(floor * NT_PER_T, color='k', ls='--', lw=0.8, label='noise floor')
    ax.set_xlabel('time from the first set used, s')
    ax.set_ylabel('nT/m')
    rms = float(np.sqrt(np.mean(residual**2))) * NT_PER_T
    ax.set_title(f'Residual over the window {result.window} (RMS {rms:.3g} nT/m)', fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)


def _plot_parameters(path: Path, parameters: dict[str, Any]) -> None:
    """Values (left) and 1-sigma (right: usually far below the values, where error bars would
    not show) of ``K_i1`` and ``B_i1^h``, per pair."""
    fig = _figure((9.0, 4.6))
    axes = fig.subplots(2, 2, squeeze=False)
    panels = (
        ('k_soft', 'k_soft_sigma', 'K_i1 (dimensionless)'),
        ('b_hard_nT', 'b_hard_sigma_nT', 'B_i1^h, nT'),
    )
    for row, (key, sigma_key, label) in enumerate(panels):
        values = np.asarray(parameters[key], dtype=float).ravel()
        sigma = parameters.get(sigma_key)
        x = np.arange(len(values))
        per_pair = len(values) // 3
        axes[row, 0].plot(x, values, 'o', ms=3)
        axes[row, 0].axhline(0.0, color='0.6', lw=0.5)
        axes[row, 0].set_ylabel(label, fontsize=8)
        if sigma is not None:
            axes[row, 1].plot(x, np.asarray(sigma, dtype=float).ravel(), 's', ms=3)
            axes[row, 1].set_ylim(bottom=0.0)
        axes[row, 1].set_ylabel(f'1-sigma of {label}', fontsize=8)
        for ax in axes[row]:
            ax.set_xticks([per_pair * p + per_pair / 2 - 0.5 for p in range(3)])
            ax.set_xticklabels([f'pair {p + 2}-1' for p in range(3)], fontsize=7)
            ax.tick_params(labelsize=7)
    source = parameters.get('sigma_source') or 'none'
    fig.suptitle(f'Parameters and their 1-sigma (sigma: {source})', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)


def _plot_coverage(path: Path, assessment: TrimAssessment) -> None:
    coverage = assessment.coverage
    edges = coverage.edges_deg
    if coverage.source == 'attitude':
        maps = [
            ('roll', coverage.counts.sum(axis=2), edges[1]),
            ('pitch', coverage.counts.sum(axis=1), edges[2]),
        ]
        xlabel = 'compass heading, deg'
    else:
        maps = [('elevation', coverage.counts, edges[1])]
        xlabel = "azimuth of B_1' in the body frame, deg"
    fig = _figure((4.2 * len(maps) + 0.6, 3.4))
    axes = np.atleast_1d(fig.subplots(1, len(maps)))
    for ax, (name, counts, y_edges) in zip(axes, maps, strict=True):
        image = ax.imshow(counts.T, origin='lower', aspect='auto', cmap='viridis')
        ax.set_xticks(np.arange(len(edges[0])) - 0.5, [f'{e:g}' for e in edges[0]], fontsize=6)
        ax.set_yticks(np.arange(len(y_edges)) - 0.5, [f'{e:g}' for e in y_edges], fontsize=6)
        ax.set_xlabel(xlabel, fontsize=7)
        ax.set_ylabel(f'{name}, deg', fontsize=7)
        fig.colorbar(image, ax=ax, label='samples')
    fig.suptitle(f'Coverage: {coverage.text}', fontsize=8)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)


def _plot_survey(path: Path, assessment: TrimAssessment) -> None:
    headings = np.array(SURVEY_HEADINGS_DEG)
    per_heading = assessment.to_dict()['survey']['sigma_per_heading_nT_per_m']
    floor = assessment.noise_floor * NT_PER_T
    fig = _figure((6.5, 3.2))
    ax = fig.subplots()
    ax.plot(headings, per_heading, 'o-', label=f'predicted (level, ±{SURVEY_SWAY_DEG:g}° sway)')
    ax.axhline(floor, color='k', ls='--', lw=0.8, label='noise floor')
    ax.axhline(ENOUGH_RATIO * floor, color='tab:green', ls=':', lw=0.8, label='enough')
    ax.set_yscale('log')
    ax.set_xlabel('survey heading, deg')
    ax.set_ylabel('compensated sigma, nT/m')
    advice = assessment.advice
    verdict = 'enough' if assessment.enough else 'not enough'
    verdict += f'; next: {advice.text}' if advice is not None else ''
    ax.set_title(f'Predicted survey accuracy: {verdict}', fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, format='png', dpi=90)


def _effects_lines(effects: dict[str, Any]) -> list[str]:
    """The vehicle effects: which were kept, each test (held-out RMS without and with it)."""
    selected = ', '.join(effects['selected']) or 'none'
    lines = [f'**Vehicle effects fitted:** {selected}.', '']
    for name, test in effects.get('tests', {}).items():
        lines.append(
            f'- {name}: held-out {test["heldout_rms_without_nT"]:.3g} -> '
            f'{test["heldout_rms_with_nT"]:.3g} nT per sensor axis, F {test["F"]:.3g}, '
            f'p {test["p_value"]:.2g}: {"kept" if test["kept"] else "not kept"}'
        )
    lines += [
        f'- {name}: not tested, its held-out solve failed ({why}): not kept'
        for name, why in effects.get('unsolved', {}).items()
    ]
    lines += [
        f'- {name}: cannot be fitted, needs {what}' for name, what in effects['lacking'].items()
    ]
    return [*lines, '']


def report_markdown(document: dict[str, Any], figures: dict[str, str]) -> str:
    """``report.md``: the figures with one line each of what they show."""
    residual = document['residual']
    lines = [
        '# Calibration report',
        '',
        f'Window {document["window"]["window_s"]}, {document["window"]["sets_used"]} sets used; '
        f'residual RMS {residual["rms_nT_per_m"]:.4g} nT/m.',
        '',
    ]
    assessment = document['assessment']
    if assessment is not None:
        lines += [f'**Trim assessment:** {assessment["text"]}', '']
    lines += _effects_lines(document['effects'])
    lines += [f'- {note}' for note in document['notes']] + ['']
    for key in FIGURES:
        if key in figures:
            lines += [f'![{key}]({figures[key]})', '']
    return '\n'.join(lines)


def write_calibration_report(
    out_dir: str | os.PathLike[str],
    result: BagCalibration,
    window: WindowAssessment,
    geometry: TetraGeometry,
    *,
    force: bool = False,
    inputs: Iterable[str | os.PathLike[str]] = (),
) -> Path:
    """Write ``report.json``, ``report.md`` and the PNGs into the folder ``out_dir``,
    atomically (a previous calibration report is replaced only with ``force``)."""
    document = report_document(result, window, geometry)
    assessment = window.assessment
    with atomic_output(
        out_dir, CALIBRATION_REPORT, force=force, inputs=inputs, command='calibrate'
    ) as out:
        out.mkdir()
        figures = {'residual': FIGURES['residual'], 'parameters': FIGURES['parameters']}
        floor = None if assessment is None else assessment.noise_floor
        _plot_residual(out / figures['residual'], result, geometry, floor)
        _plot_parameters(out / figures['parameters'], document['parameters'])
        if assessment is not None:
            figures.update(coverage=FIGURES['coverage'], survey=FIGURES['survey'])
            _plot_coverage(out / figures['coverage'], assessment)
            _plot_survey(out / figures['survey'], assessment)
        document['figures'] = figures
        text = json.dumps(document, indent=2, allow_nan=False) + '\n'
        (out / 'report.json').write_text(text, encoding='utf-8')
        (out / 'report.md').write_text(report_markdown(document, figures), encoding='utf-8')
    return Path(out_dir)
