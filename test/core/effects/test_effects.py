"""Vehicle effects (core/effects, core/identification/terms): regressors, the joint fit of
k, b and the terms against the simulator's truth, the selection, and the live path."""
import numpy as np
import pytest

from tetra_gradiometer.core import (
    Effects,
    Scenario,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    random_interference,
    simulate,
)
from tetra_gradiometer.core.effects import (
    EFFECTS,
    TEMPERATURE,
    Channels,
    LiveTerms,
    causal_rate,
    current_channel,
    term_from_dict,
    term_regressors,
    term_to_dict,
)
from tetra_gradiometer.core.identification import Options, identify
from tetra_gradiometer.core.identification.terms import (
    candidates_for,
    fit_with_terms,
    select_terms,
)
from tetra_gradiometer.core.effects.base import Term
from tetra_gradiometer.core.model import compensate
from tetra_gradiometer.errors import InputError

GEOMETRY = TetraGeometry(np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], float))
NOISE_T = 0.05e-9
BATTERY = current_channel('/battery_state')


def _effects(rng, names):
    """Per-sensor magnitudes as the issue's bags have them (sensor 1 included)."""
    out = {}
    if 'vehicle_current' in names:
        out['vehicle_current'] = rng.uniform(0.5e-9, 2.4e-9, (4, 3)) * rng.choice([-1, 1], (4, 3))
    if 'eddy_current' in names:
        out['eddy_current'] = rng.normal(0, 3e-4, (4, 3, 3))
    if 'thermal_drift' in names:
        out['thermal_drift'] = rng.uniform(0.08e-9, 0.28e-9, (4, 3)) * rng.choice([-1, 1], (4, 3))
    return Effects(**out)


def _trim(seed, names, duration_s=120.0, rate_hz=50.0):
    rng = np.random.default_rng(seed)
    scenario = Scenario(
        GEOMETRY,
        np.array([0.0, 2e-5, -4.5e-5]),
        (TrimManoeuvre(duration_s),),
        sample_rate_hz=rate_hz,
        interference=random_interference(rng),
        noise_t=NOISE_T,
        effects=_effects(rng, names),
    )
    mission = simulate(scenario, rng)
    g = difference_tensor(mission.fields_measured, GEOMETRY)
    b1 = mission.fields_measured[:, 0]
    channels = Channels(
        mission.t, b1, {BATTERY: mission.current_a, TEMPERATURE: mission.temperature_c}
    )
    return scenario, mission, g, b1, channels


def test_the_causal_rate_is_exact_for_a_quadratic_and_uses_only_the_past():
    t = np.cumsum(np.random.default_rng(1).uniform(0.008, 0.012, 400))
    y = np.stack([3.0 * t**2 - t, np.full_like(t, 2.0), -0.5 * t**2], axis=1)
    rate = causal_rate(t, y, 0.05)
    truth = np.stack([6.0 * t - 1.0, 0 * t, -t], axis=1)
    first_window = t <= t[0] + 0.05  # the window holds the first sample: unknown
    assert np.all(np.isnan(rate[first_window]))
    np.testing.assert_allclose(rate[~first_window], truth[~first_window], rtol=1e-7, atol=1e-7)
    # Changing the future changes nothing before it.
    y2 = y.copy()
    y2[200:] += 1.0
    np.testing.assert_array_equal(causal_rate(t, y2, 0.05)[:200], rate[:200])


def test_live_terms_give_the_offline_regressors_sample_by_sample():
    _, mission, g, b1, channels = _trim(4, ('vehicle_current', 'eddy_current', 'thermal_drift'))
    candidates, _ = candidates_for(channels)
    selection = select_terms(g @ GEOMETRY.a, b1, candidates)
    calibration = fit_with_terms(g, b1, GEOMETRY, selection.chosen)
    terms = calibration.parameters.terms
    offline = term_regressors(terms, channels)
    live = LiveTerms(terms)
    pushed = np.array(
        [
            live.push(t, b, {BATTERY: i, TEMPERATURE: c})
            for t, b, i, c in zip(
                mission.t, b1, mission.current_a, mission.temperature_c, strict=True
            )
        ]
    )
    np.testing.assert_allclose(pushed, offline, rtol=1e-9, atol=1e-15, equal_nan=True)


def test_without_terms_the_joint_solve_is_the_general_known_gradient_fit():
    """An independent implementation (QR of the shared design) against lstsq.py's."""
    _, _, g, b1, _ = _trim(5, ())
    ours = fit_with_terms(g, b1, GEOMETRY, ())
    theirs = identify('known_gradient_lstsq_general', g, b1, GEOMETRY, Options())
    np.testing.assert_allclose(ours.parameters.k_soft, theirs.parameters.k_soft, atol=1e-12)
    np.testing.assert_allclose(ours.parameters.b_hard, theirs.parameters.b_hard, atol=1e-18)
    scale = np.abs(theirs.covariance).max()
    np.testing.assert_allclose(ours.covariance, theirs.covariance, rtol=1e-6, atol=1e-9 * scale)


