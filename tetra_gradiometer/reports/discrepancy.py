"""``report.json``, ``report.md`` and the PNG plots of a discrepancy :class:`Report`, in one
report folder written atomically (:func:`~tetra_gradiometer.io.outputs.atomic_output`)."""

from __future__ import annotations

import json
import os
import sys
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..core.discrepancy import CANDIDATES, LIBRARY, Report, criterion_text
from ..core.effects import RecordedSignal, parse_declaration
from ..io import conversions as cv
from ..io.outputs import REPORT, atomic_output
from .discrepancy_targets import excluded_section, targets_section

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Array = NDArray[np.float64]

_AXES = 'xyz'
_MAX_POINTS = 4000


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')


#: The optional recorded channels: ``Candidate.requires`` entry -> (topic, what it gives,
#: the ``Report.data`` flag that says it was recorded).
CHANNELS: dict[str, tuple[str, str, str]] = {
    'odom': (cv.ODOM_TOPIC, 'attitude', 'has_odom'),
    'temperature': (cv.TEMPERATURE_TOPIC, 'sensor temperature', 'has_temperature'),
    'current': (cv.BATTERY_TOPIC, 'vehicle current', 'has_current'),
}


def _blamed_channel(requires: tuple[str, ...], recorded: dict[str, bool]) -> str | None:
    """The channel that makes a candidate untestable, in the order the workflow checks
    (``core.discrepancy.prepare.testable``): a missing /odom first, then temperature, then
    current (missing, or recorded without variation)."""
    if 'odom' in requires and not recorded['odom']:
        return 'odom'
    return next((key for key in ('temperature', 'current') if key in requires), None)


def channel_notes(report: Report) -> dict[str, dict[str, Any]]:
    """Per optional channel (topic): whether the run recorded it, the library's candidates
    that need it, those the run could therefore not test, and one line saying so.

    The four magnetometer topics are needed by everything; ``/odom`` (attitude) gives the
    absolute view (every sensor against the Earth field) and the attitude-dependent
    candidates; ``/tetra/temperature`` and ``/battery_state`` are the regressors of
    ``thermal_drift`` and ``vehicle_current``.
    """
    recorded = {key: bool(report.data.get(flag)) for key, (_, _, flag) in CHANNELS.items()}
    blamed = {
        name: _blamed_channel(LIBRARY[name].requires, recorded)
        for name in report.untestable
        if name in LIBRARY
    }
    out: dict[str, dict[str, Any]] = {}
    for key, (topic, what, _) in CHANNELS.items():
        needed_by = [c.name for c in CANDIDATES if key in c.requires]
        untested = [name for name, channel in blamed.items() if channel == key]
        effects = ', '.join(untested)
        if not recorded[key] and not untested:
            note = f'no {topic} ({what}): needed by {", ".join(needed_by)}, not asked for'
        elif not recorded[key]:
            note = f'no {topic} ({what}): {effects} not tested'
        elif untested:
            note = f'{topic} recorded but without variation: {effects} not tested'
        else:
            note = f'{topic} recorded: {", ".join(needed_by)} testable'
        if key == 'odom' and not recorded[key]:
            note += "; residuals are pair differences against sensor 1 (B_i' - B_1')"
        out[topic] = dict(
            recorded=recorded[key], needed_by=needed_by, untested=untested, note=note
        )
    return out


def channel_warnings(report: Report) -> list[str]:
    """The notes of the channels that were missing or left an effect untested."""
    return [
        c['note'] for c in channel_notes(report).values() if not c['recorded'] or c['untested']
    ]


def report_json(report: Report) -> str:
    """The text of ``report.json``: :meth:`Report.to_dict` and ``channels``
    (:func:`channel_notes`)."""
    document = report.to_dict()
    document['channels'] = channel_notes(report)
    return json.dumps(document, indent=2, default=_json_default, allow_nan=False) + '\n'


