"""Live vs offline channel timing (issue 28): how far a channel's last message is from
``compensate``'s interpolated value, and what that does to the compensated tensor: what the
compensator node did before it held a set for its channels' next message (and does for a set
released at the hold's bound; docs/ros.md, *Vehicle effects*).

    .venv/bin/python bench/bench_channel_timing.py [--json FILE]

Offline, ``compensate`` interpolates each channel linearly onto the set's stamp between the
messages on both sides (``io/channels.ChannelSeries.on``). Live, the compensator node has
only the messages received so far (``nodes/channels.ChannelBuffer.at``): a set taken before
the channel's message at or after its stamp gets the last message's value. This
script takes the bag of ``test/ros/test_effects.py`` (its scenario, copied: 60 s trim then a
60 s line at 20 Hz, battery current stepping 12 A every 10 s, eddy currents, thermal
drift; ``/battery_state`` and ``/tetra/temperature`` at every set's stamp), calibrates on the
trim as the test does, and compensates every set twice: with the channels interpolated
(offline) and with the last message strictly before the set's stamp (live, the worst case:
the channel's message of the set's own instant not yet received). The same again with the
channels recorded at 1 Hz (a typical BatteryState rate), live then being up to 1 s behind.
Printed: RMS and largest difference over the sets and nine components, nT/m, and over the
tensor's noise floor.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tetra_gradiometer.__main__ import main  # noqa: E402
from tetra_gradiometer.core import TetraGeometry, compensate, difference_tensor  # noqa: E402
from tetra_gradiometer.core.effects import Channels, term_regressors, terms_channels  # noqa: E402
from tetra_gradiometer.core.metrics import noise_floor  # noqa: E402
from tetra_gradiometer.io.bag import MagneticBag  # noqa: E402
from tetra_gradiometer.io.calibration import load_calibration  # noqa: E402
from tetra_gradiometer.io.channels import ChannelSeries, channel_topic  # noqa: E402

NT = 1e-9
GEOMETRY = TetraGeometry.regular(0.5)
NOISE_NT = 0.05
TRIM_S = 59.975


def scenario() -> dict:
    """test/ros/test_effects.py's ``_scenario()``."""
    rng = np.random.default_rng(28)
    return {
        'seed': 2028,
        'geometry': {'regular_edge_m': 0.5},
        'earth_field': {'enu_nT': [0.0, 21000.0, -45376.2]},
        'sample_rate_hz': 20,
        'noise_nT': NOISE_NT,
        'interference': {'random': {'b_scale_nT': 300, 'k_scale': 0.01, 'reference_clean': True}},
        'effects': {
            'vehicle_current': {'nT_per_A': np.round(rng.uniform(-2.5, 2.5, (4, 3)), 3).tolist()},
            'eddy_current': {
                'coefficients_s': np.round(rng.uniform(-6e-4, 6e-4, (4, 3, 3)), 6).tolist()
            },
            'thermal_drift': {'nT_per_degC': np.round(rng.uniform(-0.3, 0.3, (4, 3)), 3).tolist()},
        },
        'current': {'base_a': -15.0, 'step_amplitude_a': 12.0, 'step_s': 10.0},
        'temperature': {'mean_c': 15.0, 'ramp_c': 4.0, 'amplitude_c': 0.5, 'period_s': 437.0},
        'dipoles': [{'position_m': [0.0, 0.0, -80.0], 'moment_Am2': [30000.0, 20000.0, -33000.0]}],
        'segments': [
            {
                'trim': {
                    'duration_s': 60,
                    'center_m': [3000.0, 3000.0, -50.0],
                    'heading_rate_deg_s': 6.0,
                    'roll_amplitude_deg': 25.0,
                    'roll_period_s': 11.0,
                    'pitch_amplitude_deg': 20.0,
                    'pitch_period_s': 17.0,
                    'speed_m_s': 1.0,
                }
            },
            {
                'line': {
                    'start_m': [-60.0, 0.0, -50.0],
                    'end_m': [60.0, 0.0, -50.0],
                    'speed_m_s': 2.0,
                    'roll_amplitude_deg': 2.0,
                    'pitch_amplitude_deg': 1.0,
                }
            },
        ],
    }


def last_before(series: ChannelSeries, stamps_ns: np.ndarray) -> np.ndarray:
    """The live worst case: each set takes the last message strictly before its stamp
    (NaN before the first)."""
    index = np.searchsorted(series.stamps_ns, stamps_ns, side='left') - 1
    out = series.values[np.maximum(index, 0)].astype(float)
    out[index < 0] = np.nan
    return out


