"""The section 6 reproduction (``python -m tetra_gradiometer paper``), checked against truths
computed here independently of the code under test: the noise floor by Monte Carlo from the
sensor positions, the constraint rank by a dimension count and a from-scratch design, the
closest approach from the stated geometry."""
from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from tetra_gradiometer.__main__ import main
from tetra_gradiometer.cli import paper

METHODS = {'paper_ga', 'constraint_lstsq', 'known_gradient_lstsq', 'known_gradient_lstsq_general',
           'pei_yeo_2009'}
METRICS = {'epsilon', 'compensated_percent', 'rms_residual_nT_per_m', 'improvement_ratio', 'solve_seconds'}
SIGMA_NT = 0.1
EDGE_M = 0.5


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    """The whole command, as a user runs it (default 1000 GA generations: a few seconds)."""
    out = tmp_path_factory.mktemp('paper')
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(['paper', '--out', str(out)])
    assert code == 0
    results = json.loads((out / 'results.json').read_text())
    return out, results, printed.getvalue()


def _regular_positions(edge):
    """A regular tetrahedron from its definition: 4 points, all 6 distances equal to edge."""
    p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    return p * edge / (2 * math.sqrt(2))


def _noise_floor_monte_carlo(sigma, positions, n=40_000, seed=0):
    """RMS tensor-component noise: fit G (and a mean field) to 4 noisy readings by least
    squares from the positions alone (for 4 points this is exactly the difference algorithm)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, sigma, (n, 4, 3))
    design = np.column_stack([np.ones(4), positions - positions.mean(axis=0)])  # B_s = B0 + G r_s
    coef, *_ = np.linalg.lstsq(design, noise.transpose(1, 0, 2).reshape(4, -1), rcond=None)
    gradient = coef[1:].reshape(3, n, 3)  # [j, n, i] = dB_i/dx_j
    return float(np.sqrt(np.mean(gradient**2)))


def _check_reading(reading):
    assert set(reading) >= {'scenario', 'identifiability', 'methods'}
    assert set(reading['methods']) == METHODS
    rms_before = reading['scenario']['uncompensated']['rms_interference_nT_per_m']
    for name, metrics in reading['methods'].items():
        assert set(metrics) == METRICS, name
        # The metrics' definitions (eq. 24 and the RMS ratio), by hand from the reported numbers.
        assert metrics['compensated_percent'] == pytest.approx(100 * (1 - metrics['epsilon']), rel=1e-12)
        assert metrics['improvement_ratio'] == pytest.approx(rms_before / metrics['rms_residual_nT_per_m'],
                                                             rel=1e-9), name
        assert metrics['epsilon'] > 0 and metrics['rms_residual_nT_per_m'] > 0
        assert 0 < metrics['solve_seconds'] < 60
    assert reading['identifiability']['n_parameters'] == 27  # 3 symmetric K_i1 (6 each) + 3 b_i1


def test_results_schema_and_the_stated_scenario(run):
    _, results, printed = run
    assert set(results) >= {'scenario', 'identifiability', 'methods', 'scenarios'}
    _check_reading(results)
    _check_reading(results['scenarios']['dipole_only'])
    top, dip = results['scenario'], results['scenarios']['dipole_only']['scenario']
    assert top['reading'] == 'earth_field' and dip['reading'] == 'dipole_only'
    assert np.linalg.norm(top['earth_field_enu_nT']) == pytest.approx(50_000.0)
    assert np.linalg.norm(dip['earth_field_enu_nT']) == 0.0
    # Section 6.1 and 6.2 as printed.
    assert np.array(top['k_soft'])[1].tolist() == [[0.501, 0.0202, 0.0301], [0.0202, 0.1, 0.005],
                                                   [0.0301, 0.005, 0.2]]
    assert top['b_hard_nT'][0] == [4.0, 6.0, 9.0]
    assert top['dipole']['moment_A_m2'] == [4.0e6, 0.0, 0.0]
    line = top['survey_line']
    assert line['n_points'] == 230
    assert line['identification_points'] == [0, 29] and line['compensated_points'] == [30, 229]
    # The closest approach follows from the stated line and target position.
    start, end, target = (np.array(v) for v in (line['start_enu_m'], line['end_enu_m'],
                                                top['dipole']['position_enu_m']))
    direction = (end - start) / np.linalg.norm(end - start)
    offset = (target - start) - direction * ((target - start) @ direction)
    assert line['closest_approach_m'] == pytest.approx(np.linalg.norm(offset), abs=0.5 * line['spacing_m'])
    # Dipole-only interference is "hundreds of nT/m" (the paper's words), Earth-field tens of thousands.
    assert 100.0 < dip['uncompensated']['max_interference_frobenius_nT_per_m'] < 1000.0
    assert top['uncompensated']['max_interference_frobenius_nT_per_m'] > 10_000.0
    # The trim far from the target in reading (b) really sees no gradient.
    assert top['trim_manoeuvre']['max_true_gradient_nT_per_m'] < 0.01 * top['noise_floor_nT_per_m']
    for name in METHODS:
        assert name in printed


def test_noise_floor_matches_an_independent_monte_carlo(run):
    _, results, _ = run
    floor_mc = _noise_floor_monte_carlo(SIGMA_NT, _regular_positions(EDGE_M))
    assert floor_mc == pytest.approx(1.42 * SIGMA_NT / EDGE_M, rel=0.03)  # NOTES.md
    for reading in (results, results['scenarios']['dipole_only']):
        assert reading['scenario']['noise_nT_per_axis'] == SIGMA_NT
        assert reading['scenario']['noise_floor_nT_per_m'] == pytest.approx(floor_mc, rel=0.03)


def test_earth_field_targets_for_the_general_model(run):
    _, results, _ = run
    floor_mc = _noise_floor_monte_carlo(SIGMA_NT, _regular_positions(EDGE_M))
    general = results['methods']['known_gradient_lstsq_general']
    assert general['compensated_percent'] >= 99.9
    assert general['rms_residual_nT_per_m'] <= 2.0 * floor_mc
    # Cannot beat the noise: the residual includes the pass's own sensor noise.
    assert general['rms_residual_nT_per_m'] >= 0.8 * floor_mc
    # Dipole-only reading: the same method, trim near the target with its tensor known.
    dipole_general = results['scenarios']['dipole_only']['methods']['known_gradient_lstsq_general']
    assert dipole_general['rms_residual_nT_per_m'] <= 2.0 * floor_mc


def test_the_other_methods_fall_short_for_the_stated_reasons(run):
    _, results, _ = run
    floor = results['scenario']['noise_floor_nT_per_m']
    methods = results['methods']
    # K_1 = 0.05 makes the exact parameters K_i1 (I + K_1)^-1, not symmetric: the 27-parameter
    # model leaves a modelling error far above the noise in a 50 000 nT field.
    assert methods['known_gradient_lstsq']['rms_residual_nT_per_m'] > 20 * floor
    assert methods['known_gradient_lstsq']['rms_residual_nT_per_m'] > \
        50 * methods['known_gradient_lstsq_general']['rms_residual_nT_per_m']
    # The printed bounds (k <= 0.01) exclude the printed truth (diag K_21 ~ 0.45): the GA can
    # remove almost nothing in reading (b).
    assert methods['paper_ga']['improvement_ratio'] < 1.2
    # Rank 15 of 27: the symmetric traceless part of D is invisible, so the exact solve of the
    # paper's objective does not compensate either (it can even make things worse).
    assert methods['constraint_lstsq']['improvement_ratio'] < 2.0


def _constraint_rank_from_scratch(b_samples, a_inv):
    """Rank of eq. 21's design, built here from eq. 18 alone: columns = the 4 constraint
    values of D for each of the 27 unit parameters (symmetric K_21, K_31, K_41; b)."""
    basis = []
    for pair in range(3):
        for r, c in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
            k = np.zeros((3, 3, 3))
            k[pair, r, c] = k[pair, c, r] = 1.0
            basis.append((k, np.zeros((3, 3))))
    for pair in range(3):
        for r in range(3):
            h = np.zeros((3, 3))
            h[pair, r] = 1.0
            basis.append((np.zeros((3, 3, 3)), h))
    columns = []
    for k, h in basis:
        values = []
        for b in b_samples:
            m = np.column_stack([k[i] @ b + h[i] for i in range(3)])  # (K_i1 B + b_i) columns
            d = m @ a_inv
            values += [d[0, 1] - d[1, 0], d[0, 2] - d[2, 0], d[1, 2] - d[2, 1], np.trace(d)]
        columns.append(values)
    design = np.array(columns).T
    design /= np.linalg.norm(design, axis=0)
    s = np.linalg.svd(design, compute_uv=False)
    return int(np.sum(s > 1e-9 * s[0]))


def test_constraint_rank_is_the_derived_15(run):
    """Why 15: D = (k B_1m + b) a^-1 is affine in x = (B_1', 1). With 4 independent x
    directions in the data, the 4 constraint values (3 asymmetries, trace) see
    * from b: any 3x3 matrix times a^-1, i.e. any D: all 4 values -> rank 4 (5 of 9 invisible);
    * from the symmetric K_i1: a tensor U[r, c, j] symmetric in (r, c), arbitrary otherwise
      (a^-1 is invertible), 18 dims; it is invisible when it is also symmetric in (r, j) -
      hence fully symmetric - and traceless over (r, j) for every c: fully symmetric traceless
      3-tensors = harmonic cubics, dimension 2*3 + 1 = 7; rank 18 - 7 = 11.
    Total 4 + 11 = 15 of 27; null space 12."""
    _, results, _ = run
    expected = 15
    positions = _regular_positions(EDGE_M)
    a_inv = np.linalg.inv((positions[1:] - positions[0]).T)  # eq. 6, from the positions
    rng = np.random.default_rng(3)
    assert _constraint_rank_from_scratch(rng.normal(size=(20, 3)) * 5e-5, a_inv) == expected
    # One field direction only (x spans 2 dims) loses rank, so the count needs the diversity:
    assert _constraint_rank_from_scratch(np.outer(rng.normal(size=20), [1.0, 2.0, 3.0]) * 1e-5,
                                         a_inv) < expected
    # The pass's 30 identification points: a dipole field seen along a straight line varies in
    # 3 directions (r0, v and m span 3D), so x = (B_1', 1) has 4 independent directions.
    for reading in (results, results['scenarios']['dipole_only']):
        assert reading['identifiability']['constraint_rank'] == expected
        assert reading['diagnostics']['constraint_lstsq']['null_space_dim'] == 27 - expected


def test_the_figures_exist_and_show_something(run):
    import matplotlib.image
    out, _, _ = run
    for name in paper.FIGURES:
        path = out / name
        assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', name
        assert path.stat().st_size > 30_000, name
        image = matplotlib.image.imread(path)
        assert image.shape[0] > 400 and image.shape[1] > 800, (name, image.shape)
        assert image[..., :3].std() > 0.05, name  # not blank
        assert (image[..., :3].reshape(-1, 3).std(axis=1) > 0.2).mean() > 0.002, name  # has colour lines
