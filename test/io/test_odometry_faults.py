"""Fault table, odometry: ``/odom`` is checked before use (core/odometry.py through
io/recording.odometry_at). Zero-norm quaternions, a frozen pose and an attitude that does not
agree with the magnetometers are named; ``calibrate`` and ``discrepancy`` go on without
``/odom`` and say what that costs, ``locate`` refuses with one line (no track, no targets).

Truth: the simulator's attitudes (a right one explains the body field's rotation; a reversed,
frozen, identity or wrongly framed one does not), the pose written, the bag's bytes.
"""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from cli_helpers import assert_refused, run_cli, snapshot
from scipy.spatial.transform import Rotation
from stream_faults import EARTH_ENU, START_NS, short_mission, write_bag, write_params

from tetra_gradiometer.core.attitude import attitude_verdict, world_frame_fault
from tetra_gradiometer.core.odometry import check_odometry


@pytest.fixture(scope='module')
def mission():
    return short_mission(trim_s=40.0, survey_s=20.0)


@pytest.fixture(scope='module')
def params(tmp_path_factory):
    return write_params(tmp_path_factory.mktemp('params') / 'params.yaml')


@pytest.fixture(scope='module')
def good_calibration(mission, params, tmp_path_factory):
    root = tmp_path_factory.mktemp('good')
    bag = write_bag(root / 'bag', mission)
    from tetra_gradiometer.__main__ import main
    assert main(['calibrate', str(bag), '--params', str(params), '--out', str(root / 'c.yaml')]) == 0
    return yaml.safe_load((root / 'c.yaml').read_text())


def _calibrate(capsys, tmp_path, bag, params):
    code, out, err = run_cli(capsys, 'calibrate', bag, '--params', params, '--out', tmp_path / 'c.yaml')
    assert code == 0 and 'Traceback' not in err, err
    return out, yaml.safe_load((tmp_path / 'c.yaml').read_text())


COST = '/odom orientation and position not used: no regional gradient (assumed zero)'


def test_zero_norm_quaternions_calibrate_without_odom_and_say_so(mission, params, tmp_path, capsys):
    n = len(mission.t)
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=np.zeros((n, 4)))
    before = snapshot(bag)
    out, calibration = _calibrate(capsys, tmp_path, bag, params)
    assert f'{n} of {n} /odom messages have a zero-norm or non-finite pose' in out and COST in out
    assert 'regional gradient estimated jointly' not in out
    assert any('zero-norm' in note for note in calibration['diagnostics']['notes'])
    assert snapshot(bag) == before


def test_some_zero_norm_quaternions_are_dropped_and_the_rest_used(mission, params, tmp_path, capsys,
                                                                   good_calibration):
    q = mission.orientation_xyzw.copy()
    q[100:104] = 0.0  # 0.4 s of unfilled orientations inside the trim (within MAX_ODOM_GAP_S)
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=q)
    out, calibration = _calibrate(capsys, tmp_path, bag, params)
    assert '4 of 600 /odom messages have a zero-norm or non-finite pose' in out and '(an unfilled orientation; ' \
           '10.0-10.3 s): dropped' in out
    assert 'regional gradient estimated jointly' in out
    # The attitude across the hole is slerped: the parameters are those of the whole /odom.
    assert np.allclose(calibration['k_soft'], good_calibration['k_soft'], atol=1e-7)


def test_unnormalized_quaternions_are_normalized(mission, params, tmp_path, capsys, good_calibration):
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=mission.orientation_xyzw * 3.0)
    out, calibration = _calibrate(capsys, tmp_path, bag, params)
    assert '600 /odom orientations are not unit quaternions (norm 3-3): normalized' in out
    assert np.allclose(calibration['k_soft'], good_calibration['k_soft'], atol=1e-12)
    assert np.allclose(calibration['b_hard_T'], good_calibration['b_hard_T'], atol=1e-18)


def test_a_frozen_odom_is_not_used_and_locate_refuses(mission, params, tmp_path, capsys):
    n = len(mission.t)
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=np.repeat(mission.orientation_xyzw[:1], n, axis=0),
                    odom_position=np.repeat(mission.position_enu[:1], n, axis=0))
    before = snapshot(bag)
    out, _ = _calibrate(capsys, tmp_path, bag, params)
    assert 'the /odom orientation is frozen (unchanged over 59.9 s, 600 messages)' in out and COST in out
    assert_refused(run_cli(capsys, 'locate', bag, '--params', params, '--raw', '--out', tmp_path / 'targets'),
                   'the /odom position is frozen (unchanged over 59.9 s, 600 messages)', 'no targets',
                   'needs the pose')
    assert snapshot(bag) == before and not (tmp_path / 'targets').exists()


