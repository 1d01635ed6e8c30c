"""The workflow's records: its :class:`Settings` in, and the :class:`Report` (with one
:class:`Step` per named effect) out, with the text of the base model and the criterion."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .effects import CANDIDATES

BASE_MODEL = (
    "Yu et al. 2014 eq. 10: B_i' = B_i + K_i B^b + B_i^h, symmetric K_i, constant B_i^h, "
    'sensor 1 clean (K_1 = 0, B_1^h = 0)'
)


@dataclass(frozen=True)
class Settings:
    """Tuning of the workflow (defaults are the documented method).

    Attributes
    ----------
    n_folds : cross-validation folds (interleaved contiguous blocks)
    block_s : block length, s (default: duration / 40 within [5, 30] s)
    knot_s : knot spacing of the ``external_field`` candidate's spline, s
    relevance : minimum held-out RMS explained by an effect, in noise floors
    alpha : level of the held-out F-test
    max_effects : stop after this many effects
    adequate_ratio : the model is adequate when no effect is missing and the final gap is
        within this factor of the noise floor
    candidates : names to test (default all)
    max_samples : analyse at most this many sample sets (every k-th of a longer record)
    exclude_targets : find and leave out spans where a localized field that no candidate
        represents (a target passed close to the track) dominates the residual
    target_high, target_low : a span reaches ``target_high`` and ends below ``target_low``
        x the run's median level of the full model's residual (mean square in noise sigmas,
        averaged over ~2 s)
    target_margin : each span is widened by this share of its length (at least 2 s) each side
    target_max_fraction : spans are excluded only when they cover at most this share of the run
    target_confirm : a span is confirmed when, fitted with its samples in, its mean square
        residual stays at least this factor above the rest of the run's median
    target_edge : a span is excluded only when its residual falls below this share of its
        peak (mean square) at both ends (or to the noise): the evidence of a passage
    target_one_sensor : a span whose residual (sum of squares in noise sigmas) is at least
        this share in one sensor is a change of that sensor, not a passage: not excluded
    max_excluded : a run with more than this share of its samples excluded is never
        adequate (what was left out is not explained)
    model_targets : with the track (/odom position) and the geometry, fit localized fields
        as dipoles in the base model (:mod:`.dipoles`) before excluding what they leave
    """

    n_folds: int = 5
    block_s: float | None = None
    knot_s: float = 30.0
    relevance: float = 1.0
    alpha: float = 1e-6
    max_effects: int = 6
    adequate_ratio: float = 1.25
    candidates: tuple[str, ...] | None = None
    max_samples: int = 6000
    exclude_targets: bool = True
    target_high: float = 12.0
    target_low: float = 2.5
    target_margin: float = 0.5
    target_max_fraction: float = 0.6
    target_confirm: float = 2.0
    target_edge: float = 0.5
    target_one_sensor: float = 0.8
    max_excluded: float = 0.1
    model_targets: bool = True


@dataclass(frozen=True)
class Step:
    """One named effect: the held-out gap before and after adding it, its fitted
    parameters (final joint fit) and the evidence that named it."""

    effect: str
    gap_before_nT: float
    gap_after_nT: float
    parameters: dict[str, Any]
    evidence: str
    n_parameters: int
    delta_bic: float
    f_statistic: float
    p_value: float

    def to_dict(self) -> dict[str, Any]:
        return {
            'effect': self.effect,
            'gap_before_nT': self.gap_before_nT,
            'gap_after_nT': self.gap_after_nT,
            'parameters': self.parameters,
            'evidence': self.evidence,
            'n_parameters': self.n_parameters,
            'delta_bic': self.delta_bic,
            'f_statistic': self.f_statistic,
            'p_value': self.p_value,
        }


@dataclass(frozen=True)
class Report:
    """What the workflow found; ``to_dict()`` is ``report.json``. ``series`` holds the arrays
    for the plots (not serialised)."""

    named_effects: list[str]
    steps: list[Step]
    gap_initial_nT: float
    gap_final_nT: float
    noise_floor_nT: float
    base_model: str
    adequate: bool
    untestable: dict[str, str]
    view: str
    notes: list[str]
    rounds: list[dict[str, Any]]
    diagnostics: dict[str, Any]
    base_parameters: dict[str, Any]
    data: dict[str, Any]
    runtime_s: float
    excluded_spans: list[dict[str, Any]] = field(default_factory=list)
    #: Share (0-1) of the analysed samples left out of the fits and the gap.
    excluded_fraction: float = 0.0
    #: One entry per named effect: effect, sensors (1-based), confounded_with, evidence,
    #: t_s (steps) or frequency_hz (periodic terms), and status ('named' or 'unresolved',
    #: then with unresolved_because and separated_by).
    findings: list[dict[str, Any]] = field(default_factory=list)
    settings: Settings = field(default_factory=Settings)
    series: dict[str, Any] = field(default_factory=dict, repr=False)
    #: The targets fitted as dipoles in the base model (:meth:`.dipoles.Target.to_dict`).
    targets: list[dict[str, Any]] = field(default_factory=list)
    #: Effects fitted but not named: every finding of theirs is unresolved (its evidence
    #: sits at a target's edge or at a recorded channel's frequency; :mod:`.unresolved`).
    unresolved_effects: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            'named_effects': list(self.named_effects),
            'steps': [s.to_dict() for s in self.steps],
            'gap_initial_nT': self.gap_initial_nT,
            'gap_final_nT': self.gap_final_nT,
            'noise_floor_nT': self.noise_floor_nT,
            'base_model': self.base_model,
            'adequate': self.adequate,
            'untestable': dict(self.untestable),
            'view': self.view,
            'notes': list(self.notes),
            'rounds': self.rounds,
            'diagnostics': self.diagnostics,
            'base_parameters': self.base_parameters,
            'data': self.data,
            'excluded_spans': list(self.excluded_spans),
            'excluded_fraction': self.excluded_fraction,
            'findings': list(self.findings),
            'targets': list(self.targets),
            'unresolved_effects': list(self.unresolved_effects),
            'criterion': criterion_text(self.settings),
            'library': {c.name: c.physics for c in CANDIDATES},
            'runtime_s': self.runtime_s,
        }


def criterion_text(settings: Settings | None = None) -> str:
    """The selection criterion in words, with the values of ``settings`` (default ones)."""
    s = settings or Settings()
    return (
        f'Blocked {s.n_folds:d}-fold cross-validation; per unit (family x sensor), the one with '
        'the lowest CV-BIC n ln(SS_cv/n) + p ln n (p: identifiable parameters) is added when its '
        "CV-BIC is lower than the current model's, the held-out F-test of its parameters gives "
        f'p < {s.alpha:g}, and it explains at least ({s.relevance:g} x noise floor)^2 of the '
        'held-out mean square of its own sensor; the step extends the family to the other '
        'sensors that pass; named units are re-checked every round (removed when no longer '
        'needed, replaced by a unit of another family with no more parameters and a lower '
        'CV-BIC); the loop stops when no unit passes.'
    )


def sensor_name(s: int) -> str:
    """Report key of sensor ``s`` (0-based; negative: a term common to all sensors)."""
    return 'all_sensors' if s < 0 else f'sensor_{s + 1}'


def format_parameters(
    labels: list[tuple[int, str]], coef: NDArray[np.float64], absolute: bool
) -> dict[str, Any]:
    """Fitted values per sensor, ``{'per_sensor': {sensor: {name: value}}}`` (and a note on
    what the pair view fixes)."""
    per_sensor: dict[str, dict[str, float]] = {}
    for (s, name), value in zip(labels, coef, strict=True):
        per_sensor.setdefault(sensor_name(s), {})[name] = float(value)
    out: dict[str, Any] = {'per_sensor': per_sensor}
    if not absolute:
        out['note'] = (
            'pair view (no /odom): only differences between a sensor and sensor 1 are '
            'observable; a value at sensor 1 is a term common to all pairs (e.g. tau_i - tau_1 '
            'is what the data fix)'
        )
    return out
