"""An effect no declaration can express, added by an installed package: one module and an
entry point (``tetra_gradiometer.effects``), nothing else. A pump whose motor current goes
as the square of its recorded speed (``/pump/rpm``): calibrate selects it on the trim,
compensate applies it on the survey.

Truth: the pump's cable field from magpylib (Biot-Savart of a return pair of segments
carrying the current), not the regressor the effect fits; the simulator's true gradient."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import yaml

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1] / 'io')]
from stream_faults import EARTH_ENU, GEOMETRY, START_NS, short_mission  # noqa: E402
from test_recorded_signals import _wire_field  # noqa: E402

from tetra_gradiometer.core.metrics import noise_floor  # noqa: E402
from tetra_gradiometer.io import conversions as cv  # noqa: E402
from tetra_gradiometer.io.bag import BagWriter  # noqa: E402
from tetra_gradiometer.io.params import params_document  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

PUMP_MODULE = '''
"""A pump's motor current goes as the square of its speed (the load torque of a pump)."""
import numpy as np

from tetra_gradiometer.core.effects.base import Effect


class PumpLoad(Effect):
    name = 'pump_load'
    physics = "A pump motor's cable: its current, and so its field, as the square of the speed."
    file_unit = 'nT per (krpm)^2'
    file_factor = 1e9
    channels = ('signal:/pump/rpm#data',)

    def labels(self, inputs):
        return ('(rpm/1000)^2',)

    def regressors(self, channels, inputs, reference):
        krpm = np.asarray(channels.series[self.channels[0]], dtype=float) / 1000.0
        return (krpm**2)[:, None]
'''


def _install(root: Path) -> dict[str, str]:
    """The pump's package on a path of its own: its module and its entry point."""
    root.mkdir()
    (root / 'tetra_pump.py').write_text(PUMP_MODULE)
    info = root / 'tetra_pump-1.0.dist-info'
    info.mkdir()
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: tetra-pump\nVersion: 1.0\n')
    (info / 'entry_points.txt').write_text('[tetra_gradiometer.effects]\npump_load = tetra_pump:PumpLoad\n')
    return {'PYTHONPATH': f'{root}:{REPO}'}


def _cli(env: dict[str, str], *args) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, '-m', 'tetra_gradiometer', *map(str, args)], cwd=REPO,
                          env={**os.environ, **env}, capture_output=True, text=True, timeout=300)


def test_an_installed_effect_is_selected_fitted_and_applied(tmp_path):
    mission = short_mission(trim_s=150.0, survey_s=40.0, seed=41)
    rpm = 1800.0 + 900.0 * np.sin(2 * np.pi * mission.t / 37.0) + 400.0 * np.sign(np.sin(2 * np.pi * mission.t / 53.0))
    amps = 2.5 * (rpm / 1000.0) ** 2
    fields = mission.fields_measured + _wire_field(np.column_stack([amps, np.zeros_like(amps)]), 8)
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64)
    with BagWriter(tmp_path / 'bag') as writer:
        for i, stamp in enumerate(log.tolist()):
            for s in range(4):
                data = cv.magnetic_field_cdr(fields[i, s], stamp, cv.MAG_FRAMES[s])
                writer.write_raw(cv.BAG_MAG_TOPICS[s], cv.MAGNETIC_FIELD, data, stamp)
            writer.write(cv.ODOM_TOPIC, cv.odometry_msg(writer.types, mission.position_enu[i],
                                                         mission.orientation_xyzw[i], stamp), stamp)
            writer.write('/pump/rpm', writer.types['std_msgs/msg/Float64'](data=float(rpm[i])), stamp)
    params = tmp_path / 'params.yaml'
    params.write_text(params_document({'sensor_positions': GEOMETRY.to_flat(), 'earth_field_enu': EARTH_ENU.tolist()}))
    env = _install(tmp_path / 'site')
    calibration, csv = tmp_path / 'calibration.yaml', tmp_path / 'out.csv'
    done = _cli(env, 'calibrate', tmp_path / 'bag', '--params', params, '--window', '0:149.9', '--out', calibration)
    assert done.returncode == 0, done.stdout + done.stderr
    terms = yaml.safe_load(calibration.read_text())['terms']
    assert [t['effect'] for t in terms] == ['pump_load'], terms
    done = _cli(env, 'compensate', tmp_path / 'bag', '--params', params, '--calibration', calibration, '--csv', csv)
    assert done.returncode == 0, done.stdout + done.stderr
    g = np.loadtxt(csv, delimiter=',', skiprows=1, usecols=range(1, 10)).reshape(-1, 3, 3) * 1e-9
    survey = mission.segment > 0
    ratio = np.sqrt(np.mean((g[survey] - mission.g_true[survey]) ** 2)) / noise_floor(1e-10, GEOMETRY)
    print(f'\ninstalled pump effect: survey {ratio:.3f} x the noise floor')
    assert ratio <= 1.2
    # Not installed: the effect is unknown, and the calibration that has it says so.
    done = _cli({'PYTHONPATH': str(REPO)}, 'compensate', tmp_path / 'bag', '--params', params,
                '--calibration', calibration, '--csv', tmp_path / 'no.csv')
    assert done.returncode == 1 and "unknown effect 'pump_load'" in done.stderr, done.stderr
