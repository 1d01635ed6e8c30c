"""Report assembly: the final joint fit's parameters per step, the data summary, the notes
and the plot series, gathered into a :class:`~.result.Report`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..geometry import TetraGeometry
from .cv import ALL_SENSORS
from .diagnostics import diagnostics, tensor_rms
from .dipoles import Located, Track, describe
from .findings import findings
from .fit import column_bounds, effect_field
from .prepare import Prepared
from .result import BASE_MODEL, Report, Settings, Step, format_parameters
from .search import SearchResult
from .targets import TargetSpans
from .unresolved import named_and_unresolved, pass_intervals, resolve

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RunInfo:
    """What the report says about the run beyond the search.

    Attributes
    ----------
    settings : the workflow's settings
    window_s : the analysed window (s from the first sample), or None: the whole run
    earth_from_params : the Earth field came from the parameters (not estimated)
    missing : topic -> why it is unavailable
    untestable : candidate -> why the run cannot test it
    targets : the excluded target passages
    located, track : the targets fitted as dipoles and the track, or None
    notes : what preparing the data and the detector decided
    """

    settings: Settings
    window_s: tuple[float, float] | None
    earth_from_params: bool
    missing: Mapping[str, str]
    untestable: dict[str, str]
    targets: TargetSpans
    notes: list[str]
    located: Located | None = None
    track: Track | None = None


def _final_steps(search: SearchResult) -> tuple[list[Step], list[Array]]:
    """Every step with the parameters of its units from the final joint fit, and the field
    (N, 4, 3) nT each step's effect contributes."""
    prep, active, coef = search.prep, search.active, search.fit.coef
    bounds = column_bounds(prep, active)
    steps: list[Step] = []
    fields: list[Array] = []
    for step, members in zip(search.steps, search.step_units, strict=True):
        labels: list[tuple[int, str]] = []
        values: list[Array] = []
        fld = np.zeros_like(prep.fields)
        for k in members:
            c = coef[bounds[k] : bounds[k + 1]]
            labels += active[k].labels
            values.append(c)
            fld += effect_field(active[k], c)
        parameters = format_parameters(labels, np.concatenate(values), prep.absolute)
        parameters['units'] = active[members[0]].candidate.parameters if members else ''
        parameters['rms_contribution_nT'] = {
            f'sensor_{s + 1}': float(np.sqrt(np.mean(fld[:, s] ** 2)))
            for s in ALL_SENSORS
            if np.any(fld[:, s])
        }
        n_parameters = int(sum(active[k].cols.shape[-1] for k in members))
        steps.append(replace(step, n_parameters=n_parameters, parameters=parameters))
        fields.append(fld)
    return steps, fields


def _base_parameters(search: SearchResult) -> dict[str, Any]:
    prep = search.prep
    base_p = prep.base_cols.shape[-1]
    params = format_parameters(prep.base_labels, search.fit.coef[:base_p], prep.absolute)
    if 'all_sensors' in params['per_sensor']:
        params['earth_field_correction_enu_nT'] = params['per_sensor'].pop('all_sensors')
    return params


def _data(search: SearchResult, info: RunInfo) -> dict[str, Any]:
    """The ``data`` section: samples, rates, inputs, window, exclusions, Earth field."""
    prep, coef, window_s = search.prep, search.fit.coef, info.window_s
    n = len(prep.t)
    duration = float(prep.t[-1] - prep.t[0])
    data: dict[str, Any] = {
        'samples': n,
        'duration_s': duration,
        'sample_rate_hz': float((n - 1) / duration) if duration else 0.0,
        'cv_block_s': search.block_s,
        'folds': info.settings.n_folds,
        'has_odom': prep.absolute,
        'has_temperature': prep.temperature_c is not None,
        'has_current': prep.current_a is not None or bool(prep.extra_currents),
        'missing_topics': dict(info.missing or {}),
        'window_s': None
        if window_s is None
        else [window_s[0], window_s[1] if np.isfinite(window_s[1]) else None],
        'excluded_s': float(sum(e['duration_s'] for e in info.targets.spans)),
        'target_detector': info.targets.detector,
    }
    if prep.earth_field_nT is not None:
        data['earth_field_enu_nT'] = [float(v) for v in prep.earth_field_nT + coef[:3]]
        data['earth_field_drift_enu_nT'] = [float(v) for v in coef[3:6]]
        data['earth_field_source'] = (
            'params, corrected by the fit'
            if info.earth_from_params
            else 'estimated from sensor 1 and /odom, refined by the fit'
        )
        if info.earth_from_params:
            data['earth_field_params_enu_nT'] = [float(v) for v in prep.earth_field_nT]
    return data


