"""The tetra_gradiometer graph as ``bringup`` starts it, one process per node.

``ros2 launch tetra_gradiometer tetra_gradiometer.launch.py [mode:=sim|replay] [bag:=PATH]
[params_file:=FILE] [namespace:=NS] [use_sim_time:=true|false] [nodes:=a,b,...]
[autostart:=true|false] [rate:=R] [scenario:=YAML] [calibration_file:=FILE]``
(``--show-args`` lists them with their defaults).

Nodes. The four managed (lifecycle) nodes ``tensor``, ``calibrator``, ``compensator`` and
``driver`` (the console scripts of the same names), or the subset named by ``nodes``, in the
namespace ``namespace`` (default ``tetra``: ``/tetra``, or ``/<pushed>/tetra`` when this
file is included under a ``PushROSNamespace``). Every node reads ``params_file`` (default:
the installed ``config/tetra_gradiometer.yaml``; ``''``: the declared defaults) and then
``use_sim_time``. As in ``bringup``, the driver takes ``mode``, ``bag`` (a bag without a
mode means replay), ``rate`` and ``scenario``, the calibrator and compensator take
``calibration_file``, relative paths are taken from the working directory, and the driver
waits for the tensor node's subscriptions (``min_subscribers`` 1) when both are launched.
An empty argument leaves the parameter to the params file.

Lifecycle. With ``autostart`` true (the default) each node is configured and then
activated, one after the other in ``bringup``'s order (tensor, calibrator, compensator,
driver): the next node is configured once the previous one is active, so the chain listens
before the driver publishes. This uses the standard launch_ros lifecycle events
(``ChangeState`` with ``lifecycle_msgs/Transition`` configure and activate, triggered by
``OnStateTransition``). A node that fails a transition stops the sequence there (launch_ros
logs the failure) and the nodes after it stay unconfigured. With ``autostart`` false every
node is left unconfigured for an external lifecycle manager. A node process that exits
ends the whole launch, as one failing node ends ``bringup``.

Static transforms: NOT YET (issue 14 continues). The intended design was the tensor node
publishing ``base_link`` -> ``tetra_mag1`` .. ``tetra_mag4`` on ``/tf_static`` from its
``sensor_positions``, but ``tf2_msgs`` has no wheel here (the node could not be tested);
the next step is one ``tf2_ros static_transform_publisher`` per sensor, its offset read
from the params file's ``sensor_positions``.

The launch arguments are read when the launch runs (an ``OpaqueFunction``), so a bad value is
refused with one message naming the argument before any node starts.
"""

import os

from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    LogInfo,
    OpaqueFunction,
    RegisterEventHandler,
    Shutdown,
)
from launch.events import matches_action
from launch.launch_description import LaunchDescription
from launch.substitutions import PathJoinSubstitution
from launch_ros.actions import LifecycleNode
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition

PACKAGE = 'tetra_gradiometer'

#: The nodes (executable = node name), in bringup's start order (cli/bringup.create_nodes):
#: the driver last, so the chain is active before the first set is published.
NODES = ('tensor', 'calibrator', 'compensator', 'driver')

MODES = ('sim', 'replay')

#: Boolean words, as launch's own conditions read them.
_TRUE = ('true', '1')
_FALSE = ('false', '0')

#: Launch arguments: name, default ('' = from the params file), description.
ARGUMENTS = (
    ('mode', '', 'driver mode: sim or replay ("": the params file\'s; a bag implies replay)'),
    ('bag', '', 'replay: rosbag2 folder, relative to the working directory'),
    (
        'params_file',
        PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'tetra_gradiometer.yaml']),
        'ROS 2 parameter file read by every node ("": the declared defaults)',
    ),
    ('namespace', 'tetra', 'namespace of the nodes and their topics'),
    ('use_sim_time', 'false', 'true or false, passed to every node'),
    ('nodes', ','.join(NODES), f'comma-separated subset of {", ".join(NODES)}'),
    (
        'autostart',
        'true',
        'true: configure and activate the nodes in order; false: leave them unconfigured '
        'for an external lifecycle manager',
    ),
    ('rate', '', 'driver speed, multiple of real time (0: as fast as the graph takes it)'),
    ('scenario', '', 'sim: scenario YAML, relative to the working directory'),
    ('calibration_file', '', 'calibration file of the calibrator and the compensator'),
)


def generate_launch_description():
    """The declared arguments, then the nodes built from their values at launch time."""
    declared = [
        DeclareLaunchArgument(name, default_value=default, description=description)
        for name, default, description in ARGUMENTS
    ]
    return LaunchDescription([*declared, OpaqueFunction(function=launch_setup)])


