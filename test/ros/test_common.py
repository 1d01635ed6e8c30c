"""nodes/common.py: declared parameters. The node modules' ``PARAMETERS`` lists are the single
source of truth: config/tetra_gradiometer.yaml and the table in docs/ros.md must agree with
them (no ROS graph needed: the lists are read by import), and bad values are refused at
start with the reason (nodes as processes)."""
from __future__ import annotations

import re

import pytest
import yaml
from ros_helpers import REPO, NodeProcess, unique_domain

#: Read by the offline tools only (simulate, discrepancy), not declared by any node.
OFFLINE_ONLY = {'earth_field_enu'}



def _declared() -> dict[str, dict[str, object]]:
    """``{node: {parameter: default}}`` from the nodes' PARAMETERS lists."""
    from tetra_gradiometer.nodes import calibrator, compensator, driver, tensor

    return {module.__name__.rsplit('.', 1)[1]: {spec.name: spec.default for spec in module.PARAMETERS}
            for module in (driver, tensor, calibrator, compensator)}


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
    assert set(yaml_parameters) - every - OFFLINE_ONLY == set(), 'YAML keys no node declares'
    assert OFFLINE_ONLY <= set(yaml_parameters)


def test_the_docs_table_names_every_declared_parameter_and_no_other():
    every = set().union(*_declared().values())
    documented = _docs_parameters()
    assert len(documented) > 20  # the table was found and parsed
    assert documented - every == set(), 'docs/ros.md documents parameters no node declares'
    assert every - documented == set(), (
        f'docs/ros.md lacks these declared parameters: {sorted(every - documented)}')


@pytest.mark.parametrize('name, params, expected', [
    ('tensor', {'sensor_positions': [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0]}, 'coplanar'),
    ('tensor', {'stamp_tolerance_s': -1.0}, 'stamp_tolerance_s'),
    ('calibrator', {'method': 'simplex'}, 'must be one of'),
    ('driver', {'mode': 'replay', 'bag': '/nonexistent/bag'}, 'bag not found'),
])
def test_bad_parameters_are_refused_at_start_with_the_reason(name, params, expected):
    process = NodeProcess(name, unique_domain(), params)
    try:
        code = process.process.wait(timeout=30)
        output = process.output()
    finally:
        process.stop()
    assert code == 1, output
    assert expected in output
