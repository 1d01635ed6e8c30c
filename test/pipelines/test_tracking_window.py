"""The tracker does not learn from sets stamped up to the calibration's last fitted set
(pipelines/tracking.py: ``learn_after_ns``, ``TrackedStream.learn_after_ns``): up to there
the sets are the frozen ones, after it the change is learnt."""

from __future__ import annotations

import numpy as np

from tetra_gradiometer.core import (
    InterferenceParameters,
    Scenario,
    TetraGeometry,
    TrimManoeuvre,
    difference_tensor,
    simulate,
)
from tetra_gradiometer.pipelines.tracking import TrackedStream, learn_after_ns

GEOMETRY = TetraGeometry.regular(0.5)


def test_the_last_fitted_stamp_is_read_from_the_calibration_diagnostics():
    assert learn_after_ns({'samples_window_s': [1_700_000_000.0, 1_700_000_839.9]}) == 1_700_000_839_900_000_000
    assert learn_after_ns({'bag': 'b', 'window_s': '0:10 s'}) is None  # no stamps: learnt from the start
    assert learn_after_ns({'samples_window_s': 'somewhere'}) is None


def test_sets_up_to_the_window_end_are_the_frozen_ones_and_the_change_is_learnt_after():
    """A rotation in the Earth field (true gradient zero) with an offset on sensor 2 from the
    start that the constraints see within a second: nothing is taken from it before the
    window's end (20 s); after it the gate stays closed, and 3 s later (no monitor) the next
    5 s are fitted for each sensor's step: sensor 2's is kept and removed."""
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=np.array([0.0, 2.1e-5, -4.5e-5]),
                        segments=(TrimManoeuvre(40.0),), sample_rate_hz=10.0, noise_t=0.05e-9)
    data = simulate(scenario, np.random.default_rng(5))
    fields = data.fields_measured.copy()
    fields[:, 1] += np.array([2.0, -1.0, 1.5]) * 1e-9
    g = difference_tensor(fields, GEOMETRY)
    stamps = 1_700_000_000 * 10**9 + np.round(data.t * 1e9).astype(np.int64)
    stream = TrackedStream(GEOMETRY, InterferenceParameters.zero(), 0.05e-9)
    stream.learn_after_ns = int(stamps[0]) + 20 * 10**9
    halves = [stream(stamps[rows], fields[rows], g[rows], int(stamps[0]))
              for rows in (slice(0, 150), slice(150, None))]
    tracked = np.concatenate([h[0] for h in halves])
    variance = np.concatenate([h[1] for h in halves])
    before = data.t <= 20.0
    np.testing.assert_array_equal(tracked[before], g[before])
    assert np.all(variance[before] == 0.0)
    floor = 0.1414e-9  # T/m: 0.05 nT through the regular 0.5 m tetrahedron
    late = data.t >= 30.0
    frozen_rms = np.sqrt(np.mean((g[late] - data.g_true[late]) ** 2))
    tracked_rms = np.sqrt(np.mean((tracked[late] - data.g_true[late]) ** 2))
    assert frozen_rms > 5 * floor and tracked_rms < 1.5 * floor
    assert [e.sensors for e in stream.tracker.events if e.kind == 'step'] == [(2,)]
    assert min(e.t_s for e in stream.tracker.events) > 20.0
