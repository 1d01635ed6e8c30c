"""``compensate --track-calibration`` on a bag of a magpylib hull mission (test/core/
hull_missions.py: remanence relaxing after the trim, a step on one sensor): the CSV's tensors
against the clean fields' tensor (ground truth), the step in the report's audit trail on the
sensor that stepped, and ``--freeze-calibration`` writing what the calibration alone gives."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from hull_missions import EARTH_ENU, GEOMETRY, build_mission, spans

from tetra_gradiometer.__main__ import main
from tetra_gradiometer.io.calibration import CalibrationFile, save_calibration
from tetra_gradiometer.io.params import params_document
from tetra_gradiometer.io.recording import write_mission_bag
from tetra_gradiometer.pipelines.tracking import TRACKING_COLUMNS


def _cli(*args) -> str:
    """``python -m tetra_gradiometer compensate ARGS`` in-process: its stdout."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(['compensate', *(str(a) for a in args)])
    assert code == 0, err.getvalue()
    return out.getvalue()


@pytest.fixture(scope='module')
def compensated(tmp_path_factory):
    folder = tmp_path_factory.mktemp('tracking')
    mission = build_mission(21)
    bag = write_mission_bag(folder / 'bag', mission.data, temperature=False, battery=False)
    params = folder / 'params.yaml'
    params.write_text(params_document({'sensor_positions': GEOMETRY.to_flat(),
                                       'earth_field_enu': EARTH_ENU.tolist()}))
    calibration = save_calibration(folder / 'cal.yaml',
                                   CalibrationFile.from_calibration(mission.calibration, GEOMETRY))
    common = (bag, '--params', params, '--calibration', calibration)
    text = _cli(*common, '--csv', folder / 'tracked.csv', '--track-calibration',
                '--report', folder / 'report')
    _cli(*common, '--csv', folder / 'frozen.csv', '--freeze-calibration')
    return mission, folder, text


def _read(path):
    with open(path, encoding='ascii') as handle:
        header = handle.readline().strip().split(',')
    return header, np.loadtxt(path, delimiter=',', skiprows=1)


@pytest.mark.slow
def test_the_tracked_csv_is_at_the_floor_where_the_frozen_one_is_not(compensated):
    mission, folder, _ = compensated
    header, tracked = _read(folder / 'tracked.csv')
    assert header[-9:] == list(TRACKING_COLUMNS)
    _, frozen = _read(folder / 'frozen.csv')
    assert frozen.shape[1] == 19 and tracked.shape[0] == frozen.shape[0] == len(mission.t_s)
    truth = mission.g_true.reshape(-1, 9) * 1e9
    floor = mission.floor_t_per_m * 1e9
    for name, mask in spans(mission).items():
        if name == 'first_5_min':
            continue  # the bag's tracker has learnt on the trim: a different start
        frozen_ratio = np.sqrt(np.mean((frozen[mask, 1:10] - truth[mask]) ** 2)) / floor
        tracked_ratio = np.sqrt(np.mean((tracked[mask, 1:10] - truth[mask]) ** 2)) / floor
        assert frozen_ratio > 4.0 and tracked_ratio <= 1.2, name


@pytest.mark.slow
def test_the_audit_trail_names_the_step_and_its_sensor(compensated):
    mission, folder, text = compensated
    document = json.loads((folder / 'report' / 'tracking.json').read_text())
    assert document['attitude'] is True
    steps = document['steps']
    assert [s['sensors'] for s in steps] == [[mission.step_sensor + 1]]
    assert abs(steps[0]['t_s'] - mission.t_step_s) < 1.0  # times from the first set
    assert document['counts']['update'] > 0.9 * len(document['blocks']['t_s'])
    assert 'calibration tracked (with the attitude)' in text
    assert f'sensor {mission.step_sensor + 1} at ' in text and 'nT (1-sigma' in text
    assert abs(np.linalg.norm(steps[0]['step_nT']) - 1.0) < 5 * max(steps[0]['step_sigma_nT'])