def launch_setup(context, *args, **kwargs):
    """The actions for the resolved launch arguments (``context.launch_configurations``).

    Raises
    ------
    ValueError
        When an argument has a value the graph cannot start with (the message names it).
    """
    values = context.launch_configurations
    names = selected_nodes(values['nodes'])
    autostart = as_bool('autostart', values['autostart'])
    # The nodes never configure themselves here: the sequence below (or a manager) does.
    common = {'use_sim_time': as_bool('use_sim_time', values['use_sim_time']), 'autostart': False}
    params_file = values['params_file']
    if params_file and not os.path.isfile(params_file):
        raise ValueError(f'params_file {params_file!r}: no such file')
    files = [params_file] if params_file else []
    nodes = {
        name: LifecycleNode(
            package=PACKAGE,
            executable=name,
            name=name,
            namespace=values['namespace'],
            parameters=[*files, {**common, **node_overrides(name, names, values)}],
            output='screen',
            on_exit=Shutdown(reason=f'{PACKAGE}: {name} exited'),
        )
        for name in names
    }
    if not autostart:
        return list(nodes.values())
    first = nodes[names[0]]
    return [*lifecycle_sequence(nodes), *nodes.values(), _change_state(first, 'configure')]


def selected_nodes(text):
    """The node names of the ``nodes`` argument, in start order (duplicates dropped)."""
    given = [name.strip() for name in text.split(',') if name.strip()]
    unknown = sorted(set(given) - set(NODES))
    if unknown or not given:
        what = f'unknown {", ".join(map(repr, unknown))}' if unknown else 'no node named'
        raise ValueError(f'nodes {text!r}: {what}; choose from {", ".join(NODES)}')
    return [name for name in NODES if name in given]


def as_bool(argument, text):
    """A boolean launch argument (``true``/``false``, ``1``/``0``, any case)."""
    word = text.strip().lower()
    if word not in _TRUE + _FALSE:
        raise ValueError(f'{argument} {text!r}: must be true or false')
    return word in _TRUE


def node_overrides(name, names, values):
    """Parameters of node ``name`` given by launch arguments (bringup's overrides)."""
    if name == 'driver':
        return _driver_overrides(names, values)
    if name in ('calibrator', 'compensator') and values['calibration_file']:
        return {'calibration_file': _path(values['calibration_file'])}
    return {}


def _driver_overrides(names, values):
    mode, bag = values['mode'], values['bag']
    if mode and mode not in MODES:
        raise ValueError(f'mode {mode!r}: must be one of {", ".join(MODES)}')
    out = {'min_subscribers': 1} if 'tensor' in names else {}
    if bag:
        out.update(bag=_path(bag), mode=mode or 'replay')
    elif mode:
        out['mode'] = mode
    if values['rate']:
        out['rate'] = _float('rate', values['rate'])
    if values['scenario']:
        out['scenario'] = _path(values['scenario'])
    return out


def _path(text):
    return os.path.abspath(os.path.expanduser(text))


def _float(argument, text):
    try:
        return float(text)  # a double parameter: the node refuses an integer
    except ValueError:
        raise ValueError(f'{argument} {text!r}: must be a number') from None


def lifecycle_sequence(nodes):
    """Event handlers that activate each node of ``nodes`` (name -> LifecycleNode, in start
    order) once configured, and configure the next one once it is active. Each fires once,
    and only on the transition out of ``configuring`` or ``activating``, so a later
    deactivate/activate by hand restarts nothing."""
    names = list(nodes)
    handlers = []
    for name, following in zip(names, [*names[1:], None], strict=True):
        handlers.append(
            _on_transition(
                nodes[name],
                'configuring',
                'inactive',
                f'{name} configured, activating it',
                _change_state(nodes[name], 'activate'),
            )
        )
        if following is not None:
            handlers.append(
                _on_transition(
                    nodes[name],
                    'activating',
                    'active',
                    f'{name} active, configuring {following}',
                    _change_state(nodes[following], 'configure'),
                )
            )
    return handlers


def _on_transition(node, start_state, goal_state, message, action):
    return RegisterEventHandler(
        OnStateTransition(
            target_lifecycle_node=node,
            start_state=start_state,
            goal_state=goal_state,
            entities=[LogInfo(msg=f'{PACKAGE}: {message}'), action],
            handle_once=True,
        )
    )


def _change_state(node, transition):
    transition_id = {
        'configure': Transition.TRANSITION_CONFIGURE,
        'activate': Transition.TRANSITION_ACTIVATE,
    }[transition]
    return EmitEvent(
        event=ChangeState(lifecycle_node_matcher=matches_action(node), transition_id=transition_id)
    )
