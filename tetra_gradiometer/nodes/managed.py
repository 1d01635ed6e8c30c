"""The base of the four nodes: a ROS 2 managed (lifecycle) node, ``rclpy.lifecycle``.

States and what each node does in them (docs/ros.md, *Lifecycle*):

* constructed (``unconfigured``): the parameters are declared (a refused start-up value ends
  the process, see ``process.spin_node``); nothing else exists, nothing is published;
* ``on_configure``: :meth:`ManagedNode.configure` reads the parameters, checks what spans
  several of them and the files they name (calibration file, bag, scenario), and creates
  publishers, subscriptions, services and timers. A refusal (any ``TetraError``) fails the
  transition with one ``configure refused:`` log line naming the value and why; everything
  created is released and the node stays ``unconfigured`` (fix the value, configure again);
* ``inactive``: the timers are stopped, subscription callbacks ignore their messages and the
  services answer ``success=false`` ("inactive"): nothing is published;
* ``on_activate``: the timers run, data flows (:meth:`ManagedNode.activated` hook);
* ``on_deactivate``: back to inactive; what the node holds (the calibration, collected
  samples, the replay position) is kept (:meth:`ManagedNode.deactivated` hook);
* ``on_cleanup`` / ``on_shutdown`` / ``on_error``: everything ``configure`` created is
  destroyed and the node's long work is stopped (:meth:`ManagedNode.released` hook).

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

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from ..errors import TetraError
from .common import NAMESPACE, ParamSpec, declare_parameters

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


class ManagedNode(LifecycleNode):
    """A lifecycle node whose ``configure`` creates everything and whose other transitions
    are generic: subclasses set :attr:`PARAMETERS` (and :attr:`DYNAMIC`, the names that may
    change at run time) and implement :meth:`configure`; they wrap their subscription and
    service callbacks in :meth:`when_active`."""

    PARAMETERS: ClassVar[list[ParamSpec]] = []
    DYNAMIC: ClassVar[tuple[str, ...]] = ()

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        kwargs.setdefault('namespace', NAMESPACE)
        super().__init__(node_name, **kwargs)
        p = declare_parameters(self, [*self.PARAMETERS, AUTOSTART_SPEC], self.DYNAMIC)
        self.active = False
        self._configured = False
        self._refusal: BaseException | None = None
        self._base = self._entities()  # the node's own: parameter and lifecycle services
        self._raising = False  # bring_up raises the refusal: the log line would repeat it
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
        finally:
            self._raising = False
        if outcome != TransitionCallbackReturn.SUCCESS:
            error, self._refusal = self._refusal, None
            raise error if error is not None else TetraError(f'{self.get_name()}: not configured')
        self.trigger_activate()

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
        ``std_srvs/Trigger`` service answers ``success=false`` with the state."""

        def gated(*args: Any) -> Any:
            if self.active:
                return callback(*args)
            if len(args) == 2:  # a service: (request, response)
                response = args[1]
                response.success = False
                response.message = f'{self.get_name()} is inactive: activate it first'
                return response
            return None

        return gated

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
                    destroy(entity)

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
            return TransitionCallbackReturn.FAILURE
        except Exception as error:  # a bug: keep its traceback in the log
            self.get_logger().error(f'configure failed:\n{traceback.format_exc()}')
            self._refusal = error
            self._release()
            return TransitionCallbackReturn.ERROR
        for timer in self._new_entities()['timers']:
            timer.cancel()
        self._configured = True
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.activated()
        self.active = True
        for timer in self._new_entities()['timers']:
            timer.reset()
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        for timer in self._new_entities()['timers']:
            timer.cancel()
        self.deactivated()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS  # back to unconfigured

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

    @property
    def state_label(self) -> str:
        """The lifecycle state: ``unconfigured``, ``inactive``, ``active``, ``finalized``."""
        return str(self._state_machine.current_state[1])