def test_without_odom_the_constrained_combinations_are_tracked(tmp_path, monkeypatch):
    """A bag without ``/odom``: the tracker says so, follows the constrained combinations
    only, and still re-estimates a sensor's step from them; the compensator node does the
    same live."""
    from dataclasses import replace

    from tetra_gradiometer.core import (
        Scenario,
        SensorInterference,
        TrimManoeuvre,
        difference_tensor,
        known_gradient_lstsq,
        simulate,
    )

    rng = np.random.default_rng(8)
    k = rng.uniform(-5e-3, 5e-3, (4, 3, 3))
    k = 0.5 * (k + np.swapaxes(k, 1, 2))
    k[0] = 0.0
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH_ENU,
                        segments=(TrimManoeuvre(240.0),), sample_rate_hz=10.0, noise_t=0.05e-9,
                        interference=SensorInterference(k, rng.uniform(-1e-7, 1e-7, (4, 3))))
    data = simulate(scenario, rng)
    first = data.t < 120.0
    fit = known_gradient_lstsq(difference_tensor(data.fields_measured[first], GEOMETRY),
                               data.fields_measured[first, 0], GEOMETRY, symmetric_k=False)
    measured = data.fields_measured.copy()
    measured[data.t >= 180.0, 2] += np.array([0.8, -0.4, 0.3]) * 1e-9
    bag = write_mission_bag(tmp_path / 'bag', replace(data, fields_measured=measured), odom=False,
                            temperature=False, battery=False)
    params = tmp_path / 'params.yaml'
    params.write_text(params_document({'sensor_positions': GEOMETRY.to_flat(),
                                       'earth_field_enu': EARTH_ENU.tolist()}))
    calibration = save_calibration(tmp_path / 'cal.yaml', CalibrationFile.from_calibration(fit, GEOMETRY))
    _cli(bag, '--params', params, '--calibration', calibration, '--csv', tmp_path / 'out.csv',
         '--track-calibration', '--report', tmp_path / 'report')
    document = json.loads((tmp_path / 'report' / 'tracking.json').read_text())
    assert document['attitude'] is False
    assert [s['sensors'] for s in document['steps']] == [[3]]
    _, rows = _read(tmp_path / 'out.csv')
    after = data.t >= 185.0
    floor = 0.1414  # nT/m: 0.05 nT through the regular 0.5 m tetrahedron
    residual = rows[after, 1:10] - data.g_true[after].reshape(-1, 9) * 1e9
    assert np.sqrt(np.mean(residual**2)) <= 1.2 * floor
    # Live: the compensator node tracking the same calibration gives the offline tensors.
    live = _compensator_live(monkeypatch, bag, calibration)
    assert len(live) == len(rows)
    worst = np.max(np.abs(live.reshape(-1, 9) * 1e9 - rows[:, 1:10])) / floor
    print(f'\ncompensator node tracking: max |live - offline| {worst:.2e} x the floor')
    assert worst <= 0.01


@pytest.mark.slow
def test_live_with_odom_equals_offline(compensated, monkeypatch):
    """The compensator node, given the bag's ``/odom`` beside its sets (in stamp order, as a
    replay plays them), tracks with the attitude and publishes the offline tracked tensors."""
    mission, folder, _ = compensated
    _, rows = _read(folder / 'tracked.csv')
    live = _compensator_live(monkeypatch, folder / 'bag', folder / 'cal.yaml', odom=True)
    floor = mission.floor_t_per_m * 1e9
    worst = np.max(np.abs(live.reshape(-1, 9) * 1e9 - rows[:, 1:10])) / floor
    print(f'\ncompensator node tracking with odom: max |live - offline| {worst:.2e} x the floor')
    assert len(live) == len(rows) and worst <= 0.01


