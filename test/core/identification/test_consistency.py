"""core/identification/consistency.py: the residual-versus-noise test on residuals whose truth
is known: sensor noise differenced into tensors (white, and MA(1) as linear interpolation at
a constant fractional offset makes it), a passing dipole written out by hand, excess noise
too slow for the differences, gaps; and a known-gradient fit in a regional gradient."""

import json

import numpy as np
import pytest
from interference_helpers import make_interference
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from tetra_gradiometer.core import (
    TetraGeometry,
    calibration_residual,
    difference_tensor,
    fit_consistency,
    known_gradient_lstsq,
)
from tetra_gradiometer.core.identification.consistency import OVERLAP_FACTOR
from tetra_gradiometer.errors import InputError

GEOMETRY = TetraGeometry.regular(0.5)
RATE_HZ, DURATION_S = 50.0, 120.0
N = int(RATE_HZ * DURATION_S)
T_S = 1000.0 + np.arange(N) / RATE_HZ  # any time base
NOISE = 0.1e-9  # per sensor axis, tesla
P = 27


def white_noise(rng, n=N):
    return difference_tensor(rng.normal(0, NOISE, (n, 4, 3)), GEOMETRY)


def interpolated_noise(rng, fraction=0.4):
    """Sensors 2-4 linearly interpolated at a constant fractional offset: MA(1) noise."""
    raw = rng.normal(0, NOISE, (N + 1, 4, 3))
    fields = raw[:N].copy()
    fields[:, 1:] = (1 - fraction) * raw[:N, 1:] + fraction * raw[1:, 1:]
    return difference_tensor(fields, GEOMETRY)


def slow_excess(rng, factor, width=25):
    """Extra sensor noise, correlated over ~``width`` samples (invisible to lag-3 second
    differences), making the total ``factor`` times the white noise."""
    slow = gaussian_filter1d(rng.normal(0, 1, (N, 4, 3)), width, axis=0, mode='wrap')
    slow *= NOISE * np.sqrt(factor**2 - 1) * np.sqrt(2 * width * np.sqrt(np.pi))
    return difference_tensor(slow, GEOMETRY)


def dipole_pass(t_s, peak=2e-9, t0_s=1060.0, speed=2.0, distance=10.0):
    """A dipole passed at ``distance`` m: ``dB_i/dx_j = 3/r^5 [m_j r_i + m_i r_j + (m.r)
    delta_ij - 5 (m.r) r_i r_j / r^2]`` scaled to ``peak`` T/m, ~20 s wide at 2 m/s."""
    along = speed * (t_s - t0_s)
    r = np.column_stack([along, np.full_like(t_s, distance), np.full_like(t_s, 3.0)])
    m = np.array([0.3, -0.5, 1.0])
    r2 = np.sum(r**2, axis=1)
    mr = r @ m
    g = (np.einsum('j,ni->nij', m, r) + np.einsum('i,nj->nij', m, r)
         + mr[:, None, None] * np.eye(3)
         - 5 * (mr / r2)[:, None, None] * np.einsum('ni,nj->nij', r, r))
    g *= (3 / r2**2.5)[:, None, None]
    return g * peak / np.abs(g).max()


def test_white_noise_is_not_refused():
    results = [fit_consistency(white_noise(np.random.default_rng(s)), T_S, GEOMETRY, P)
               for s in range(100)]
    assert sum(r.passed for r in results) >= 99
    assert sum(all(b.passed for b in r.blocks) for r in results) >= 99
    ratios = np.array([r.ratio for r in results])
    assert abs(ratios.mean() - 1.0) < 0.003  # both estimate the same variance
    # The noise estimate is the sensor noise (whitened units are tesla per sensor axis).
    assert np.mean([r.sensor_noise for r in results]) == pytest.approx(NOISE, rel=0.01)
    tensor_rms = np.sqrt(np.mean(white_noise(np.random.default_rng(0)) ** 2))
    assert results[0].noise_rms == pytest.approx(tensor_rms, rel=0.03)


def test_a_noise_free_fit_passes_by_its_roundoff_and_femtotesla_noise_is_still_tested():
    """Roundoff (here 1e-20 T, fit to exact data) is not noise to compare with: ratio 0. Noise
    just above it (1e-15 T, SQUID level) with a slow misfit is still refused."""
    rng = np.random.default_rng(7)
    roundoff = fit_consistency(white_noise(rng) * 1e-10 + dipole_pass(T_S) * 1e-11, T_S, GEOMETRY, P)
    assert roundoff.passed and roundoff.ratio == 0.0
    squid = fit_consistency(white_noise(rng) * 1e-5 + dipole_pass(T_S) * 1e-5, T_S, GEOMETRY, P)
    assert not squid.passed


