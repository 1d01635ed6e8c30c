"""One source of the array geometry (issue 14): the simulating driver refuses to start when
its scenario's array is not the ``sensor_positions`` the tensor node differences with."""
from __future__ import annotations

from ros_helpers import NodeProcess, unique_domain

from tetra_gradiometer import core


def test_a_scenario_array_other_than_sensor_positions_is_refused_at_start():
    other = list(core.TetraGeometry.regular(0.6).to_flat())
    code, output = NodeProcess('driver', unique_domain(), {'sensor_positions': other}).refusal()
    assert code == 1 and 'Traceback' not in output, output
    line = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(line) == 1 and 'sensor_positions' in line[0] and 'wrong positions' in line[0], output