@pytest.mark.parametrize('wrong, named', [
    ('reversed in time', 'no convention or lag within 2 s fits either'),
    ('body frame FRD', 'fits the magnetometers with the body frame FRD (x forward, y right, z down)'),
    ('stamped 1 s late', 'fits the magnetometers as declared, with the /odom stamps 1.00 s late'),
])
def test_an_attitude_that_disagrees_with_the_magnetometers_is_named_and_not_used(
        mission, params, tmp_path, capsys, wrong, named):
    q = mission.orientation_xyzw
    if wrong == 'reversed in time':
        q = q[::-1].copy()
    elif wrong == 'body frame FRD':  # a body frame x forward, y right, z down (not REP 103's)
        q = (Rotation.from_quat(q) * Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))).as_quat()
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=q,
                    odom_late_s=1.0 if wrong == 'stamped 1 s late' else 0.0)
    out, _ = _calibrate(capsys, tmp_path, bag, params)
    assert named in out
    assert '/odom orientation not used: no regional gradient (assumed zero)' in out


def test_discrepancy_with_zero_norm_quaternions_goes_on_without_odom(mission, params, tmp_path, capsys):
    bag = write_bag(tmp_path / 'bag', mission, odom_xyzw=np.zeros((len(mission.t), 4)))
    code, out, err = run_cli(capsys, 'discrepancy', bag, '--params', params, '--out', tmp_path / 'report')
    assert code == 0 and 'Traceback' not in err, err
    assert 'no /odom' in out  # B^b falls back to B_1' (what going without costs)
    report = (tmp_path / 'report' / 'report.json').read_text()
    assert 'zero-norm' in report


# ----------------------------------------------------------------------------- the core tests


NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # ENU <-> NED
FRD = np.diag([1.0, -1.0, -1.0])


def _verdict(mission, q, late_s=0.0, span=slice(None)):
    stamps = (mission.t[span] * 1e9).astype(np.int64) + START_NS
    return attitude_verdict(stamps + int(late_s * 1e9), q[span], stamps, mission.fields_measured[span, 0])


def test_the_attitude_test_names_the_convention_that_fits(mission):
    q = mission.orientation_xyzw
    right = _verdict(mission, q)
    assert right.tested and right.fault() is None and abs(right.carried - 1.0) < 0.01
    assert world_frame_fault(right.world_field, EARTH_ENU) is None
    # Truth: the rotations as a navigation stack would publish them, built from the simulator's.
    as_published = {
        'body FRD, world NED': (Rotation.from_matrix(NED) * Rotation.from_quat(q) * Rotation.from_matrix(FRD)),
        'inverse': Rotation.from_quat(q).inv(),
    }
    ned_frd = _verdict(mission, as_published['body FRD, world NED'].as_quat())
    assert 'with the body frame FRD' in ned_frd.fault() and 'as declared the attitude carries' in ned_frd.fault()
    inverse = _verdict(mission, as_published['inverse'].as_quat())
    assert 'as the inverse rotation (world -> body)' in inverse.fault()
    scalar_first = _verdict(mission, np.roll(q, 1, axis=1))
    assert 'read scalar first (w, x, y, z)' in scalar_first.fault()
    ned = _verdict(mission, (Rotation.from_matrix(NED) * Rotation.from_quat(q)).as_quat())
    assert ned.fault() is None  # a constant world rotation: the field is steady...
    assert 'looks NED, not ENU' in world_frame_fault(ned.world_field, EARTH_ENU)  # ...but points north-down
    for late in (0.7, -0.4):
        text = _verdict(mission, q, late_s=late).fault()
        assert f'{abs(late):.2f} s {"late" if late > 0 else "early"}' in text, text
    # The clocks of navigation stacks: GPS against UTC, a time zone (no overlap at all).
    assert '18.00 s late (GPS time against UTC)' in _verdict(mission, q, late_s=18.0).fault()
    assert '3600.00 s late (1 h: a time zone)' in _verdict(mission, q, late_s=3600.0).fault()
    # Any other offset: the two recordings' starts (they began together).
    assert '1234.50 s late (100% of the field carried' in _verdict(mission, q, late_s=1234.5).fault()
    foreign = _verdict(mission, q[::-1].copy(), late_s=1234.5).fault()  # and not this vehicle's attitude
    assert "stamps cover only 0% of the magnetometers' (another clock)" in foreign and 'no clock offset' in foreign


def test_a_wrong_attitude_is_refused_and_a_still_one_untested(mission):
    q = mission.orientation_xyzw
    for wrong in (q[::-1], np.roll(q, 150, axis=0)):
        assert 'no convention or lag within 2 s fits either' in _verdict(mission, wrong).fault()
    noise = Rotation.from_rotvec(np.random.default_rng(1).normal(0, 1e-3, (len(q), 3))).as_quat()
    assert 'hardly turns' in _verdict(mission, noise).fault()  # the field turns, the attitude does not
    survey = _verdict(mission, q, span=slice(400, None))  # a straight line: nothing turns, nothing to test
    assert not survey.tested and survey.fault() is None


def test_check_odometry_counts_what_it_changes():
    stamps = np.arange(10, dtype=np.int64) * 10**8
    pose = np.zeros((10, 7))
    pose[:, 6] = 1.0
    pose[:, 0] = np.arange(10.0)
    pose[3, 3:] = 0.0
    pose[5, 3:] *= 2.0
    check = check_odometry(stamps, pose)
    assert len(check.stamps_ns) == 9 and np.allclose(np.linalg.norm(check.pose[:, 3:], axis=1), 1.0)
    assert check.orientation_ok is False and check.position_ok is True  # the identity does not turn
    assert check.faults[0].startswith('1 of 10 /odom messages have a zero-norm')


