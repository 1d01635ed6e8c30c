"""Shared builders of the core tests: physical interference and trim-manoeuvre readings,
independent of the code under test except ``SensorInterference.apply`` (eq. 10, tested
against a hand-written eq. 10 in test/core/test_model.py)."""

import numpy as np

from tetra_gradiometer.core import SensorInterference


def random_symmetric(rng, scale, n):
    k = rng.uniform(-scale, scale, (n, 3, 3))
    return 0.5 * (k + np.swapaxes(k, 1, 2))


def make_interference(rng, *, clean_reference=True):
    k = random_symmetric(rng, 5e-3, 4)
    b = rng.uniform(-150e-9, 150e-9, (4, 3))
    if clean_reference:
        k[0], b[0] = 0.0, 0.0
    return SensorInterference(k, b)


def uniform_field_attitudes(rng, n, magnitude=5e-5):
    """Body-frame readings of a uniform field under random attitudes (a trim manoeuvre)."""
    directions = rng.normal(size=(n, 3))
    return magnitude * directions / np.linalg.norm(directions, axis=1)[:, None]


def trim_data(rng, interference, n=400, noise=0.0):
    background = uniform_field_attitudes(rng, n)
    fields_true = np.repeat(background[:, None, :], 4, axis=1)
    measured = interference.apply(fields_true, background) + rng.normal(0, noise, (n, 4, 3)) if noise else \
        interference.apply(fields_true, background)
    return measured

