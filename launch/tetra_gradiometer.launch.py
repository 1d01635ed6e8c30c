"""The tetra_gradiometer graph as ``bringup`` starts it, one process per node.

``ros2 launch tetra_gradiometer tetra_gradiometer.launch.py [mode:=sim|replay] [bag:=PATH]
[params_file:=FILE] [namespace:=NS] [use_sim_time:=true|false] [nodes:=a,b,...]
[autostart:=true|false] [static_transforms:=true|false] [rate:=R] [scenario:=YAML]
[calibration_file:=FILE] [enclaves:=true|false]`` (``--show-args`` lists them with their
defaults).

Nodes. The four managed (lifecycle) nodes ``tensor``, ``calibrator``, ``compensator`` and
``driver`` (the console scripts of the same names), or the subset named by ``nodes``, which
may also name the ``target`` node (not started by default: a search takes a core for tens of
seconds on an hour of survey), in the namespace ``namespace`` (default ``tetra``:
``/tetra``, or ``/<pushed>/tetra`` when this file is included under a ``PushROSNamespace``).
Every node reads ``params_file`` (default: the installed ``config/tetra_gradiometer.yaml``;
``''``: the declared defaults) and then ``use_sim_time``. As in ``bringup``, the driver
takes ``mode``, ``bag`` (a bag without a mode means replay; a driver with neither, here or
in the params file, is refused: it fabricates no vehicle data by default), ``rate`` and
``scenario``, the calibrator and compensator take ``calibration_file``, relative paths are
taken from the working directory, and the driver waits for the tensor node's subscriptions
(``min_subscribers`` 1) when both are launched.
An empty argument leaves the parameter to the params file.

Lifecycle. With ``autostart`` true (the default) each node is configured and then activated,
one after the other in ``bringup``'s order (tensor, calibrator, compensator, the target node
when named, driver): the next node is configured once the previous one is active, so the
chain listens before the driver publishes. This uses the standard launch_ros lifecycle
events (``ChangeState`` with ``lifecycle_msgs/Transition`` configure and activate, triggered
by ``OnStateTransition``). A node that fails a transition stops the sequence there
(launch_ros logs the failure) and the nodes after it stay unconfigured. With ``autostart``
false every node is left unconfigured for an external lifecycle manager. A node process that
exits ends the whole launch, as one failing node ends ``bringup``, with one ``Shutdown``
(:func:`end_launch_once`): Ctrl-C, or a node that exits, stops the launch with exit code 0.

Static transforms (REP 105). With ``static_transforms`` true (the default) one
``tf2_ros static_transform_publisher`` per child of the body frame publishes on the absolute
``/tf_static``: ``base_frame_id`` -> ``sensor_frame_ids[i]`` at sensor i's position
(``sensor_positions[3i:3i+3]``, metres, REP 103 body axes) and ``base_frame_id`` ->
``array_frame_id`` (the gradient tensors' frame) at the centroid of the four positions, all
with the identity rotation (the sensors' and the tensor's axes are the body axes). Their
names are ``tetra_tf_mag1`` .. ``tetra_tf_mag4`` and ``tetra_tf_array``, in the nodes'
namespace. They are plain nodes: started whatever ``nodes`` names, outside the lifecycle
sequence, and one that exits does not end the launch. The values are those of
``params_file``, read as the nodes read it: the ``ros__parameters`` of every section whose
node name matches the node's fully qualified name ``/<namespace>/<node>`` (``/**``,
``/**/tensor``, ``/tetra/tensor``, nested ``tetra: tensor:``; ``/*`` is one name, ``/**``
any number; a later section overrides an earlier one), ``sensor_positions`` and
``array_frame_id`` as the tensor node reads them, ``base_frame_id`` and
``sensor_frame_ids`` as the driver does. A section naming the full path of a namespace
pushed from outside this file (``/robot1/tetra/tensor`` under ``PushROSNamespace('robot1')``)
is not seen: use ``/**`` or ``/**/tensor`` there. A key no section sets, or ``params_file``
``''``, takes the package's declared default. A file that is not a ROS 2 parameter file,
positions that are not 12 finite numbers, or frame ids that are not non-empty strings
without a leading ``/`` are refused (the message names the file and the key). With
``static_transforms`` false nothing is published: the vehicle's URDF
(robot_state_publisher) provides these frames. ``odom`` -> ``base_link`` is the vehicle
navigation's; the driver only publishes ``/odom`` messages, no transform.

SROS2 (docs/ros.md, *Security*). With ``enclaves`` true every node gets ``--enclave
/tetra_gradiometer/<node>`` (the static transform publishers ``/tetra_gradiometer/
static_transforms``), the enclaves of the installed ``security/policy.xml``; whether DDS
security is enforced is the environment's (``ROS_SECURITY_KEYSTORE``,
``ROS_SECURITY_ENABLE``, ``ROS_SECURITY_STRATEGY=Enforce``).

The launch arguments are read when the launch runs (an ``OpaqueFunction``), so a bad value is
refused with one message naming the argument before any node starts.
"""

