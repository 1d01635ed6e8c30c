"""Stand-ins for the parts of ``launch`` and ``launch_ros`` that
``launch/tetra_gradiometer.launch.py`` uses (neither can be installed here), and a small
launch runner to run that file with them (used by test/test_launch_file.py).

Each class keeps its constructor's arguments as attributes. The constructors take the same
keyword-only arguments as the real Jazzy classes (a subset of them), so a misspelled or
positional argument fails here as it would under ``ros2 launch``. :func:`install` puts the
modules in ``sys.modules`` for one test (through pytest's ``monkeypatch``).

:class:`Launch` runs a launch description the way ``launch`` does, for these actions only:
declared arguments take their default unless given, an ``OpaqueFunction`` runs with the
context and its actions run in turn, a ``LifecycleNode`` starts unconfigured, a plain
``Node`` starts (no lifecycle: it is only recorded), and a ``ChangeState`` event moves the
matching lifecycle nodes through the lifecycle state machine, which emits a
``StateTransition`` event per step (state labels as rcl_lifecycle's) to the registered
handlers, as launch_ros's ``LifecycleNode`` does on ``transition_event``.
"""

from __future__ import annotations

import os
import sys
import types
from collections.abc import Callable
from typing import Any

from lifecycle_msgs.msg import Transition

# --------------------------------------------------------------------------- launch


class LaunchDescription:
    def __init__(self, initial_entities: list[Any] | None = None) -> None:
        self.entities = list(initial_entities or [])


class DeclareLaunchArgument:
    def __init__(
        self,
        name: str,
        *,
        default_value: Any = None,
        description: str | None = None,
        choices: list[str] | None = None,
    ) -> None:
        self.name = name
        self.default_value = default_value
        self.description = description
        self.choices = choices


class OpaqueFunction:
    def __init__(
        self, *, function: Callable[..., Any], args: list | None = None, kwargs: dict | None = None
    ) -> None:
        self.function = function
        self.args = list(args or [])
        self.kwargs = dict(kwargs or {})


class EmitEvent:
    def __init__(self, *, event: Any) -> None:
        self.event = event


class RegisterEventHandler:
    def __init__(self, event_handler: Any) -> None:
        self.event_handler = event_handler


class LogInfo:
    def __init__(self, *, msg: str) -> None:
        self.msg = msg


class Shutdown:
    def __init__(self, *, reason: str = 'reason not given') -> None:
        self.reason = reason


def matches_action(target_action: Any) -> Callable[[Any], bool]:
    return lambda action: action is target_action


class PathJoinSubstitution:
    def __init__(self, substitutions: list[Any]) -> None:
        self.substitutions = list(substitutions)

    def perform(self, context: LaunchContext) -> str:
        return os.path.join(*(perform(part, context) for part in self.substitutions))


# --------------------------------------------------------------------------- launch_ros


class FindPackageShare:
    def __init__(self, package: str) -> None:
        self.package = package

    def perform(self, context: LaunchContext) -> str:
        return context.share_directories[self.package]


class Node:
    """launch_ros's plain ``Node``: its own keyword-only arguments (Jazzy) and, of those it
    passes on to ``ExecuteProcess``, ``output`` and ``on_exit``."""

    def __init__(
        self,
        *,
        executable: str,
        package: str | None = None,
        name: str | None = None,
        namespace: str | None = None,
        parameters: list[Any] | None = None,
        remappings: list[tuple[str, str]] | None = None,
        arguments: list[str] | None = None,
        ros_arguments: list[str] | None = None,
        output: str = 'log',
        on_exit: Any = None,
    ) -> None:
        self.executable = executable
        self.package = package
        self.name = name
        self.namespace = namespace
        self.parameters = parameters
        self.remappings = remappings
        self.arguments = arguments
        self.ros_arguments = ros_arguments
        self.output = output
        self.on_exit = on_exit