def _compensator_live(monkeypatch, bag, calibration, odom=False):
    """The bag's sets (and with ``odom`` its /odom messages, in stamp order) handed to the
    compensator node (``track_calibration``) in this process, its clock and health monitor
    advanced with them: the tensors (n, 3, 3) T/m it publishes."""
    import sys
    from pathlib import Path

    from rclpy.time import Time

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'ros'))
    from in_process import node_in_process

    from tetra_gradiometer.core import difference_tensor
    from tetra_gradiometer.io import conversions as cv
    from tetra_gradiometer.io.bag import MagneticBag
    from tetra_gradiometer.nodes.compensator import CompensatorNode

    from nav_msgs.msg import Odometry

    with MagneticBag(bag) as recorded:
        stamps, fields = recorded.read_sets()
        series = recorded.read_series(cv.ODOM_TOPIC) if odom else None
    messages = []
    for stamp, pose in zip(*(([], []) if series is None else (series.stamps_ns.tolist(), series.values))):
        msg = Odometry()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        q = msg.pose.pose.orientation
        q.x, q.y, q.z, q.w = (float(v) for v in pose[cv.POSE_ORIENTATION])
        messages.append((stamp, msg))
    from tetra_gradiometer.io import gradient_tensor as gt

    tensor_cdr = gt.GradientTensorCdr('tetra_array')
    with node_in_process(CompensatorNode, monkeypatch, calibration_file=str(calibration), use_sim_time=True,
                         sensor_positions=GEOMETRY.to_flat(), track_calibration=True) as (node, published):
        for stamp, field, g in zip(stamps.tolist(), fields, difference_tensor(fields, GEOMETRY)):
            while messages and messages[0][0] <= stamp:
                node._tracking._on_odom(messages.pop(0)[1])
            node.get_clock().set_ros_time_override(Time(nanoseconds=stamp))
            node._on_raw(tensor_cdr.write(stamp, gt.pack(gt.TensorSet(stamp, g, reference_field=field[0]))))
            node._feed_health()  # its timer's work, set by set
    return np.array([tensor_cdr.read(m)[1][:9].reshape(3, 3) for topic, m in published
                     if topic == '/tetra/gradient/compensated'])


def test_the_live_tracker_starts_afresh_when_a_replay_starts_again():
    """The compensator's tracker (nodes/calibration_tracking.py) given the same sets twice,
    the second time from the first stamp again (a looping replay): the second pass gives what
    the first gave, not a state carried over from the end of the first."""
    from tetra_gradiometer.core import InterferenceParameters, difference_tensor
    from tetra_gradiometer.nodes.calibration_tracking import LiveTracking

    class Node:  # what LiveTracking asks of its node
        def create_lifecycle_publisher(self, *args):
            return type('Publisher', (), {'publish': lambda self, msg: None})()

        def create_subscription(self, *args):
            return None

        def get_logger(self):
            return type('Logger', (), {'info': lambda self, text: None})()

    rng = np.random.default_rng(3)
    fields = np.broadcast_to(EARTH_ENU, (300, 4, 3)) + rng.normal(0, 0.05e-9, (300, 4, 3))
    fields[150:, 2] += 0.5e-9  # an offset change within the pass: the tracker moves
    g = difference_tensor(fields, GEOMETRY)
    stamps = 1_700_000_000 * 10**9 + np.arange(300) * 10**8
    live = LiveTracking(Node(), lambda callback: callback, None)
    live.start(GEOMETRY, InterferenceParameters.zero(), 0.05e-9)

    def one_pass():  # the step handed over as the node's health monitor hands it
        out = []
        for i, (stamp, tensor) in enumerate(zip(stamps, g)):
            if i == 152:
                live.step((3,), stamps[150] * 1e-9)
            out.append(live.one(int(stamp), tensor)[0])
        return out

    passes = [one_pass() for _ in range(2)]
    first, second = np.array(passes[0]), np.array(passes[1])
    assert np.abs(first[-1] - g[-1]).max() > 1e-12  # it did track something
    np.testing.assert_array_equal(second, first)
