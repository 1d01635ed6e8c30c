"""core/identification/terms.without_redundant: a channel column the constant and the other
columns span on the window (within its own noise, or exactly up to float32 rounding) is left
out with a note; an independent one stays; the battery's is the one left out of a dependent
set. Truth: columns built here with a known dependence."""
import numpy as np

from tetra_gradiometer.core.identification.terms import Candidate, without_redundant

RNG = np.random.default_rng(5)
N = 2000
PORT, STARBOARD, BATTERY = 'current:/port', 'current:/starboard', 'current:/battery_state'


def _candidate(columns: dict[str, np.ndarray], noise: float) -> Candidate:
    names = tuple(sorted(columns))
    return Candidate('vehicle_current', names, (), np.column_stack([columns[n] for n in names]),
                     channel_noise=(noise,) * len(names))


def test_the_battery_that_sums_the_thrusters_within_its_noise_is_left_out():
    port, starboard = RNG.uniform(-8, 0, N), RNG.uniform(-8, 0, N)
    battery = -3.0 + port + starboard + RNG.normal(0, 0.01, N)  # recorded with 0.01 A noise
    reduced, notes = without_redundant(_candidate({PORT: port, STARBOARD: starboard, BATTERY: battery}, 0.01))
    assert reduced.inputs == (PORT, STARBOARD)
    np.testing.assert_array_equal(reduced.regressors, np.column_stack([port, starboard]))
    assert len(notes) == 1 and notes[0].startswith(f'vehicle_current: {BATTERY} = -3')


def test_exact_dependence_in_float32_and_a_constant_are_found():
    port = RNG.uniform(-8, 0, N).astype(np.float32).astype(float)
    battery = (-3.0 + 2.0 * port).astype(np.float32).astype(float)
    reduced, notes = without_redundant(_candidate({PORT: port, BATTERY: battery}, 0.0))
    assert reduced.inputs == (PORT,) and '= -3 +2 x current:/port' in notes[0]
    reduced, notes = without_redundant(_candidate({BATTERY: np.full(N, -4.25)}, 0.0))
    assert reduced is None and 'constant on the window (-4.25' in notes[0]


def test_independent_currents_all_stay():
    columns = {PORT: RNG.uniform(-8, 0, N), STARBOARD: RNG.uniform(-8, 0, N)}
    columns[BATTERY] = -3.0 + columns[PORT] + columns[STARBOARD] + RNG.uniform(-1.5, 1.5, N)  # a varying hotel
    candidate = _candidate(columns, 0.01)
    reduced, notes = without_redundant(candidate)
    assert reduced is candidate and notes == []