@pytest.mark.parametrize('name', ['vehicle_current', 'eddy_current', 'thermal_drift'])
def test_each_term_is_selected_and_recovered_within_its_sigma(name):
    z = []
    for seed in (11, 12, 13):
        scenario, _, g, b1, channels = _trim(seed, (name,))
        candidates, _ = candidates_for(channels)
        selection = select_terms(g @ GEOMETRY.a, b1, candidates)
        assert [c.name for c in selection.chosen] == [name]
        calibration = fit_with_terms(g, b1, GEOMETRY, selection.chosen)
        (term,) = calibration.parameters.terms
        per_sensor = getattr(scenario.effects, name).reshape(4, 3, -1)
        # B^b = B_1' - W_1 x (sensor 1 has no iron here), so pair i sees
        # (W_i - W_1) x - K_i1 W_1 x: the exact pair coefficient, as effective_parameters.
        k_pairs = scenario.interference.k_soft[1:] - scenario.interference.k_soft[0]
        truth = per_sensor[1:] - per_sensor[0] - k_pairs @ per_sensor[0]  # [pair, axis, j]
        sigma = np.sqrt(np.diag(calibration.covariance)[36:]).reshape(truth.shape)
        z.append(((term.coefficients - truth) / sigma).ravel())
    z = np.concatenate(z)
    assert np.max(np.abs(z)) < 5.0
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6


def test_a_clean_vehicle_gets_no_term():
    for seed in range(20, 26):
        _, _, g, b1, channels = _trim(seed, (), duration_s=90.0)
        candidates, _ = candidates_for(channels)
        assert select_terms(g @ GEOMETRY.a, b1, candidates).chosen == ()


def test_the_compensated_trim_is_at_the_noise_with_every_effect():
    scenario, mission, g, b1, channels = _trim(7, tuple(EFFECTS))
    candidates, _ = candidates_for(channels)
    selection = select_terms(g @ GEOMETRY.a, b1, candidates)
    assert {c.name for c in selection.chosen} == set(EFFECTS)
    calibration = fit_with_terms(g, b1, GEOMETRY, selection.chosen)
    x = term_regressors(calibration.parameters.terms, channels)
    residual = compensate(g, b1, calibration.parameters, GEOMETRY, x) - mission.g_true
    ok = np.all(np.isfinite(x), axis=1)
    noise_only = np.sqrt(2.0) * NOISE_T * np.sqrt(np.mean(GEOMETRY.a_inv**2) * 3)
    assert np.sqrt(np.mean(residual[ok] ** 2)) < 1.1 * noise_only
    # Every term against the truth, each in its place of the joint covariance.
    sigma = np.sqrt(np.diag(calibration.covariance))
    k_pairs = scenario.interference.k_soft[1:] - scenario.interference.k_soft[0]
    offset = 36
    for term in calibration.parameters.terms:
        per_sensor = getattr(scenario.effects, term.effect).reshape(4, 3, -1)
        truth = per_sensor[1:] - per_sensor[0] - k_pairs @ per_sensor[0]
        block = sigma[offset : offset + truth.size].reshape(truth.shape)
        offset += truth.size
        assert np.max(np.abs((term.coefficients - truth) / block)) < 5.0, term.effect


def test_terms_are_never_taken_as_zero():
    _, _, g, b1, channels = _trim(8, ('vehicle_current',))
    candidates, _ = candidates_for(channels)
    calibration = fit_with_terms(g, b1, GEOMETRY, tuple(candidates[:1]))
    with pytest.raises(InputError, match='regressors'):
        compensate(g, b1, calibration.parameters, GEOMETRY)
    without_current = Channels(channels.t_s, channels.b_reference, {})
    with pytest.raises(InputError, match='current:/battery_state'):
        term_regressors(calibration.parameters.terms, without_current)
    _, lacking = candidates_for(without_current)
    assert set(lacking) == {'vehicle_current', 'thermal_drift'}


# ------------------------------------------------------------------------ the file form

AVAILABLE = (BATTERY, current_channel('/thruster1/battery'), TEMPERATURE)


def _term(name: str, rng) -> Term:
    """A term of effect ``name`` on the channels it takes of AVAILABLE, random values."""
    spec = EFFECTS[name]
    inputs = spec.inputs(AVAILABLE)
    m = len(spec.labels(inputs))
    return Term(name, inputs, rng.normal(0.0, 1e-9, (3, 3, m)), tuple(rng.normal(0.0, 1.0, len(inputs))),
                tuple(rng.uniform(0.1, 1.0, m)), {'test': 'F', 'gap_nT': [1.5, 0.2]},
                tuple(rng.normal(0.0, 1.0, m)), tuple(tuple(row) for row in np.eye(m) * 2.0))


