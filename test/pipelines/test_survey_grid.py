"""pipelines/survey_grid.py: the grid against verde's own BlockReduce + KNeighbors, the
cell sigma against a Monte Carlo of the per-sample noise, the default cell and the line
spacing on a lawnmower."""
import numpy as np
import pytest

from tetra_gradiometer.pipelines.survey_grid import GridSettings, default_cell_m, grid_track, line_spacing_m


def lawnmower(spacing=16.0, n_lines=5, step=0.2):
    x = np.arange(-100.0, 100.0, step)
    xy = np.concatenate([np.column_stack([x, np.full_like(x, i * spacing)]) for i in range(n_lines)])
    legs = [(i * len(x), (i + 1) * len(x)) for i in range(n_lines)]
    return xy, legs


def test_the_grid_is_verdes_block_mean_then_k_nearest_blocks():
    import verde as vd  # here, not at collection: ~0.9 s of CPU for every worker

    xy, legs = lawnmower()
    rng = np.random.default_rng(1)
    values = np.sin(xy[:, 0] / 20.0)[:, None, None] * rng.normal(size=(1, 3, 3)) + xy[:, 1, None, None] * 1e-3
    zeros = np.zeros_like(values)
    grids = grid_track(xy, values, zeros, zeros, legs=legs, array_size_m=0.8,
                       settings=GridSettings(cell_m=4.0, max_distance_m=12.0, neighbours=3))
    # verde alone, with the same blocks (the grid's region and spacing)
    region = (grids.x[0] - 2.0, grids.x[-1] + 2.0, grids.y[0] - 2.0, grids.y[-1] + 2.0)
    coordinates, block = vd.BlockReduce(np.mean, spacing=4.0, region=region).filter(
        (xy[:, 0], xy[:, 1]), values[:, 0, 1])
    gx, gy = np.meshgrid(grids.x, grids.y)
    expected = vd.KNeighbors(k=3).fit(coordinates, block).predict((gx, gy))
    mask = grids.mask
    assert mask.sum() > 0.5 * mask.size
    np.testing.assert_allclose(grids.values['gxy'][mask], expected[mask], rtol=1e-10, atol=1e-12)
    assert grids.line_spacing_m == pytest.approx(16.0)


def test_the_cell_sigma_is_the_spread_of_gridded_noise():
    xy, legs = lawnmower(n_lines=3, step=0.5)
    noise = np.full((len(xy), 3, 3), 0.3)
    calibration = np.full((len(xy), 3, 3), 0.05)
    rng = np.random.default_rng(5)
    settings = GridSettings(cell_m=4.0, max_distance_m=10.0, neighbours=4)
    runs = []
    for _ in range(100):
        common = rng.normal(0.0, 0.05)  # the calibration error: one draw for every sample
        values = rng.normal(0.0, 0.3, size=(len(xy), 3, 3)) + common
        runs.append(grid_track(xy, values, noise, calibration, legs=legs, array_size_m=0.8,
                               settings=settings).values['gzz'])
    grids = grid_track(xy, values, noise, calibration, legs=legs, array_size_m=0.8, settings=settings)
    spread = np.std(np.array(runs), axis=0)[grids.mask]
    stated = grids.sigmas['gzz'][grids.mask]
    np.testing.assert_allclose(np.median(spread / stated), 1.0, atol=0.1)


def test_default_cell_follows_the_lines_and_the_array():
    assert default_cell_m(16.0, 0.8) == 4.0
    assert default_cell_m(2.0, 0.8) == 0.8  # never below the array
    assert default_cell_m(float('nan'), 0.8) == 8.0
    xy, legs = lawnmower(spacing=25.0)
    assert line_spacing_m(xy, legs) == pytest.approx(25.0)
    assert np.isnan(line_spacing_m(xy, legs[:1]))
