"""Live = offline when the channels come late: a 1 Hz BatteryState (a usual rate)
whose messages reach the compensator 0.3 s after their stamps, behind the 20 Hz sets. The
compensator holds each set until the battery and temperature messages at or after its stamp
have arrived, so every compensated tensor is the offline one (``compensate``'s channels
interpolated onto the set's stamp) within 1 % of the noise floor; without the hold it took
the last message, up to 89x the floor away (bench/bench_channel_timing.py; checked here on
the same data). Truth: ``core.compensate`` with the regressors of the decimated channels
interpolated (io/channels.ChannelSeries.on), the offline path."""
from __future__ import annotations

import numpy as np
import yaml
from in_process import deserialized, last_status, node_in_process

from tetra_gradiometer import core
from tetra_gradiometer.__main__ import main
from tetra_gradiometer.core.effects import Channels, term_regressors
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import MagneticBag
from tetra_gradiometer.io.calibration import load_calibration
from tetra_gradiometer.io.channels import ChannelSeries

NT = 1e-9
GEOMETRY = core.TetraGeometry.regular(0.5)
CHANNELS = 'tetra/compensator: channels'
BATTERY = 'current:/battery_state'
LATENCY_NS = 3 * 10**8
SCENARIO = {
    'seed': 2029,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
    'sample_rate_hz': 20,
    'noise_nT': 0.05,
    'interference': {'random': {'b_scale_nT': 300, 'k_scale': 0.01, 'reference_clean': True}},
    'effects': {'vehicle_current': {'nT_per_A': [[0.0, 0.0, 0.0], [1.9, -2.2, 1.4],
                                                 [-1.6, 2.4, 0.9], [2.1, 1.1, -2.3]]}},
    'current': {'base_a': -15.0, 'step_amplitude_a': 12.0, 'step_s': 10.0},
    'temperature': {'mean_c': 15.0, 'ramp_c': 4.0, 'amplitude_c': 0.5, 'period_s': 437.0},
    'segments': [
        {'trim': {'duration_s': 60, 'center_m': [3000.0, 3000.0, -50.0], 'heading_rate_deg_s': 6.0,
                  'roll_amplitude_deg': 25.0, 'roll_period_s': 11.0, 'pitch_amplitude_deg': 20.0,
                  'pitch_period_s': 17.0, 'speed_m_s': 1.0}},
    ],
}


def _offline(tmp_path):
    """The bag, its calibration (a battery-current term), its sets and 1 Hz channels, and the
    offline tensors on those channels (and the last-message ones, for the size)."""
    scenario, bag, calibration = tmp_path / 's.yaml', tmp_path / 'bag', tmp_path / 'c.yaml'
    scenario.write_text(yaml.safe_dump(SCENARIO))
    assert main(['simulate', '--scenario', str(scenario), '--out', str(bag)]) == 0
    assert main(['calibrate', str(bag), '--params', str(tmp_path / 'bag.params.yaml'), '--window', '0:59.9',
                 '--out', str(calibration), '--effects', 'vehicle_current']) == 0
    parameters = load_calibration(calibration).parameters
    with MagneticBag(bag) as reader:
        stamps, fields = reader.read_sets()
        recorded = reader.read_series(cv.BATTERY_TOPIC)
    battery = ChannelSeries(BATTERY, recorded.stamps_ns[::20], recorded.values[::20, 0])  # 1 Hz
    raw = core.difference_tensor(fields, GEOMETRY)
    b1 = fields[:, 0, :]
    t_s = (stamps - stamps[0]) * 1e-9
    expected = {}
    for kind, values in (('offline', battery.on(stamps)), ('last', _last_before(battery, stamps))):
        x = term_regressors(parameters.terms, Channels(t_s, b1, {BATTERY: values}))
        expected[kind] = core.compensate(raw, b1, parameters, GEOMETRY, x)
    return calibration, stamps, raw, b1, battery, expected


def _last_before(series: ChannelSeries, stamps: np.ndarray) -> np.ndarray:
    index = np.searchsorted(series.stamps_ns, stamps, side='left') - 1
    return np.where(index >= 0, series.values[np.maximum(index, 0)], np.nan)


def test_late_channel_messages_give_the_offline_tensors(monkeypatch, tmp_path):
    """The compensator in this process (test/ros/in_process.py), handed the sets and the late
    battery messages in the order they arrive; the sets after the last message are released
    by its timer once the steady clock is two battery periods on."""
    from rclpy.serialization import serialize_message

    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.nodes import compensator as compensator_module

    calibration, stamps, raw, b1, battery, expected = _offline(tmp_path)
    floor = core.noise_floor(0.05 * NT, GEOMETRY)
    # Without the hold the last message would be used: far from offline.
    last = np.abs(expected['last'] - expected['offline']).reshape(len(stamps), 9).max(axis=1)
    assert np.nanmax(last) > 5 * floor
    types = cv.rclpy_types()
    with node_in_process(compensator_module.CompensatorNode, monkeypatch,
                         calibration_file=str(calibration), track_calibration=False) as (node, published):
        # Against the frozen calibration's offline tensors: the hold, not the tracker, is tested.
        sent = 0
        for i, stamp in enumerate(stamps):
            tensor = gt.TensorSet(int(stamp), raw[i], reference_field=b1[i])
            node._on_raw(serialize_message(gt.gradient_tensor_msg(types, tensor)))
            # The battery messages 0.3 s old by this set's stamp: behind the sets.
            while sent < len(battery.stamps_ns) and battery.stamps_ns[sent] + LATENCY_NS <= stamp:
                node._on_channel(BATTERY, cv.battery_msg(types, battery.values[sent], int(battery.stamps_ns[sent])))
                sent += 1
        while sent < len(battery.stamps_ns):
            node._on_channel(BATTERY, cv.battery_msg(types, battery.values[sent], int(battery.stamps_ns[sent])))
            sent += 1
        later = compensator_module.time.monotonic() + 10.0
        monkeypatch.setattr(compensator_module.time, 'monotonic', lambda: later)
        node._release_held()
        node._publish_diagnostics()
        held = int(last_status(published, CHANNELS)['sets held for a channel message'])
    live = {t.stamp_ns: t.g for t in map(gt.tensor_set_from_msg,
                                         deserialized(published, '/tetra/gradient/compensated', gt.rclpy_class()))}
    index = np.searchsorted(stamps, np.array(sorted(live)))
    got = np.array([live[s] for s in sorted(live)])
    # Every set after the battery's first delivery (0.3 s) but the first eddy-free ones.
    first = int(np.searchsorted(stamps, battery.stamps_ns[0] + LATENCY_NS))
    assert len(live) >= len(stamps) - first - 1, (len(live), len(stamps), first)
    error = np.abs(got - expected['offline'][index]).reshape(len(got), 9).max(axis=1)
    assert error.max() < 0.01 * floor, error.max() / floor
    assert held > 0.9 * len(stamps)
    print(f'\nlive - offline max {error.max() / floor:.2g} x the floor over {len(live)} sets '
          f'(the last message: up to {np.nanmax(last) / floor:.3g} x); {held} sets held')
