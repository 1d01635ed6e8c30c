"""The tracker does not learn over the calibration's own window in its bag (pipelines/
tracking.py: ``fitted_window``, ``learning_start_s``, ``TrackedStream.learn_after_s``): up
to the window's end the sets are the frozen ones, after it the change is learnt."""

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
from tetra_gradiometer.pipelines.tracking import TrackedStream, fitted_window, learning_start_s

GEOMETRY = TetraGeometry.regular(0.5)


def test_the_window_is_read_from_the_calibration_diagnostics():
    assert fitted_window({'bag': 'b', 'window_s': '600:839.9 s'}) == ('b', 839.9)
    assert fitted_window({'bag': 'b', 'window_s': 'whole bag'}) == ('b', float('inf'))
    assert fitted_window({'window_s': '0:10 s'}) is None  # which bag it was is not known
    assert fitted_window({'bag': 'b', 'window_s': 'somewhere'}) is None


def test_only_the_calibration_s_own_bag_waits_for_the_window_end(tmp_path):
    bag = tmp_path / 'mission'
    bag.mkdir()
    assert learning_start_s(bag, (str(bag), 42.0)) == 42.0
    assert learning_start_s(tmp_path / '.' / 'mission', (str(bag), 42.0)) == 42.0
    assert learning_start_s(tmp_path / 'other', (str(bag), 42.0)) == float('-inf')
    assert learning_start_s(bag, None) == float('-inf')


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
    stream.learn_after_s = 20.0
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
