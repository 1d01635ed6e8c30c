"""core/_distributions against scipy.stats (an independent implementation)."""
import numpy as np
import pytest
from scipy import stats

from tetra_gradiometer.core._distributions import chi2_isf, f_isf, f_sf


@pytest.mark.parametrize('dof', [1, 2, 4, 6, 9.5, 300])
@pytest.mark.parametrize('p', [0.5, 1e-3, 1e-9, 1e-15])
def test_chi2_isf(dof, p):
    np.testing.assert_allclose(chi2_isf(p, dof), stats.chi2.isf(p, dof), rtol=1e-10)


@pytest.mark.parametrize(('dfn', 'dfd'), [(1, 10), (9, 270000), (45.5, 1200.25)])
def test_f_quantile_and_tail(dfn, dfd):
    for q in (0.5, 0.999, 1 - 1e-9):
        np.testing.assert_allclose(f_isf(1 - q, dfn, dfd), stats.f.ppf(q, dfn, dfd), rtol=1e-9)
    for p in (0.5, 1e-3, 1e-9, 1e-15):  # through stats.f.sf: stats.f.isf takes 1 - p (8e-4 off at 1e-15)
        np.testing.assert_allclose(stats.f.sf(f_isf(p, dfn, dfd), dfn, dfd), p, rtol=1e-9)
    for x in (0.0, 0.3, 1.0, 2.5, 40.0):
        np.testing.assert_allclose(f_sf(x, dfn, dfd), stats.f.sf(x, dfn, dfd), rtol=1e-9, atol=1e-300)