def _closing_notes(search: SearchResult, info: RunInfo, excluded: float) -> list[str]:
    """The run's notes, the revisions, and what an inadequate model means."""
    notes = list(info.notes) + list(search.notes)
    if excluded > info.settings.max_excluded:
        notes.append(
            f'{100 * excluded:.1f} % of the samples were excluded as target passages, more '
            f'than {100 * info.settings.max_excluded:g} %: the model cannot be called '
            'adequate on what was left'
        )
    ratio = info.settings.adequate_ratio
    if search.gaps[-1] > ratio * search.floors[-1]:
        notes.append(
            f'the final gap {search.gaps[-1]:.3g} nT exceeds {ratio} x the noise floor '
            f'({search.floors[-1]:.3g} nT) but no candidate in the library explains the rest: '
            'an effect outside the library (or a target close to the track) remains'
        )
        if info.targets.spans:
            notes.append(
                'target passage(s) were excluded, but the rest of the run is not at the noise '
                "floor either: the target's field may reach the manoeuvre (a trim flown near "
                'the target); analyse a run, or a --window, flown away from targets'
            )
    return notes


def _excluded_fraction(prep: Prepared, info: RunInfo) -> float:
    """The excluded samples' share of the analysed ones (kept + excluded)."""
    excluded = sum(int(e['samples']) for e in info.targets.spans)
    return float(excluded / max(excluded + len(prep.t), 1))


def _series(prep: Prepared, search: SearchResult, fields: list[Array]) -> dict[str, Any]:
    """The arrays of the plots."""
    return {
        't': prep.t,
        'sensors': prep.sensors,
        'residuals': search.residuals,
        'gaps': search.gaps,
        'floors': search.floors,
        'effect_fields': fields,
        'b_rate': prep.b_rate,
        'attitude': prep.attitude,
        'temperature_c': prep.temperature_c,
        'current_a': prep.current_a,
    }


def _targets(search: SearchResult, info: RunInfo) -> list[dict[str, Any]]:
    """The fitted targets with their moments from the final joint fit, and the share of
    the base model's residual (without the targets: their fitted field added back) each
    one's field is."""
    located, track, prep = info.located, info.track, search.prep
    if located is None or track is None or prep.target_cols is None:
        return []
    start = prep.base_cols.shape[-1] - prep.target_cols.shape[-1]
    moments = search.fit.coef[start : prep.base_cols.shape[-1]].reshape(-1, 3)
    records = describe(
        prep,
        track,
        located.positions,
        located.position_sigma,
        moments,
        located.moment_sigma,
        search.floors[-1],
    )
    per_target = [
        np.einsum('nsak,k->nsa', prep.target_cols[..., 3 * k : 3 * k + 3], moments[k])
        for k in range(len(moments))
    ]
    sensors = list(prep.sensors)
    without = search.residuals[0] + sum(per_target)
    total = float(np.mean(without[:, sensors] ** 2))
    out = []
    for k, record in enumerate(records):
        if not record.passes:
            continue  # its field nowhere 10 x the noise: a stand-in, not a target to list
        entry = record.to_dict()
        rest = without - per_target[k]
        entry['share_of_gap'] = (total - float(np.mean(rest[:, sensors] ** 2))) / max(
            total, 1e-300
        )
        out.append(entry)
    return out


def build_report(
    search: SearchResult,
    info: RunInfo,
    geometry: TetraGeometry | None,
    *,
    keep_series: bool,
    runtime_s: float,
) -> Report:
    """The :class:`Report` of a finished search."""
    prep = search.prep
    steps, fields = _final_steps(search)
    gap_final, floor_final = search.gaps[-1], search.floors[-1]
    excluded = _excluded_fraction(prep, info)
    adequate = (
        gap_final <= info.settings.adequate_ratio * floor_final
        and excluded <= info.settings.max_excluded
    )
    diag: dict[str, Any] = {
        'base': diagnostics(prep, search.residuals[0]),
        'final': diagnostics(prep, search.residuals[-1]),
    }
    if geometry is not None:
        diag['final_tensor_rms_nT_per_m'] = tensor_rms(prep, search.residuals[-1], geometry)
    view = '; B^b = R^T earth_field_enu from /odom' if prep.absolute else "; B^b = B_1' (no /odom)"
    targets = _targets(search, info)
    passes = []
    if info.track is not None:
        passes = [
            pass_intervals(prep.t, info.track.position, np.asarray(t['position_m']))
            for t in targets
        ]
        for target, own in zip(targets, passes, strict=True):
            target['pass_intervals_s'] = [list(p) for p in own]
    found = resolve(findings(search, steps), passes, info.targets.spans)
    named, unresolved = named_and_unresolved([s.effect for s in steps], found)
    notes = _closing_notes(search, info, excluded)
    if unresolved:
        notes.append(
            f'unresolved (fitted, not named): {", ".join(unresolved)}; see unresolved_because '
            'and separated_by in the findings'
        )
    return Report(
        named_effects=named,
        steps=steps,
        gap_initial_nT=search.gaps[0],
        gap_final_nT=gap_final,
        noise_floor_nT=floor_final,
        base_model=BASE_MODEL + view,
        adequate=bool(adequate),
        untestable=info.untestable,
        view='absolute' if prep.absolute else 'pair',
        notes=notes,
        rounds=search.rounds,
        diagnostics=diag,
        base_parameters=_base_parameters(search),
        data=_data(search, info),
        runtime_s=runtime_s,
        excluded_spans=info.targets.spans,
        excluded_fraction=excluded,
        findings=found,
        settings=info.settings,
        series=_series(prep, search, fields) if keep_series else {},
        targets=targets,
        unresolved_effects=unresolved,
    )
