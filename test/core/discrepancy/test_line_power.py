"""line_power's running median, one column at a time, against scipy's n-D median filter over
the same (NOISE_WIDTH, 1) window (the form it replaced, 100x slower): the same values, bit for
bit, on random exponential powers (the periodogram's distribution) of several shapes."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import median_filter

from tetra_gradiometer.core.discrepancy.openworld import NOISE_WIDTH, line_power


@pytest.mark.parametrize('shape', [(5000, 12), (300, 3), (NOISE_WIDTH + 1, 1), (2000,)])
def test_line_power_equals_the_nd_running_median_bit_for_bit(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    scale = rng.uniform(0.1, 10.0, size=shape[1:])  # one noise level per column
    power = rng.exponential(size=shape) * scale
    power[rng.integers(0, shape[0], 5)] = 0.0  # exact zeros: the 1e-300 floor
    size = (NOISE_WIDTH,) + (1,) * (len(shape) - 1)
    level = median_filter(power, size=size, mode='reflect') / np.log(2.0)
    expected = power / np.maximum(level, 1e-300)
    got = line_power(power)
    assert got.shape == power.shape
    np.testing.assert_array_equal(got, expected)
