"""Shared by the stream and odometry fault tables: a short simulated mission (a trim
manoeuvre, then a survey line) and a writer of faulty bags with the project's bag writer.

A bag is written as a recorder logs it: every message at its log time (the true sample
time), whatever its header stamp says; a fault changes one sensor's header stamps, values,
or the ``/odom`` pose, never the log times (unless a case says so).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tetra_gradiometer.core import Scenario, SurveyLine, TetraGeometry, TrimManoeuvre, simulate
from tetra_gradiometer.io import conversions as cv
from tetra_gradiometer.io.bag import BagWriter
from tetra_gradiometer.io.params import params_document

GEOMETRY = TetraGeometry.regular(0.5)
EARTH_ENU = np.array([0.0, 2.0e-5, -4.5e-5])  # |B| 49.2 uT
START_NS = 1_767_225_600 * 10**9
RATE_HZ = 10.0


def short_mission(trim_s: float = 30.0, survey_s: float = 20.0, seed: int = 5):
    """A trim of ``trim_s`` then a survey line of ``survey_s`` at 10 Hz, 0.1 nT noise."""
    segments = [TrimManoeuvre(trim_s), SurveyLine((0, 0, -50), (2.0 * survey_s, 0, -50), speed_m_s=2.0)]
    scenario = Scenario(geometry=GEOMETRY, earth_field_enu=EARTH_ENU.tolist(), segments=segments,
                        noise_t=1e-10, sample_rate_hz=RATE_HZ)
    return simulate(scenario, np.random.default_rng(seed))


def write_params(path: Path, earth: bool = True) -> Path:
    values = {'sensor_positions': GEOMETRY.to_flat()}
    if earth:
        values['earth_field_enu'] = EARTH_ENU.tolist()
    path.write_text(params_document(values))
    return path


def write_bag(path: Path, mission, *, stamps=None, fields=None, keep=None, log=None,
              odom_xyzw=None, odom_position=None, odom: bool = True, odom_late_s: float = 0.0) -> Path:
    """The mission's four magnetometers (and ``/odom``) with faults.

    stamps : per sensor (n,) int64 header stamps (default: the log times)
    fields : (n, 4, 3) T (default: the mission's)
    keep : per sensor (n,) bool, the messages written (default all)
    log : (n,) int64 log times (default START_NS + t)
    odom_xyzw, odom_position : (n, 4), (n, 3) the /odom pose (default the mission's)
    odom_late_s : the /odom header stamps this much after the pose's instant (a filter delay)
    """
    n = len(mission.t)
    log = START_NS + np.round(mission.t * 1e9).astype(np.int64) if log is None else log
    stamps = [log] * 4 if stamps is None else stamps
    fields = mission.fields_measured if fields is None else fields
    keep = [np.ones(n, bool)] * 4 if keep is None else keep
    quats = mission.orientation_xyzw if odom_xyzw is None else odom_xyzw
    position = mission.position_enu if odom_position is None else odom_position
    with BagWriter(path) as writer:
        for i in range(n):
            for sensor in range(4):
                if keep[sensor][i]:
                    data = cv.magnetic_field_cdr(fields[i, sensor], int(stamps[sensor][i]), cv.MAG_FRAMES[sensor])
                    writer.write_raw(cv.BAG_MAG_TOPICS[sensor], cv.MAGNETIC_FIELD, data, int(log[i]))
            if odom:
                stamp = int(log[i]) + int(odom_late_s * 1e9)
                msg = cv.odometry_msg(writer.types, position[i], quats[i], stamp)
                writer.write(cv.ODOM_TOPIC, msg, int(log[i]))
    return path