def test_interpolated_ma1_noise_is_not_refused():
    results = [fit_consistency(interpolated_noise(np.random.default_rng(s)), T_S, GEOMETRY, P)
               for s in range(100)]
    assert sum(r.passed for r in results) >= 99
    assert abs(np.mean([r.ratio for r in results]) - 1.0) < 0.005


def test_the_noise_estimate_has_the_stated_degrees_of_freedom():
    """Var(s_d^2) / E(s_d^2)^2 = 2 / nu2 with nu2 = 9 N' / 1.944 (the docstring's derivation)."""
    noise2 = np.array([fit_consistency(white_noise(np.random.default_rng(s), n=600),
                                       T_S[:600], GEOMETRY, 0).sensor_noise ** 2
                       for s in range(400)])
    nu2 = 9 * (600 - 6) / OVERLAP_FACTOR
    assert OVERLAP_FACTOR == pytest.approx(1.944, abs=1e-3)
    assert np.var(noise2) / np.mean(noise2) ** 2 == pytest.approx(2 / nu2, rel=0.2)


def test_a_passing_dipole_fails_in_its_own_blocks():
    bump = dipole_pass(T_S)
    for seed in range(3):
        result = fit_consistency(white_noise(np.random.default_rng(seed)) + bump, T_S, GEOMETRY, P)
        assert not result.passed
        failing = result.failing_spans()
        # The failing blocks cover the dipole's peak (its half-maximum is ~1057-1063 s)...
        assert any(t0 <= 1056.0 and t1 >= 1064.0 for t0, t1 in failing), failing
        # ...and nothing far from it fails.
        assert all(1045.0 < t0 and t1 < 1075.0 for t0, t1 in failing), failing
        start, end = result.longest_passing_span()
        assert end <= 1056.0 or start >= 1064.0
        assert end - start > 50.0
        assert 'fails in' in result.text and 'nT/m' in result.text


@pytest.mark.parametrize(('factor', 'passes'), [(1.1, True), (1.5, False)])
def test_excess_noise_passes_within_tolerance_and_fails_beyond(factor, passes):
    for seed in range(5):
        rng = np.random.default_rng(seed)
        result = fit_consistency(white_noise(rng) + slow_excess(rng, factor), T_S, GEOMETRY, P)
        assert result.ratio == pytest.approx(factor, rel=0.05)
        assert result.passed is passes
        assert result.threshold_ratio == pytest.approx(1.2 * 1.02, abs=0.01)  # tolerance x F


def test_blocks_name_the_part_of_the_window_that_fails():
    rng = np.random.default_rng(21)
    residual = white_noise(rng)
    inside = (T_S >= 1030.0) & (T_S < 1042.0)
    residual[inside] += 2.0 * slow_excess(rng, 1.5)[inside]
    result = fit_consistency(residual, T_S, GEOMETRY, P, block_s=6.0)
    assert [(b.t0_s, b.t1_s) for b in result.blocks if not b.passed] == [
        (pytest.approx(1030.0), pytest.approx(1036.0)),
        (pytest.approx(1036.0), pytest.approx(1042.0)),
    ]
    assert result.failing_spans() == [(pytest.approx(1030.0), pytest.approx(1042.0))]
    assert result.longest_passing_span() == (pytest.approx(1042.0), pytest.approx(T_S[-1]))
    assert len(result.blocks) == 20 and sum(b.n_samples for b in result.blocks) == N


def test_differences_do_not_span_gaps():
    keep = (T_S < 1040.0) | (T_S >= 1052.0)  # a 12 s gap
    t_s = T_S[keep]
    noise = white_noise(np.random.default_rng(22))[keep]
    # A steep ramp: second differences cancel it within each segment, not across the gap.
    ramp = 1e-9 * (t_s - 1000.0)[:, None, None] * np.ones((3, 3))
    with_ramp = fit_consistency(noise + ramp, t_s, GEOMETRY, P, block_s=6.0)
    plain = fit_consistency(noise, t_s, GEOMETRY, P, block_s=6.0)
    assert with_ramp.noise_rms == pytest.approx(plain.noise_rms, rel=1e-6)
    assert with_ramp.ratio > 50 and not with_ramp.passed  # the ramp itself is a misfit
    # The same estimate by hand: lag-3 second differences inside each segment only.
    d = [seg[6:] - 2 * seg[3:-3] + seg[:-6] for seg in (noise[t_s < 1040], noise[t_s >= 1052])]
    by_hand = np.sqrt(sum(np.sum(x**2) for x in d) / (6 * sum(x.size for x in d)))
    assert plain.noise_rms == pytest.approx(by_hand, rel=1e-12)
    # The empty block [1042, 1048) is left out and ends the passing run.
    assert plain.passed and all(b.passed for b in plain.blocks)
    assert not any(1041.0 < b.t0_s < 1047.0 for b in plain.blocks)
    assert plain.longest_passing_span() == (pytest.approx(1048.0), pytest.approx(t_s[-1]))


