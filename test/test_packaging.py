"""The packaging the launch file and ``ros2 run`` rely on: the two ROS packages colcon finds
in the checkout, setup.py (console scripts, data files, read with ast, never run), setup.cfg,
package.xml, and the launch file read as text (its node executables, the packages it runs,
its arguments against docs/ros.md).

The launch file itself runs under the real ``ros2 launch`` in scripts/realros/run.sh (the
unit suite has no launch/launch_ros): every node active, arguments, refusals, a replay.
"""

from __future__ import annotations

import ast
import configparser
import os
import re
import sys
import xml.etree.ElementTree as ElementTree
from glob import glob
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / 'launch' / 'tetra_gradiometer.launch.py'
PACKAGE = 'tetra_gradiometer'
#: The ROS package's description (package.xml, setup.py, setup.cfg); its data are links.
ROS_PACKAGE = REPO / 'ros' / PACKAGE
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


# --------------------------------------------------------------------------- the layout


def _colcon_packages(root: Path) -> dict[str, str]:
    """Folder (relative to ``root``) -> package name of the packages colcon's recursive crawl
    finds: a folder with package.xml (or setup.py) is a package and is not descended into;
    links are followed, dot folders and the git-ignored build outputs skipped."""
    ignored = {'build', 'install', 'log', 'out', 'mutants'}
    found = {}
    for folder, subfolders, files in os.walk(root, followlinks=True):
        if 'package.xml' in files or 'setup.py' in files:
            name = ElementTree.parse(Path(folder) / 'package.xml').getroot().findtext('name')
            found[str(Path(folder).relative_to(root))] = name
            subfolders[:] = []
        subfolders[:] = [f for f in subfolders if not f.startswith('.') and f not in ignored]
    return found


def test_colcon_finds_the_python_package_and_its_interfaces_side_by_side():
    """A ``colcon build`` over the checkout builds both: neither package lies inside the other
    (colcon does not look inside a package)."""
    assert _colcon_packages(REPO) == {
        f'ros/{PACKAGE}': PACKAGE, 'tetra_gradiometer_msgs': 'tetra_gradiometer_msgs'}
    linked = {p.name: p.resolve() for p in ROS_PACKAGE.iterdir() if p.is_symlink()}
    assert linked[PACKAGE] == REPO / PACKAGE                     # the module colcon installs
    modules = (REPO / PACKAGE).rglob('__init__.py')
    assert _setup_argument('packages') == sorted(
        '.'.join(p.parent.relative_to(REPO).parts) for p in modules)


# --------------------------------------------------------------------------- setup.py


def _setup_call() -> tuple[ast.Call, dict[str, Any]]:
    tree = ast.parse((ROS_PACKAGE / 'setup.py').read_text(encoding='utf-8'))
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
    and ``glob('pattern')`` (run in the package's folder, as colcon runs setup.py)."""
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
        return sorted(glob(_evaluate(node.args[0], names), root_dir=ROS_PACKAGE))
    if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'find_packages':
        from setuptools import find_packages

        options = {k.arg: _evaluate(k.value, names) for k in node.keywords}
        return sorted(find_packages(str(ROS_PACKAGE), **options))
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


# --------------------------------------------------------------------------- the launch file


def _launch_tree() -> ast.Module:
    return ast.parse(LAUNCH_FILE.read_text(encoding='utf-8'))


def _launch_constant(name: str) -> Any:
    """A module-level constant of the launch file (a literal)."""
    for statement in _launch_tree().body:
        if isinstance(statement, ast.Assign) and [t.id for t in statement.targets] == [name]:
            return ast.literal_eval(statement.value)
    raise AssertionError(f'{LAUNCH_FILE.name}: no constant {name}')


def launched_packages() -> set[str]:
    """The ``package=`` of every node the launch file starts (literals or its constants)."""
    out = set()
    for node in ast.walk(_launch_tree()):
        for keyword in getattr(node, 'keywords', []) if isinstance(node, ast.Call) else []:
            if keyword.arg == 'package':
                value = keyword.value
                out.add(_launch_constant(value.id) if isinstance(value, ast.Name) else value.value)
    return out


def declared_arguments() -> set[str]:
    """The launch arguments: ARGUMENTS' literal keys and the ``<topic>_topic`` of REMAPPED."""
    text = LAUNCH_FILE.read_text(encoding='utf-8')
    block = text.split('ARGUMENTS = {', 1)[1].split('\n}\n', 1)[0]
    names = set(re.findall(r"^    '(\w+)': \(", block, re.MULTILINE))
    return names | {f'{topic}_topic' for topic in _launch_constant('REMAPPED')}


# --------------------------------------------------------------------------- packaging


def test_every_executable_launched_is_a_console_script_with_a_main():
    scripts = console_scripts()
    executables = set(_launch_constant('NODES'))
    assert _launch_constant('NODES') == ORDER_WITH_TARGET  # bringup's order, the driver last
    assert launched_packages() == {PACKAGE, 'tf2_ros'}  # tf2_ros: static_transform_publisher
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


def test_the_launch_arguments_are_the_documented_ones():
    text = (REPO / 'docs' / 'ros.md').read_text(encoding='utf-8')
    table = text.split('## Launch', 1)[1].split('\n\n| argument |', 1)[1].split('\n\n', 1)[0]
    documented = {
        name
        for row in table.splitlines()[2:]
        for name in re.findall(r'`(\w+)`', row.split('|')[1])
    }
    assert documented == declared_arguments()


def test_the_package_name_agrees_everywhere():
    name = ElementTree.parse(ROS_PACKAGE / 'package.xml').getroot().findtext('name')
    assert _setup_argument('name') == name == _launch_constant('PACKAGE') == PACKAGE
    assert (ROS_PACKAGE / 'resource' / PACKAGE).is_file()
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
    config.read(ROS_PACKAGE / 'setup.cfg')
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
        ROS_PACKAGE / 'package.xml',
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


def test_package_xml_declares_every_package_the_launch_file_runs():
    depends, _ = _package_xml()
    run = depends.get('exec_depend', set()) | depends.get('depend', set())
    assert sorted(launched_packages() - {PACKAGE} - run) == []


def test_package_xml_test_depends_on_pytest_and_pytest_timeout():
    depends, _ = _package_xml()
    assert {'python3-pytest', 'python3-pytest-timeout'} <= depends.get('test_depend', set())
    assert re.search(r'^timeout\s*=', (REPO / 'pytest.ini').read_text(), re.MULTILINE)