import math
import os
import re

import yaml
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
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition

from tetra_gradiometer.io.conversions import ARRAY_FRAME, BASE_FRAME, MAG_FRAMES
from tetra_gradiometer.nodes.common import DEFAULT_POSITIONS, frame_ids

PACKAGE = 'tetra_gradiometer'

#: The nodes (executable = node name), in bringup's start order (cli/bringup.create_nodes;
#: the target node, which bringup does not start, before the driver): the driver last, so the
#: chain is active before the first set is published.
NODES = ('tensor', 'calibrator', 'compensator', 'target', 'driver')
#: The nodes started when ``nodes`` is not given: bringup's four.
DEFAULT_NODES = ('tensor', 'calibrator', 'compensator', 'driver')

MODES = ('sim', 'replay')

#: The static transform publishers: node name suffix of each child of the body frame.
TRANSFORMS = ('mag1', 'mag2', 'mag3', 'mag4', 'array')

#: Boolean words, as launch's own conditions read them.
_TRUE = ('true', '1')
_FALSE = ('false', '0')

#: Launch arguments: name, default ('' = from the params file), description.
ARGUMENTS = (
    (
        'mode',
        '',
        'driver source: sim or replay ("": the params file\'s, which has none; a bag implies '
        'replay; a driver without a source is refused)',
    ),
    ('bag', '', 'replay: rosbag2 folder, relative to the working directory'),
    (
        'params_file',
        PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'tetra_gradiometer.yaml']),
        'ROS 2 parameter file read by every node ("": the declared defaults)',
    ),
    ('namespace', 'tetra', 'namespace of the nodes and their topics'),
    ('use_sim_time', 'false', 'true or false, passed to every node'),
    ('nodes', ','.join(DEFAULT_NODES), f'comma-separated subset of {", ".join(NODES)}'),
    (
        'autostart',
        'true',
        'true: configure and activate the nodes in order; false: leave them unconfigured '
        'for an external lifecycle manager',
    ),
    (
        'static_transforms',
        'true',
        'true: publish base_link -> tetra_mag1..4 and tetra_array on /tf_static from the params '
        "file (tf2_ros static_transform_publisher); false: leave them to the vehicle's URDF",
    ),
    ('rate', '', 'driver speed, multiple of real time (0: as fast as the graph takes it)'),
    ('scenario', '', 'sim: scenario YAML, relative to the working directory'),
    ('calibration_file', '', 'calibration file of the calibrator and the compensator'),
    (
        'enclaves',
        'false',
        'true: run each node in its SROS2 enclave /tetra_gradiometer/<node> (security/policy.xml; '
        'enforcement needs a keystore and a security-enabled DDS)',
    ),
)

