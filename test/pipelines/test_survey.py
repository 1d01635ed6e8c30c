"""pipelines/survey.py: the placement of a survey by its NavSatFix topic (the products end
to end are test/cli/test_survey.py's)."""
import math

import numpy as np
import pytest

from tetra_gradiometer.errors import InputError
from tetra_gradiometer.io.bag import BagWriter, typestore
from tetra_gradiometer.io.geo import Georeference
from tetra_gradiometer.io.recording import Recording
from tetra_gradiometer.pipelines.survey import georeference_of

pytest.importorskip('pyproj')


def test_a_survey_is_placed_by_the_fixes_of_its_navsatfix_topic(tmp_path):
    """pipelines/survey.georeference_of: fixes written from a known placement at the surface
    stretches of a track (0.3 m noise) place the whole track to a few decimetres."""
    truth = Georeference((43.2, 5.3, 0.0), math.radians(-40.0), (35.0, 12.0, 0.0))
    t = np.arange(0.0, 600.0, 0.1)
    track = np.column_stack([400 * np.cos(t / 100), 250 * np.sin(t / 70), -20 + 20 * np.cos(t / 50)])
    stamps = (1_700_000_000 * 10**9 + t * 1e9).astype(np.int64)
    recording = Recording(stamps, np.zeros((len(t), 4, 3)), position_m=track)
    store = typestore()
    NavSatFix, Status = store.types['sensor_msgs/msg/NavSatFix'], store.types['sensor_msgs/msg/NavSatStatus']
    Header, Time = store.types['std_msgs/msg/Header'], store.types['builtin_interfaces/msg/Time']
    rng = np.random.default_rng(8)
    surface = np.flatnonzero(track[:, 2] > -0.5)[::20]  # at the surface only
    enu = truth.to_enu(track[surface]) + np.column_stack([rng.normal(0, 0.3, (len(surface), 2)),
                                                         np.zeros(len(surface))])
    lonlat = truth.to_lonlat(truth.from_enu(enu))
    with BagWriter(tmp_path / 'bag', storage='mcap') as writer:
        for i, (lon, lat, h) in zip(surface, lonlat, strict=True):
            stamp = int(stamps[i])
            writer.write('/fix', NavSatFix(
                header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id='gps'),
                status=Status(status=0, service=1), latitude=lat, longitude=lon, altitude=h,
                position_covariance=np.zeros(9), position_covariance_type=0), stamp)
    placed = georeference_of(tmp_path / 'bag', recording, None, '/fix')
    assert placed.n_fixes == len(surface) > 10
    assert placed.residual_m == pytest.approx(0.3 * math.sqrt(2), rel=0.3)
    error = np.linalg.norm(placed.to_lonlat(track)[:, :2] - truth.to_lonlat(track)[:, :2], axis=1)
    assert error.max() * 111_000 < 0.5  # degrees -> m (upper bound in longitude)
    with pytest.raises(InputError, match='one of them'):
        georeference_of(tmp_path / 'bag', recording, (43.0, 5.0, 0.0), '/fix')


def test_lost_and_refused_spans_along_the_track():
    from tetra_gradiometer.pipelines.survey import Span, track_spans

    t = np.r_[np.arange(0.0, 10.0, 0.1), np.arange(12.0, 20.0, 0.1)]  # 2 s lost after 9.9 s
    known = np.ones(len(t), bool)
    known[150:160] = False  # no compensated tensor from 17.0 to 17.9 s
    spans = track_spans(t, known)
    assert [s.kind for s in spans] == ['lost', 'refused']
    assert spans[0] == Span('lost', pytest.approx(9.9), pytest.approx(12.0))
    assert spans[1].start_s == pytest.approx(17.0) and spans[1].stop_s == pytest.approx(17.9)
    assert track_spans(np.arange(0.0, 5.0, 0.1), np.ones(50, bool)) == []