def test_the_nodes_live_check_keeps_drops_and_normalizes_as_check_odometry_does():
    """One rule: message by message, the nodes' check keeps, drops and
    normalizes exactly the messages `check_odometry` does, at norms either side of its bounds
    (zero-norm 1e-6, unit tolerance 1e-3), non-finite orientations and positions."""
    from tetra_gradiometer.core.odometry import LiveOdometryCheck

    norms = [0.0, 1e-7, 2e-6, 0.5, 0.998, 0.9995, 1.0, 1.0005, 1.002, 3.0, np.nan, np.inf, 1.0, 1.0]
    rng = np.random.default_rng(30)
    q = Rotation.random(len(norms), random_state=rng).as_quat() * np.array(norms)[:, None]
    pose = np.column_stack([rng.normal(size=(len(norms), 3)), q])
    pose[-2, 0], pose[-1, 2] = np.nan, np.inf  # a unit quaternion, a position not known
    stamps = np.arange(len(norms), dtype=np.int64) * 10**8
    offline = check_odometry(stamps, pose)
    live = LiveOdometryCheck()
    accepted = [live.accept(p[3:], p[:3]) for p in pose]
    kept = [i for i, a in enumerate(accepted) if a is not None]
    assert kept == [2, 3, 4, 5, 6, 7, 8, 9]  # independent of both: the bounds as documented
    np.testing.assert_array_equal(offline.stamps_ns, stamps[kept])
    np.testing.assert_allclose(np.array([accepted[i] for i in kept]), offline.pose[:, 3:], rtol=0, atol=1e-15)
    assert (live.dropped, live.normalized) == (6, 5)  # 2e-6, 0.5, 0.998, 1.002, 3; not 0.9995, 1.0005
    assert offline.faults[0].startswith('6 of 14') and offline.faults[1].startswith('5 /odom orientations')
    # The calibrator reads only the orientation: a position not known does not drop it.
    assert live.accept(pose[-1, 3:]) is not None


def test_a_jump_between_two_navigation_sources_is_named(mission):
    """The survey line at 2 m/s, then 35 m east from 10 s on (a second source taking over).
    (The simulator starts the line at the trim circle's centre: a jump too, left out.)"""
    line = mission.segment == 1
    stamps = (mission.t[line] * 1e9).astype(np.int64) + START_NS
    pose = np.column_stack([mission.position_enu[line], mission.orientation_xyzw[line]])
    jumped = pose.copy()
    jumped[100:, 0] += 35.0
    assert not any('jumps' in f for f in check_odometry(stamps, pose).faults)
    faults = check_odometry(stamps, jumped).faults
    assert any(f.startswith('the /odom position jumps 1 time (35.2 m at 10.0 s;') for f in faults), faults  # 35 m + a step


def test_ned_odometry_is_named_by_locate_and_survey(mission, params, tmp_path, capsys, good_calibration):
    """/odom in NED (position N, E, D; attitude FLU -> NED): the world frame is tested against
    the params file's Earth field (locate) or IGRF at --origin (survey without one), and
    named; nothing is written. The same bag in ENU passes the same check."""
    q = (Rotation.from_matrix(NED) * Rotation.from_quat(mission.orientation_xyzw)).as_quat()
    bag = write_bag(tmp_path / 'ned', mission, odom_xyzw=q, odom_position=mission.position_enu @ NED.T)
    calibration = tmp_path / 'c.yaml'
    calibration.write_text(yaml.safe_dump(good_calibration))
    assert_refused(run_cli(capsys, 'locate', bag, '--params', params, '--raw', '--out', tmp_path / 'targets'),
                   'the /odom world frame looks NED, not ENU', 'no targets')
    no_earth = write_params(tmp_path / 'no_earth.yaml', earth=False)
    # IGRF at 43.2 N 5.3 E points within 8 deg of the mission's Earth field
    for origin, refused in (('43.2,5.3', True), ('-43.2,5.3', False)):
        result = run_cli(capsys, 'survey', bag, '--params', no_earth, '--calibration', calibration,
                         f'--origin={origin}', '--out', tmp_path / 'survey')
        code, _, err = result  # survey prints its stages on stderr before the error line
        error = err.splitlines()[-1]
        assert code == 1 and error.startswith('error: ') and 'Traceback' not in err, err
        if refused:
            assert 'the /odom world frame looks NED, not ENU' in error and 'no survey' in error
        else:  # the southern hemisphere's field points up: neither frame fits, said so
            assert 'the /odom orientation does not agree with the Earth field' in error
    assert not (tmp_path / 'targets').exists() and not (tmp_path / 'survey').exists()
    enu = write_bag(tmp_path / 'enu', mission)
    code, _, err = run_cli(capsys, 'survey', enu, '--params', no_earth, '--calibration', calibration,
                           '--origin=43.2,5.3', '--out', tmp_path / 'survey')
    assert 'compensating and placing the track' in err and '/odom' not in err, err  # the track is used