def difference(bag: Path, calibration: Path, stride: int, lagged: tuple[str, ...] = ()) -> dict:
    """Offline against live on the bag's sets with every ``stride``-th channel message, the
    channels ``lagged`` (all when empty) taken live; and each against the channels at their
    recorded rate interpolated (the closest to their true value at the set)."""
    parameters = load_calibration(calibration).parameters
    with MagneticBag(bag) as reader:
        stamps, fields = reader.read_sets()
        full = {}
        for name in terms_channels(parameters.terms):
            s = reader.read_series(channel_topic(name))
            full[name] = ChannelSeries(name, s.stamps_ns, s.values[:, 0])
    series = {
        n: ChannelSeries(n, s.stamps_ns[::stride], s.values[::stride]) for n, s in full.items()
    }
    t_s = (stamps - stamps[0]) * 1e-9
    b1 = fields[:, 0, :]
    raw = difference_tensor(fields, GEOMETRY)
    lagged = lagged or tuple(series)
    values = {
        'recorded': {n: s.on(stamps) for n, s in full.items()},
        'offline': {n: s.on(stamps) for n, s in series.items()},
        'live': {
            n: last_before(s, stamps) if n in lagged else s.on(stamps) for n, s in series.items()
        },
    }
    tensors = {}
    for kind, on_sets in values.items():
        x = term_regressors(parameters.terms, Channels(t_s, b1, on_sets))
        tensors[kind] = compensate(raw, b1, parameters, GEOMETRY, x).reshape(len(stamps), 9) / NT
    floor = noise_floor(NOISE_NT * NT, GEOMETRY) / NT
    ok = np.all(np.isfinite(tensors['live'] - tensors['offline']), axis=1)

    def rms(a: str, b: str) -> float:
        return float(np.sqrt(np.mean((tensors[a][ok] - tensors[b][ok]) ** 2)))

    diff = tensors['live'][ok] - tensors['offline'][ok]
    largest = float(np.max(np.abs(diff)))
    return {
        'channel_rate_hz': 20.0 / stride,
        'lagged': list(lagged),
        'sets': int(ok.sum()),
        'rms_nT_per_m': rms('live', 'offline'),
        'max_nT_per_m': largest,
        'noise_floor_nT_per_m': floor,
        'rms_over_floor': rms('live', 'offline') / floor,
        'max_over_floor': largest / floor,
        'sets_over_floor': float(np.mean(np.sqrt(np.mean(diff**2, axis=1)) > floor)),
        'offline_vs_recorded_nT_per_m': rms('offline', 'recorded'),
        'live_vs_recorded_nT_per_m': rms('live', 'recorded'),
    }


def run() -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = folder / 'effects.yaml'
        path.write_text(yaml.safe_dump(scenario()))
        bag, params, calibration = folder / 'bag', folder / 'bag.params.yaml', folder / 'c.yaml'
        for args in (
            ['simulate', '--scenario', path, '--out', bag],
            [
                'calibrate',
                bag,
                '--params',
                params,
                '--window',
                f'0:{TRIM_S}',
                '--out',
                calibration,
            ],
        ):
            assert main([str(a) for a in args]) == 0
        return [
            difference(bag, calibration, stride, lagged)
            for stride in (1, 20)
            for lagged in ((), ('current:/battery_state',), ('temperature',))
        ]


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--json', type=Path, default=None)
    args = parser.parse_args()
    rows = run()
    for row in rows:
        print(
            f'channels at {row["channel_rate_hz"]:g} Hz, {"+".join(row["lagged"])} live, '
            f'{row["sets"]} sets: live - offline '
            f'RMS {row["rms_nT_per_m"]:.3g} nT/m ({row["rms_over_floor"]:.2g} x the floor '
            f'{row["noise_floor_nT_per_m"]:.3g}), max {row["max_nT_per_m"]:.3g} nT/m '
            f'({row["max_over_floor"]:.2g} x), {100 * row["sets_over_floor"]:.1f} % of sets '
            'above the floor; against the recorded rate interpolated: offline '
            f'{row["offline_vs_recorded_nT_per_m"]:.3g}, live {row["live_vs_recorded_nT_per_m"]:.3g}'
            ' nT/m RMS'
        )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + '\n')


if __name__ == '__main__':
    cli()
