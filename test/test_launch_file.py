"""launch/tetra_gradiometer.launch.py, run against stand-ins for launch/launch_ros
(test/launch_standins.py), and the packaging it relies on: setup.py (console scripts, data
files, read with ast, never run), setup.cfg and package.xml.

Truth from outside the launch file: the console scripts and data files of setup.py, the
repository's files installed into a temporary share directory as setup.py lists them, the
imports of the package's source, the lifecycle state machine (launch_standins.Launch),
bringup's start order (tensor, calibrator, compensator, driver: cli/bringup.create_nodes),
the params files read here with yaml (the static transforms' values and their mean) and
the params-file matching rules of rclpy (``/*`` one name, ``/**`` any number).
"""

from __future__ import annotations

import ast
import configparser
import importlib.util
import re
import shutil
import sys
import xml.etree.ElementTree as ElementTree
from glob import glob
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / 'launch' / 'tetra_gradiometer.launch.py'
PACKAGE = 'tetra_gradiometer'
#: bringup's order (cli/bringup.create_nodes): the driver last.
ORDER = ('tensor', 'calibrator', 'compensator', 'driver')
ORDER_WITH_TARGET = ('tensor', 'calibrator', 'compensator', 'target', 'driver')
SCRIPT_DIR = '$base/lib/' + PACKAGE

#: Third-party imports that are pure-Python packages: their rosdep key, or None where
#: rosdep has none (then package.xml's "pip:" comment must name the pip package).
PYTHON_KEYS = {
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'matplotlib': 'python3-matplotlib',
    'yaml': 'python3-yaml',
    'tqdm': 'python3-tqdm',
    'rosbags': None,
    'ppigrf': None,
    'dask': None,
    'threadpoolctl': None,
}
PIP_NAMES = {'dask': 'dask[distributed]'}


