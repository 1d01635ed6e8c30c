"""Regression: the time_skew family's Gauss-Newton must not diverge (a ValueError about
non-finite values from the spline of ``_time_skew`` / ``refresh_background`` on a trim flown
20 m from a 4e4 A m^2 dipole). Snippet for test/core/discrepancy/test_analysis.py."""

import numpy as np
import pytest

from tetra_gradiometer.core.discrepancy import analyze
from tetra_gradiometer.core.discrepancy.candidate import Context
from tetra_gradiometer.core.discrepancy.effects import LIBRARY
from tetra_gradiometer.core.discrepancy.fit import fit_current
from tetra_gradiometer.core.discrepancy.prepare import RecordedRun, prepare
from tetra_gradiometer.core.discrepancy.search import _candidates
from tetra_gradiometer.core.simulator import simulate
from tetra_gradiometer.io.scenario import scenario_from_dict


def _trim_near_a_target(seed: int, odom: bool = True) -> tuple[RecordedRun, object]:
    """60 s of trim whose circle centre is 20 m from a 4e4 A m^2 dipole: its field
    (hundreds of nT, changing by the second) reaches every sample, so no span can be left out
    and the search names flexible terms side by side (a delay beside an eddy term)."""
    scenario, _ = scenario_from_dict(
        {
            'seed': seed,
            'sample_rate_hz': 10.0,
            'noise_nT': 0.05,
            'interference': {
                'random': {'k_scale': 0.005, 'b_scale_nT': 150.0, 'reference_clean': False}
            },
            'dipoles': [
                {'position_m': [-1.11, -10.69, -33.13], 'moment_Am2': [21724.0, -33456.0, -2962.0]}
            ],
            'segments': [
                {
                    'trim': {
                        'duration_s': 60.0,
                        'center_m': [0.0, 0.0, -50.0],
                        'heading_rate_deg_s': 5.48,
                        'speed_m_s': 1.81,
                    }
                }
            ],
        }
    )
    m = simulate(scenario, np.random.default_rng(seed))
    run = RecordedRun(
        m.t - m.t[0],
        m.fields_measured,
        m.orientation_xyzw if odom else None,
        m.temperature_c,
        m.current_a,
    )
    return run, scenario


def test_a_trim_near_a_target_is_analysed_with_finite_delays():
    run, scenario = _trim_near_a_target(34)
    report = analyze(run, scenario.geometry, keep_series=False)
    assert np.isfinite(report.gap_final_nT) and report.gap_final_nT < report.gap_initial_nT
    assert not report.adequate  # the target's field is outside the library
    for step in report.steps:
        for values in step.parameters['per_sensor'].values():
            if 'tau_s' in values:
                assert abs(values['tau_s']) < 1.0


def test_the_delay_is_linearised_at_its_estimate():
    # Gauss-Newton: the column is the derivative of the family's exact field
    # B(t - tau) - B(t) (= column x tau + offset) at the estimate, not at tau = 0.
    t = np.arange(0.0, 60.0, 0.1)
    prediction = np.zeros((len(t), 4, 3))
    prediction[:, 1, 0] = 5e4 * np.sin(0.6 * t)
    prediction[:, 1, 2] = 3e4 * np.cos(0.9 * t)
    still = prediction[:, 0]
    ctx = Context(t, (0, 1, 2, 3), True, still, still, prediction, None, None)
    build = LIBRARY['time_skew'].build

    def exact(tau: float) -> np.ndarray:
        cols, offset, _ = build(ctx, {(1, 'tau_s'): tau})
        return cols[:, 1, :, 1] * tau + offset[:, 1]

    tau, h = 0.4, 1e-4
    cols, _, _ = build(ctx, {(1, 'tau_s'): tau})
    inner = slice(10, -10)  # the shifted spline extrapolates at the ends
    derivative = (exact(tau + h) - exact(tau - h)) / (2 * h)
    assert cols[inner, 1, :, 1] == pytest.approx(derivative[inner], abs=1e-3 * 5e4 * 0.6)


def test_pair_view_delay_estimate_leaves_out_the_reference_units():
    # Without /odom a unit of sensor 1 enters every pair difference: eddy terms named in
    # sensors 1, 3 and 4 span one (a delay included) in sensor 2, which must not make the
    # linearisation point of sensor 2's delay wild.
    run, _ = _trim_near_a_target(34, odom=False)
    prep = prepare(run, None, 12000)
    y = prep.fields - prep.base_offset
    eddy = _candidates(prep, fit_current(prep, (), y, 30.0), (LIBRARY['eddy_current'],), y)
    by_sensor = {u.sensor: k for k, u in enumerate(eddy.units)}
    active = (eddy.plain[by_sensor[0]], eddy.units[by_sensor[2]], eddy.units[by_sensor[3]])
    fit = fit_current(prep, active, y, 30.0)
    delays = _candidates(prep, fit, (LIBRARY['time_skew'],), y)
    for unit in delays.units:
        assert unit.estimate is not None
        assert all(abs(v) < 0.05 for v in unit.estimate.values()), unit.estimate
        assert unit.offset is not None and np.max(np.abs(unit.offset)) < 1.0


def test_a_diverged_joint_fit_is_a_clear_error_not_a_spline_value_error():
    from tetra_gradiometer.core.discrepancy.fit import Family, restrict
    from tetra_gradiometer.errors import IdentifiabilityError

    run, _ = _trim_near_a_target(34)
    prep = prepare(run, None, 12000)
    y = prep.fields - prep.base_offset
    fit = fit_current(prep, (), y, 30.0)
    delay = LIBRARY['time_skew']
    estimate = {(1, 'tau_s'): 1e200}  # a linearisation point no fit should reach
    cols, offset, labels = delay.build(fit.ctx, estimate)
    unit = restrict(Family(delay, cols, offset, labels, estimate), 1)
    with pytest.raises(IdentifiabilityError, match=r'time_skew@2\) diverged'):
        fit_current(prep, (unit,), y, 30.0)
