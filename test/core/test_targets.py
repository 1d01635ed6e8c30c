"""core/targets: the array's view of a dipole against magpylib (an independent
implementation), tensors between frames against scipy's rotations, and the survey pipeline
against the simulator's targets (ground truth)."""
from __future__ import annotations

import magpylib
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import TetraGeometry, difference_tensor, dipole_gradient, simulate
from tetra_gradiometer.core.targets import Survey, array_tensor, locate, to_body, to_world
from tetra_gradiometer.core.targets.forward import normalized_source_strength
from tetra_gradiometer.io.scenario import scenario_from_dict


def _magpylib_field(points: np.ndarray, moment: np.ndarray, source: np.ndarray) -> np.ndarray:
    dipole = magpylib.misc.Dipole(position=source, moment=moment)
    return np.asarray(dipole.getB(points.reshape(-1, 3))).reshape(points.shape)


def test_dipole_gradient_is_magpylibs_field_differentiated():
    rng = np.random.default_rng(1)
    source, moment = np.array([3.0, -2.0, -25.0]), np.array([2e4, -1e4, 3e4])
    points = rng.uniform(-15, 15, (20, 3))
    h = 1e-3
    numeric = np.stack(
        [(_magpylib_field(points + h * e, moment, source) - _magpylib_field(points - h * e, moment, source)) / (2 * h)
         for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(dipole_gradient(points, moment, source), numeric, rtol=1e-6, atol=1e-16)


def test_the_array_tensor_is_eq7_on_magpylibs_fields_at_the_four_sensors():
    """Exact at 3 m from the target, where eq. 7 and the centroid's gradient differ."""
    rng = np.random.default_rng(2)
    geometry = TetraGeometry.regular(0.5)
    n = 15
    rotations = Rotation.random(n, random_state=3).as_matrix()
    positions = rng.uniform(-2, 2, (n, 3))
    source, moment = np.array([0.5, 0.5, -3.0]), np.array([1e3, 2e3, -5e2])
    sensors = positions[:, None, :] + np.einsum('nij,sj->nsi', rotations, geometry.positions)
    body = np.einsum('nji,nsj->nsi', rotations, _magpylib_field(sensors, moment, source))
    background = np.array([[1.0, 2.0, 0.5], [2.0, -3.0, 1.0], [0.5, 1.0, 2.0]]) * 1e-9
    expected = difference_tensor(body, geometry) + np.einsum('nji,jk,nkl->nil', rotations, background, rotations)
    got = array_tensor(positions, rotations, geometry, source, moment, background)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-18)
    centroid_gradient = dipole_gradient(positions + rotations @ geometry.centroid, moment, source)
    assert np.max(np.abs(to_world(got, rotations) - background - centroid_gradient)) > 1e-3 * np.max(np.abs(got))


def test_tensors_rotate_between_body_and_odom_as_scipy_rotates_vectors():
    rng = np.random.default_rng(4)
    rotation = Rotation.random(7, random_state=5)
    g_body = rng.normal(size=(7, 3, 3))
    vectors = rng.normal(size=(7, 3))
    # G maps a displacement to a field change: the world tensor maps rotated displacements
    # to rotated field changes.
    np.testing.assert_allclose(
        np.einsum('nij,nj->ni', to_world(g_body, rotation.as_matrix()), rotation.apply(vectors)),
        rotation.apply(np.einsum('nij,nj->ni', g_body, vectors)), atol=1e-12)
    np.testing.assert_allclose(to_body(to_world(g_body, rotation.as_matrix()), rotation.as_matrix()), g_body,
                               atol=1e-12)


def test_the_normalized_source_strength_of_a_dipole_is_3_mu0_m_over_4pi_r4():
    rng = np.random.default_rng(6)
    source, moment = np.zeros(3), rng.normal(size=3) * 1e4
    points = rng.normal(size=(50, 3)) * 20
    r = np.linalg.norm(points, axis=1)
    np.testing.assert_allclose(normalized_source_strength(dipole_gradient(points, moment, source)),
                               3e-7 * np.linalg.norm(moment) / r**4, rtol=1e-9)


TARGETS = [
    {'position_m': [-60.0, -10.0, -45.0], 'moment_Am2': [15000.0, 5000.0, -8000.0]},
    {'position_m': [50.0, 8.0, -48.0], 'moment_Am2': [-20000.0, 30000.0, -25000.0]},
]


def _survey(seed: int, targets: list[dict], lines: int = 4, spacing: float = 16.0) -> tuple[Survey, TetraGeometry]:
    """Lines 20-30 m above ``targets`` (clean fields plus the sensor noise): the tensor the
    compensation would leave, without its residual."""
    segments = []
    for i in range(lines):
        y = -spacing * (lines - 1) / 2 + spacing * i
        a, b = (-180.0, 180.0) if i % 2 == 0 else (180.0, -180.0)
        segments.append({'line': {'start_m': [a, y, -25.0], 'end_m': [b, y, -25.0], 'speed_m_s': 2.0,
                                  'roll_amplitude_deg': 2.0, 'pitch_amplitude_deg': 1.0}})
    scenario, _ = scenario_from_dict({'seed': seed, 'sample_rate_hz': 10.0, 'noise_nT': 0.05, 'dipoles': targets,
                                      'segments': segments})
    rng = np.random.default_rng(seed)
    mission = simulate(scenario, rng)
    noisy = mission.fields_true + rng.normal(0.0, scenario.noise_t, mission.fields_true.shape)
    rotations = Rotation.from_quat(mission.orientation_xyzw).as_matrix()
    return Survey(mission.t, mission.position_enu, rotations, difference_tensor(noisy, scenario.geometry)), \
        scenario.geometry


@pytest.mark.parametrize('seed', [11, pytest.param(12, marks=pytest.mark.slow)])
def test_every_target_is_found_and_located_and_nothing_else(seed):
    survey, geometry = _survey(seed, TARGETS)
    targets, _ = locate(survey, geometry)
    assert len(targets) == len(TARGETS), [t.fit.position for t in targets]
    for truth in TARGETS:
        fit = min(targets, key=lambda t: np.linalg.norm(t.fit.position - truth['position_m'])).fit
        assert np.linalg.norm(fit.position - truth['position_m']) <= 0.2
        moment = np.array(truth['moment_Am2'])
        assert np.linalg.norm(fit.moment - moment) <= 0.03 * np.linalg.norm(moment)
        assert np.all(fit.position_sigma > 0)


PAIR = [-10000.0, 20000.0, -15000.0]


@pytest.mark.parametrize('separation_m, ratio, seed', [
    pytest.param(2.0, 1.0, 32, marks=pytest.mark.slow), (5.0, 0.1, 33), pytest.param(20.0, 1.0, 35, marks=pytest.mark.slow)])
def test_a_close_pair_is_resolved_into_two_targets_fitted_together(separation_m, ratio, seed):
    """Two dipoles 2-20 m apart, 22 m under the lines, equal or 10:1 in moment: both found
    (each error within 4 of its sigma, which the joint fit makes larger than alone), nothing
    else, and each says it was fitted with the other."""
    truth = [{'position_m': [10.0, 0.0, -47.0], 'moment_Am2': [15000.0, 5000.0, -8000.0]},
             {'position_m': [10.0 + 0.8 * separation_m, 0.6 * separation_m, -47.0],
              'moment_Am2': [ratio * m for m in PAIR]}]
    survey, geometry = _survey(seed, truth)
    targets, _ = locate(survey, geometry)
    assert len(targets) == 2, [t.fit.position for t in targets]
    assert sorted(t.fitted_with for t in targets) == [(0,), (1,)]
    for dipole in truth:
        fit = min(targets, key=lambda t: np.linalg.norm(t.fit.position - dipole['position_m'])).fit
        error = fit.position - dipole['position_m']
        assert np.linalg.norm(error) <= 0.3
        assert np.all(np.abs(error) <= 4 * fit.position_sigma)
        moment_error = fit.moment - np.array(dipole['moment_Am2'])
        assert np.all(np.abs(moment_error) <= 4 * fit.moment_sigma)


def test_a_target_free_survey_reports_no_target_and_no_detection():
    """At 0.1 false alarms per hour, 12 minutes of noise has a 2 % chance of one."""
    survey, geometry = _survey(13, [])
    targets, detected = locate(survey, geometry)
    assert targets == []
    assert detected.detections == []
    assert detected.noise.dof == pytest.approx(20, rel=0.1)  # white noise: the window's 20 samples


def test_the_noise_models_effective_samples_match_an_ar1_process():
    """Coloured noise (AR(1), coefficient phi): the window of w samples counts as
    w^2 / sum_k (w - |k|) phi^(2|k|) independent ones, and the threshold keeps its rate."""
    from scipy import stats

    from tetra_gradiometer.core.targets.detection import NoiseModel, window_mean

    rng = np.random.default_rng(7)
    phi, w, n = 0.6, 20, 200_000
    white = rng.normal(size=(n, 5)) * np.sqrt(1 - phi**2)
    noise = np.empty_like(white)
    noise[0] = rng.normal(size=5)
    for i in range(1, n):
        noise[i] = phi * noise[i - 1] + white[i]
    mixing = np.array([[2, 0, 0, 0, 0], [1, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, .5, 3, 0], [0, 0, 0, 0, 1]])
    components = noise @ mixing.T * 1e-10
    model = NoiseModel.fit(components, np.ones(n, bool), [(0, n)], w)
    k = np.arange(-w + 1, w)
    expected = w**2 / np.sum((w - np.abs(k)) * phi ** (2 * np.abs(k)))
    assert model.dof == pytest.approx(expected, rel=0.05)
    averaged = window_mean(model.statistic(components), w)[::w]
    point = model.point(1e-2)
    assert np.mean(averaged > point) == pytest.approx(1e-2, rel=0.3)
    assert point > stats.chi2.isf(1e-2, 5 * w) / w  # the white-noise point would not hold


@pytest.mark.parametrize('phi', [0.0, 0.3])
def test_the_threshold_is_crossed_upwards_at_the_stated_rate(phi):
    """The running mean of q crosses the threshold upwards as often per hour as stated, on
    white and on AR(1) noise simulated for 10 hours at 10 Hz (a tail probability per window
    length would be crossed several times as often: the bench's 0.33 per hour at 0.1)."""
    from scipy import signal

    from tetra_gradiometer.core.targets.detection import NoiseModel, window_mean

    rng = np.random.default_rng([11, int(phi * 10)])
    w, rate_hz, hours, stated = 20, 10.0, 10, 60.0
    n = int(hours * 3600 * rate_hz)
    white = rng.normal(size=(n, 5)) * np.sqrt(1 - phi**2)
    components = signal.lfilter([1.0], [1.0, -phi], white, axis=0) * 1e-10
    model = NoiseModel.fit(components, np.ones(n, bool), [(0, n)], w)
    averaged = window_mean(model.statistic(components), w)
    threshold = model.threshold(stated, rate_hz)
    crossings = np.count_nonzero((averaged[1:] > threshold) & (averaged[:-1] <= threshold))
    assert crossings / hours == pytest.approx(stated, rel=0.15)
