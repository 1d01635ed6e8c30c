"""The base of the four nodes: a ROS 2 managed (lifecycle) node, ``rclpy.lifecycle``.

States and what each node does in them (docs/ros.md, *Lifecycle*):

* constructed (``unconfigured``): the parameters are declared (a refused start-up value ends
  the process, see ``process.spin_node``); nothing else exists, nothing is published;
* ``on_configure``: :meth:`ManagedNode.configure` reads the parameters, checks what spans
  several of them and the files they name (calibration file, bag, scenario), and creates
  publishers (the data's with ``create_lifecycle_publisher``: rclpy enables them on
  activation and drops what they are given while inactive), subscriptions, services and
  timers. A refusal (any ``TetraError``) fails the
  transition with one ``configure refused:`` log line naming the value and why; everything
  created is released and the node stays ``unconfigured`` (fix the value, configure again);
* ``inactive``: the timers are stopped, subscription callbacks ignore their messages and the
  services answer ``success=false`` ("inactive"): nothing is published;
* ``on_activate``: the timers run, data flows (:meth:`ManagedNode.activated` hook);
* ``on_deactivate``: back to inactive; what the node holds (the calibration, collected
  samples, the replay position) is kept (:meth:`ManagedNode.deactivated` hook);
* ``on_cleanup`` / ``on_shutdown`` / ``on_error``: everything ``configure`` created is
  destroyed and the node's long work is stopped (:meth:`ManagedNode.released` hook).

Lifecycle requests (``~/change_state``) are rclpy's: a valid one runs the transition (each
logged at WARN: ``configure: unconfigured -> inactive``); one that is not a valid
transition from the current state is refused by ``rcl_lifecycle`` (its WARN ``No transition
matching ...``; rclpy sends no reply) and cannot end the process: ``process.spin`` logs it
and spins on.

While configured, the node's ``/diagnostics`` timer runs on the steady clock (``use_sim_time``
without ``/clock`` cannot freeze it) also while inactive: every status is then WARN, its
message prefixed ``inactive:`` (a deactivated node never leaves its last OK standing).
The parameters named in :attr:`ManagedNode.LOCKED` and ``use_sim_time`` can be set only
while unconfigured (cleanup, set, configure): they decide what is written or how data is
judged; every accepted parameter change is logged at WARN.

``autostart`` (default true): the constructor configures and activates the node, so
``ros2 run tetra_gradiometer tensor`` works on its own (a refusal is then raised from the
constructor: the process ends with ``cannot start:``). ``bringup`` and the launch file set it
false and drive the transitions themselves, in order; an external manager does the same
through the standard ``lifecycle_msgs`` services (``~/change_state``, ``~/get_state``).
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any, ClassVar

from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import (
    LifecycleNode,
    LifecyclePublisher,
    LifecycleState,
    TransitionCallbackReturn,
)

from ..errors import TetraError
from .common import NAMESPACE, WARN, ParamSpec, declare_parameters
from .publishers import InputPublishers

AUTOSTART_SPEC = ParamSpec(
    'autostart',
    True,
    'Configure and activate at construction (false: stay unconfigured for a lifecycle '
    'manager, bringup or the launch file).',
    read_only=True,
)

#: Node property -> its destroy method, for what ``configure`` creates.
_ENTITIES = {
    'publishers': 'destroy_publisher',
    'subscriptions': 'destroy_subscription',
    'services': 'destroy_service',
    'clients': 'destroy_client',
    'timers': 'destroy_timer',
    'guards': 'destroy_guard_condition',
}

#: Set while unconfigured only (as :attr:`ManagedNode.LOCKED`): rclpy declares it itself.
LOCKED_BUILTINS = ('use_sim_time',)


def steady_clock() -> Clock:
    """The steady clock, for the timers that must run whatever ``/clock`` does."""
    return Clock(clock_type=ClockType.STEADY_TIME)


class ManagedNode(LifecycleNode):
    """A lifecycle node whose ``configure`` creates everything and whose other transitions
    are generic: subclasses set :attr:`PARAMETERS` (and :attr:`DYNAMIC`, the names that may
    change at run time) and implement :meth:`configure`; they wrap their subscription and
    service callbacks in :meth:`when_active`."""

    PARAMETERS: ClassVar[list[ParamSpec]] = []
    #: Parameters that may be set after start-up (the others are read-only)...
    DYNAMIC: ClassVar[tuple[str, ...]] = ()
    #: ... of which these only while unconfigured: they decide what is written or how data is
    #: judged (with ``use_sim_time``), so a configured node refuses them.
    LOCKED: ClassVar[tuple[str, ...]] = ()

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        kwargs.setdefault('namespace', NAMESPACE)
        super().__init__(node_name, **kwargs)
        # Before the validators' callback (rclpy runs the last added first): a bad value is
        # refused with the validator's reason, a good one then by this rule.
        self.add_on_set_parameters_callback(self._refuse_while_configured)
        p = declare_parameters(self, [*self.PARAMETERS, AUTOSTART_SPEC], self.DYNAMIC)
        self.active = False
        self._configured = False
        self._refusal: BaseException | None = None
        self._base = self._entities()  # the node's own: parameter and lifecycle services
        self._raising = False  # in bring_up: it raises the refusal, it logs at INFO
        self._always: set[Any] = set()  # timers that run while inactive too (diagnostics)
        self.diagnostics_state = 'inactive'  # how a status reads while the node is not active
        self.state_label = 'unconfigured'  # the lifecycle state, as the transitions leave it
        self.add_post_set_parameters_callback(self._log_parameters)
        if p['autostart']:
            try:
                self.bring_up()
            except BaseException:
                self.destroy_node()
                raise

    def bring_up(self) -> None:
        """Configure, then activate (what ``autostart``, ``bringup`` and the launch file do).

        Raises
        ------
        TetraError
            The configuration was refused (the node stays unconfigured); any other
            exception is a bug of ``configure``.
        """
        self._raising = True
        try:
            outcome = self.trigger_configure()
            if outcome == TransitionCallbackReturn.SUCCESS:
                self.trigger_activate()
        finally:
            self._raising = False
        if outcome != TransitionCallbackReturn.SUCCESS:
            error, self._refusal = self._refusal, None
            raise error if error is not None else TetraError(f'{self.get_name()}: not configured')

    # ------------------------------------------------------------------ subclass hooks

    def configure(self, p: dict[str, Any]) -> None:
        """Read the parameter values ``p`` (name -> value), check them, create the node's
        entities. Raise ``TetraError`` to refuse."""
        raise NotImplementedError

    def activated(self) -> None:
        """Called on activation, before the timers run (e.g. restart pacing)."""

    def deactivated(self) -> None:
        """Called on deactivation, after the timers stopped."""

    def released(self) -> None:
        """Called before the entities are destroyed (cleanup, shutdown, error): stop long
        work, close files."""

    # ------------------------------------------------------------------ helpers

    def when_active(self, callback: Callable[..., Any]) -> Callable[..., Any]:
        """``callback`` that runs only while active: a subscription's message is ignored, a
        ``std_srvs/Trigger`` service answers ``success=false`` with the state. Every service
        call (each changes the node's state: start, stop, calibrate, cancel, reset_metrics,
        resume, pause) is logged at WARN with its reply, named after the callback
        (``_on_start``: ``~/start``)."""

        service = '~/' + getattr(callback, '__name__', 'service').removeprefix('_on_')

        def gated(*args: Any) -> Any:
            if len(args) != 2:  # a message
                return callback(*args) if self.active else None
            response = args[1]  # a service: (request, response); each changes the node's state
            if self.active:
                response = callback(*args)
            else:
                response.success = False
                response.message = f'{self.get_name()} is inactive: activate it first'
            self.get_logger().warning(
                f'{service} called: {"done" if response.success else "refused"}: '
                f'{response.message}'
            )
            return response

        return gated

    def create_diagnostics_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady clock that runs while configured, inactive too (see
        :class:`DiagnosticsPublisher`)."""
        timer = self.create_timer(period_s, callback, clock=steady_clock())
        self._always.add(timer)
        return timer

    def diagnostics_publisher(self, inputs: InputPublishers | None = None) -> DiagnosticsPublisher:
        """``/diagnostics``, with every status WARN ``inactive: ...`` while inactive and the
        ``inputs`` status (who publishes the node's input topics; default: one watch of all
        its subscriptions) appended to every array."""
        from diagnostic_msgs.msg import DiagnosticArray

        publisher = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        return DiagnosticsPublisher(self, publisher, inputs or InputPublishers(self))

    def publish_diagnostics_now(self) -> None:
        """The node's ``_publish_diagnostics`` (when it has one), at a state change."""
        publish = getattr(self, '_publish_diagnostics', None)
        if self._configured and publish is not None:
            publish()

    # ------------------------------------------------------------------ parameters

    def _refuse_while_configured(self, parameters: list) -> Any:
        from rcl_interfaces.msg import SetParametersResult

        locked = set(self.LOCKED) | set(LOCKED_BUILTINS)
        if getattr(self, '_configured', False):
            for parameter in parameters:
                if parameter.name in locked:
                    return SetParametersResult(
                        successful=False,
                        reason=f'{parameter.name}: read-only while {self.get_name()} is '
                        f'configured ({self.state_label}): deactivate, cleanup, set it, configure',
                    )
        return SetParametersResult(successful=True)

    def _log_parameters(self, parameters: list) -> None:
        """Every accepted change at WARN (a parameter decides what the node does)."""
        for parameter in parameters:
            self.get_logger().warning(
                f'parameter {parameter.name} set to {parameter.value!r} ({self.state_label})'
            )

    def _entities(self) -> dict[str, set[Any]]:
        return {kind: set(getattr(self, kind)) for kind in _ENTITIES}

    def _new_entities(self) -> dict[str, set[Any]]:
        now = self._entities()
        return {kind: now[kind] - self._base[kind] for kind in _ENTITIES}

    def _release(self) -> None:
        """Destroy what ``configure`` created (after :meth:`released` when it completed)."""
        self.active = False
        try:
            self.stop_work()
        finally:
            for kind, entities in self._new_entities().items():
                destroy = getattr(self, _ENTITIES[kind])
                for entity in entities:
                    if isinstance(entity, LifecyclePublisher):  # rclpy's managed entities too
                        self.destroy_lifecycle_publisher(entity)
                    else:
                        destroy(entity)
            self._always.clear()

    # ------------------------------------------------------------------ transitions

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        p = {spec.name: self.get_parameter(spec.name).value for spec in self.PARAMETERS}
        try:
            self.configure(p)
        except TetraError as error:
            if not self._raising:
                self.get_logger().error(f'configure refused: {error}')
            self._refusal = error
            self._release()
            self._entered('configure refused', 'unconfigured')
            return TransitionCallbackReturn.FAILURE
        except Exception as error:  # a bug: keep its traceback in the log
            self.get_logger().error(f'configure failed:\n{traceback.format_exc()}')
            self._refusal = error
            self._release()
            return TransitionCallbackReturn.ERROR
        for timer in self._new_entities()['timers'] - self._always:
            timer.cancel()
        self._configured = True
        self._entered('configure', 'inactive')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.activated()
        self.active = True
        for timer in self._new_entities()['timers'] - self._always:
            timer.reset()
        self._entered('activate', 'active')
        self.publish_diagnostics_now()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        for timer in self._new_entities()['timers'] - self._always:
            timer.cancel()
        self.deactivated()
        self._entered('deactivate', 'inactive')
        self.publish_diagnostics_now()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._last_statuses('unconfigured (cleaned up)')
        self._release()
        self._entered('cleanup', 'unconfigured')
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._last_statuses('finalized (shut down)')
        self._release()
        self._entered('shutdown', 'finalized')
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._last_statuses('unconfigured (after an error)')
        self._release()
        self._entered('error', 'unconfigured')
        return TransitionCallbackReturn.SUCCESS  # back to unconfigured

    def _last_statuses(self, state: str) -> None:
        """Before ``/diagnostics`` goes with the rest: every status WARN ``<state>: ...``, so
        an aggregator is not left holding the node's last OK."""
        self.active = False
        self.diagnostics_state = state
        try:
            self.publish_diagnostics_now()
        except Exception:  # a bug: never in the way of the transition
            self.get_logger().error(f'last diagnostics failed:\n{traceback.format_exc()}')
        finally:
            self.diagnostics_state = 'inactive'

    def stop_work(self) -> None:
        """Stop the node's long work (a solve, an open bag) when it is configured: before its
        executor stops (``process.spin_node``), so no callback waits on it."""
        if self._configured:
            self.active = False
            self._configured = False
            self.released()

    def destroy_node(self) -> None:
        self.stop_work()
        super().destroy_node()

    def _entered(self, transition: str, state: str) -> None:
        """Record the state a transition leaves the node in; every one is logged at WARN
        (``autostart``'s own at INFO)."""
        before, self.state_label = self.state_label, state
        text = f'{transition}: {before} -> {state}'
        if self._raising:  # (rclpy fixes one severity per call site)
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)


class DiagnosticsPublisher:
    """``/diagnostics`` of a managed node: while it is not active every status goes out WARN
    with its message prefixed ``inactive:`` (the node's own values kept), so a monitor sees
    a deactivated node instead of its last OK."""

    def __init__(self, node: ManagedNode, publisher: Any, inputs: InputPublishers) -> None:
        self._node = node
        self.publisher = publisher
        self.inputs = inputs

    def publish(self, array: Any) -> None:
        self.inputs.check()
        array.status.append(self.inputs.status())
        if not self._node.active:
            for item in array.status:
                item.level = bytes([max(item.level[0], WARN)])
                item.message = f'{self._node.diagnostics_state}: {item.message}'
        self.publisher.publish(array)
