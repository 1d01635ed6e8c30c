"""The simulator as the offline tools use it: effects that must stay physical across the
joins between segments (where the pose jumps)."""
import numpy as np

from tetra_gradiometer.io.scenario import scenario_from_dict
from tetra_gradiometer.core import simulate

EDDY_S = 3e-4


def _scenario(eddy: bool):
    document = {
        'seed': 1, 'sample_rate_hz': 10, 'noise_nT': 0.0,
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'segments': [{'trim': {'duration_s': 30, 'center_m': [3000.0, 3000.0, -50.0]}},
                     {'line': {'start_m': [-50.0, 0.0, -50.0], 'end_m': [50.0, 0.0, -50.0]}},
                     {'trim': {'duration_s': 20, 'center_m': [0.0, 3000.0, -50.0], 'initial_heading_deg': 90}}],
    }
    if eddy:
        document['effects'] = {'eddy_current': {'coefficients_s': (np.eye(3)[None] * EDDY_S
                                                                   * np.ones((4, 1, 1))).tolist()}}
    return scenario_from_dict(document)[0]


def test_eddy_current_term_is_bounded_by_the_rotation_rate_also_at_segment_joins():
    with_eddy = simulate(_scenario(True), np.random.default_rng(0))
    without = simulate(_scenario(False), np.random.default_rng(0))
    eddy = with_eddy.fields_measured - without.fields_measured
    # Physics bound: in a uniform field the body-frame field only turns, |dB/dt| <= |B| w_max,
    # with w_max <= heading 6 deg/s + roll 25 deg * 2 pi / 11 s + pitch 20 deg * 2 pi / 17 s.
    w_max = np.radians(6.0 + 25.0 * 2 * np.pi / 11.0 + 20.0 * 2 * np.pi / 17.0)
    bound = EDDY_S * 50_000e-9 * w_max
    assert np.abs(eddy).max() <= bound
    joins = np.flatnonzero(np.diff(with_eddy.segment)) + 1
    assert len(joins) == 2
    assert np.abs(eddy).max() > 0.1 * bound


def test_time_skew_reads_the_same_trajectory_also_at_segment_joins():
    skew_s = 0.05
    scenario = _scenario(False)
    document_skew = scenario_from_dict({
        'seed': 1, 'sample_rate_hz': 10, 'noise_nT': 0.0, 'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'segments': [{'trim': {'duration_s': 30, 'center_m': [3000.0, 3000.0, -50.0]}},
                     {'line': {'start_m': [-50.0, 0.0, -50.0], 'end_m': [50.0, 0.0, -50.0]}},
                     {'trim': {'duration_s': 20, 'center_m': [0.0, 3000.0, -50.0], 'initial_heading_deg': 90}}],
        'effects': {'time_skew_s': {'delay_s': [0.0, 0.0, 0.0, skew_s]}}})[0]
    skewed = simulate(document_skew, np.random.default_rng(0))
    plain = simulate(scenario, np.random.default_rng(0))
    change = skewed.fields_measured - plain.fields_measured
    assert np.abs(change[:, :3]).max() == 0.0
    # |B(t - tau) - B(t)| <= tau |B| w_max in a uniform field (as above).
    w_max = np.radians(6.0 + 25.0 * 2 * np.pi / 11.0 + 20.0 * 2 * np.pi / 17.0)
    assert np.abs(change[:, 3]).max() <= skew_s * 50_000e-9 * w_max
    assert np.abs(change[:, 3]).max() > 0.0
