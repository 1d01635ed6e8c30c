"""The report.md sections of the targets: those the discrepancy workflow fitted as dipoles,
and the spans it left out."""

from __future__ import annotations

from ..core.discrepancy import Report


def targets_section(report: Report) -> list[str]:
    """The table of the targets modelled as point dipoles (odom frame, ENU)."""
    if not report.targets:
        return []
    lines = [
        '',
        '## Targets (modelled as dipoles)',
        '',
        'Localized fields fitted as point dipoles with the track (/odom) and the base model: '
        'their field is part of the model over the whole run (no pass is left out). Position '
        'and moment in the odom frame (ENU) with 1-sigma; "share" is the share of the base '
        "model's residual (without the targets) that the target's field is.",
        '',
        '| # | position, m | sigma, m | moment, A m^2 | |m|, A m^2 | closest, m | passes | '
        'field RMS, nT | share |',
        '|---|---|---|---|---|---|---|---|---|',
    ]
    for k, t in enumerate(report.targets, 1):
        pos = ', '.join(f'{v:.2f}' for v in t['position_m'])
        sig = ', '.join(f'{v:.2g}' for v in t['position_sigma_m'])
        mom = ', '.join(f'{v:.3g}' for v in t['moment_Am2'])
        lines.append(
            f'| {k} | {pos} | {sig} | {mom} | {t["moment_magnitude_Am2"]:.3g} | '
            f'{t["closest_approach_m"]:.1f} | {t["passes"]} | {t["field_rms_nT"]:.3g} | '
            f'{100 * t["share_of_gap"]:.1f} % |'
        )
    return lines


def excluded_section(report: Report) -> list[str]:
    """The table of excluded target passages, and why each was left out."""
    if not report.excluded_spans:
        return []
    lines = [
        '',
        '## Excluded spans (target passages)',
        '',
        'Spans where the residual is dominated by a localized field that no candidate '
        'represents (it differs between the sensors and rises and falls within the span: a '
        'target passed close to the track). They are left out of every fit and of the '
        'held-out gap, with a margin; "adequate" refers to the rest of the run.',
        '',
        '| start, s | end, s | peak at, s | peak residual, nT | x noise | between sensors, nT | '
        'common, nT | attitude change, deg |',
        '|---|---|---|---|---|---|---|---|',
    ]
    reasons = ['']
    for e in report.excluded_spans:
        common = '-' if e['peak_common_rms_nT'] is None else f'{e["peak_common_rms_nT"]:.3g}'
        turn = '-' if e['attitude_change_deg'] is None else f'{e["attitude_change_deg"]:.1f}'
        lines.append(
            f'| {e["start_s"]:.1f} | {e["end_s"]:.1f} | {e["peak_time_s"]:.1f} | '
            f'{e["peak_residual_rms_nT"]:.3g} | {e["peak_over_noise"]:.0f} | '
            f'{e["peak_difference_rms_nT"]:.3g} | {common} | {turn} |'
        )
        reasons.append(f'- {e["start_s"]:.1f}-{e["end_s"]:.1f} s: {e["reason"]}')
    return lines + reasons
