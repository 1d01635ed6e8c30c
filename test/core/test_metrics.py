"""core/metrics.py: the metrics by hand and the noise floor by Monte Carlo."""
import warnings

import numpy as np
import pytest

from tetra_gradiometer.core import (TetraGeometry, compensated_percent, difference_tensor, epsilon,
                                    improvement_ratio, noise_floor, rms_residual)
from tetra_gradiometer.core.metrics import epsilon_terms, summarize

GEOMETRY = TetraGeometry.regular(0.5)


def _diag(values):
    return np.array([np.diag(v) for v in values], dtype=float)


def test_epsilon_and_percent_by_hand():
    g_true = _diag([[1, 0, 0], [0, 2, 0]])
    g_before = _diag([[3, 0, 0], [0, 4, 0]])   # norms 3, 4 vs true 1, 2
    g_after = _diag([[1.5, 0, 0], [0, 2.2, 0]])  # norms 1.5, 2.2
    expected = np.mean([0.5 / 2.0, 0.2 / 2.0])
    assert epsilon(g_before, g_after, g_true) == pytest.approx(expected)
    assert compensated_percent(expected) == pytest.approx(100 * (1 - expected))
    assert rms_residual(g_after, g_true) == pytest.approx(np.sqrt((0.25 + 0.04) / 18))
    assert improvement_ratio(g_before, g_after, g_true) == pytest.approx(np.sqrt((4 + 4) / (0.25 + 0.04)))


def test_summary_by_hand_in_report_units():
    g_true = _diag([[1, 0, 0], [0, 2, 0]]) * 1e-9
    g_before = _diag([[3, 0, 0], [0, 4, 0]]) * 1e-9
    g_after = _diag([[1.5, 0, 0], [0, 2.2, 0]]) * 1e-9
    expected_eps = np.mean([0.5 / 2.0, 0.2 / 2.0])
    assert summarize(g_before, g_after, g_true) == pytest.approx({
        'epsilon': expected_eps,
        'compensated_percent': 100 * (1 - expected_eps),
        'rms_residual_nT_per_m': np.sqrt((0.25 + 0.04) / 18),
        'improvement_ratio': np.sqrt((4 + 4) / (0.25 + 0.04)),
    }, rel=1e-12)


def test_epsilon_refuses_an_undefined_ratio():
    g = _diag([[1, 0, 0]])
    with pytest.raises(ValueError, match=r'^epsilon is undefined: a sample has \|G_before\|_F == \|G_true\|_F$'):
        epsilon(g, g, g)
    # Only the undefined sample is NaN (not an inf from x / 0); a denominator of exactly 1 is fine.
    g_true = _diag([[1, 0, 0], [1, 0, 0]])
    g_before = _diag([[1, 0, 0], [2, 0, 0]])  # norms 1 (undefined), 2 (denominator 1)
    g_after = _diag([[3, 0, 0], [1.5, 0, 0]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # quietly: no divide-by-zero warning escapes
        terms = epsilon_terms(g_before, g_after, g_true)
        assert np.isnan(epsilon_terms(g_true, g_true, g_true)[0])  # 0 / 0 is quiet too
    assert np.isnan(terms[0]) and terms[1] == pytest.approx(0.5)
    with pytest.raises(ValueError, match=r'g_after must have shape \(N, 3, 3\)'):
        epsilon(g_before, np.zeros((2, 3)), g_true)


def test_improvement_ratio_edge_cases_by_hand():
    g_true = _diag([[1, 0, 0]])
    g_before = _diag([[4, 0, 0]])   # rms (3^2 / 9)^0.5 = 1
    assert improvement_ratio(g_before, g_true, g_true) == float('inf')  # a perfect compensation
    g_after = _diag([[4, 0, 0]]) + 0.0
    assert improvement_ratio(_diag([[7, 0, 0]]), g_after, g_true) == pytest.approx(2.0)  # rms after exactly 1


def test_noise_floor_matches_monte_carlo_and_the_regular_tetrahedron_rule():
    rng = np.random.default_rng(0)
    sigma = 0.1e-9
    noise = rng.normal(0, sigma, (200_000, 4, 3))
    simulated = np.sqrt(np.mean(difference_tensor(noise, GEOMETRY) ** 2))
    assert noise_floor(sigma, GEOMETRY) == pytest.approx(simulated, rel=0.01)
    assert noise_floor(sigma, GEOMETRY) == pytest.approx(1.42 * sigma / 0.5, rel=0.01)
    # An irregular array (no symmetry between rows and columns of a^-1).
    irregular = TetraGeometry([[0.0, 0.0, 0.0], [0.6, 0.1, 0.0], [0.1, 0.3, 0.05], [0.2, 0.1, 0.45]])
    simulated = np.sqrt(np.mean(difference_tensor(noise, irregular) ** 2))
    assert noise_floor(sigma, irregular) == pytest.approx(simulated, rel=0.01)