#: The SROS2 enclaves (security/policy.xml): ``/tetra_gradiometer/<node>``, and one for the
#: static transform publishers.
ENCLAVE_ROOT = '/tetra_gradiometer'
TRANSFORMS_ENCLAVE = f'{ENCLAVE_ROOT}/static_transforms'


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
    use_sim_time = as_bool('use_sim_time', values['use_sim_time'])
    enclaves = as_bool('enclaves', values['enclaves'])
    # The nodes never configure themselves here: the sequence below (or a manager) does.
    common = {'use_sim_time': use_sim_time, 'autostart': False}
    params_file = values['params_file']
    if params_file and not os.path.isfile(params_file):
        raise ValueError(f'params_file {params_file!r}: no such file')
    files = [params_file] if params_file else []
    if 'driver' in names:
        _require_source(values, params_file)
    publishers = []
    if as_bool('static_transforms', values['static_transforms']):
        frames = static_frames(params_file, values['namespace'])
        publishers = [
            _transform_publisher(suffix, frame, values['namespace'], use_sim_time, enclaves)
            for suffix, frame in zip(TRANSFORMS, frames, strict=True)
        ]
    end_launch = end_launch_once()
    nodes = {
        name: LifecycleNode(
            package=PACKAGE,
            executable=name,
            name=name,
            namespace=values['namespace'],
            parameters=[*files, {**common, **node_overrides(name, names, values)}],
            output='screen',
            on_exit=end_launch,
            **enclave_arguments(f'{ENCLAVE_ROOT}/{name}', enclaves),
        )
        for name in names
    }
    if not autostart:
        return [*publishers, *nodes.values()]
    first = nodes[names[0]]
    return [
        *publishers,
        *lifecycle_sequence(nodes),
        *nodes.values(),
        _change_state(first, 'configure'),
    ]


def end_launch_once():
    """The ``on_exit`` of every node: the first node process to exit ends the launch with one
    ``Shutdown``; later exits (the other nodes stopping, or every node after Ctrl-C) send
    none. launch_ros shuts its ROS adapter down on each ``Shutdown`` event and raises on the
    second ("Cannot shutdown a ROS adapter that is not running"), which made every stop
    exit 1 with one ``[ERROR]`` line per node. One closure per launch, shared by its nodes.
    """
    sent = []

    def on_exit(event, context):
        if sent or context.is_shutdown:
            return None
        sent.append(event.process_name)
        return [Shutdown(reason=f'{PACKAGE}: {event.process_name} exited')]

    return on_exit


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


def _require_source(values, params_file):
    """Refuse a driver with no source: it fabricates no vehicle data by default
    (nodes/driver.py), so ``mode`` comes from an argument, a ``bag`` or the params file."""
    if values['mode'] or values['bag']:
        return
    driver = _node_parameters(parameter_sections(params_file), values['namespace'], 'driver')
    if not driver.get('mode'):
        raise ValueError(
            'the driver needs a source: mode:=sim (simulated vehicle data) or bag:=PATH '
            '(replay); on a vehicle, launch the others on the real magnetometer topics: '
            'nodes:=tensor,calibrator,compensator'
        )


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


def static_frames(params_file, namespace):
    """``(parent, child, (x, y, z))`` of each static transform, in :data:`TRANSFORMS` order:
    the body frame -> each sensor at its position, and -> the array frame at the centroid.

    The array frame's origin: the tensor (``core.geometry.difference_tensor``, eq. 7:
    ``(B_2 - B_1, B_3 - B_1, B_4 - B_1) a^-1``) is exact for a uniform gradient and otherwise
    refers to no single point (to second order, ``B_i - B_1`` is the derivative along
    ``r_i - r_1`` at the midpoint of the two sensors). The package takes the centroid of the
    four sensors as the tensor's point (``TetraGeometry.centroid``; the simulator's
    ``g_analytic`` is the gradient there and differs from eq. 7 by its truncation, ~d/R), so
    the array frame sits at the centroid.
    """
    sections = parameter_sections(params_file)
    tensor = _node_parameters(sections, namespace, 'tensor')
    driver = _node_parameters(sections, namespace, 'driver')
    positions = _positions(params_file, tensor.get('sensor_positions', DEFAULT_POSITIONS))
    base = _frame_id(params_file, 'base_frame_id', driver.get('base_frame_id', BASE_FRAME))
    array = _frame_id(params_file, 'array_frame_id', tensor.get('array_frame_id', ARRAY_FRAME))
    sensors = driver.get('sensor_frame_ids', list(MAG_FRAMES))
    if not isinstance(sensors, list) or len(sensors) != 4:
        raise ValueError(
            f'params_file {params_file!r}: sensor_frame_ids must be a list of 4 frame ids, '
            f'got {sensors!r}'
        )
    sensors = [_frame_id(params_file, 'sensor_frame_ids', sensor) for sensor in sensors]
    offsets = [tuple(positions[3 * i : 3 * i + 3]) for i in range(4)]
    centroid = tuple(sum(offset[axis] for offset in offsets) / 4 for axis in range(3))
    frames = [(base, sensor, offset) for sensor, offset in zip(sensors, offsets, strict=True)]
    return [*frames, (base, array, centroid)]


