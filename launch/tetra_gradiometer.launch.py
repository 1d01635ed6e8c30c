"""The tetra_gradiometer nodes, one process each, as managed (lifecycle) nodes.

``ros2 launch tetra_gradiometer tetra_gradiometer.launch.py mode:=sim``; ``--show-args``
lists the arguments, docs/ros.md (*Launch*) explains them. With ``autostart`` the launch
configures and activates the nodes in bringup's order (tensor, calibrator, compensator,
target, driver), each once the one before it is active, so the chain listens before the
driver publishes: launch_ros ``ChangeState`` events, on start and from ``OnStateTransition``
handlers. The nodes' own ``autostart`` parameter is false. The first node to exit ends the
launch. ``static_transforms`` adds tf2_ros static transform publishers: base_link -> each
sensor frame at its position and -> the array frame at their centroid, from ``params_file``.
"""

import os

import yaml
from ament_index_python.packages import PackageNotFoundError, get_package_prefix
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    LogInfo,
    OpaqueFunction,
    RegisterEventHandler,
    Shutdown,
)
from launch.conditions import IfCondition
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition

from launch import LaunchDescription
from tetra_gradiometer.io.conversions import ARRAY_FRAME, BASE_FRAME, MAG_FRAMES
from tetra_gradiometer.nodes.common import DEFAULT_POSITIONS

PACKAGE = 'tetra_gradiometer'
NODES = ('tensor', 'calibrator', 'compensator', 'target', 'driver')  # the start order
REMAPPED = ('mag1', 'mag2', 'mag3', 'mag4', 'odom')  # the topics of the *_topic arguments
PARAMS = PathJoinSubstitution([FindPackageShare(PACKAGE), 'config', 'tetra_gradiometer.yaml'])
ARGUMENTS = {  # name: (default, description)
    'mode': ('', 'driver source: sim or replay ("": the params file\'s; a bag means replay)'),
    'bag': ('', 'replay: rosbag2 folder, relative to the working directory'),
    'params_file': (PARAMS, 'parameter file of every node ("": the declared defaults)'),
    'namespace': ('tetra', 'namespace of the nodes and their topics'),
    **{f'{t}_topic': (t, f'topic used as {t} (relative: in the namespace)') for t in REMAPPED},
    'use_sim_time': ('false', 'passed to every node'),
    'nodes': ('tensor,calibrator,compensator,driver', f'comma-separated subset of {NODES}'),
    'autostart': ('true', 'configure and activate the nodes in order (false: leave them)'),
    'static_transforms': ('true', 'publish the sensor and array frames on /tf_static'),
    'rate': ('', 'driver speed, multiple of real time (0: as fast as the graph takes it)'),
    'scenario': ('', 'sim: scenario YAML, relative to the working directory'),
    'calibration_file': ('', 'calibration file of the calibrator and the compensator'),
    'enclaves': ('false', 'run each node in its SROS2 enclave /tetra_gradiometer/<node>'),
}


def generate_launch_description():
    declared = [DeclareLaunchArgument(n, default_value=d, description=text)
                for n, (d, text) in ARGUMENTS.items()]  # fmt: skip
    return LaunchDescription([*declared, OpaqueFunction(function=launch_setup)])


def launch_setup(context):
    """The actions for the arguments' values; a bad value raises before any node starts."""
    arg = context.launch_configurations.get
    flags = ('use_sim_time', 'autostart', 'static_transforms', 'enclaves')
    flag = {n: IfCondition(LaunchConfiguration(n)).evaluate(context) for n in flags}
    given = {n.strip() for n in arg('nodes').split(',')} - {''}
    if not given or given - set(NODES):
        unknown = ', '.join(map(repr, sorted(given - set(NODES))))
        raise ValueError(f'nodes {arg("nodes")!r}: unknown {unknown}; choose from {NODES}')
    names = [n for n in NODES if n in given]
    params_file = arg('params_file')
    if params_file and not os.path.isfile(params_file):
        raise ValueError(f'params_file {params_file!r}: no such file')
    own = {n: {} for n in names}
    if 'driver' in names:
        own['driver'] = driver_parameters(arg, params_file, 'tensor' in names)
    if arg('calibration_file'):
        for n in {'calibrator', 'compensator'} & given:
            own[n]['calibration_file'] = _path(arg('calibration_file'))
    end_launch = end_launch_once()
    nodes = [
        LifecycleNode(
            package=PACKAGE, executable=n, name=n, namespace=arg('namespace'),
            parameters=[*filter(None, [params_file]),
                        {'use_sim_time': flag['use_sim_time'], 'autostart': False, **own[n]}],
            remappings=[(t, arg(f'{t}_topic')) for t in REMAPPED if arg(f'{t}_topic') != t],
            ros_arguments=enclave(n, flag['enclaves']),
            output='screen', on_exit=end_launch,
        )
        for n in names
    ]  # fmt: skip
    actions = [*nodes, *(lifecycle_chain(names, nodes) if flag['autostart'] else [])]
    if flag['static_transforms']:
        actions += static_transforms(params_file, arg('namespace'), flag)
    return actions


