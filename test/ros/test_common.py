"""nodes/common.py: declared parameters. The node modules' ``PARAMETERS`` lists are the single
source of truth: config/tetra_gradiometer.yaml and the table in docs/ros.md must agree with
them (no ROS graph needed: the lists are read by import), and bad values are refused at
start with the reason: in this process, as nodes/process.spin_node starts a node (the
arguments ``python -m tetra_gradiometer node`` gives rclpy, the node's constructor, the
check of its overrides), and one of each kind as a process (exit 1, one line, no traceback)."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest
import yaml
from ros_helpers import PARAMS, REPO, NodeProcess, ros_value, unique_domain




def _declared() -> dict[str, dict[str, object]]:
    """``{node: {parameter: default}}`` from the nodes' PARAMETERS lists and the lifecycle
    base's ``autostart`` (every node declares it)."""
    from tetra_gradiometer.nodes import calibrator, compensator, driver, target, tensor
    from tetra_gradiometer.nodes.managed import AUTOSTART_SPEC

    return {module.__name__.rsplit('.', 1)[1]:
            {spec.name: spec.default for spec in [*module.PARAMETERS, AUTOSTART_SPEC]}
            for module in (driver, tensor, calibrator, compensator, target)}


def _same(value: object, default: object) -> bool:
    """Equal and of the ROS type the default fixes (1 is not 1.0 for a double parameter)."""
    if isinstance(default, (list, tuple)):
        return (isinstance(value, list) and len(value) == len(default)
                and all(type(v) is type(d) and v == d for v, d in zip(value, default)))
    return type(value) is type(default) and value == default


def _yaml_parameters() -> dict[str, object]:
    document = yaml.safe_load((REPO / 'config' / 'tetra_gradiometer.yaml').read_text())
    return document['/**']['ros__parameters']


def _docs_parameters() -> set[str]:
    """The names in the parameter column of the table under '## Parameters' in docs/ros.md."""
    text = (REPO / 'docs' / 'ros.md').read_text()
    section = text.split('\n## Parameters\n', 1)[1].split('\n## ', 1)[0]
    rows = [line.split('|') for line in section.splitlines() if line.startswith('|')]
    return {name for row in rows[2:] for name in re.findall(r'`([a-z0-9_]+)`', row[2])}


def test_the_declarations_of_a_shared_name_agree_between_nodes():
    # One `/**` YAML section feeds every node: a name two nodes declare needs one default.
    seen: dict[str, tuple[str, object]] = {}
    for node, parameters in _declared().items():
        for name, default in parameters.items():
            if name in seen:
                other, other_default = seen[name]
                assert _same(list(default) if isinstance(default, tuple) else default, other_default), (
                    f'{name}: {node} declares {default!r}, {other} {other_default!r}')
            seen[name] = (node, default)


def test_every_declared_parameter_is_in_the_yaml_with_its_default_and_nothing_else_is():
    yaml_parameters = _yaml_parameters()
    declared = _declared()
    wrong = {f'{node}.{name}': (default, yaml_parameters.get(name, '<missing>'))
             for node, parameters in declared.items() for name, default in parameters.items()
             if not _same(yaml_parameters.get(name), default)}
    assert wrong == {}, f'config/tetra_gradiometer.yaml differs from the declarations (declared, yaml): {wrong}'
    every = set().union(*declared.values())
    assert set(yaml_parameters) - every == set(), 'YAML keys no node declares'
    assert 'earth_field_enu' in every  # the calibrator's; simulate and discrepancy read it too


def test_the_docs_table_names_every_declared_parameter_and_no_other():
    every = set().union(*_declared().values())
    documented = _docs_parameters()
    assert len(documented) > 20  # the table was found and parsed
    assert documented - every == set(), 'docs/ros.md documents parameters no node declares'
    assert every - documented == set(), (
        f'docs/ros.md lacks these declared parameters: {sorted(every - documented)}')


def _assert_one_line_refusal(code, output, *expected):
    """Exit 1, no traceback, exactly one 'cannot start:' line holding every ``expected`` text."""
    assert code == 1, output
    assert 'Traceback' not in output, output
    lines = [line for line in output.splitlines() if 'cannot start:' in line]
    assert len(lines) == 1, output
    for text in expected:
        assert text in lines[0], lines[0]


