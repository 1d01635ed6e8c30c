"""io/targets.py: targets.json round trips through its reader, and the reader names what is
wrong with a broken one."""
import json

import numpy as np
import pytest

from tetra_gradiometer.core.targets import Detection, DipoleFit, Target
from tetra_gradiometer.errors import InputError
from tetra_gradiometer.io.targets import TARGET_KEYS, dumps, read_targets, targets_document


def _target(rng: np.random.Generator, fitted_with: tuple[int, ...] = ()) -> Target:
    a = rng.normal(size=(6, 6))
    fit = DipoleFit(rng.normal(size=3) * 50, rng.normal(size=3) * 1e4, a @ a.T, np.zeros((1, 3, 3)),
                    1.4e-10, 1.02, 0.01, 1234)
    detection = Detection(100, 200, 150, 40.0, 0, 1000)
    return Target(fit, [detection], 110.0, 190.0, True, fitted_with)


def test_targets_json_round_trips(tmp_path):
    rng = np.random.default_rng(3)
    targets = [_target(rng, (1,)), _target(rng, (0,)), _target(rng)]
    document = targets_document(targets, tensor='compensated', t0_stamp_s=1.7e9, false_alarms_per_hour=0.1,
                                detections=4, t0_s=100.0)
    (tmp_path / 'targets.json').write_text(dumps(document))
    back = read_targets(tmp_path / 'targets.json')
    assert back == json.loads(json.dumps(document))
    for entry, target in zip(back['targets'], targets, strict=True):
        np.testing.assert_array_equal(entry['position_m'], target.fit.position)
        np.testing.assert_array_equal(entry['moment_Am2'], target.fit.moment)
        np.testing.assert_allclose(entry['position_sigma_m'], np.sqrt(np.diag(target.fit.covariance)[:3]))
        np.testing.assert_allclose(entry['moment_sigma_Am2'], np.sqrt(np.diag(target.fit.covariance)[3:]))
        assert entry['first_seen_s'] == 10.0 and entry['last_seen_s'] == 90.0
        assert entry['fit_rms_nT_per_m'] == pytest.approx(0.14)
        assert set(TARGET_KEYS) <= set(entry)
        assert entry['fitted_with'] == list(target.fitted_with)


@pytest.mark.parametrize('damage, message', [
    (lambda d: d['targets'][0].pop('moment_Am2'), 'targets[0] lacks moment_Am2'),
    (lambda d: d['targets'][1].__setitem__('position_m', [1.0, 'x', 2.0]), 'targets[1].position_m is not finite'),
    (lambda d: d.__setitem__('frame', 'map'), "frame 'map'"),
])
def test_a_broken_targets_json_is_refused_by_name(tmp_path, damage, message):
    rng = np.random.default_rng(4)
    document = targets_document([_target(rng), _target(rng)], tensor='raw', t0_stamp_s=0.0,
                                false_alarms_per_hour=0.1, detections=2)
    damage(document)
    (tmp_path / 'targets.json').write_text(json.dumps(document))
    with pytest.raises(InputError, match=message.replace('[', r'\[').replace(']', r'\]')):
        read_targets(tmp_path / 'targets.json')
