"""What the tests of nodes/channels.py share (test_channels.py, test_channel_hold.py): the
battery channel and a calibration's three effect terms with seeded coefficients."""
from __future__ import annotations

import numpy as np

from tetra_gradiometer.core.effects import TEMPERATURE, Term, current_channel

NT = 1e-9
BATTERY = current_channel('/battery_state')


def example_terms() -> tuple[Term, ...]:
    """A vehicle current on ``/battery_state``, eddy currents (0.2 s) and a thermal drift
    (15 degC reference), coefficients drawn from seed 3."""
    rng = np.random.default_rng(3)
    return (
        Term('vehicle_current', (BATTERY,), rng.normal(size=(3, 3, 1)) * NT),
        Term('eddy_current', ('reference_rate',), rng.normal(size=(3, 3, 3)) * 1e-4, (0.2,)),
        Term('thermal_drift', (TEMPERATURE,), rng.normal(size=(3, 3, 1)) * 0.1 * NT, (15.0,)),
    )
