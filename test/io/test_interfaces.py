"""Our interfaces (tetra_gradiometer_msgs) offline: rosbags reads their .msg/.srv text
(io/interfaces.py, no compiled package, no rclpy), and bags carrying them in sqlite3 and mcap
read back to the values written. The expected fields and values are written out here, not
taken from the code under test; decoded values are compared, never raw bytes."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tetra_gradiometer.io import interfaces
from tetra_gradiometer.io.bag import BagWriter, typestore

GRADIENT = 'tetra_gradiometer_msgs/msg/GradientTensor'
CALIBRATION = 'tetra_gradiometer_msgs/msg/Calibration'

# (name, rosbags field kind, element type) as the brief for the messages lists them
GRADIENT_FIELDS = [
    ('header', 'std_msgs/msg/Header'),
    ('g', 'float64[9]'),
    ('g_sigma', 'float64[9]'),
    ('reference_field', 'geometry_msgs/msg/Vector3'),
    ('reference_field_covariance', 'float64[9]'),
    ('state', 'uint8'),
    ('calibration_id', 'string'),
]
CALIBRATION_FIELDS = [
    ('header', 'std_msgs/msg/Header'),
    ('method', 'string'),
    ('symmetric_k', 'bool'),
    ('sensor_positions', 'float64[12]'),
    ('terms', 'string[]'),
    ('parameter_names', 'string[]'),
    ('parameters', 'float64[]'),
    ('covariance', 'float64[]'),
    ('sensor_noise_t', 'float64'),
    ('residual_t_per_m', 'float64'),
    ('rank', 'uint32'),
    ('created_utc', 'string'),
    ('source', 'string'),
    ('window_s', 'float64[2]'),
    ('signature', 'string'),
    ('document', 'string'),
]
REQUEST_FIELDS = [('window_s', 'float64[2]'), ('force', 'bool'), ('effects', 'string')]
RESPONSE_FIELDS = [
    ('success', 'bool'),
    ('message', 'string'),
    ('residual_t_per_m', 'float64'),
    ('residual_over_floor', 'float64'),
    ('samples', 'uint32'),
    ('rank', 'uint32'),
    ('calibration_file', 'string'),
]


def _spelled(desc) -> str:
    """A rosbags field description as .msg text spells the type."""
    kind, rest = desc
    if kind == 1:  # BASE: (type, string bound)
        return rest[0]
    if kind == 2:  # NAME
        return rest
    element = _spelled(rest[0])
    return f'{element}[{rest[1]}]' if kind == 3 else f'{element}[]'  # ARRAY, SEQUENCE


def _fields(store, name: str) -> list[tuple[str, str]]:
    _, fields = store.fielddefs[name]
    return [(field, _spelled(desc)) for field, desc in fields]


def test_the_typestore_has_our_messages_and_the_service_parts_with_the_documented_fields():
    store = typestore()
    assert _fields(store, GRADIENT) == GRADIENT_FIELDS
    assert _fields(store, CALIBRATION) == CALIBRATION_FIELDS
    assert _fields(store, 'tetra_gradiometer_msgs/srv/Calibrate_Request') == REQUEST_FIELDS
    assert _fields(store, 'tetra_gradiometer_msgs/srv/Calibrate_Response') == RESPONSE_FIELDS
    consts, _ = store.fielddefs[GRADIENT]
    assert sorted(consts) == [('COMPENSATED', 'uint8', 1), ('RAW', 'uint8', 0), ('UNCOMPENSATED', 'uint8', 2)]
    assert store.types[GRADIENT].UNCOMPENSATED == 2


def _gradient(store):
    t = store.types
    header = t['std_msgs/msg/Header'](
        stamp=t['builtin_interfaces/msg/Time'](sec=1_700_000_000, nanosec=123_456_789), frame_id='tetra_array'
    )
    return t[GRADIENT](
        header=header,
        g=np.array([1.5e-9, -2.25e-9, 3.0e-10, -2.25e-9, 4.0e-9, 0.0, 3.0e-10, 0.0, -5.5e-9]),
        g_sigma=np.array([1e-11, np.nan, 2e-11, 3e-11, 4e-11, np.nan, 5e-11, 6e-11, 7e-11]),
        reference_field=t['geometry_msgs/msg/Vector3'](x=2.1e-5, y=-3.4e-6, z=4.4e-5),
        reference_field_covariance=np.array([1e-20, 0, 0, 0, 2e-20, 0, 0, 0, 3e-20]),
        state=1,
        calibration_id='2026-11-22T10:00:00Z',
    )


def _calibration(store):
    t = store.types
    header = t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](sec=12, nanosec=5), frame_id='tetra_array')
    return t[CALIBRATION](
        header=header,
        method='known_gradient_lstsq_general',
        symmetric_k=False,
        sensor_positions=np.array([0.0, 0, 0, 0.5, 0, 0, 0.25, 0.433, 0, 0.25, 0.144, 0.408]),
        terms=['vehicle_current'],
        parameter_names=['k21_xx', 'b21_x_T', 'w21_x_I'],
        parameters=np.array([1.25e-3, -4.5e-8, 2.0e-10]),
        covariance=np.array([1e-8, 0, 0, 0, 4e-18, 1e-20, 0, 1e-20, 9e-22]),
        sensor_noise_t=5e-11,
        residual_t_per_m=2.5e-11,
        rank=45,
        created_utc='2026-11-22T10:00:00Z',
        source='bags/trim',
        window_s=np.array([12.5, 312.5]),
        signature='',
        document='tetra_gradiometer_calibration: 1\nmethod: known_gradient_lstsq_general\nnote: ± 0.1 nT\n',
    )


def _check_gradient(msg) -> None:
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_456_789, 'tetra_array')
    np.testing.assert_array_equal(msg.g, [1.5e-9, -2.25e-9, 3.0e-10, -2.25e-9, 4.0e-9, 0.0, 3.0e-10, 0.0, -5.5e-9])
    np.testing.assert_array_equal(msg.g_sigma, [1e-11, np.nan, 2e-11, 3e-11, 4e-11, np.nan, 5e-11, 6e-11, 7e-11])
    assert (msg.reference_field.x, msg.reference_field.y, msg.reference_field.z) == (2.1e-5, -3.4e-6, 4.4e-5)
    np.testing.assert_array_equal(msg.reference_field_covariance, [1e-20, 0, 0, 0, 2e-20, 0, 0, 0, 3e-20])
    assert (msg.state, msg.calibration_id) == (1, '2026-11-22T10:00:00Z')


def _check_calibration(msg) -> None:
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (12, 5)
    assert (msg.method, msg.symmetric_k, list(msg.terms)) == ('known_gradient_lstsq_general', False, ['vehicle_current'])
    np.testing.assert_array_equal(msg.sensor_positions, [0.0, 0, 0, 0.5, 0, 0, 0.25, 0.433, 0, 0.25, 0.144, 0.408])
    assert list(msg.parameter_names) == ['k21_xx', 'b21_x_T', 'w21_x_I']
    np.testing.assert_array_equal(msg.parameters, [1.25e-3, -4.5e-8, 2.0e-10])
    np.testing.assert_array_equal(msg.covariance, [1e-8, 0, 0, 0, 4e-18, 1e-20, 0, 1e-20, 9e-22])
    assert (msg.sensor_noise_t, msg.residual_t_per_m, msg.rank) == (5e-11, 2.5e-11, 45)
    assert (msg.created_utc, msg.source, msg.signature) == ('2026-11-22T10:00:00Z', 'bags/trim', '')
    np.testing.assert_array_equal(msg.window_s, [12.5, 312.5])
    assert msg.document.endswith('note: ± 0.1 nT\n')


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
@pytest.mark.parametrize('default_typestore', [True, False], ids=['our_typestore', 'bag_definitions_only'])
def test_a_bag_of_our_messages_reads_back_to_the_values_written(tmp_path, storage, default_typestore):
    path = tmp_path / 'bag'
    with BagWriter(path, storage=storage) as writer:
        writer.write('/tetra/gradient', _gradient(writer.store), 1_700_000_000_123_456_789)
        writer.write('/tetra/calibration', _calibration(writer.store), 1_700_000_001_000_000_000)
    # without our typestore the bag's own definitions (written by rosbags) must be enough
    with AnyReader([path], default_typestore=typestore() if default_typestore else None) as reader:
        got = [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]
    assert [(topic, msgtype, t) for topic, msgtype, t, _ in got] == [
        ('/tetra/gradient', GRADIENT, 1_700_000_000_123_456_789),
        ('/tetra/calibration', CALIBRATION, 1_700_000_001_000_000_000),
    ]
    _check_gradient(got[0][3])
    _check_calibration(got[1][3])


def test_the_service_parts_round_trip_through_cdr():
    store = typestore()
    request = store.types['tetra_gradiometer_msgs/srv/Calibrate_Request'](
        window_s=np.array([10.0, 250.0]), force=True, effects='vehicle_current,thermal_drift'
    )
    raw = store.serialize_cdr(request, request.__msgtype__)
    back = store.deserialize_cdr(raw, 'tetra_gradiometer_msgs/srv/Calibrate_Request')
    np.testing.assert_array_equal(back.window_s, [10.0, 250.0])
    assert (back.force, back.effects) == (True, 'vehicle_current,thermal_drift')


def test_the_definitions_are_found_in_an_installed_share_folder_when_not_beside_the_package(tmp_path, monkeypatch):
    """A colcon install: no tetra_gradiometer_msgs/ beside the Python package, the
    definitions under PREFIX/share/tetra_gradiometer_msgs of AMENT_PREFIX_PATH."""
    checkout = interfaces.candidate_dirs()[0]
    share = tmp_path / 'install' / 'share' / 'tetra_gradiometer_msgs'
    for kind in ('msg', 'srv'):
        shutil.copytree(checkout / kind, share / kind)
    monkeypatch.setenv('AMENT_PREFIX_PATH', f'{tmp_path / "elsewhere"}:{tmp_path / "install"}')
    monkeypatch.setattr(interfaces, '__file__', str(tmp_path / 'site-packages' / 'tetra_gradiometer' / 'io' / 'interfaces.py'))
    assert interfaces.candidate_dirs()[:3] == [
        tmp_path / 'site-packages' / 'tetra_gradiometer_msgs',
        tmp_path / 'elsewhere' / 'share' / 'tetra_gradiometer_msgs',
        share,
    ]
    assert interfaces.package_dir() == share
    assert GRADIENT in interfaces.types_from(share)


def test_missing_definitions_are_one_error_naming_the_places_searched(tmp_path, monkeypatch):
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'install'))
    monkeypatch.setattr(interfaces, '__file__', str(tmp_path / 'site-packages' / 'tetra_gradiometer' / 'io' / 'interfaces.py'))
    monkeypatch.setattr(interfaces.sys, 'prefix', str(tmp_path / 'venv'))
    with pytest.raises(interfaces.InterfacesNotFound, match='install/share/tetra_gradiometer_msgs'):
        interfaces.package_dir()
    interfaces.interface_types.cache_clear()
    try:
        # the offline tools' typestore: the standard types still, ours absent
        store = typestore()
        assert GRADIENT not in store.types and 'sensor_msgs/msg/MagneticField' in store.types
        with pytest.raises(interfaces.InterfacesNotFound):
            interfaces.register(store)
    finally:
        interfaces.interface_types.cache_clear()


def test_a_service_definition_needs_exactly_one_separator():
    assert interfaces.split_service('bool force\n---\nbool success\n') == ('bool force\n', 'bool success\n')
    with pytest.raises(ValueError, match='one --- line'):
        interfaces.split_service('bool force\n')
