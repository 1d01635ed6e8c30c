"""A calibration that finds its own window: ``calibrate BAG`` without ``--window``.

For each mission: simulate it (or take a sample bag), run ``calibrate`` **without** a window
through the command line, ``compensate`` the survey with the calibration (frozen, ``--freeze-calibration``, and
with the defaults, the calibration tracked), and compare each
CSV with the truth on the survey (the simulator's ``g_true`` where the segment is a line; for
``bags/survey`` its ``/tetra/gradient/truth`` topic). Prints the window found and the RMS
residual over the noise floor (``metrics.noise_floor`` of the scenario's noise), frozen and
with the defaults.

    .venv/bin/python bench/bench_window.py [--out DIR] [--json FILE]

Target: every survey within 1.2x the noise floor; with the defaults within 5 % of frozen.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tetra_gradiometer.core import noise_floor  # noqa: E402
from tetra_gradiometer.io.params import geometry_from_params, load_params  # noqa: E402

PY = sys.executable
#: ``compensate``'s options: the calibration frozen, then the defaults (tracked).
FROZEN_AND_DEFAULT = (('--freeze-calibration',), ())
#: A held-out-like mission: a survey leg first, a trim over the target (the window check must
#: refuse it), a line, then a trim far from it (the one to find), another line.
SHUFFLED = {
    'description': 'survey first; a trim over the target, a line, a trim far away, a line',
    'seed': 31,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [1500.0, 19000.0, -47000.0]},
    'dipoles': [{'position_m': [0.0, 0.0, -75.0], 'moment_Am2': [40000.0, -20000.0, 30000.0]}],
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300, 'reference_clean': False}},
    'segments': [
        {'line': {'start_m': [-200.0, 10.0, -50.0], 'end_m': [200.0, 10.0, -50.0],
                  'speed_m_s': 2.0, 'roll_amplitude_deg': 3.0, 'pitch_amplitude_deg': 2.0}},
        {'trim': {'duration_s': 200, 'center_m': [0.0, 0.0, -50.0], 'heading_rate_deg_s': 5.0,
                  'roll_amplitude_deg': 20.0, 'roll_period_s': 9.0,
                  'pitch_amplitude_deg': 15.0, 'pitch_period_s': 14.0, 'speed_m_s': 1.0}},
        {'line': {'start_m': [200.0, -10.0, -50.0], 'end_m': [-200.0, -10.0, -50.0],
                  'speed_m_s': 2.0, 'roll_amplitude_deg': 3.0, 'pitch_amplitude_deg': 2.0}},
        {'trim': {'duration_s': 240, 'center_m': [4000.0, 3000.0, -50.0],
                  'heading_rate_deg_s': 4.0, 'roll_amplitude_deg': 25.0, 'roll_period_s': 11.0,
                  'pitch_amplitude_deg': 20.0, 'pitch_period_s': 17.0, 'speed_m_s': 1.0}},
        {'line': {'start_m': [-200.0, 30.0, -55.0], 'end_m': [200.0, 30.0, -55.0],
                  'speed_m_s': 2.0, 'roll_amplitude_deg': 3.0, 'pitch_amplitude_deg': 2.0}},
    ],
}


#: A gentle trim (2 deg/s, roll +-8 deg, pitch +-6 deg) between two rough-sea lines (roll
#: +-5 deg): the trim's spread is 1.5-2.5x the lines', not 10x.
GENTLE = {
    'description': 'a gentle trim between rough-sea lines',
    'seed': 9,
    'sample_rate_hz': 10,
    'noise_nT': 0.05,
    'geometry': {'regular_edge_m': 0.5},
    'earth_field': {'enu_nT': [0.0, 15000.0, -48000.0]},
    'dipoles': [{'position_m': [0.0, 10.0, -75.0], 'moment_Am2': [40000.0, 0.0, 30000.0]}],
    'interference': {'random': {'k_scale': 0.01, 'b_scale_nT': 300}},
    'segments': [
        {'line': {'start_m': [-200.0, 0.0, -50.0], 'end_m': [200.0, 0.0, -50.0],
                  'speed_m_s': 2.0, 'roll_amplitude_deg': 5.0, 'pitch_amplitude_deg': 3.0}},
        {'trim': {'duration_s': 200, 'center_m': [3000.0, 3000.0, -50.0],
                  'heading_rate_deg_s': 2.0, 'roll_amplitude_deg': 8.0, 'roll_period_s': 15.0,
                  'pitch_amplitude_deg': 6.0, 'pitch_period_s': 23.0, 'speed_m_s': 1.0}},
        {'line': {'start_m': [200.0, 20.0, -50.0], 'end_m': [-200.0, 20.0, -50.0],
                  'speed_m_s': 2.0, 'roll_amplitude_deg': 5.0, 'pitch_amplitude_deg': 3.0}},
    ],
}


def run(*args: str) -> str:
    done = subprocess.run([PY, '-m', 'tetra_gradiometer', *args], cwd=REPO, text=True,
                          capture_output=True, check=False)
    if done.returncode:
        raise SystemExit(f'{args[0]} failed: {done.stderr.strip()}')
    return done.stdout


def survey_rms_simulated(csv: Path, truth: Path) -> float:
    data = np.load(truth)
    line = np.array([str(kind) == 'line' for kind in data['segment_kind']])[data['segment']]
    table = np.loadtxt(csv, delimiter=',', skiprows=1, usecols=range(1, 10))
    residual = table - data['g_true'].reshape(-1, 9) * 1e9
    return float(np.sqrt(np.mean(residual[line] ** 2)))


def survey_rms_bag(csv: Path, bag: Path) -> float:
    from rosbags.highlevel import AnyReader

    from tetra_gradiometer.io import gradient_tensor as gt
    from tetra_gradiometer.io.bag import typestore

    with AnyReader([bag], default_typestore=typestore()) as reader:
        connections = [c for c in reader.connections if c.topic == '/tetra/gradient/truth']
        truth = {}
        for connection, _, raw in reader.messages(connections=connections):
            # A GradientTensor, or the JointState of bags recorded before it.
            tensor = gt.tensor_set_from_msg(reader.deserialize(raw, connection.msgtype), connection.msgtype)
            truth[tensor.stamp_ns] = tensor.g.reshape(9) * 1e9
    stamps = np.loadtxt(csv, delimiter=',', skiprows=1, usecols=0, dtype=str)
    table = np.loadtxt(csv, delimiter=',', skiprows=1, usecols=range(1, 10))
    keys = [int(s.replace('.', '')) for s in stamps]
    kept = [i for i, key in enumerate(keys) if key in truth]
    residual = table[kept] - np.array([truth[keys[i]] for i in kept])
    return float(np.sqrt(np.mean(residual**2)))


def window_of(output: str) -> str:
    found = re.search(r'window (\S+) s found in the bag', output)
    return found.group(1) if found else '?'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--out', default=None)
    parser.add_argument('--json', type=Path, default=None, help='also write the rows here')
    args = parser.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix='bench_window_'))
    out.mkdir(parents=True, exist_ok=True)
    (out / 'shuffled.yaml').write_text(yaml.safe_dump(SHUFFLED), encoding='utf-8')
    (out / 'gentle.yaml').write_text(yaml.safe_dump(GENTLE), encoding='utf-8')
    rows = []
    for name, scenario in (
        ('README mission', 'config/scenarios/realistic_mission.yaml'),
        ('README mission, sensor 1 dirty', 'config/scenarios/realistic_mission_dirty_reference.yaml'),
        ('shuffled (trim over the target first)', str(out / 'shuffled.yaml')),
        ('gentle trim between rough-sea lines', str(out / 'gentle.yaml')),
    ):
        bag = out / Path(scenario).stem
        run('simulate', '--scenario', scenario, '--out', str(bag), '--force')
        params = f'{bag}.params.yaml'
        text = run('calibrate', str(bag), '--params', params, '--out', f'{bag}.calib.yaml',
                   '--force')
        rms = []
        for how in FROZEN_AND_DEFAULT:
            run('compensate', str(bag), '--params', params, '--calibration', f'{bag}.calib.yaml',
                '--csv', f'{bag}.csv', '--force', *how)
            rms.append(survey_rms_simulated(Path(f'{bag}.csv'), Path(f'{bag}.truth.npz')))
        noise = yaml.safe_load(Path(scenario).read_text())['noise_nT']
        floor = noise_floor(noise * 1e-9, geometry_from_params(load_params(params))) * 1e9
        rows.append((name, window_of(text), *rms, floor))
    # The sample bags' params: what simulate writes beside a bag of their scenario.
    run('simulate', '--scenario', 'bags/trim.yaml', '--out', str(out / 'trim_sim'), '--mag-only',
        '--force')
    params = str(out / 'trim_sim.params.yaml')
    calib = out / 'bags_trim.calib.yaml'
    text = run('calibrate', 'bags/trim', '--params', params, '--out', str(calib), '--force')
    rms = []
    for how in FROZEN_AND_DEFAULT:
        run('compensate', 'bags/survey', '--params', params, '--calibration', str(calib),
            '--csv', str(out / 'survey.csv'), '--force', *how)
        rms.append(survey_rms_bag(out / 'survey.csv', REPO / 'bags/survey'))
    floor = noise_floor(0.1e-9, geometry_from_params(load_params(params))) * 1e9
    rows.append(('bags/trim -> bags/survey', window_of(text), *rms, floor))
    print('| mission | window found (s) | floor nT/m | frozen x floor | default x floor | '
          'default / frozen |')
    print('|---|---|---:|---:|---:|---:|')
    for name, window, frozen, default, floor in rows:
        print(f'| {name} | {window} | {floor:.4f} | {frozen / floor:.3f} | '
              f'{default / floor:.3f} | {default / frozen:.3f} |')
    if args.json is not None:
        args.json.write_text(json.dumps([
            {'mission': name, 'window_s': window, 'floor_nT_per_m': floor,
             'frozen_floor_ratio': round(frozen / floor, 4),
             'floor_ratio': round(default / floor, 4),
             'default_over_frozen': round(default / frozen, 4)}
            for name, window, frozen, default, floor in rows], indent=1) + '\n')


if __name__ == '__main__':
    main()