class LifecycleNode(Node):
    """launch_ros's ``LifecycleNode``, a ``Node`` whose name and namespace are required."""

    def __init__(self, *, name: str, namespace: str, **kwargs: Any) -> None:
        super().__init__(name=name, namespace=namespace, **kwargs)


class ChangeState:
    def __init__(
        self, *, lifecycle_node_matcher: Callable[[Any], bool], transition_id: int
    ) -> None:
        self.lifecycle_node_matcher = lifecycle_node_matcher
        self.transition_id = transition_id


class StateTransition:
    """The event launch_ros emits per ``transition_event`` message (labels, not ids)."""

    def __init__(self, *, action: Any, transition: str, start_state: str, goal_state: str) -> None:
        self.action = action
        self.transition = transition
        self.start_state = start_state
        self.goal_state = goal_state


class OnStateTransition:
    """Matches as the real handler does: every criterion given must equal the event's."""

    def __init__(
        self,
        *,
        entities: list[Any],
        target_lifecycle_node: Any = None,
        transition: str | None = None,
        start_state: str | None = None,
        goal_state: str | None = None,
        matcher: Callable[[Any], bool] | None = None,
        handle_once: bool = False,
    ) -> None:
        self.entities = list(entities)
        self.target_lifecycle_node = target_lifecycle_node
        self.transition = transition
        self.start_state = start_state
        self.goal_state = goal_state
        self.matcher = matcher
        self.handle_once = handle_once

    def matches(self, event: Any) -> bool:
        if self.matcher is not None:
            return self.matcher(event)
        wanted = {
            'action': self.target_lifecycle_node,
            'transition': self.transition,
            'start_state': self.start_state,
            'goal_state': self.goal_state,
        }
        return isinstance(event, StateTransition) and all(
            value is None or getattr(event, key) == value for key, value in wanted.items()
        )


# --------------------------------------------------------------------------- installing

MODULES: dict[str, dict[str, Any]] = {
    'launch': {'LaunchDescription': LaunchDescription},
    'launch.launch_description': {'LaunchDescription': LaunchDescription},
    'launch.actions': {
        'DeclareLaunchArgument': DeclareLaunchArgument,
        'EmitEvent': EmitEvent,
        'LogInfo': LogInfo,
        'OpaqueFunction': OpaqueFunction,
        'RegisterEventHandler': RegisterEventHandler,
        'Shutdown': Shutdown,
    },
    'launch.events': {'matches_action': matches_action},
    'launch.substitutions': {'PathJoinSubstitution': PathJoinSubstitution},
    'launch_ros': {},
    'launch_ros.actions': {'LifecycleNode': LifecycleNode, 'Node': Node},
    'launch_ros.event_handlers': {'OnStateTransition': OnStateTransition},
    'launch_ros.events': {},
    'launch_ros.events.lifecycle': {
        'ChangeState': ChangeState,
        'StateTransition': StateTransition,
    },
    'launch_ros.substitutions': {'FindPackageShare': FindPackageShare},
}


def install(monkeypatch: Any) -> None:
    """Put the stand-in modules in ``sys.modules`` until the test ends."""
    modules = {name: types.ModuleType(name) for name in MODULES}
    for name, module in modules.items():
        for attribute, value in MODULES[name].items():
            setattr(module, attribute, value)
        parent, _, child = name.rpartition('.')
        if parent:
            setattr(modules[parent], child, module)
        monkeypatch.setitem(sys.modules, name, module)


# --------------------------------------------------------------------------- running


class LaunchContext:
    """``launch_configurations`` records which names were read (:attr:`read`)."""

    def __init__(self, configurations: dict[str, str], share_directories: dict[str, str]):
        self.launch_configurations = _RecordingDict(configurations)
        self.share_directories = share_directories


class _RecordingDict(dict):
    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.read: set[str] = set()

    def __getitem__(self, key: str) -> Any:
        self.read.add(key)
        return super().__getitem__(key)

    def get(self, key: str, default: Any = None) -> Any:
        self.read.add(key)
        return super().get(key, default)