def test_a_fit_in_a_regional_gradient_fails_unless_the_gradient_is_fitted():
    """A smooth trim (heading twice round, pitch +-20 deg, roll +-25 deg) in 4 nT/m."""
    rng = np.random.default_rng(23)
    t = T_S - T_S[0]
    euler = np.column_stack([360 * t / 60, 20 * np.sin(2 * np.pi * t / 23),
                             25 * np.sin(2 * np.pi * t / 17)])
    rotation = Rotation.from_euler('ZYX', euler, degrees=True)
    g_world = np.array([[2.0, 1.0, 0.5], [1.0, 1.0, -1.5], [0.5, -1.5, -3.0]])
    g_world *= 4e-9 / np.linalg.norm(g_world)
    matrices = rotation.as_matrix()
    g_body = np.einsum('nai,ab,nbj->nij', matrices, g_world, matrices)
    background = rotation.inv().apply([0.0, 20000e-9, -45000e-9])
    offsets = GEOMETRY.positions - GEOMETRY.positions[0]
    fields = background[:, None, :] + np.einsum('nij,sj->nsi', g_body, offsets)
    measured = make_interference(rng).apply(fields, background) + rng.normal(0, NOISE, (N, 4, 3))
    g, b, q = difference_tensor(measured, GEOMETRY), measured[:, 0], rotation.as_quat()
    old = known_gradient_lstsq(g, b, GEOMETRY)
    refused = fit_consistency(calibration_residual(old, g, b, GEOMETRY), T_S, GEOMETRY, 27)
    assert not refused.passed and refused.ratio > 2.0
    joint = known_gradient_lstsq(g, b, GEOMETRY, orientation_xyzw=q)
    residual = calibration_residual(joint, g, b, GEOMETRY, orientation_xyzw=q)
    accepted = fit_consistency(residual, T_S, GEOMETRY, 32)
    assert accepted.passed and all(block.passed for block in accepted.blocks)


def test_to_dict_is_json_safe_in_nT_per_m():
    result = fit_consistency(white_noise(np.random.default_rng(24)), T_S, GEOMETRY, P)
    record = json.loads(json.dumps(result.to_dict()))
    assert record['residual_rms_nT_per_m'] == pytest.approx(result.residual_rms * 1e9)
    assert record['noise_rms_nT_per_m'] == pytest.approx(result.noise_rms * 1e9)
    assert record['sensor_noise_nT'] == pytest.approx(0.1, rel=0.02)
    assert record['passed'] is True and len(record['blocks']) == 20
    assert record['longest_passing_span_s'] == [pytest.approx(T_S[0]), pytest.approx(T_S[-1])]
    assert record['text'].startswith('residual 0.28') and record['text'].endswith('passes')
    zero = fit_consistency(np.zeros((100, 3, 3)), T_S[:100], GEOMETRY, P).to_dict()
    assert zero['ratio'] == 0.0 and zero['passed'] is True


def test_refuses_bad_input():
    residual = white_noise(np.random.default_rng(25), n=100)
    t_s = T_S[:100].copy()
    with pytest.raises(InputError, match='increase strictly; it does not at index 50'):
        bad = t_s.copy()
        bad[50] = bad[49]
        fit_consistency(residual, bad, GEOMETRY, P)
    with pytest.raises(InputError, match='n_parameters must be in'):
        fit_consistency(residual, t_s, GEOMETRY, 900)
    with pytest.raises(InputError, match='sample counts differ'):
        fit_consistency(residual, t_s[:99], GEOMETRY, P)
    with pytest.raises(InputError, match='too few for a noise estimate'):
        fit_consistency(residual[:12], t_s[:12], GEOMETRY, P)
    with pytest.raises(InputError, match='alpha must be in'):
        fit_consistency(residual, t_s, GEOMETRY, P, alpha=0.0)
    with pytest.raises(InputError, match='block_s must be'):
        fit_consistency(residual, t_s, GEOMETRY, P, block_s=-1.0)
    with pytest.raises(InputError, match='non-finite'):
        residual[3, 1, 1] = np.nan
        fit_consistency(residual, t_s, GEOMETRY, P)