@pytest.mark.parametrize('name', sorted(EFFECTS))
def test_a_term_round_trips_through_its_file_form_in_the_effects_file_unit(name):
    """What a calibration file holds of a term (term_to_dict), read back (term_from_dict): the
    same term; coefficients written in the effect's file unit (nT/A, s, nT/degC) with its
    labels, plain types only."""
    import yaml

    rng = np.random.default_rng(sorted(EFFECTS).index(name))
    term = _term(name, rng)
    spec = EFFECTS[name]
    data = term_to_dict(term)
    assert yaml.safe_load(yaml.safe_dump(data)) == data  # plain types
    assert data['effect'] == name and data['unit'] == spec.file_unit
    assert data['labels'] == list(spec.labels(term.inputs))
    np.testing.assert_allclose(np.array(data['coefficients']), term.coefficients * spec.file_factor)
    back = term_from_dict(yaml.safe_load(yaml.safe_dump(data)), 'calibration.yaml terms[0]')
    for field in ('effect', 'inputs', 'reference', 'channel_noise', 'evidence', 'window_mean',
                  'window_covariance'):
        assert getattr(back, field) == getattr(term, field), field
    np.testing.assert_allclose(back.coefficients, term.coefficients, rtol=1e-15)
    older = {k: v for k, v in data.items() if k not in ('window', 'evidence', 'channel_noise')}
    read = term_from_dict(older, 'old.yaml')  # an older file: no window, evidence or noise
    assert read.window_mean == () and read.window_covariance == () and read.evidence == {}
    np.testing.assert_allclose(read.coefficients, term.coefficients, rtol=1e-15)


@pytest.mark.parametrize('data, fragment', [
    (['effect'], 'where: a term must be a mapping, got list'),
    ({'effect': 'magic'}, "where: unknown effect 'magic'; known: "),
    ({'effect': 'thermal_drift', 'inputs': ['temperature:/tetra/temperature']},
     "where (thermal_drift): not a term: 'coefficients'"),
    ({'effect': 'thermal_drift', 'inputs': ['temperature:/tetra/temperature'], 'coefficients': [[1, 2]]},
     'where (thermal_drift): coefficients must be finite (3, 3, 1) [pair][axis][regressor], got (1, 2)'),
    ({'effect': 'thermal_drift', 'inputs': ['temperature:/tetra/temperature'],
      'coefficients': np.full((3, 3, 1), np.nan).tolist()}, 'must be finite (3, 3, 1)'),
    ({'effect': 'thermal_drift', 'inputs': ['temperature:/tetra/temperature'],
      'coefficients': np.zeros((3, 3, 1)).tolist(), 'reference': ['warm']}, 'not a term: could not convert'),
])
def test_a_term_that_is_not_one_is_refused_naming_where_and_what(data, fragment):
    with pytest.raises(InputError) as refused:
        term_from_dict(data, 'where')
    assert fragment in str(refused.value), str(refused.value)


@pytest.mark.parametrize('basis', ['rate', 'harmonic', 'onoff', 'linear'])
def test_a_declared_signal_live_gives_its_offline_regressors_and_a_rate_the_derivative(basis):
    """Sample by sample as on the whole window; the rate of x = sin(0.7 t) is 0.7 cos(0.7 t)."""
    from tetra_gradiometer.core.effects import effect

    rng = np.random.default_rng(9)
    t = np.cumsum(rng.uniform(0.09, 0.11, 600))
    x = np.sin(0.7 * t)
    x[300:305] = np.nan  # a gap: unknown there and (rate) while it is in the window
    name = 'signal:/board#data'
    signal = effect(f'{name}:{basis}')
    channels = Channels(t, np.zeros((len(t), 3)), {name: x})
    reference = signal.reference(channels, (name,))
    offline = signal.regressors(channels, (name,), reference)
    live = signal.live((name,), reference)
    pushed = np.array([live.push(ti, np.zeros(3), {name: xi}) for ti, xi in zip(t, x, strict=True)])
    np.testing.assert_allclose(pushed, offline, rtol=1e-9, atol=1e-12, equal_nan=True)
    if basis == 'rate':
        known = np.isfinite(offline[:, 0])
        assert known.sum() > 580 and not known[300:305].any()
        # within 1 % of its amplitude: a causal quadratic over 4 periods lags a sine a little
        np.testing.assert_allclose(offline[known, 0], 0.7 * np.cos(0.7 * t[known]), atol=7e-3)
