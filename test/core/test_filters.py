"""core/_filters.exponential_filter against the recursion written as a loop."""

import numpy as np

from tetra_gradiometer.core._filters import exponential_filter


def test_the_filter_is_the_first_order_recursion_from_its_initial_state():
    rng = np.random.default_rng(5)
    lam = 0.97
    inputs = rng.normal(size=(50, 3))
    state = rng.normal(size=3)  # the previous output
    expected = np.empty_like(inputs)
    for n, row in enumerate(inputs):
        state = row + lam * state
        expected[n] = state
    previous = expected[0] - inputs[0]  # lam * the state before
    got = exponential_filter(lam, inputs, previous[None])
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    one_d = exponential_filter(lam, inputs[:, 0], previous[:1])
    np.testing.assert_allclose(one_d, expected[:, 0], rtol=1e-12, atol=1e-12)


def test_long_inputs_across_blocks_keep_the_recursion_for_slow_and_fast_forgetting():
    rng = np.random.default_rng(6)
    inputs = rng.normal(size=(20_000, 2))
    for lam in (0.9999, 0.999, 0.5, 1e-3):
        state = np.array([3.0, -2.0])
        expected = np.empty_like(inputs)
        for n, row in enumerate(inputs):
            state = row + lam * state
            expected[n] = state
        got = exponential_filter(lam, inputs, lam * np.array([[3.0, -2.0]]))
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