def perform(value: Any, context: LaunchContext) -> str:
    return value if isinstance(value, str) else value.perform(context)


#: transition id -> (label, start state, intermediate state, goal state) on success.
TRANSITIONS = {
    Transition.TRANSITION_CONFIGURE: ('configure', 'unconfigured', 'configuring', 'inactive'),
    Transition.TRANSITION_ACTIVATE: ('activate', 'inactive', 'activating', 'active'),
    Transition.TRANSITION_DEACTIVATE: ('deactivate', 'active', 'deactivating', 'inactive'),
}


class Launch:
    """Runs launch descriptions with the stand-ins (see the module docstring).

    Attributes: ``declared`` (argument names), ``nodes`` (LifecycleNode, in start order),
    ``plain_nodes`` (Node, not managed, in start order), ``state`` (lifecycle node name ->
    lifecycle state), ``requests`` ((node name, transition label)
    in the order requested), ``refused`` (requests not valid in the node's state, which the
    real node answers with success false), ``log`` (LogInfo messages), ``actions`` (every
    action run).
    """

    def __init__(self, arguments: dict[str, str], share_directories: dict[str, str]) -> None:
        self.context = LaunchContext(dict(arguments), share_directories)
        self.declared: list[str] = []
        self.nodes: list[LifecycleNode] = []
        self.plain_nodes: list[Node] = []
        self.state: dict[str, str] = {}
        self.requests: list[tuple[str, str]] = []
        self.refused: list[tuple[str, str]] = []
        self.log: list[str] = []
        self.actions: list[Any] = []
        self._handlers: list[OnStateTransition] = []

    def run(self, description: LaunchDescription) -> Launch:
        for entity in description.entities:
            self.execute(entity)
        return self

    def node(self, name: str) -> LifecycleNode:
        return next(node for node in self.nodes if node.name == name)

    def execute(self, action: Any) -> None:
        self.actions.append(action)
        if isinstance(action, DeclareLaunchArgument):
            self.declared.append(action.name)
            configurations = self.context.launch_configurations
            if action.name not in configurations:
                configurations[action.name] = perform(action.default_value, self.context)
        elif isinstance(action, OpaqueFunction):
            for entity in action.function(self.context, *action.args, **action.kwargs) or []:
                self.execute(entity)
        elif isinstance(action, RegisterEventHandler):
            self._handlers.append(action.event_handler)
        elif isinstance(action, LifecycleNode):
            self.nodes.append(action)
            self.state[action.name] = 'unconfigured'
        elif isinstance(action, Node):
            self.plain_nodes.append(action)
        elif isinstance(action, EmitEvent):
            self.emit(action.event)
        elif isinstance(action, LogInfo):
            self.log.append(action.msg)
        else:
            raise TypeError(f'the stand-in launch cannot run {action!r}')

    def emit(self, event: Any) -> None:
        if isinstance(event, ChangeState):
            for node in [n for n in self.nodes if event.lifecycle_node_matcher(n)]:
                self.change_state(node, event.transition_id)
        elif isinstance(event, StateTransition):
            for handler in list(self._handlers):
                if handler.matches(event):
                    if handler.handle_once:
                        self._handlers.remove(handler)
                    for entity in handler.entities:
                        self.execute(entity)
        else:
            raise TypeError(f'the stand-in launch cannot emit {event!r}')

    def change_state(self, node: LifecycleNode, transition_id: int) -> None:
        """One transition of ``node`` (its callbacks succeed), as its ``change_state``
        service does: two ``StateTransition`` events, into the intermediate state and out."""
        label, start, middle, goal = TRANSITIONS[transition_id]
        self.requests.append((node.name, label))
        if self.state[node.name] != start:
            self.refused.append((node.name, label))
            return
        for before, after, step in ((start, middle, label), (middle, goal, f'on_{label}_success')):
            self.state[node.name] = after
            self.emit(
                StateTransition(action=node, transition=step, start_state=before, goal_state=after)
            )