def _refusal(name: str, params: dict | None = None, params_file=PARAMS) -> str | None:
    """Why the node ``name`` refuses to start with ``params`` (``-p`` overrides) and
    ``params_file``, or None: nodes/process.spin_node's steps in this process, each in a
    context of its own (rclpy's arguments, the constructor, the overrides' check)."""
    import rclpy
    from rclpy.exceptions import ParameterException

    from tetra_gradiometer.cli.node import ros_arguments
    from tetra_gradiometer.errors import TetraError
    from tetra_gradiometer.nodes.calibrator import CalibratorNode
    from tetra_gradiometer.nodes.compensator import CompensatorNode
    from tetra_gradiometer.nodes.driver import DriverNode
    from tetra_gradiometer.nodes.process import _rcl_reason, _start_refusal
    from tetra_gradiometer.nodes.target import TargetNode
    from tetra_gradiometer.nodes.tensor import TensorNode

    node_class = {'driver': DriverNode, 'tensor': TensorNode, 'calibrator': CalibratorNode,
                  'compensator': CompensatorNode, 'target': TargetNode}[name]

    extra = [item for key, value in (params or {}).items() for item in ('-p', f'{key}:={ros_value(value)}')]
    args = ros_arguments(str(params_file), extra)
    context = rclpy.Context()
    try:
        rclpy.init(args=args, context=context, domain_id=unique_domain())
    except RuntimeError as error:
        return _rcl_reason(error)
    try:
        try:
            node = node_class(context=context)
        except (TetraError, ParameterException) as error:
            return str(error)
        try:
            return _start_refusal(node, args)
        finally:
            node.destroy_node()
    finally:
        context.try_shutdown()


def _assert_refused(reason: str | None, *expected: str) -> None:
    """One line holding every ``expected`` text."""
    assert reason is not None and '\n' not in reason, reason
    for text in expected:
        assert text in reason, reason


@pytest.mark.parametrize('name, params, expected', [
    ('tensor', {'sensor_positions': [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0]}, ['coplanar']),
    ('tensor', {'stamp_tolerance_s': -1.0}, ["'stamp_tolerance_s' = -1.0", '[1e-06, 1]']),
    ('calibrator', {'method': 'simplex'}, ["'method' = 'simplex'", 'must be one of']),
    ('driver', {'mode': 'replay', 'bag': '/nonexistent/bag'}, ['bag not found']),
    ('driver', {'mode': 'simulated'}, ["'mode' = 'simulated'", "must be 'sim' or 'replay'"]),
    # Out of the physical range (was accepted up to 1e6 generations: minutes of a blocked node).
    ('calibrator', {'ga_generations': 0}, ["'ga_generations' = 0", '[1, 20000]']),
    ('calibrator', {'ga_generations': 1_000_000}, ["'ga_generations' = 1000000", '[1, 20000]']),
    ('tensor', {'max_field_t': 0.01}, ["'max_field_t' = 0.01", '[0.0001, 0.001]']),
    ('compensator', {'max_pending': 0}, ["'max_pending' = 0", '[1, 100000]']),
    ('compensator', {'sensor_noise_t': 1e-3}, ["'sensor_noise_t' = 0.001", '[0, 1e-06]']),
    ('target', {'history_s': 10.0}, ["'history_s' = 10.0", '[60, 14400]']),
    ('driver', {'sensor_noise_t': -1e-10}, ["'sensor_noise_t' = -1e-10", '[0, 1e-06]']),
    ('driver', {'rate': 5000.0}, ["'rate' = 5000.0", '[0, 1000]']),
    ('calibrator', {'max_solve_s': 0.0}, ["'max_solve_s' = 0.0", '[0.1, 600]']),
    ('calibrator', {'min_samples': 1000, 'max_samples': 500}, ["'min_samples' = 1000", 'max_samples (500)']),
    # Wrong type: a string, a double for an integer (over the params file's integer, which rcl
    # would otherwise keep silently), an integer for a double (ROS refuses it too).
    ('calibrator', {'ga_generations': 'abc'}, ["'ga_generations' = 'abc'", 'a string', 'an integer', '[1, 20000]']),
    ('calibrator', {'ga_generations': '5.0'}, ["'ga_generations' = 5.0", 'a double', 'an integer']),
    ('driver', {'rate': 10}, ["'rate' = 10", 'an integer', 'a double', 'decimal point']),
    # A name the node does not declare (a typo), also one another node declares.
    ('driver', {'mode': 'sim', 'rat': 10.0}, ["unknown parameter 'rat'", 'declared:', 'rate']),
    ('driver', {'mode': 'sim', 'max_pending': 10}, ["unknown parameter 'max_pending'", 'declared:']),
])
def test_bad_parameters_are_refused_at_start_with_one_line(name, params, expected):
    _assert_refused(_refusal(name, params), *expected)