def parameter_sections(params_file):
    """``(node name, parameters)`` of each ``ros__parameters`` section of ``params_file`` in
    file order, the name as rcl's parser makes it (nested keys joined by ``/``, a leading
    ``/``); none for ``''``."""
    if not params_file:
        return []
    try:
        with open(params_file, encoding='utf-8') as stream:
            data = yaml.safe_load(stream)
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f'params_file {params_file!r}: cannot read it: {error}') from None
    sections = []

    def walk(mapping, path):
        if not isinstance(mapping, dict) or not mapping:
            where = '/' + '/'.join(path) if path else 'the top level'
            raise ValueError(
                f'params_file {params_file!r}: {where}: not a ROS 2 parameter file '
                '(node name: ros__parameters: name: value)'
            )
        for key, item in mapping.items():
            if key != 'ros__parameters':
                walk(item, [*path, str(key).strip('/')])
            elif isinstance(item, dict):
                sections.append(('/' + '/'.join(path), item))
            else:
                raise ValueError(
                    f'params_file {params_file!r}: /{"/".join(path)}: ros__parameters must '
                    f'map parameter names to values, got {item!r}'
                )

    walk(data, [])
    return sections


def _node_parameters(sections, namespace, node):
    """The parameters the sections give node ``node`` in ``namespace``, as rclpy matches
    them: ``/*`` one name, ``/**`` any number, a later section over an earlier one."""
    prefix = namespace.strip('/')
    name = f'/{prefix}/{node}' if prefix else f'/{node}'
    out = {}
    for section, parameters in sections:
        pattern = re.escape(section).replace(r'/\*\*', r'(/\w+)*').replace(r'/\*', r'(/\w+)')
        if re.fullmatch(pattern, name, re.ASCII):
            out.update(parameters)
    return out


def _positions(params_file, value):
    numbers = isinstance(value, (list, tuple)) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value
    )
    if not numbers or len(value) != 12:
        raise ValueError(
            f'params_file {params_file!r}: sensor_positions must be 12 finite numbers '
            f'(x1 y1 z1 x2 .. z4, metres), got {value!r}'
        )
    return [float(v) for v in value]


def _frame_id(params_file, key, value):
    """``value`` if it is a frame id as the nodes take it (``nodes.common.frame_ids``): a
    non-empty string without a leading ``/``."""
    problem = frame_ids(value) if isinstance(value, str) else 'a frame id must be a string'
    if problem:
        raise ValueError(f'params_file {params_file!r}: {key}: {problem} (got {value!r})')
    return value


def enclave_arguments(enclave, enabled):
    """``Node`` keyword arguments that run the node in SROS2 ``enclave`` when ``enabled``."""
    return {'ros_arguments': ['--enclave', enclave]} if enabled else {}


def _transform_publisher(suffix, frame, namespace, use_sim_time, enclaves=False):
    """A tf2_ros static_transform_publisher of ``frame`` (identity rotation), not managed:
    no lifecycle, and its exit leaves the launch running (default ``on_exit``)."""
    parent, child, (x, y, z) = frame
    return Node(
        package='tf2_ros',
        executable='static_transform_publisher',
        name=f'tetra_tf_{suffix}',
        namespace=namespace,
        arguments=[
            *('--x', repr(x), '--y', repr(y), '--z', repr(z)),
            *('--roll', '0', '--pitch', '0', '--yaw', '0'),
            *('--frame-id', parent, '--child-frame-id', child),
        ],
        parameters=[{'use_sim_time': use_sim_time}],
        output='screen',
        **enclave_arguments(TRANSFORMS_ENCLAVE, enclaves),
    )


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
