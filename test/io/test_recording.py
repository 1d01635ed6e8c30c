"""io/recording.py: a simulated mission written to a bag and read back as it was simulated."""
import numpy as np
import pytest

from tetra_gradiometer.core import Scenario, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.io.recording import read_recording, write_mission_bag

GEOMETRY = TetraGeometry.regular(0.5)


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_mission_bag_round_trip(tmp_path, storage):
    rng = np.random.default_rng(2)
    mission = simulate(Scenario(geometry=GEOMETRY, earth_field_enu=[0, 2e-5, -4.5e-5],
                                segments=[TrimManoeuvre(20.0)], noise_t=1e-10), rng)
    write_mission_bag(tmp_path / 'run', mission, storage=storage, battery=False)
    recording = read_recording(tmp_path / 'run')
    np.testing.assert_array_equal(recording.fields, mission.fields_measured)
    np.testing.assert_allclose(recording.t_s, mission.t, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(recording.orientation_xyzw * mission.orientation_xyzw, axis=1)), 1.0,
                               atol=1e-12)
    np.testing.assert_allclose(recording.temperature_c, mission.temperature_c)
    assert recording.current_a is None and '/battery_state' in recording.missing