def _load(path: Path, name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


standins = _load(Path(__file__).with_name('launch_standins.py'), 'launch_standins')


# --------------------------------------------------------------------------- setup.py


def _setup_call() -> tuple[ast.Call, dict[str, Any]]:
    tree = ast.parse((REPO / 'setup.py').read_text(encoding='utf-8'))
    names: dict[str, Any] = {}
    for statement in tree.body:  # module-level constants such as package_name
        if isinstance(statement, ast.Assign) and isinstance(statement.value, ast.Constant):
            for target in statement.targets:
                if isinstance(target, ast.Name):
                    names[target.id] = statement.value.value
    calls = [
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'setup'
    ]
    assert len(calls) == 1, 'setup.py must call setup() once'
    return calls[0], names


def _evaluate(node: ast.AST, names: dict[str, Any]) -> Any:
    """The value of a setup() argument built from literals, constants, ``+``, f-strings
    and ``glob('pattern')`` (run in the repository, as colcon runs setup.py)."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name):
        return names[node.id]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return _evaluate(node.left, names) + _evaluate(node.right, names)
    if isinstance(node, (ast.List, ast.Tuple)):
        return [_evaluate(item, names) for item in node.elts]
    if isinstance(node, ast.Dict):
        return {
            _evaluate(k, names): _evaluate(v, names)
            for k, v in zip(node.keys, node.values, strict=True)
        }
    if isinstance(node, ast.JoinedStr):
        return ''.join(str(_evaluate(part, names)) for part in node.values)
    if isinstance(node, ast.FormattedValue):
        return _evaluate(node.value, names)
    if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'glob':
        return sorted(glob(_evaluate(node.args[0], names), root_dir=REPO))
    raise AssertionError(f'setup.py: cannot evaluate {ast.unparse(node)} here; extend _evaluate')


def _setup_argument(keyword: str) -> Any:
    call, names = _setup_call()
    for item in call.keywords:
        if item.arg == keyword:
            return _evaluate(item.value, names)
    raise AssertionError(f'setup.py: setup() has no {keyword}=')


def console_scripts() -> dict[str, str]:
    """Script name -> ``module:function``."""
    entries = _setup_argument('entry_points')['console_scripts']
    return dict(tuple(part.strip() for part in entry.split('=', 1)) for entry in entries)


def installed_files() -> dict[str, str]:
    """Install path (``share/...``) -> repository path, for every data file of setup.py."""
    out = {}
    for destination, sources in _setup_argument('data_files'):
        for source in sources:
            out[f'{destination}/{Path(source).name}'] = source
    return out


@pytest.fixture
def share(tmp_path: Path) -> Path:
    """The package's share directory of an install made from setup.py's data files."""
    for target, source in installed_files().items():
        (tmp_path / target).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / source, tmp_path / target)
    return tmp_path / 'share' / PACKAGE


# --------------------------------------------------------------------------- launching


@pytest.fixture
def launch(monkeypatch: pytest.MonkeyPatch, share: Path):
    """``launch(**arguments)``: the launch file run by the stand-in launch."""
    standins.install(monkeypatch)
    monkeypatch.chdir(REPO)

    def run(**arguments: str) -> Any:
        module = _load(LAUNCH_FILE, 'tetra_gradiometer_launch')
        runner = standins.Launch(arguments, {PACKAGE: str(share)})
        run.last = runner  # type: ignore[attr-defined]  # what had started when it raised
        return runner.run(module.generate_launch_description())

    return run


def _chain(names: list[str]) -> list[tuple[str, str]]:
    return [(name, step) for name in names for step in ('configure', 'activate')]


class _Exited:
    def __init__(self, name: str) -> None:
        self.process_name = name


class _Context:
    def __init__(self, is_shutdown: bool) -> None:
        self.is_shutdown = is_shutdown


def test_the_first_node_to_exit_ends_the_launch_with_one_shutdown(launch):
    """launch_ros raises on every Shutdown event after the first ("Cannot shutdown a ROS
    adapter that is not running": exit 1 with an [ERROR] per node), so the nodes' exits
    send one between them, and none once the launch is shutting down (Ctrl-C)."""
    nodes = launch(mode='sim').nodes
    assert len({id(node.on_exit) for node in nodes}) == 1  # one per launch, shared
    running = _Context(is_shutdown=False)
    first = nodes[2].on_exit(_Exited('compensator-3'), running)
    assert [type(action) for action in first] == [standins.Shutdown]
    assert 'compensator-3 exited' in first[0].reason
    assert [node.on_exit(_Exited(node.name), running) for node in nodes] == [None] * len(nodes)
    # Ctrl-C: the launch is already shutting down when the nodes exit.
    after_sigint = launch(mode='sim').nodes
    stopping = _Context(is_shutdown=True)
    assert [node.on_exit(_Exited(node.name), stopping) for node in after_sigint] == [None] * 4
    # A second launch has its own: its first exit still ends it.
    assert after_sigint[0].on_exit(_Exited('tensor-1'), running) is not None


def test_sim_starts_the_four_nodes_and_activates_them_one_after_the_other(launch, share):
    run = launch(mode='sim')
    assert [node.name for node in run.nodes] == list(ORDER)
    for node in run.nodes:
        assert (node.package, node.executable, node.namespace) == (PACKAGE, node.name, 'tetra')
        assert node.output == 'screen'
        assert callable(node.on_exit)
        params_file, overrides = node.parameters
        assert params_file == str(share / 'config' / 'tetra_gradiometer.yaml')
        expected = {'use_sim_time': False, 'autostart': False}  # the sequence configures them
        if node.name == 'driver':  # bringup: wait for the tensor node's subscriptions
            expected.update(min_subscribers=1, mode='sim')
        assert overrides == expected
    assert run.requests == _chain(list(ORDER))
    assert run.state == dict.fromkeys(ORDER, 'active')
    assert run.refused == []


def test_every_argument_read_is_declared_and_every_declared_one_is_read(launch):
    run = launch(mode='sim')
    assert sorted(run.context.launch_configurations.read) == sorted(run.declared)
    assert len(set(run.declared)) == len(run.declared)


@pytest.mark.parametrize(
    'nodes, expected',
    [
        ('tensor', ['tensor']),
        ('driver', ['driver']),
        ('compensator, tensor,tensor', ['tensor', 'compensator']),
        ('driver,calibrator', ['calibrator', 'driver']),
        ('calibrator,compensator,driver', ['calibrator', 'compensator', 'driver']),
        ('driver,compensator,calibrator,tensor', list(ORDER)),
    ],
)
def test_a_subset_starts_only_its_nodes_in_bringup_order(launch, nodes, expected):
    run = launch(mode='sim', nodes=nodes)
    assert [node.name for node in run.nodes] == expected
    assert run.requests == _chain(expected)
    assert run.state == dict.fromkeys(expected, 'active')
    if 'driver' in expected:
        waits = run.node('driver').parameters[-1].get('min_subscribers')
        assert waits == (1 if 'tensor' in expected else None)


def test_the_target_node_starts_only_when_named_and_before_the_driver(launch):
    run = launch(mode='sim', nodes='driver,target,tensor,calibrator,compensator')
    expected = ['tensor', 'calibrator', 'compensator', 'target', 'driver']
    assert [node.name for node in run.nodes] == expected
    assert run.requests == _chain(expected)
    target = run.node('target')
    assert (target.package, target.executable) == (PACKAGE, 'target')
    assert console_scripts()['target'] == 'tetra_gradiometer.nodes.process:main_target'
    assert target.parameters[-1] == {'use_sim_time': False, 'autostart': False}
    assert 'target' not in [node.name for node in launch(mode='sim').nodes]


def test_autostart_false_leaves_every_node_unconfigured(launch):
    run = launch(mode='sim', autostart='False')
    assert [node.name for node in run.nodes] == list(ORDER)
    assert run.requests == []
    assert run.state == dict.fromkeys(ORDER, 'unconfigured')
    assert not [a for a in run.actions if isinstance(a, standins.RegisterEventHandler)]


def test_a_later_manual_deactivate_and_activate_restarts_nothing(launch):
    from lifecycle_msgs.msg import Transition

    run = launch(mode='sim')
    before = list(run.requests)
    run.change_state(run.node('tensor'), Transition.TRANSITION_DEACTIVATE)
    run.change_state(run.node('tensor'), Transition.TRANSITION_ACTIVATE)
    assert run.requests == before + [('tensor', 'deactivate'), ('tensor', 'activate')]
    assert run.refused == []
    assert run.state == dict.fromkeys(ORDER, 'active')


@pytest.mark.parametrize(
    'word, value', [('true', True), ('True', True), ('1', True), ('0', False)]
)
def test_use_sim_time_reaches_every_node(launch, word, value):
    run = launch(mode='sim', use_sim_time=word)
    assert [node.parameters[-1]['use_sim_time'] for node in run.nodes] == [value] * 4
    assert [node.parameters[-1]['use_sim_time'] for node in run.plain_nodes] == [value] * 5


@pytest.mark.parametrize(
    'arguments, driver',
    [
        ({'bag': 'bags/survey'}, {'mode': 'replay', 'bag': str(REPO / 'bags' / 'survey')}),
        ({'bag': 'bags/survey', 'mode': 'sim'}, {'mode': 'sim', 'bag': str(REPO / 'bags/survey')}),
        ({'mode': 'replay'}, {'mode': 'replay'}),
        ({'mode': 'sim', 'rate': '0'}, {'mode': 'sim', 'rate': 0.0}),
        (
            {'mode': 'sim', 'scenario': 'scenarios/x.yaml'},
            {'mode': 'sim', 'scenario': str(REPO / 'scenarios' / 'x.yaml')},
        ),
    ],
)
def test_driver_arguments_become_its_parameters_as_bringup_passes_them(launch, arguments, driver):
    run = launch(**arguments)
    assert run.node('driver').parameters[-1] == {
        'use_sim_time': False,
        'autostart': False,
        'min_subscribers': 1,
        **driver,
    }
    rate = run.node('driver').parameters[-1].get('rate')
    assert rate is None or type(rate) is float  # the node refuses an integer for a double
    for name in ('tensor', 'calibrator', 'compensator'):
        assert run.node(name).parameters[-1] == {'use_sim_time': False, 'autostart': False}


@pytest.mark.parametrize('word', ['true', '1'])
def test_enclaves_true_runs_every_node_in_its_sros2_enclave_and_false_in_none(launch, word):
    """Issue 34: one enclave per node, as security/policy.xml names them."""
    import xml.etree.ElementTree as ET

    run = launch(mode='sim', nodes='tensor,calibrator,compensator,target,driver', enclaves=word)
    assert {node.name: node.ros_arguments for node in run.nodes} == {
        name: ['--enclave', f'/tetra_gradiometer/{name}'] for name in ORDER_WITH_TARGET}
    assert all(node.ros_arguments == ['--enclave', '/tetra_gradiometer/static_transforms']
               for node in run.plain_nodes)
    policy = ET.parse(REPO / 'security' / 'policy.xml').getroot()
    paths = {enclave.get('path') for enclave in policy.iter('enclave')}
    assert {args[1] for args in (n.ros_arguments for n in [*run.nodes, *run.plain_nodes])} <= paths
    default = launch(mode='sim')
    assert all(node.ros_arguments is None for node in [*default.nodes, *default.plain_nodes])


def test_calibration_file_goes_to_calibrator_and_compensator_only(launch):
    run = launch(calibration_file='~/cal.yaml', nodes='calibrator,compensator,tensor')
    path = str(Path('~/cal.yaml').expanduser())
    assert run.node('calibrator').parameters[-1]['calibration_file'] == path
    assert run.node('compensator').parameters[-1]['calibration_file'] == path
    assert 'calibration_file' not in run.node('tensor').parameters[-1]


def test_namespace_and_an_empty_params_file(launch):
    run = launch(mode='sim', namespace='robot1/tetra', params_file='')
    assert {node.namespace for node in run.nodes} == {'robot1/tetra'}
    assert {node.namespace for node in run.plain_nodes} == {'robot1/tetra'}
    assert [len(node.parameters) for node in run.nodes] == [1] * 4  # only the overrides


@pytest.mark.parametrize(
    'arguments, message',
    [
        ({'nodes': 'tensr,driver'}, r"nodes 'tensr,driver': unknown 'tensr'; choose from tensor,"),
        ({'nodes': ' , '}, r"nodes ' , ': no node named"),
        ({'mode': 'simulation'}, r"mode 'simulation': must be one of sim, replay"),
        ({'use_sim_time': 'yes'}, r"use_sim_time 'yes': must be true or false"),
        ({'autostart': 'maybe'}, r"autostart 'maybe': must be true or false"),
        ({'rate': 'fast'}, r"rate 'fast': must be a number"),
        ({'params_file': '/nonexistent/p.yaml'}, r"params_file '/nonexistent/p.yaml': no such"),
    ],
)
def test_a_bad_argument_is_refused_before_any_node_starts(launch, arguments, message):
    with pytest.raises(ValueError, match=message):
        launch(**{'mode': 'sim', **arguments})


@pytest.mark.parametrize('arguments', [{}, {'rate': '0'}, {'scenario': 'x.yaml'}])
def test_a_driver_without_a_source_is_refused_before_any_node_starts(launch, arguments):
    """The installed params file sets no mode: the driver fabricates nothing by default."""
    with pytest.raises(ValueError, match=r'the driver needs a source: mode:=sim .* bag:=PATH'):
        launch(**arguments)
    assert launch.last.nodes == []


def test_without_the_driver_no_source_is_needed(launch):
    run = launch(nodes='tensor,calibrator,compensator')
    assert [node.name for node in run.nodes] == ['tensor', 'calibrator', 'compensator']
    assert run.state == dict.fromkeys(['tensor', 'calibrator', 'compensator'], 'active')


@pytest.mark.parametrize('section', ['/**', '/tetra/driver', '/**/driver'])
def test_a_params_file_that_sets_the_mode_is_a_source(launch, tmp_path, section):
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(f"{section}:\n  ros__parameters:\n    mode: sim\n")
    run = launch(params_file=str(params_file))
    assert run.state == dict.fromkeys(ORDER, 'active')
    other = tmp_path / 'other.yaml'
    other.write_text("/tetra/tensor:\n  ros__parameters:\n    mode: sim\n")
    with pytest.raises(ValueError, match='the driver needs a source'):
        launch(params_file=str(other))


# --------------------------------------------------------------------------- static transforms

#: tf2_ros static_transform_publisher's flags (Jazzy), the value each takes.
TRANSFORM_FLAGS = (
    '--x', '--y', '--z', '--roll', '--pitch', '--yaw', '--frame-id', '--child-frame-id',
)  # fmt: skip
#: The publishers' names, sensors 1..4 then the array frame.
PUBLISHERS = ('tetra_tf_mag1', 'tetra_tf_mag2', 'tetra_tf_mag3', 'tetra_tf_mag4', 'tetra_tf_array')


#: (parent frame, child frame, translation x y z in metres) of a static transform.
Transform = tuple[str, str, tuple[float, ...]]


def _transforms(run: Any) -> list[Transform]:
    """(parent, child, translation) of each static transform publisher launched, checking
    that it is tf2_ros's, with the named-argument form and the identity rotation."""
    out = []
    for node in run.plain_nodes:
        assert (node.package, node.executable) == ('tf2_ros', 'static_transform_publisher')
        arguments = node.arguments
        assert all(isinstance(argument, str) for argument in arguments)
        flags = dict(zip(arguments[::2], arguments[1::2], strict=True))
        assert tuple(flags) == TRANSFORM_FLAGS, arguments
        assert [float(flags[f]) for f in ('--roll', '--pitch', '--yaw')] == [0.0] * 3
        translation = tuple(float(flags[f]) for f in ('--x', '--y', '--z'))
        out.append((flags['--frame-id'], flags['--child-frame-id'], translation))
    return out


def _expected(
    positions: list[float], base: str, sensors: list[str], array: str
) -> list[Transform]:
    """Sensor i at positions[3i:3i+3], the array frame at the mean of the four."""
    points = [tuple(float(v) for v in positions[3 * i : 3 * i + 3]) for i in range(4)]
    mean = tuple(sum(point[axis] for point in points) / 4 for axis in range(3))
    frames: list[Transform] = [(base, s, p) for s, p in zip(sensors, points, strict=True)]
    return [*frames, (base, array, mean)]


def _assert_transforms(run: Any, expected: list[Transform]) -> None:
    """The frames exactly, the sensors' translations to the last bit (the arguments carry
    the floats' repr), the array's (a mean) to rounding."""
    got = _transforms(run)
    assert [(parent, child) for parent, child, _ in got] == [(p, c) for p, c, _ in expected]
    assert [t for _, _, t in got[:4]] == [t for _, _, t in expected[:4]]
    assert got[4][2] == pytest.approx(expected[4][2], rel=1e-12, abs=1e-15)


def _params_file(tmp_path: Path, text: str) -> str:
    path = tmp_path / 'params.yaml'
    path.write_text(text, encoding='utf-8')
    return str(path)


def test_static_transforms_are_the_default_params_file_sensors_and_their_centroid(launch, share):
    run = launch(mode='sim')
    data = yaml.safe_load((share / 'config' / 'tetra_gradiometer.yaml').read_text())
    ros = data['/**']['ros__parameters']
    expected = _expected(
        ros['sensor_positions'], ros['base_frame_id'], ros['sensor_frame_ids'], 'tetra_array'
    )
    assert ros['array_frame_id'] == 'tetra_array'
    _assert_transforms(run, expected)
    assert [(parent, child) for parent, child, _ in _transforms(run)] == [
        ('base_link', 'tetra_mag1'),
        ('base_link', 'tetra_mag2'),
        ('base_link', 'tetra_mag3'),
        ('base_link', 'tetra_mag4'),
        ('base_link', 'tetra_array'),
    ]


def test_static_transforms_follow_another_params_file(launch, tmp_path):
    positions = [0.1234567891, -0.2, 0.05, 0.7, -0.2, 0.05, 0.4, 0.35, 0.05, 0.4, -0.05, 0.6]
    params_file = _params_file(
        tmp_path,
        '/**:\n  ros__parameters:\n'
        f'    sensor_positions: {positions}\n'
        '    base_frame_id: auv7/base\n'
        '    sensor_frame_ids: [auv7/m_a, auv7/m_b, auv7/m_c, auv7/m_d]\n'
        '    array_frame_id: auv7/gradiometer\n',
    )
    run = launch(mode='sim', params_file=params_file)
    ros = yaml.safe_load(Path(params_file).read_text())['/**']['ros__parameters']
    assert ros['sensor_positions'] == positions
    sensors = ['auv7/m_a', 'auv7/m_b', 'auv7/m_c', 'auv7/m_d']
    expected = _expected(positions, 'auv7/base', sensors, 'auv7/gradiometer')
    _assert_transforms(run, expected)
    assert expected[4][2] == pytest.approx((0.405864197275, -0.025, 0.1875))  # by hand
    assert [node.parameters[0] for node in run.nodes] == [params_file] * 4  # the same file


def test_node_sections_count_as_the_nodes_read_them(launch, tmp_path):
    """sensor_positions and array_frame_id as the tensor node reads them, base_frame_id
    and sensor_frame_ids as the driver does; a later matching section wins."""
    wild = [0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5]
    tensor = [1.0, 0.0, 0.0, 1.5, 0.0, 0.0, 1.0, 0.5, 0.0, 1.0, 0.0, 0.5]
    other = [9.0] * 12
    params_file = _params_file(
        tmp_path,
        f"""
/**:
  ros__parameters:
    sensor_positions: {wild}
    base_frame_id: everyone_base
    array_frame_id: everyone_array
/tetra/calibrator:
  ros__parameters:
    sensor_positions: {other}
/**/tensor:
  ros__parameters:
    sensor_positions: {tensor}
    array_frame_id: tensor_array
/other/driver:
  ros__parameters:
    base_frame_id: other_base
tetra:
  driver:
    ros__parameters:
      base_frame_id: driver_base
      sensor_frame_ids: [d1, d2, d3, d4]
/*:
  ros__parameters:
    sensor_frame_ids: [root1, root2, root3, root4]
""",
    )
    run = launch(mode='sim', params_file=params_file)
    expected = _expected(tensor, 'driver_base', ['d1', 'd2', 'd3', 'd4'], 'tensor_array')
    _assert_transforms(run, expected)
    # At the root namespace "/*" (one name) matches /driver and comes last; tetra: driver:
    # (/tetra/driver) no longer matches.
    run = launch(mode='sim', params_file=params_file, namespace='')
    roots = ['root1', 'root2', 'root3', 'root4']
    _assert_transforms(run, _expected(tensor, 'everyone_base', roots, 'tensor_array'))


def test_missing_keys_and_no_params_file_take_the_declared_defaults(launch, tmp_path):
    from tetra_gradiometer.io.conversions import ARRAY_FRAME, BASE_FRAME, MAG_FRAMES
    from tetra_gradiometer.nodes.common import DEFAULT_POSITIONS

    positions = list(DEFAULT_POSITIONS)
    defaults = _expected(positions, BASE_FRAME, list(MAG_FRAMES), ARRAY_FRAME)
    _assert_transforms(launch(mode='sim', params_file=''), defaults)
    params_file = _params_file(
        tmp_path, '/**:\n  ros__parameters:\n    sensor_frame_ids: [s1, s2, s3, s4]\n'
    )
    expected = _expected(positions, BASE_FRAME, ['s1', 's2', 's3', 's4'], ARRAY_FRAME)
    _assert_transforms(launch(mode='sim', params_file=params_file), expected)


def test_static_transform_publishers_are_plain_nodes_outside_the_lifecycle(launch):
    for arguments in ({}, {'nodes': 'driver'}, {'autostart': 'false'}, {'namespace': 'r2'}):
        run = launch(**{'mode': 'sim', **arguments})
        assert [node.name for node in run.plain_nodes] == list(PUBLISHERS)
        namespace = arguments.get('namespace', 'tetra')
        for node in run.plain_nodes:
            assert node.namespace == namespace
            assert node.on_exit is None  # its exit does not end the launch
            assert node.remappings is None  # /tf_static, absolute
        lifecycle = [node.name for node in run.nodes]
        assert {name for name, _ in run.requests} <= set(lifecycle)
        assert set(run.state) == set(lifecycle)
    # The publishers start before the lifecycle nodes (the frames exist before any data).
    run = launch(mode='sim')
    first_lifecycle = min(run.actions.index(node) for node in run.nodes)
    assert max(run.actions.index(node) for node in run.plain_nodes) < first_lifecycle


@pytest.mark.parametrize('word', ['false', 'False', '0'])
def test_static_transforms_false_starts_none(launch, word):
    run = launch(mode='sim', static_transforms=word)
    assert run.plain_nodes == []
    assert [node.name for node in run.nodes] == list(ORDER)
    assert run.state == dict.fromkeys(ORDER, 'active')


@pytest.mark.parametrize(
    'body, message',
    [
        ('sensor_positions: [0.0, 0.0, 0.0, 0.5]', 'sensor_positions must be 12 finite numbers'),
        ('sensor_positions: [' + ', '.join(['0.1'] * 11) + ', .nan]', 'sensor_positions must'),
        ('sensor_positions: [' + ', '.join(['0.1'] * 11) + ', x]', 'sensor_positions must'),
        ('sensor_positions: [' + ', '.join(['0.1'] * 11) + ', true]', 'sensor_positions must'),
        ('sensor_positions: 0.5', 'sensor_positions must be 12 finite numbers'),
        ('sensor_frame_ids: [a, b, c]', 'sensor_frame_ids must be a list of 4 frame ids'),
        ("sensor_frame_ids: [a, b, '', d]", 'sensor_frame_ids: frame ids must be non-empty'),
        ('sensor_frame_ids: [a, b, 3, d]', 'sensor_frame_ids: a frame id must be a string'),
        ('base_frame_id: /base_link', 'base_frame_id: frame ids must be non-empty without a'),
        ('array_frame_id: 7', 'array_frame_id: a frame id must be a string'),
    ],
)
def test_a_malformed_params_file_is_refused_before_any_node_starts(
    launch, tmp_path, body, message
):
    params_file = _params_file(tmp_path, f'/**:\n  ros__parameters:\n    {body}\n')
    with pytest.raises(ValueError, match=re.escape(f'params_file {params_file!r}: {message}')):
        launch(mode='sim', params_file=params_file)
    assert launch.last.nodes == [] and launch.last.plain_nodes == []


@pytest.mark.parametrize(
    'text, message',
    [
        ('/**:\n  ros__parameters: [1, 2]\n', '/**: ros__parameters must map parameter names'),
        ('- sensor_positions\n', 'the top level: not a ROS 2 parameter file'),
        ('/**:\n  sensor_positions: [1, 2]\n', '/**/sensor_positions: not a ROS 2 parameter'),
        ('/**:\n  ros__parameters: {a: [1, 2}\n', 'cannot read it'),
    ],
)
def test_a_file_that_is_not_a_ros2_params_file_is_refused(launch, tmp_path, text, message):
    params_file = _params_file(tmp_path, text)
    pattern = re.escape(f'params_file {params_file!r}: ') + '.*' + re.escape(message)
    with pytest.raises(ValueError, match=pattern):
        launch(mode='sim', params_file=params_file)
    assert launch.last.nodes == [] and launch.last.plain_nodes == []


# --------------------------------------------------------------------------- packaging


def test_every_executable_launched_is_a_console_script_with_a_main(launch):
    scripts = console_scripts()
    run = launch(mode='sim')
    executables = {node.executable for node in run.nodes}
    assert {node.package for node in run.nodes} == {PACKAGE}
    # The only other executable: tf2_ros's static_transform_publisher (not ours).
    others = {(node.package, node.executable) for node in run.plain_nodes}
    assert others == {('tf2_ros', 'static_transform_publisher')}
    assert executables == set(ORDER)
    assert sorted(executables - set(scripts)) == []
    for name in executables:
        module, function = scripts[name].split(':')
        source = REPO / Path(*module.split('.')).with_suffix('.py')
        defined = {
            n.name
            for n in ast.parse(source.read_text(encoding='utf-8')).body
            if isinstance(n, ast.FunctionDef)
        }
        assert function in defined, f'{scripts[name]}: no function {function}'


def test_the_package_name_agrees_everywhere(launch):
    name = ElementTree.parse(REPO / 'package.xml').getroot().findtext('name')
    assert _setup_argument('name') == name == PACKAGE
    assert {node.package for node in launch(mode='sim').nodes} == {PACKAGE}
    assert (REPO / 'resource' / PACKAGE).is_file()
    assert installed_files()[f'share/ament_index/resource_index/packages/{PACKAGE}']


def test_launch_file_params_file_package_xml_and_scenarios_are_installed():
    files = installed_files()
    share = f'share/{PACKAGE}'
    assert files[f'{share}/launch/{LAUNCH_FILE.name}'] == 'launch/' + LAUNCH_FILE.name
    assert files[f'{share}/config/tetra_gradiometer.yaml'] == 'config/tetra_gradiometer.yaml'
    assert files[f'{share}/package.xml'] == 'package.xml'
    scenarios = sorted(p.name for p in (REPO / 'config' / 'scenarios').iterdir() if p.is_file())
    assert scenarios, 'config/scenarios/ is empty'
    for name in scenarios:
        assert files.get(f'{share}/config/scenarios/{name}') == f'config/scenarios/{name}'


def test_documented_executables_are_console_scripts_and_launch_files_installed():
    scripts, files = console_scripts(), installed_files()
    documents = [REPO / 'README.md', *sorted((REPO / 'docs').glob('*.md'))]
    text = '\n'.join(path.read_text(encoding='utf-8') for path in documents)
    runs = re.findall(rf'ros2 run {PACKAGE} <?([\w|]+)>?', text)
    named = {name for found in runs for name in found.split('|')}
    assert named, 'no "ros2 run" in the docs'
    assert sorted(named - set(scripts)) == []
    for launch_file in re.findall(rf'ros2 launch {PACKAGE} (\S+\.py)', text):
        assert f'share/{PACKAGE}/launch/{launch_file}' in files


def test_setup_cfg_puts_the_scripts_where_ros2_run_finds_them():
    config = configparser.ConfigParser(interpolation=None)
    config.read(REPO / 'setup.cfg')
    assert config['develop']['script_dir'] == SCRIPT_DIR
    assert config['install']['install_scripts'] == SCRIPT_DIR


def _top_level_imports(*roots: Path) -> dict[str, str]:
    """Top-level module -> one file importing it, for absolute imports under ``roots``."""
    found: dict[str, str] = {}
    for root in roots:
        for path in sorted(root.rglob('*.py')):
            for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
                if isinstance(node, ast.Import):
                    modules = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    modules = [node.module]
                else:
                    continue
                for module in modules:
                    found.setdefault(module.split('.')[0], str(path.relative_to(REPO)))
    return found


def _package_xml() -> tuple[dict[str, set[str]], str]:
    root = ElementTree.parse(
        REPO / 'package.xml',
        ElementTree.XMLParser(target=ElementTree.TreeBuilder(insert_comments=True)),
    ).getroot()
    depends: dict[str, set[str]] = {}
    for element in root:
        if isinstance(element.tag, str) and element.tag.endswith('depend'):
            depends.setdefault(element.tag, set()).add(element.text.strip())
    comments = ' '.join(e.text for e in root.iter() if e.tag is ElementTree.Comment)
    return depends, comments


def test_package_xml_declares_every_import_of_the_package_and_the_launch_file():
    depends, comments = _package_xml()
    run = depends.get('exec_depend', set()) | depends.get('depend', set())
    pip_line = re.search(r'pip:([^\n]*)', comments)
    pip_named = set(pip_line.group(1).split()) if pip_line else set()
    imports = _top_level_imports(REPO / PACKAGE, REPO / 'launch')
    missing = []
    for module, where in sorted(imports.items()):
        if module in sys.stdlib_module_names or module == PACKAGE:
            continue
        if module in PYTHON_KEYS and PYTHON_KEYS[module] is None:
            if PIP_NAMES.get(module, module) not in pip_named:
                missing.append(f'{module} ({where}): name it on package.xml\'s "pip:" line')
        elif PYTHON_KEYS.get(module, module) not in run:
            key = PYTHON_KEYS.get(module, module)
            missing.append(
                f'{module} ({where}): <exec_depend>{key}</exec_depend> (a ROS '
                'package; a pure-Python one: add it to PYTHON_KEYS here)'
            )
    assert missing == []
    assert {'launch', 'launch_ros', 'lifecycle_msgs'} <= run


def test_package_xml_declares_every_package_the_launch_file_runs(launch):
    depends, _ = _package_xml()
    run = depends.get('exec_depend', set()) | depends.get('depend', set())
    launched = launch(mode='sim')
    packages = {node.package for node in [*launched.nodes, *launched.plain_nodes]}
    assert packages == {PACKAGE, 'tf2_ros'}
    assert sorted(packages - {PACKAGE} - run) == []


def test_package_xml_test_depends_on_pytest_and_pytest_timeout():
    depends, _ = _package_xml()
    assert {'python3-pytest', 'python3-pytest-timeout'} <= depends.get('test_depend', set())
    assert re.search(r'^timeout\s*=', (REPO / 'pytest.ini').read_text(), re.MULTILINE)
