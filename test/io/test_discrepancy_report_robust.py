"""The discrepancy report is never lost: report.json is written first and
never depends on the figures; a figure that raises is left out, named in report.md and on
stderr; the gap figure's tick labels come from the rounds, so a search that revised a step
(removed, replaced, merged) still gets its figure. Hand-built reports, no analysis."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import run_cli

from tetra_gradiometer.core.discrepancy import Report, Step
from tetra_gradiometer.core.geometry import TetraGeometry
from tetra_gradiometer.reports import discrepancy as report_io
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.reports.discrepancy import (
    percent_text,
    report_json,
    report_markdown,
    round_labels,
    write_report,
)

N = 200


def _step(effect: str, before: float, after: float) -> Step:
    return Step(
        effect=effect,
        gap_before_nT=before,
        gap_after_nT=after,
        parameters={'per_sensor': {'sensor_2': {'value': 0.01}}, 'units': 'test units'},
        evidence=f'{effect} evidence',
        n_parameters=3,
        delta_bic=-50.0,
        f_statistic=40.0,
        p_value=1e-9,
    )


def _report(models: list[list[str]], effects: list[str], **extra: object) -> Report:
    """A report whose search kept one round per ``models`` entry (the units in the model at
    that round, ``family@sensor_k``) and named ``effects``, one step each: the series hold
    one gap, floor and residual per round, one effect field per step."""
    rng = np.random.default_rng(3)
    gaps = [10.0 / (i + 1) for i in range(len(models))]
    rounds = [
        {'gap_nT': g, 'noise_floor_nT': 1.0, 'model': list(m), 'candidates': []}
        for g, m in zip(gaps, models, strict=True)
    ]
    t = np.arange(N) * 0.1
    series = {
        't': t,
        'sensors': (1, 2, 3),
        'residuals': [rng.normal(size=(N, 4, 3)) * g for g in gaps],
        'gaps': gaps,
        'floors': [1.0] * len(gaps),
        'effect_fields': [np.sin(t)[:, None, None] * np.ones((1, 4, 3)) for _ in effects],
        'b_rate': rng.normal(size=(N, 3)),
        'attitude': None,
        'temperature_c': None,
        'current_a': None,
    }
    fields = dict(
        named_effects=list(effects),
        steps=[_step(e, gaps[0], gaps[-1]) for e in effects],
        gap_initial_nT=gaps[0],
        gap_final_nT=gaps[-1],
        noise_floor_nT=1.0,
        base_model='test base model',
        adequate=True,
        untestable={},
        view='pair',
        notes=[],
        rounds=rounds,
        diagnostics={'base': {'correlation': {'|dB^b/dt|': {'r': 0.4, 'where': 'sensor 2 x'}}}},
        base_parameters={},
        data={'samples': N, 'duration_s': 19.9, 'sample_rate_hz': 10.0},
        runtime_s=0.5,
        series=series,
    )
    fields.update(extra)
    return Report(**fields)  # type: ignore[arg-type]


#: (rounds' models, steps, tick labels): searches whose steps do not match their rounds.
REVISED = {
    # A unit replaced by another family's, moved into a new step: 2 steps, 2 rounds.
    'replaced': (
        [[], ['eddy_current@sensor_2', 'time_skew@sensor_3']],
        ['time_skew', 'eddy_current'],
        ['base', '+ eddy_current (2)\n+ time_skew (3)'],
    ),
    # A later step of the same family merged into the first: 1 step, 3 rounds.
    'merged': (
        [[], ['time_skew@sensor_2'], ['time_skew@sensor_2', 'time_skew@sensor_3']],
        ['time_skew'],
        ['base', '+ time_skew (2)', '+ time_skew (3)'],
    ),
    # A named unit no longer needed once the next one is in (removed): 1 step, 4 rounds.
    'removed': (
        [
            [],
            ['time_skew@sensor_2'],
            ['time_skew@sensor_2', 'eddy_current@sensor_3'],
            ['eddy_current@sensor_3'],
        ],
        ['eddy_current'],
        ['base', '+ time_skew (2)', '+ eddy_current (3)', '- time_skew (2)'],
    ),
}


@pytest.mark.parametrize('case', sorted(REVISED))
def test_gap_figure_is_drawn_after_a_step_was_revised(tmp_path, case):
    """The tick labels built from the steps ('base' + one per step) no longer match the
    gaps (one per round): set_xticks raised ValueError and the report was lost. Built from
    the rounds they match, and every figure is drawn."""
    models, effects, labels = REVISED[case]
    report = _report(models, effects)
    gaps = report.series['gaps']
    assert len(gaps) != 1 + len(report.steps)  # the mismatch of the old labels
    assert round_labels(report, len(gaps)) == labels
    failures: list = []
    out = write_report(report, tmp_path / 'out', on_figure_error=failures.append)
    assert failures == []
    names = {p.name for p in out.iterdir()}
    assert {'report.json', 'report.md', 'gap.png', 'diagnostics.png'} <= names
    for i, effect in enumerate(effects, 1):
        assert f'residual_step{i}_{effect}.png' in names
        assert f'effect_{effect}.png' in names
    text = (out / 'report.md').read_text()
    assert '![gap per round](gap.png)' in text and 'Figures not drawn' not in text


def test_round_labels_never_run_short():
    """More gaps than round records (a hand-built report): still one label per gap."""
    report = _report([[], ['time_skew@sensor_2']], ['time_skew'])
    assert round_labels(report, 3) == ['base', '+ time_skew (2)', 'round 3']
    assert round_labels(report, 1) == ['base']


def test_a_figure_that_raises_costs_only_that_figure(tmp_path, capsys, monkeypatch):
    def broken(report, path):
        raise ValueError('tick labels != number of gaps')

    monkeypatch.setattr(report_io, '_plot_gap', broken)
    report = _report([[], ['time_skew@sensor_2']], ['time_skew'])
    out = write_report(report, tmp_path / 'out')
    assert json.loads((out / 'report.json').read_text()) == json.loads(report_json(report))
    assert not (out / 'gap.png').exists() and (out / 'diagnostics.png').exists()
    text = (out / 'report.md').read_text()
    assert '## Figures not drawn' in text
    assert '`gap.png` (held-out gap per round): ValueError: tick labels != number of gaps' in text
    assert '](gap.png)' not in text  # no link to the missing figure
    assert '![residual against drivers](diagnostics.png)' in text
    err = capsys.readouterr().err
    assert (
        'warning: figure gap.png (held-out gap per round) not drawn: '
        'ValueError: tick labels != number of gaps\n' in err
    )
    assert 'Traceback (most recent call last)' in err and 'in broken' in err


def test_a_half_written_figure_is_removed(tmp_path, monkeypatch):
    def broken(report, path):
        path.write_bytes(b'\x89PNG half')
        raise MemoryError

    monkeypatch.setattr(report_io, '_plot_diagnostics', broken)
    failures: list = []
    report = _report([[], ['time_skew@sensor_2']], ['time_skew'])
    out = write_report(report, tmp_path / 'out', on_figure_error=failures.append)
    assert [(f.figure, f.error) for f in failures] == [('diagnostics.png', 'MemoryError')]
    assert 'MemoryError' in failures[0].traceback
    assert not (out / 'diagnostics.png').exists() and (out / 'gap.png').exists()
    assert json.loads((out / 'report.json').read_text())['named_effects'] == ['time_skew']
    assert '`diagnostics.png`' in (out / 'report.md').read_text()


def test_report_json_is_written_before_any_figure(tmp_path, monkeypatch):
    seen: list[bool] = []

    def spy(report, path):
        seen.append((path.parent / 'report.json').is_file())
        raise RuntimeError('spy')

    monkeypatch.setattr(report_io, '_plot_gap', spy)
    write_report(_report([[]], []), tmp_path / 'out', on_figure_error=lambda failure: None)
    assert seen == [True]


def test_findings_and_excluded_share_in_the_markdown():
    findings = [
        {
            'effect': 'hard_iron_step',
            'sensors': [2, 3],
            't_s': 41.25,
            'confounded_with': [],
            'evidence': 'step of 35 nT | held-out F = 80',
        },
        {
            'effect': 'periodic_interference',
            'sensors': [4],
            'frequency_hz': 0.125,
            'confounded_with': ['thermal_drift'],
            'evidence': 'line at 0.125 Hz',
        },
        {'effect': 'external_field', 'sensors': [], 'confounded_with': [], 'evidence': 'drift'},
    ]
    report = _report(
        [[], ['time_skew@sensor_2']], ['time_skew'], excluded_fraction=0.032, findings=findings
    )
    text = report_markdown(report, {})
    summary = text.split('## Recorded channels')[0]
    assert 'Excluded from the fits and the gap: 3.2 % of the analysed samples.' in summary
    assert '## Findings' in text
    assert '| effect | sensors | time, s / frequency, Hz | confounded with | evidence |' in text
    assert '| hard_iron_step | 2, 3 | 41.25 s | - | step of 35 nT \\| held-out F = 80 |' in text
    assert '| periodic_interference | 4 | 0.125 Hz | thermal_drift | line at 0.125 Hz |' in text
    assert '| external_field | all | - | - | drift |' in text  # a term common to all sensors
    plain = report_markdown(_report([[]], []), {})
    assert '## Findings' not in plain and 'gap: 0.0 % of the analysed samples' in plain


def test_percent_text_keeps_a_small_share_visible():
    assert percent_text(0.0) == '0.0'
    assert percent_text(0.032) == '3.2'
    assert percent_text(0.0004) == '0.04'
    assert percent_text(1.0) == '100.0'


def test_cli_summary_says_how_much_was_excluded(tmp_path, capsys, monkeypatch):
    """The printed summary line names the excluded share (analysis stood in for)."""
    report = _report([[], ['time_skew@sensor_2']], ['time_skew'], excluded_fraction=0.032)
    recording = SimpleNamespace(dropped=SimpleNamespace(total=0), skipped_messages=0, missing={})
    monkeypatch.setattr(
        'tetra_gradiometer.cli.discrepancy.analyze_bag', lambda *a, **k: (report, recording)
    )
    params = tmp_path / 'params.yaml'
    params.write_text(params_document({'sensor_positions': TetraGeometry.regular(0.5).to_flat()}))
    args = ('discrepancy', tmp_path / 'bag', '--params', params, '--out', tmp_path / 'out')
    code, out, err = run_cli(capsys, *args, '--no-plots')
    assert code == 0, err
    assert '; excluded 3.2 % of the samples; ' in out.splitlines()[-1]
    monkeypatch.setattr(
        'tetra_gradiometer.cli.discrepancy.analyze_bag',
        lambda *a, **k: (_report([[]], []), recording),
    )
    code, out, err = run_cli(capsys, *args, '--no-plots', '--force')
    assert code == 0 and 'excluded' not in out.splitlines()[-1]
