"""The driver's start-up refusals: no source chosen (it fabricates no vehicle data
by default), and, one source of the array geometry, a scenario whose array is not the
``sensor_positions`` the tensor node differences with."""
from __future__ import annotations

from ros_helpers import NodeProcess, unique_domain

from tetra_gradiometer import core


def test_a_scenario_array_other_than_sensor_positions_is_refused_at_start():
    other = list(core.TetraGeometry.regular(0.6).to_flat())
    code, output = NodeProcess('driver', unique_domain(), {'mode': 'sim', 'sensor_positions': other}).refusal()
    assert code == 1 and 'Traceback' not in output, output
    line = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(line) == 1 and 'sensor_positions' in line[0] and 'wrong positions' in line[0], output


def test_a_driver_without_a_mode_is_refused_at_start():
    code, output = NodeProcess('driver', unique_domain()).refusal()  # the installed params file
    assert code == 1 and 'Traceback' not in output, output
    line = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(line) == 1 and "parameter 'mode' is not set" in line[0], output
    assert "'sim'" in line[0] and "'replay'" in line[0], output