def driver_parameters(arg, params_file, with_tensor):
    """bringup's driver parameters. A driver with no source (mode, bag or the params file's
    mode) is refused: it fabricates no vehicle data by default."""
    mode = arg('mode') or ('replay' if arg('bag') else '')
    if not mode and not file_parameters(params_file, 'driver').get('mode'):
        raise ValueError(
            'the driver needs a source: mode:=sim or bag:=PATH; on a vehicle, '
            'launch the others on its topics: nodes:=tensor,calibrator,compensator'
        )
    out = {'min_subscribers': 1} if with_tensor else {}
    out |= {'mode': mode} if mode else {}
    out |= {k: _path(arg(k)) for k in ('bag', 'scenario') if arg(k)}
    return out | ({'rate': float(arg('rate'))} if arg('rate') else {})  # a double parameter


def _path(text):
    return os.path.abspath(os.path.expanduser(text))


def enclave(name, enabled):
    """The SROS2 enclave of ``name`` (security/policy.xml), when ``enabled``."""
    return ['--enclave', f'/tetra_gradiometer/{name}'] if enabled else None


def end_launch_once():
    """``on_exit`` of every node: the first exit ends the launch with one ``Shutdown`` (a
    second makes launch_ros fail: 'Cannot shutdown a ROS adapter that is not running')."""
    sent = []

    def on_exit(event, context):
        if sent or context.is_shutdown:
            return None
        sent.append(event.process_name)
        return [Shutdown(reason=f'{PACKAGE}: {event.process_name} exited')]

    return on_exit


def lifecycle_chain(names, nodes):
    """Configure the first node now, activate each once inactive, configure the next once
    it is active. Each handler fires once: a later manual transition restarts nothing."""

    def change(i, transition):
        matcher = matches_action(nodes[i])
        return EmitEvent(
            event=ChangeState(lifecycle_node_matcher=matcher, transition_id=transition)
        )

    def on(i, goal, message, action):
        entities = [LogInfo(msg=f'{PACKAGE}: {names[i]} {message}'), action]
        handler = OnStateTransition(
            target_lifecycle_node=nodes[i], goal_state=goal, entities=entities, handle_once=True
        )
        return RegisterEventHandler(handler)

    actions = [change(0, Transition.TRANSITION_CONFIGURE)]
    for i in range(len(names)):
        activate = change(i, Transition.TRANSITION_ACTIVATE)
        actions.append(on(i, 'inactive', 'configured, activating it', activate))
        if i + 1 < len(names):
            configure = change(i + 1, Transition.TRANSITION_CONFIGURE)
            actions.append(on(i, 'active', f'active, configuring {names[i + 1]}', configure))
    return actions


def file_parameters(params_file, node):
    """The parameters ``node`` reads from ``params_file``: its ``/**`` section and those named
    after the node (``/tetra/tensor``, ``/**/tensor``), a later one over an earlier one."""
    with open(params_file or os.devnull, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    out = {}
    try:
        for name, section in document.items():
            if name == '/**' or str(name).rstrip('/').rsplit('/', 1)[-1] == node:
                out.update(section['ros__parameters'])
    except (AttributeError, KeyError, TypeError, ValueError):
        raise ValueError(f'params_file {params_file!r}: not a ROS 2 parameter file') from None
    return out


def static_transforms(params_file, namespace, flag):
    """tf2_ros static_transform_publishers, plain nodes outside the lifecycle sequence."""
    try:
        get_package_prefix('tf2_ros')
    except PackageNotFoundError:  # the nodes come up without their transforms
        return [LogInfo(msg=f'{PACKAGE}: no tf2_ros: static transforms not published')]
    tensor, driver = file_parameters(params_file, 'tensor'), file_parameters(params_file, 'driver')
    positions = [float(v) for v in tensor.get('sensor_positions', DEFAULT_POSITIONS)]
    offsets = [positions[3 * i : 3 * i + 3] for i in range(4)]
    offsets.append([sum(o[axis] for o in offsets) / 4 for axis in range(3)])  # the centroid
    children = [
        *driver.get('sensor_frame_ids', MAG_FRAMES),
        tensor.get('array_frame_id', ARRAY_FRAME),
    ]
    base = driver.get('base_frame_id', BASE_FRAME)
    return [
        Node(
            package='tf2_ros', executable='static_transform_publisher', namespace=namespace,
            name=f'tetra_tf_{suffix}', output='screen',
            parameters=[{'use_sim_time': flag['use_sim_time']}],
            arguments=['--x', str(x), '--y', str(y), '--z', str(z),
                       '--frame-id', base, '--child-frame-id', child],
            ros_arguments=enclave('static_transforms', flag['enclaves']),
        )
        for suffix, child, (x, y, z) in zip(
            ('mag1', 'mag2', 'mag3', 'mag4', 'array'), children, offsets, strict=True
        )
    ]  # fmt: skip
