"""launch/tetra_gradiometer.launch.py, run against stand-ins for launch/launch_ros
(test/launch_standins.py), and the packaging it relies on: setup.py (console scripts, data
files, read with ast, never run), setup.cfg and package.xml.

Truth from outside the launch file: the console scripts and data files of setup.py, the
repository's files installed into a temporary share directory as setup.py lists them, the
imports of the package's source, the lifecycle state machine (launch_standins.Launch), and
bringup's start order (tensor, calibrator, compensator, driver: cli/bringup.create_nodes).
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

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / 'launch' / 'tetra_gradiometer.launch.py'
PACKAGE = 'tetra_gradiometer'
#: bringup's order (cli/bringup.create_nodes): the driver last.
ORDER = ('tensor', 'calibrator', 'compensator', 'driver')
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
        return runner.run(module.generate_launch_description())

    return run


def _chain(names: list[str]) -> list[tuple[str, str]]:
    return [(name, step) for name in names for step in ('configure', 'activate')]


def test_default_starts_the_four_nodes_and_activates_them_one_after_the_other(launch, share):
    run = launch()
    assert [node.name for node in run.nodes] == list(ORDER)
    for node in run.nodes:
        assert (node.package, node.executable, node.namespace) == (PACKAGE, node.name, 'tetra')
        assert node.output == 'screen'
        assert isinstance(node.on_exit, standins.Shutdown)
        params_file, overrides = node.parameters
        assert params_file == str(share / 'config' / 'tetra_gradiometer.yaml')
        expected = {'use_sim_time': False, 'autostart': False}  # the sequence configures them
        if node.name == 'driver':  # bringup: wait for the tensor node's subscriptions
            expected['min_subscribers'] = 1
        assert overrides == expected
    assert run.requests == _chain(list(ORDER))
    assert run.state == dict.fromkeys(ORDER, 'active')
    assert run.refused == []


def test_every_argument_read_is_declared_and_every_declared_one_is_read(launch):
    run = launch()
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
    run = launch(nodes=nodes)
    assert [node.name for node in run.nodes] == expected
    assert run.requests == _chain(expected)
    assert run.state == dict.fromkeys(expected, 'active')
    if 'driver' in expected:
        waits = run.node('driver').parameters[-1].get('min_subscribers')
        assert waits == (1 if 'tensor' in expected else None)


def test_autostart_false_leaves_every_node_unconfigured(launch):
    run = launch(autostart='False')
    assert [node.name for node in run.nodes] == list(ORDER)
    assert run.requests == []
    assert run.state == dict.fromkeys(ORDER, 'unconfigured')
    assert not [a for a in run.actions if isinstance(a, standins.RegisterEventHandler)]


def test_a_later_manual_deactivate_and_activate_restarts_nothing(launch):
    from lifecycle_msgs.msg import Transition

    run = launch()
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
    run = launch(use_sim_time=word)
    assert [node.parameters[-1]['use_sim_time'] for node in run.nodes] == [value] * 4


@pytest.mark.parametrize(
    'arguments, driver',
    [
        ({'bag': 'bags/survey'}, {'mode': 'replay', 'bag': str(REPO / 'bags' / 'survey')}),
        ({'bag': 'bags/survey', 'mode': 'sim'}, {'mode': 'sim', 'bag': str(REPO / 'bags/survey')}),
        ({'mode': 'replay'}, {'mode': 'replay'}),
        ({'mode': 'sim', 'rate': '0'}, {'mode': 'sim', 'rate': 0.0}),
        ({'scenario': 'scenarios/x.yaml'}, {'scenario': str(REPO / 'scenarios' / 'x.yaml')}),
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


def test_calibration_file_goes_to_calibrator_and_compensator_only(launch):
    run = launch(calibration_file='~/cal.yaml', nodes='calibrator,compensator,tensor')
    path = str(Path('~/cal.yaml').expanduser())
    assert run.node('calibrator').parameters[-1]['calibration_file'] == path
    assert run.node('compensator').parameters[-1]['calibration_file'] == path
    assert 'calibration_file' not in run.node('tensor').parameters[-1]


def test_namespace_and_an_empty_params_file(launch):
    run = launch(namespace='robot1/tetra', params_file='')
    assert {node.namespace for node in run.nodes} == {'robot1/tetra'}
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
        launch(**arguments)


# --------------------------------------------------------------------------- packaging


def test_every_executable_launched_is_a_console_script_with_a_main(launch):
    scripts = console_scripts()
    executables = {node.executable for node in launch().nodes}
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
    assert {node.package for node in launch().nodes} == {PACKAGE}
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


def test_package_xml_test_depends_on_pytest_and_pytest_timeout():
    depends, _ = _package_xml()
    assert {'python3-pytest', 'python3-pytest-timeout'} <= depends.get('test_depend', set())
    assert re.search(r'^timeout\s*=', (REPO / 'pytest.ini').read_text(), re.MULTILINE)
