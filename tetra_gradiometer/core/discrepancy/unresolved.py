"""The unresolved rule: a finding whose evidence another explanation fits as well
is reported as *unresolved*, with the data that would separate the two, not named.

Two kinds of evidence are open to a second reading (the choice, written down in
docs/discrepancy.md):

* **At a target's edge** (``hard_iron_step``): a step whose time lies within a listed
  target's pass, or within an excluded span's reach. A target's pass here is where the
  track is within sqrt(2) x its closest approach (|x| <= d along a straight line: the
  field is above ~35 % of its peak and changes fastest), the same half-width the tests
  keep real steps out of; an excluded span reaches half its length beyond either end (its
  tails, which the model does not hold, are what the change-point scan splits at: on a
  survey modelled without its targets, 12 spurious steps all sat there). A target's field
  that the dipole model or the exclusion leaves slightly wrong changes there like a step.
* **At a recorded frequency** (``periodic_interference``): a line where a recorded channel
  has one too (the scan's ``recorded``: the field rate, i.e. the manoeuvre's roll, pitch and
  heading rates, the temperature, a current). A missing effect of that channel, which the
  library has no form for, would show the same line.

An unresolved finding stays in the fitted model (its field is in the data either way, and
the gap is measured with it) but its effect is not named unless another of its findings
is resolved.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: A target's pass: the track within this factor of the closest approach.
PASS_FACTOR = float(np.sqrt(2.0))
#: An excluded span reaches this share of its length beyond either end.
SPAN_REACH = 0.5

#: What data separate a line from a recorded channel's effect, per channel kind.
_LINE_SEPARATION = {
    'field_rate': 'a trim with the heading rate and the roll and pitch periods changed '
    '(a manoeuvre effect moves with them, a rotating part does not)',
    'temperature': 'a recording with the temperature held steady or cycling at another period',
    'current': 'a recording with the current held constant (or switched at another rate)',
}


def pass_intervals(t: Array, position: Array, source: Array) -> list[tuple[float, float]]:
    """Times (s) where the track ``position`` (N, 3) m is within :data:`PASS_FACTOR` x its
    closest approach of ``source`` (3,) m: the target's passes."""
    distance = np.linalg.norm(position - source, axis=1)
    inside = distance <= PASS_FACTOR * float(distance.min())
    edges = np.diff(np.concatenate([[0], inside.astype(int), [0]]))
    first, last = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(t[i]), float(t[j])) for i, j in zip(first, last, strict=True)]


def _edge_reason(
    t_s: float, passes: list[tuple[int, tuple[float, float]]], spans: list[dict[str, Any]]
) -> str | None:
    for k, (t0, t1) in passes:
        if t0 <= t_s <= t1:
            return (
                f"the step at {t_s:.1f} s lies within target {k + 1}'s pass "
                f'({t0:.1f}-{t1:.1f} s, track within {PASS_FACTOR:.2g} x its closest '
                'approach), where an error of the '
                "target's fitted field changes like a step"
            )
    for span in spans:
        reach = SPAN_REACH * span['duration_s']
        if span['start_s'] - reach <= t_s <= span['end_s'] + reach:
            return (
                f'the step at {t_s:.1f} s lies at the edge of the excluded span '
                f"{span['start_s']:.1f}-{span['end_s']:.1f} s, where the left-out target's "
                'tails change like a step'
            )
    return None


def _line_reason(finding: dict[str, Any]) -> tuple[str, str] | None:
    recorded = list(finding.get('recorded_with_line') or [])
    if not recorded:
        return None
    kinds = sorted({_kind(name) for name in recorded})
    because = (
        f'the line at {finding["frequency_hz"]:.5g} Hz is also in the recorded '
        f'{", ".join(recorded)}: an effect of '
        + ('the manoeuvre' if kinds == ['field_rate'] else 'that channel')
        + ' that the library has no form for would show the same line'
    )
    return because, '; or '.join(_LINE_SEPARATION[k] for k in kinds)


def _kind(channel: str) -> str:
    if channel.startswith('field_rate'):
        return 'field_rate'
    return 'temperature' if channel == 'temperature' else 'current'


def resolve(
    findings: list[dict[str, Any]],
    passes: list[list[tuple[float, float]]],
    spans: list[dict[str, Any]],
) -> list[dict[str, Any]]:
    """``findings`` with ``status`` ('named' or 'unresolved'); an unresolved one also gets
    ``unresolved_because`` and ``separated_by`` (the data that would tell the two readings
    apart). ``passes``: per listed target, its passes (s, :func:`pass_intervals`);
    ``spans``: the excluded spans (``start_s``, ``end_s``, ``duration_s``)."""
    flat = [(k, p) for k, target in enumerate(passes) for p in target]
    out = []
    for finding in findings:
        entry = dict(finding, status='named')
        if finding.get('effect') == 'hard_iron_step' and 't_s' in finding:
            why = _edge_reason(float(finding['t_s']), flat, spans)
            if why is not None:
                entry.update(
                    status='unresolved',
                    unresolved_because=why,
                    separated_by='another pass over the target with the vehicle unchanged, or '
                    'a line whose track stays farther from it (a step of the vehicle stays, '
                    "the target's field does not)",
                )
        elif finding.get('effect') == 'periodic_interference' and 'frequency_hz' in finding:
            line = _line_reason(finding)
            if line is not None:
                entry.update(status='unresolved', unresolved_because=line[0], separated_by=line[1])
        out.append(entry)
    return out


def named_and_unresolved(
    effects: list[str], findings: list[dict[str, Any]]
) -> tuple[list[str], list[str]]:
    """The named effects (in ``effects``' order) less those whose every finding is
    unresolved, and those (unresolved)."""
    unresolved = []
    for name in effects:
        own = [f for f in findings if f.get('effect') == name]
        if own and all(f['status'] == 'unresolved' for f in own):
            unresolved.append(name)
    return [e for e in effects if e not in unresolved], unresolved
