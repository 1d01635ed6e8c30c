"""The report's ``findings``: one entry per named effect (per step and per spectral line for
the open-world families), with its sensors, what it is confounded with and how to tell
them apart."""

from __future__ import annotations

from typing import Any

import numpy as np

from .detectors import line_label, step_label
from .effects import LIBRARY
from .result import Step
from .search import CONFOUNDED_SHARE, SearchResult


def findings(search: SearchResult, steps: list[Step]) -> list[dict[str, Any]]:
    """The findings of a finished search; ``steps`` carry the final fit's parameters.

    Each entry: ``effect``, ``sensors`` (1-based; ``[]`` for a term common to all sensors),
    ``confounded_with`` (names), ``evidence`` (text); steps add ``t_s`` (s from the first
    sample) and ``jump_nT`` (3,), lines ``frequency_hz``, ``amplitude_nT`` per sensor and
    ``recorded_with_line`` (recorded channels with a line at that frequency too).
    """
    out: list[dict[str, Any]] = []
    for step, members in zip(steps, search.step_units, strict=True):
        units = [search.active[k] for k in members]
        sensors = sorted({u.sensor + 1 for u in units if u.sensor >= 0})
        rivals: dict[str, float] = {}
        for k in members:
            for name, share in search.confounded[k]:
                rivals[name] = max(share, rivals.get(name, 0.0))
        confounded = sorted(rivals, key=lambda name: -rivals[name])
        text = step.evidence + _confounding_text(step.effect, rivals)
        per_sensor = step.parameters.get('per_sensor', {})
        if step.effect == 'hard_iron_step':
            out += _step_findings(search, per_sensor, confounded, text)
        elif step.effect == 'periodic_interference':
            out += _line_findings(search, per_sensor, confounded, text)
        else:
            out.append(
                {
                    'effect': step.effect,
                    'sensors': sensors,
                    'confounded_with': confounded,
                    'evidence': text,
                }
            )
    return out


def _confounding_text(effect: str, rivals: dict[str, float]) -> str:
    """What the confounded candidates explain, and what data would separate them."""
    if not rivals:
        return ''
    shares = ', '.join(f'{name} {100 * share:.0f} %' for name, share in rivals.items())
    separate = '; '.join(
        f'{name}: {LIBRARY[name].separated_by}' for name in (effect, *rivals) if name in LIBRARY
    )
    return (
        f'; confounded: in its place, other candidates explain this share of the held-out '
        f'residual it explains ({shares}; listed from {100 * CONFOUNDED_SHARE:.0f} %), so '
        f'this run cannot tell them apart. What would: {separate}'
    )


def _step_findings(
    search: SearchResult, per_sensor: dict[str, Any], confounded: list[str], text: str
) -> list[dict[str, Any]]:
    out = []
    for change in search.prep.open_world.steps:
        values = per_sensor.get(f'sensor_{change.sensor + 1}', {})
        jump = [values.get(step_label(a, change.t_s)) for a in range(3)]
        if any(v is None for v in jump):
            continue  # a step of a sensor whose unit was not named
        out.append(
            {
                'effect': 'hard_iron_step',
                'sensors': [change.sensor + 1],
                't_s': change.t_s,
                'jump_nT': jump,
                'confounded_with': confounded,
                'evidence': (
                    f'change-point scan of sensor {change.sensor + 1}: mean-shift statistic '
                    f'{change.statistic:.4g} over the threshold {change.threshold:.3g} '
                    f'(chi-square(3), Bonferroni over the possible times); jump '
                    f'{float(np.linalg.norm(jump)):.3g} nT; {text}'
                ),
            }
        )
    return out


def _line_findings(
    search: SearchResult, per_sensor: dict[str, Any], confounded: list[str], text: str
) -> list[dict[str, Any]]:
    out = []
    for line in search.prep.open_world.lines:
        keys = [line_label(w, a, line.frequency_hz) for w in ('sin', 'cos') for a in range(3)]
        amplitude, sensors = {}, []
        for s in sorted(line.sensors):
            values = per_sensor.get(f'sensor_{s + 1}', {})
            terms = [values[key] for key in keys if key in values]
            if terms:
                # sin and cos per axis: the amplitude vector's norm
                amplitude[f'sensor_{s + 1}'] = float(np.sqrt(np.sum(np.square(terms))))
                sensors.append(s + 1)
        if not amplitude:
            continue
        out.append(
            {
                'effect': 'periodic_interference',
                'sensors': sensors,
                'frequency_hz': line.frequency_hz,
                'amplitude_nT': amplitude,
                'confounded_with': confounded,
                'recorded_with_line': list(line.recorded),
                'evidence': (
                    f'spectral line at {line.frequency_hz:.5g} Hz: power {line.power:.3g} x '
                    f'the local noise level, false-alarm probability {line.false_alarm:.2g}; '
                    f'{_recorded_text(line.recorded)}; {text}'
                ),
            }
        )
    return out


def _recorded_text(recorded: tuple[str, ...]) -> str:
    if not recorded:
        return 'no recorded channel has it'
    return (
        f'{", ".join(recorded)} also has a line there: an effect of that channel the library '
        'has no form for would look the same (a run whose manoeuvre or load has no power at '
        'this frequency separates them)'
    )