def _figure(figsize: tuple[float, float]) -> Figure:
    """A figure of matplotlib's object API (no pyplot), laid out to keep its texts on it."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, layout='constrained')


def _thin(n: int) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / _MAX_POINTS))))


def _plot_residuals(
    path: Path,
    t: Array,
    sensors: tuple[int, ...],
    panels: list[tuple[str, Array]],
    title: str,
    spans: list[dict[str, Any]],
) -> None:
    """Panels of (N, 4, 3) fields in nT against time t (s), one row per sensor; ``spans``
    (excluded, s) in grey."""
    fig = _figure((5.5 * len(panels), 1.9 * len(sensors) + 0.8))
    axes = fig.subplots(len(sensors), len(panels), sharex=True, squeeze=False)
    k = _thin(len(t))
    for col, (label, residual) in enumerate(panels):
        for row, s in enumerate(sensors):
            ax = axes[row, col]
            for a in range(3):
                ax.plot(t[k], residual[k, s, a], lw=0.6, label=_AXES[a])
            for span in spans:
                ax.axvspan(span['start_s'], span['end_s'], color='0.85', zorder=0)
            rms = float(np.sqrt(np.mean(residual[:, s] ** 2)))
            ax.set_title(f'{label}: sensor {s + 1} (RMS {rms:.3g} nT)', fontsize=8)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel('nT', fontsize=7)
        axes[-1, col].set_xlabel('time, s', fontsize=7)
    axes[0, 0].legend(fontsize=6, loc='upper right')
    fig.suptitle(title, fontsize=9)
    fig.savefig(path, format='png', dpi=90)


def _units_text(units: list[str]) -> list[str]:
    """Round-record units (``family@sensor_2``) grouped per family: ``family (2, 3)``."""
    groups: dict[str, list[str]] = {}
    for unit in units:
        family, _, where = unit.partition('@')
        where = where.replace('all_sensors', 'all').replace('sensor_', '')
        groups.setdefault(family, []).append(where)
    return [f'{f} ({", ".join(w)})' if all(w) else f for f, w in groups.items()]


def round_labels(report: Report, n: int) -> list[str]:
    """``n`` tick labels, one per round (``Report.series['gaps']``, base model first): the
    model's change from the round before (``base``, ``+ family (sensors)`` added, ``- family
    (sensors)`` taken out by a revision). Built from ``Report.rounds`` (one per gap), not
    from the steps: a step revised later is renamed, merged or dropped."""
    labels: list[str] = []
    before: list[str] = []
    for i in range(n):
        record = report.rounds[i] if i < len(report.rounds) else {'model': before}
        model = [str(u) for u in record.get('model', [])]
        parts = [f'+ {u}' for u in _units_text([u for u in model if u not in before])]
        parts += [f'- {u}' for u in _units_text([u for u in before if u not in model])]
        labels.append('\n'.join(parts) or ('base' if i == 0 else f'round {i + 1}'))
        before = model
    return labels


def _plot_gap(report: Report, path: Path) -> None:
    """Bars of the held-out gap (nT, RMS) per round, first on top, against the noise floor
    (nT); the rounds' labels beside the bars, as long as they are."""
    gaps = report.series['gaps']
    floors = report.series['floors']
    labels = [label.replace('\n', ', ') for label in round_labels(report, len(gaps))]
    longest = max(map(len, labels))  # characters; about 0.055 in each at 7 pt
    fig = _figure((max(6.4, 3.8 + 0.055 * longest), 1.5 + 0.4 * len(gaps)))
    ax = fig.subplots()
    y = np.arange(len(gaps))
    ax.barh(y, gaps, color='tab:blue', label='held-out gap')
    ax.plot(floors, y, 'k--', marker='o', label='noise floor')
    ax.set_xscale('log')
    ax.set_yticks(y, labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel('RMS, nT')
    fig.suptitle('Held-out gap (measured - simulated) per round', fontsize=9)
    ax.legend(fontsize=7, loc='lower right')
    fig.savefig(path, format='png', dpi=90)


def _plot_diagnostics(report: Report, path: Path) -> None:
    """The base-model residual (nT) against field rate, attitude, temperature, current."""
    series = report.series
    residual = series['residuals'][0]
    sensors = series['sensors']
    drivers: list[tuple[str, Array]] = [
        ('|dB^b/dt|, nT/s', np.linalg.norm(series['b_rate'], axis=1))
    ]
    if series['attitude'] is not None:
        angles = ('heading', 'pitch', 'roll')
        drivers += [(f'{a}, deg', series['attitude'][:, j]) for j, a in enumerate(angles)]
    for label, key in (('temperature, degC', 'temperature_c'), ('current, A', 'current_a')):
        if series[key] is not None:
            drivers.append((label, series[key]))
    k = _thin(len(series['t']))
    fig = _figure((max(2.3 * len(drivers) + 0.5, 6.0), 1.8 * len(sensors) + 1.0))
    axes = fig.subplots(len(sensors), len(drivers), squeeze=False, sharex='col')
    for row, s in enumerate(sensors):
        for col, (label, d) in enumerate(drivers):
            ax = axes[row, col]
            for a in range(3):
                ax.plot(d[k], residual[k, s, a], '.', ms=1, alpha=0.5, label=_AXES[a])
            ax.locator_params(axis='x', nbins=4)
            ax.tick_params(labelsize=6)
            if row == len(sensors) - 1:
                ax.set_xlabel(label, fontsize=7)
            if col == 0:
                ax.set_ylabel(f'sensor {s + 1}, nT', fontsize=7)
    fig.suptitle('Base-model residual (measured - simulated) against the drivers', fontsize=9)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    labels = [f'residual along {a}' for a in labels]
    fig.legend(handles, labels, loc='outside lower center', ncols=3, fontsize=7, markerscale=6)
    fig.savefig(path, format='png', dpi=90)


def _fmt_params(parameters: dict[str, Any]) -> str:
    lines = []
    for sensor, values in parameters.get('per_sensor', {}).items():
        items = ', '.join(f'{k} = {v:.4g}' for k, v in values.items())
        lines.append(f'  - {sensor.replace("_", " ")}: {items}')
    return '\n'.join(lines)


def report_markdown(
    report: Report, figures: dict[str, str], failures: Iterable[FigureFailure] = ()
) -> str:
    """The text of ``report.md`` (``figures``: key -> file name of the figures drawn;
    ``failures``: those that raised)."""
    lines = (
        _summary_section(report)
        + _failures_section(list(failures))
        + _findings_section(report)
        + targets_section(report)
        + excluded_section(report)
        + _method_section(figures)
        + _steps_section(report, figures)
        + _untestable_section(report)
        + _rounds_section(report)
        + _disagreement_section(report, figures)
    )
    return '\n'.join(lines) + '\n'


def percent_text(fraction: float) -> str:
    """A share (0-1) in percent, without rounding a small nonzero share to 0."""
    p = 100.0 * fraction
    return f'{p:.2g}' if 0 < p < 0.1 else f'{p:.1f}'


def _failures_section(failures: list[FigureFailure]) -> list[str]:
    if not failures:
        return []
    lines = ['', '## Figures not drawn', '']
    lines += [f'- `{f.figure}` ({f.what}): {f.error}' for f in failures]
    return lines + ['', 'The rest of the report is complete; the tracebacks went to stderr.']


def _cell(value: Any) -> str:
    """A value for a markdown table cell (lists joined, numbers to 6 digits)."""
    if isinstance(value, list | tuple):
        return ', '.join(_cell(v) for v in value) or '-'
    if isinstance(value, float | np.floating):
        return f'{value:.6g}'
    text = '' if value is None else ' '.join(str(value).split())
    return text.replace('|', '\\|') or '-'


def _findings_section(report: Report) -> list[str]:
    """The table of findings: effect, sensors, when (s) or frequency (Hz), confounders."""
    if not report.findings:
        return []
    head = '| effect | sensors | time, s / frequency, Hz | confounded with | evidence |'
    lines = ['', '## Findings', '', head, '|---|---|---|---|---|']
    for f in report.findings:
        t_s, hz = f.get('t_s'), f.get('frequency_hz')
        when = f'{_cell(t_s)} s' if t_s is not None else '-' if hz is None else f'{_cell(hz)} Hz'
        effect = f.get('effect', '') + (' (unresolved)' if f.get('status') == 'unresolved' else '')
        cells = [effect, f.get('sensors') or 'all', when, f.get('confounded_with')]
        lines.append('| ' + ' | '.join(map(_cell, cells + [f.get('evidence')])) + ' |')
    return lines + _unresolved_section(report)


def _unresolved_section(report: Report) -> list[str]:
    """The unresolved findings: why, and what data would separate the readings."""
    open_ = [f for f in report.findings if f.get('status') == 'unresolved']
    if not open_:
        return []
    lines = ['', '## Unresolved (fitted, not named)', '']
    for f in open_:
        lines.append(
            f'- {f.get("effect")}: {f.get("unresolved_because")}. What would separate them: '
            f'{f.get("separated_by")}.'
        )
    return lines


def _ratio(value: float, floor: float) -> str:
    """``value / floor`` for the text; a zero floor (noise-free data) has no ratio."""
    return f'{value / floor:.3g}' if floor > 0 else 'undefined: zero noise floor'


def _summary_section(report: Report) -> list[str]:
    """Title, the named effects, the gap against the noise floor, the data and the notes."""
    data = report.data
    lines = ['# Discrepancy report', '']
    if report.named_effects:
        lines.append(f'Named effects, in the order added: **{", ".join(report.named_effects)}**.')
    else:
        lines.append(
            'No effect from the library is missing: **the base model is adequate**.'
            if report.adequate
            else 'No effect from the library explains the remaining gap.'
        )
    view = 'pair differences against sensor 1'
    if report.view == 'absolute':
        view = 'every sensor against R^T E'
    lines += [
        '',
        f'Held-out gap (RMS of measured - simulated over all sensors and axes): '
        f'**{report.gap_initial_nT:.4g} nT** with the base model, '
        f'**{report.gap_final_nT:.4g} nT** at the end; '
        f'noise floor {report.noise_floor_nT:.4g} nT '
        f'(ratio {_ratio(report.gap_final_nT, report.noise_floor_nT)}). '
        f'Adequate: **{"yes" if report.adequate else "no"}**. Excluded from the fits and '
        f'the gap: {percent_text(report.excluded_fraction)} % of the analysed samples.',
        '',
        f'- Base model: {report.base_model}',
        f'- Residual view: {report.view} ({view})',
        f'- Data: {data["samples"]} samples, {data["duration_s"]:.1f} s, '
        f'{data["sample_rate_hz"]:.3g} Hz; analysed in {report.runtime_s:.2f} s',
    ]
    if data.get('window_s'):
        w = data['window_s']
        end = 'the end' if w[1] is None else f'{w[1]:g} s'
        lines.append(f'- Window: {w[0]:g} to {end} (seconds from the first sample)')
    lines += [f'- Note: {note}' for note in report.notes]
    lines += ['', '## Recorded channels', '']
    lines += [f'- {c["note"]}' for c in channel_notes(report).values()]
    return lines


def _method_section(figures: dict[str, str]) -> list[str]:
    """How the run was simulated and tested, the criterion and the noise floor."""
    lines = [
        '',
        '## Method',
        '',
        "The recorded run is simulated with the base model: each sensor's reading is "
        "predicted from the background field B^b (from /odom and the Earth field, or B_1' "
        'without /odom). The residual (measured - simulated) is examined against time, '
        'attitude, field rate, temperature and current, and each candidate family of the '
        'library is added to the model as extra regressors and tested on held-out data.',
        '',
        f'Criterion: {criterion_text()}',
        'The noise floor is the white-noise RMS estimated from the fourth difference of the '
        'residual (median absolute deviation, so steps and spikes do not count).',
        '',
    ]
    if 'gap' in figures:
        lines += [f'![gap per round]({figures["gap"]})', '']
    return lines


def _steps_section(report: Report, figures: dict[str, str]) -> list[str]:
    """The table of steps, then each named effect: physics, evidence, parameters, plots."""
    if not report.steps:
        return []
    lines = [
        '## Steps',
        '',
        '| # | effect | gap before, nT | gap after, nT | parameters | CV-BIC change | F | p |',
        '|---|---|---|---|---|---|---|---|',
    ]
    for i, s in enumerate(report.steps, 1):
        lines.append(
            f'| {i} | {s.effect} | {s.gap_before_nT:.4g} | {s.gap_after_nT:.4g} | '
            f'{s.n_parameters} | {s.delta_bic:+.4g} | {s.f_statistic:.4g} | {s.p_value:.3g} |'
        )
    lines.append('')
    for i, s in enumerate(report.steps, 1):
        lines += [
            f'### {i}. {s.effect}',
            '',
            f'**What it is.** {_physics(s.effect)}',
            '',
            f'**Evidence.** {s.evidence}.',
            '',
            f'**Fitted parameters** ({s.parameters.get("units", "")}; final joint fit):',
            _fmt_params(s.parameters),
            '',
        ]
        if 'note' in s.parameters:
            lines += [f'({s.parameters["note"]})', '']
        key = f'step{i}'
        if key in figures:
            lines += [f'![residual before and after {s.effect}]({figures[key]})', '']
        key = f'effect_{s.effect}'
        if key in figures:
            lines += [f'![field attributed to {s.effect}]({figures[key]})', '']
    return lines


def _untestable_section(report: Report) -> list[str]:
    if not report.untestable:
        return []
    lines = [f'- **{name}**: {reason}' for name, reason in report.untestable.items()]
    return ['## Candidates that could not be tested', ''] + lines + ['']


def _rounds_section(report: Report) -> list[str]:
    """Every round's candidate table."""
    lines = ['## Candidates per round', '']
    for i, r in enumerate(report.rounds):
        model = ', '.join(r['model']) or 'base model'
        lines += [
            f'Round {i + 1} (model: {model}; held-out gap {r["gap_nT"]:.4g} nT, noise floor '
            f'{r["noise_floor_nT"]:.4g} nT):',
            '',
            '| candidate | sensor | parameters | gap after, nT | explained RMS, nT | CV-BIC '
            'change | F | p | passes |',
            '|---|---|---|---|---|---|---|---|---|',
        ]
        for c in r['candidates']:
            lines.append(
                f'| {c["effect"]} | {c.get("sensor", "-")} | {c["n_parameters"]} | '
                f'{c["gap_after_nT"]:.4g} | '
                f'{c["explained_rms_nT"]:.3g} | {c["delta_bic"]:+.4g} | {c["f_statistic"]:.4g} | '
                f'{c["p_value"]:.3g} | {"yes" if c["passes"] else "no"} |'
            )
        lines.append('')
    return lines


def _disagreement_section(report: Report, figures: dict[str, str]) -> list[str]:
    """The base-model residual's largest correlation with each driver, and its plots."""
    lines = [
        '## Where the base model disagrees',
        '',
        'Largest correlation of the base-model residual (any sensor and axis) with each driver:',
        '',
    ]
    for name, c in report.diagnostics['base']['correlation'].items():
        lines.append(f'- {name}: r = {c["r"]:+.3f} ({c["where"]})')
    lines.append('')
    if 'diagnostics' in figures:
        lines += [f'![residual against drivers]({figures["diagnostics"]})', '']
    if 'step0' in figures:
        lines += [f'![base-model residual]({figures["step0"]})', '']
    return lines


@dataclass(frozen=True)
class FigureFailure:
    """A figure that raised: file name, what it shows, ``Type: message``, the traceback."""

    figure: str
    what: str
    error: str
    traceback: str


def warn_figure_failure(failure: FigureFailure) -> None:
    """Write the warning line, then the traceback, on stderr (``write_report``'s default)."""
    line = f'warning: figure {failure.figure} ({failure.what}) not drawn: {failure.error}'
    print(line, file=sys.stderr)
    print(failure.traceback, end='', file=sys.stderr)


def write_report(
    report: Report,
    out_dir: str | os.PathLike,
    *,
    plots: bool = True,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    on_figure_error: Callable[[FigureFailure], None] = warn_figure_failure,
) -> Path:
    """Write ``report.json``, then (with ``plots``) the PNGs, then ``report.md`` into the
    folder ``out_dir``, atomically (a previous report folder is replaced only with ``force``;
    :func:`~tetra_gradiometer.io.outputs.atomic_output`). A figure that raises is left out,
    named in report.md and passed to ``on_figure_error`` (default: stderr)."""
    with atomic_output(out_dir, REPORT, force=force, inputs=inputs, command='discrepancy') as out:
        out.mkdir()
        # report.json first: it never depends on the figures (nor on report.md).
        (out / 'report.json').write_text(report_json(report), encoding='utf-8')
        figures, failures = _write_plots(report, out) if plots and report.series else ({}, [])
        for failure in failures:
            on_figure_error(failure)
        text = report_markdown(report, figures, failures)
        (out / 'report.md').write_text(text, encoding='utf-8')
    return Path(out_dir)


#: A figure to draw: key in ``report.md``, file name, what it shows, ``draw(path)``.
_Job = tuple[str, str, str, Callable[[Path], None]]


def _write_plots(report: Report, out: Path) -> tuple[dict[str, str], list[FigureFailure]]:
    """Every PNG of the report into ``out``: {key: file name} of those drawn, the failures."""
    figures: dict[str, str] = {}
    failures: list[FigureFailure] = []
    for key, name, what, draw in _figure_jobs(report):
        try:
            draw(out / name)
        # Deliberately isolated: any other non-TetraError exception is a bug that keeps its
        # traceback, but a figure that cannot be drawn must not cost the report (report.json
        # is already written). The failure is named in report.md and, with its traceback, on
        # stderr, so the bug stays visible.
        except Exception as error:
            (out / name).unlink(missing_ok=True)  # a half-written PNG
            text = ' '.join(''.join(traceback.format_exception_only(error)).split())
            trace = ''.join(traceback.format_exception(error))
            failures.append(FigureFailure(name, what, text, trace))
        else:
            figures[key] = name
    return figures, failures


def _figure_jobs(report: Report) -> list[_Job]:
    """The report's figures, drawn lazily (all their data is read inside ``draw``)."""
    diagnostics = partial(_plot_diagnostics, report)
    jobs: list[_Job] = [
        ('gap', 'gap.png', 'held-out gap per round', partial(_plot_gap, report)),
        ('diagnostics', 'diagnostics.png', 'residual against the drivers', diagnostics),
    ]
    if not report.steps:
        draw = partial(_plot_step, report, 0)
        jobs.append(('step0', 'residual_base.png', 'base-model residual', draw))
    fields = report.series.get('effect_fields') or ()
    for i, step in enumerate(report.steps, 1):
        name = step.effect
        draw = partial(_plot_step, report, i)
        jobs.append((f'step{i}', f'residual_step{i}_{name}.png', f'residual, step {i}', draw))
        key = f'effect_{name}'
        if i - 1 < len(fields) and fields[i - 1] is not None and all(j[0] != key for j in jobs):
            draw = partial(_plot_step_effect, report, i)
            jobs.append((key, f'{key}.png', f'field attributed to {name}', draw))
    return jobs


def _step_rounds(report: Report, i: int) -> tuple[int, int]:
    """The rounds before and after step ``i`` (1-based) was added: the first round whose
    model holds a unit of its family, and the round before (without such a round: i - 1, i)."""
    effect = report.steps[i - 1].effect
    for r, record in enumerate(report.rounds[1:], 1):
        if any(str(u).partition('@')[0] == effect for u in record.get('model', [])):
            return r - 1, r
    return i - 1, i


def _plot_step(report: Report, i: int, path: Path) -> None:
    """The residual (nT) before and after step ``i``; ``i = 0``: the base model's."""
    s = report.series
    grey = ' (grey: excluded spans)' if report.excluded_spans else ''
    residuals = s['residuals']
    if i == 0:
        panels = [('base model', residuals[0])]
        title = 'Residual (measured - simulated) of the base model'
    else:
        name = report.steps[i - 1].effect
        before, after = _step_rounds(report, i)
        panels = [('before', residuals[before]), (f'after + {name}', residuals[after])]
        title = f'Step {i}: residual before and after adding {name}'
    _plot_residuals(path, s['t'], s['sensors'], panels, title + grey, report.excluded_spans)


def _plot_step_effect(report: Report, i: int, path: Path) -> None:
    """The field (nT) step ``i``'s effect contributes, in the sensors where it is not 0."""
    s, name = report.series, report.steps[i - 1].effect
    field = s['effect_fields'][i - 1]
    shown = tuple(k for k in range(4) if np.any(field[:, k])) or s['sensors']
    title = f'Field attributed to {name} (final fit)'
    _plot_residuals(path, s['t'], shown, [(name, field)], title, [])


def _physics(name: str) -> str:
    """The library's text of effect ``name``, or a recorded signal's (``signal:...``)."""
    if name in LIBRARY:
        return LIBRARY[name].physics
    return RecordedSignal(parse_declaration(name, 'effect')).physics