@pytest.mark.parametrize('name, document, expected', [
    ('calibrator', {'/**': {'ros__parameters': {'ga_generations': 1_000_000}}}, ["'ga_generations' = 1000000", '[1, 20000]']),
    ('tensor', {'/**': {'ros__parameters': {'max_pending': 'many'}}}, ["'max_pending' = 'many'", 'a string']),
    ('driver', {'/**': {'ros__parameters': {'mode': 'sim', 'rat': 10.0, 'earth_field_enu': [0.0, 2e-5, -4.5e-5]}}},
     ["unknown parameter 'rat'"]),
    ('compensator', {'/tetra/compensator': {'ros__parameters': {'max_pendng': 10}}}, ["unknown parameter 'max_pendng'"]),
    # A section rcl would ignore: the node's name misspelt, or under another namespace.
    ('compensator', {'/tetra/compenstor': {'ros__parameters': {'max_pending': 10}}},
     ['no section for /tetra/compensator', "is '/tetra/compenstor' meant to be '/tetra/compensator'?"]),
    ('tensor', {'/auv1/tensor': {'ros__parameters': {'max_pending': 10}}},
     ['no section for /tetra/tensor', "is '/auv1/tensor' meant to be '/tetra/tensor'?"]),
])
def test_bad_parameters_in_a_params_file_are_refused_at_start_with_one_line(tmp_path, name, document, expected):
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump(document))
    _assert_refused(_refusal(name, params_file=params_file), *expected)


def test_entries_for_other_nodes_and_rclpy_builtins_are_not_refused(tmp_path):
    """A section addressed to another node (a typo and a bad value there are that node's
    business), another node's names in /** and rclpy's use_sim_time start the node."""
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump({
        '/**': {'ros__parameters': {'stamp_tolerance_s': 0.002, 'earth_field_enu': [0.0, 2e-5, -4.5e-5]}},
        '/tetra/tensor': {'ros__parameters': {'rat': 1.0, 'max_pending': 0}},
    }))
    assert _refusal('compensator', {'use_sim_time': False}, params_file=params_file) is None


@pytest.mark.parametrize('name, params, params_file, expected', [
    ('tensor', {'stamp_tolerance_s': -1.0}, None, ["'stamp_tolerance_s' = -1.0", '[1e-06, 1]']),
    ('driver', {'rate': 10}, None, ["'rate' = 10", 'an integer', 'a double', 'decimal point']),
    ('driver', {'mode': 'sim', 'rat': 10.0}, None, ["unknown parameter 'rat'", 'declared:', 'rate']),
    ('compensator', None, {'/tetra/compenstor': {'ros__parameters': {'max_pending': 10}}},
     ['no section for /tetra/compensator', "is '/tetra/compenstor' meant to be '/tetra/compensator'?"]),
])
def test_a_node_process_refusing_its_parameters_exits_1_with_one_line(tmp_path, name, params, params_file, expected):
    """As a user meets them: one of each kind (range, type, an undeclared name, a misnamed
    section of the params file) as the process ``python -m tetra_gradiometer node``."""
    path = PARAMS
    if params_file is not None:
        path = tmp_path / 'params.yaml'
        path.write_text(yaml.safe_dump(params_file))
    code, output = NodeProcess(name, unique_domain(), params, params_file=path).refusal()
    _assert_one_line_refusal(code, output, *expected)


def test_a_missing_params_file_is_one_error_line(tmp_path):
    result = subprocess.run([sys.executable, '-m', 'tetra_gradiometer', 'node', 'tensor', '--params',
                             str(tmp_path / 'missing.yaml')], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert 'Traceback' not in result.stderr
    assert result.stderr.strip().splitlines() == [f'error: --params {tmp_path / "missing.yaml"}: no such file']
