"""nodes/channels.py without a graph: a channel's value at a set is the offline one
(io/channels.ChannelSeries.on) on the messages received, the terms per set equal the whole-run
regressors (core/effects.term_regressors) with the same sets dropped, a restarted replay
restarts the eddy history, and the calibrator's choice of terms is ``calibrate``'s."""
from __future__ import annotations

import numpy as np
import pytest
from channel_helpers import BATTERY, NT, example_terms

from tetra_gradiometer import core
from tetra_gradiometer.core.effects import TEMPERATURE, term_regressors
from tetra_gradiometer.core.effects.eddy_current import WINDOW_PERIODS
from tetra_gradiometer.errors import InputError
from tetra_gradiometer.io.channels import ChannelSeries
from tetra_gradiometer.nodes.channels import PRUNE_STEP, ChannelBuffer, LiveEffects, sample_terms
from tetra_gradiometer.pipelines.effects_choice import EffectsChoice
from tetra_gradiometer.pipelines.terms import channels_on

T0 = 1_767_225_600 * 10**9
GEOMETRY = core.TetraGeometry.regular(0.5)


def _messages(rng: np.random.Generator, n: int, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Jittered stamps with two gaps (3 s and 15 s) and values, one NaN."""
    steps = rng.uniform(0.5, 1.5, n) * period_s
    steps[n // 3] += 3.0
    steps[2 * n // 3] += 15.0
    stamps = T0 + np.round(np.cumsum(steps) * 1e9).astype(np.int64)
    values = rng.normal(size=n)
    values[n // 2] = np.nan
    return stamps, values


@pytest.mark.parametrize('name', [TEMPERATURE, BATTERY])
def test_a_sets_value_is_the_offline_one_on_the_messages_received(name):
    rng = np.random.default_rng(1)
    stamps, values = _messages(rng, 400, 0.4)
    sets = np.sort(rng.integers(stamps[0] - 20 * 10**9, stamps[-1] + 20 * 10**9, 3000))
    offline = ChannelSeries(name, stamps, values).on(sets)
    buffer = ChannelBuffer(name)
    for stamp, value in zip(stamps, values):
        buffer.add(int(stamp), float(value))
    live = np.array([buffer.at(int(s)) for s in sets])
    np.testing.assert_array_equal(np.isnan(live), np.isnan(offline))
    np.testing.assert_allclose(live, offline, rtol=0, atol=1e-12)
    assert np.isnan(live).any() and np.isfinite(live).any()  # stale beyond the gaps and ends

    # Pruned as the compensator prunes after each set: the same values for later sets.
    pruned = ChannelBuffer(name)
    for stamp, value in zip(stamps, values):
        pruned.add(int(stamp), float(value))
    later = []
    for s in sets:
        later.append(pruned.at(int(s)))
        pruned.prune(int(s))
    np.testing.assert_array_equal(np.array(later), live)
    assert len(pruned) <= PRUNE_STEP + 30 < len(stamps)  # pruned in steps


def test_a_buffer_without_messages_is_unknown_and_a_restarted_replay_forgets():
    buffer = ChannelBuffer(BATTERY)
    assert np.isnan(buffer.at(T0)) and 'no message yet' in buffer.why_unknown(T0)
    buffer.add(T0, 10.0)
    buffer.add(T0 + 10**9, 12.0)
    assert buffer.at(T0 + 5 * 10**8) == pytest.approx(11.0)
    assert np.isnan(buffer.at(T0 + 4 * 10**9)) and 'stale' in buffer.why_unknown(T0 + 4 * 10**9)
    buffer.add(T0 - 10**9, 7.0)  # a stamp back: a new replay
    assert buffer.restarts == 1 and len(buffer) == 1 and buffer.at(T0) == 7.0


def test_the_terms_per_set_are_the_whole_run_regressors_and_a_replay_starts_again():
    rng = np.random.default_rng(2)
    n = 600
    sets = T0 + np.arange(n, dtype=np.int64) * 5 * 10**7  # 20 Hz
    angle = np.linspace(0.0, 3.0, n)
    b = 5e-5 * np.stack([np.cos(angle), np.sin(angle), 0.3 * np.ones(n)], axis=1)
    current = ChannelSeries(BATTERY, sets[::4], rng.normal(-10, 3, n // 4))
    current = ChannelSeries(BATTERY, np.delete(current.stamps_ns, range(60, 80)),
                            np.delete(current.values, range(60, 80)))  # a 4 s gap: stale sets
    temperature = ChannelSeries(TEMPERATURE, sets[::20] + 3 * 10**7, 15.0 + rng.normal(0, 0.1, n // 20))
    series = {BATTERY: current, TEMPERATURE: temperature}
    terms = example_terms()
    offline = term_regressors(terms, channels_on(sets, b, series))

    live = LiveEffects(terms)
    for name, s in series.items():  # the messages ahead of the sets (a replay's)
        for stamp, value in zip(s.stamps_ns, s.values):
            live.add(name, int(stamp), float(value))
    for replay in range(2):
        out = [live.regressors(int(s), b[i]) for i, s in enumerate(sets)]
        dropped = np.array([x is None for x in out])
        np.testing.assert_array_equal(dropped, ~np.all(np.isfinite(offline), axis=1))
        got = np.array([x for x in out if x is not None])
        np.testing.assert_allclose(got, offline[~dropped], rtol=1e-9, atol=1e-18)
        assert live.resets == replay  # the second pass went back in time: history restarted
    # Per pass: the sets whose eddy window holds the first (a window's worth of 20 Hz sets)
    # and those in the battery's 4 s gap (a message lost), beyond 2 s of a message or not.
    stale = int(np.sum(np.isnan(current.on(sets))))
    in_gap = (sets > current.stamps_ns[59]) & (sets < current.stamps_ns[60])
    assert stale == int(in_gap.sum()), stale
    assert live.dropped == {'reference_rate': 2 * WINDOW_PERIODS, BATTERY: 2 * stale}
    assert 'a message lost around the set' in live.reason  # the last dropped: in the gap


def test_the_calibrators_choice_is_calibrates_and_refuses_a_named_effect_without_its_channel():
    rng = np.random.default_rng(4)
    n = 400
    sets = T0 + np.arange(n, dtype=np.int64) * 5 * 10**7
    angle = np.linspace(0.0, 6.0, n)
    b = 5e-5 * np.stack([np.cos(angle), np.sin(angle), np.sin(0.3 * angle)], axis=1)
    g = rng.normal(size=(n, 3, 3)) * 0.1 * NT
    series = {TEMPERATURE: ChannelSeries(TEMPERATURE, sets, 15.0 + np.linspace(0, 2, n)),
              BATTERY: ChannelSeries(BATTERY, sets[:5] - 60 * 10**9, np.ones(5))}  # an hour ago
    named = EffectsChoice.parse('vehicle_current')
    with pytest.raises(InputError, match='vehicle_current needs a current'):
        sample_terms('known_gradient_lstsq_general', sets, g, b, series, GEOMETRY, named, None)
    with pytest.raises(InputError, match='fitted with known_gradient_lstsq_general, not paper_ga'):
        sample_terms('paper_ga', sets, g, b, series, GEOMETRY, named, None)
    auto = sample_terms('known_gradient_lstsq_general', sets, g, b, series, GEOMETRY, EffectsChoice(), None)
    assert auto.candidates == ()  # noise only: nothing passes the held-out test
    assert set(auto.selection.evidence) == {'eddy_current', 'thermal_drift'}
    assert 'vehicle_current' in auto.lacking and auto.channels == {TEMPERATURE: '/tetra/temperature'}


def test_samples_whose_eddy_rate_is_never_known_select_nothing_and_do_not_fail():
    """Synthetic samples whose ``B_1'`` jumps between every pair (random directions 0.1 s
    apart): no eddy rate anywhere, so the effect is not offered (it crashed the selection
    with a division by zero and left ``~/calibrate`` unanswered)."""
    rng = np.random.default_rng(6)
    n = 200
    sets = T0 + np.arange(n, dtype=np.int64) * 10**8
    b = rng.normal(size=(n, 3))
    b *= 5e-5 / np.linalg.norm(b, axis=1, keepdims=True)
    g = rng.normal(size=(n, 3, 3)) * 0.1 * NT
    chosen = sample_terms('known_gradient_lstsq_general', sets, g, b, {}, GEOMETRY, EffectsChoice(), None)
    assert chosen.candidates == () and 'none selected' in chosen.notes[0]
