"""Compensation reads a long bag in chunks (io.bag.MagneticBag.iter_sets, 20 000 sets each):
the terms' regressors chunk by chunk (pipelines.terms.StreamRegressors) are those of the
whole run, at the chunks' joins too, with a lost set, a jump, a lost battery message and a
declared signal's rate."""
from __future__ import annotations

import numpy as np
import pytest

from tetra_gradiometer.core.effects import TEMPERATURE, Channels, Term, current_channel, term_regressors
from tetra_gradiometer.io.channels import ChannelSeries
from tetra_gradiometer.pipelines import terms as pipeline_terms

BATTERY = current_channel('/battery_state')
FIN = 'signal:/fins#angle'
T0 = 1_767_225_600 * 10**9


@pytest.mark.parametrize('chunk', [7, 50, 333])
def test_chunks_give_the_whole_run_regressors(chunk, monkeypatch):
    rng = np.random.default_rng(chunk)
    n = 1000
    stamps = T0 + np.arange(n, dtype=np.int64) * 5 * 10**7  # 20 Hz
    stamps = np.delete(stamps, [120, 121, 500])  # sets lost
    angle = np.linspace(0.0, 4.0, len(stamps))
    b = 5e-5 * np.stack([np.cos(angle), np.sin(angle), 0.3 * np.ones(len(stamps))], axis=1)
    b[700:] += 2e-5  # a jump
    battery = np.delete(np.arange(0, n, 4), [30, 31])  # 5 Hz, two messages lost
    current = ChannelSeries(BATTERY, T0 + battery * 5 * 10**7, rng.normal(-10, 3, len(battery)))
    fin = ChannelSeries(FIN, stamps[::2] + 10**7, np.sin(np.linspace(0.0, 30.0, len(stamps[::2]))))
    series = {BATTERY: current, FIN: fin}
    monkeypatch.setattr(pipeline_terms, 'read_channels', lambda bag, names: series)
    rng = np.random.default_rng(3)
    terms = (
        Term('vehicle_current', (BATTERY,), rng.normal(size=(3, 3, 1)) * 1e-9),
        Term('eddy_current', ('reference_rate',), rng.normal(size=(3, 3, 3)) * 1e-4, (0.2,)),
        Term(f'{FIN}:rate', (FIN,), rng.normal(size=(3, 3, 1)) * 1e-9, (0.3,)),
    )
    t_s = (stamps - stamps[0]) * 1e-9
    whole = term_regressors(terms, Channels(t_s, b, {name: c.on(stamps) for name, c in series.items()}))
    assert np.isnan(whole).any(axis=1).sum() > 10  # the start, the losses, the jump

    stream = pipeline_terms.StreamRegressors(terms, None, 'bag')
    fields = np.zeros((len(stamps), 4, 3))
    fields[:, 0] = b
    chunked = np.concatenate([stream(stamps[i:i + chunk], fields[i:i + chunk])
                              for i in range(0, len(stamps), chunk)])
    np.testing.assert_array_equal(np.isnan(chunked), np.isnan(whole))
    np.testing.assert_allclose(chunked, whole, rtol=1e-9, atol=0)
    assert TEMPERATURE not in stream.unknown
