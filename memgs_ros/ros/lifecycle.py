"""Managed (lifecycle) nodes: the graph's four nodes follow ROS 2's node lifecycle.

- construction declares and checks the parameters (cheap; a bad one refuses the node);
- *configure* builds the node: torch/CUDA, the kernels' warm-up, the map session, the topics,
  services and timers (``configure_node``);
- *activate* starts taking frames and mapping; *deactivate* pauses (``set_active(False)``: frames
  counted as ``skipped.inactive``, the mapper stops training; the map is kept and still served);
- *cleanup* saves and releases (``close``) and removes what configure made, so a later
  *configure* starts again (the mapper resumes from its checkpoint); *shutdown* saves too.

``autostart`` (default true) configures and activates at construction: ``ros2 run``, launch and
the composed process behave as unmanaged nodes did. With ``autostart:=false`` a supervisor drives
the transitions through ``<node>/change_state`` (``lifecycle_msgs/srv/ChangeState``), as
nav2's lifecycle manager does.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from memgs_ros.errors import MemgsError

__all__ = ["ManagedNode"]


class ManagedNode(LifecycleNode):
    """A lifecycle node whose subclass builds itself in ``configure_node`` (see module docstring).

    Subclasses declare their parameters in ``__init__``, then call ``self.start_lifecycle(autostart)``;
    they implement ``configure_node()``, ``close_node()`` (save, stop threads) and may override
    ``set_active(active)``. Entities created while configuring are recorded and destroyed on cleanup.
    """

    params: Any  # the node's own parameters, a frozen dataclass (declare_config)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A node whose constructor raises (a refused parameter) is destroyed before the error
        leaves it: a half-built lifecycle node otherwise stays on the DDS graph until collected."""
        super().__init_subclass__(**kwargs)
        init = cls.__init__

        @functools.wraps(init)
        def guarded(self: ManagedNode, *args: Any, **kw: Any) -> None:
            try:
                init(self, *args, **kw)
            except BaseException:
                if type(self) is cls and getattr(self, "_state_machine", None) is not None:
                    self.destroy_node()
                raise

        cls.__init__ = guarded  # type: ignore[method-assign]

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        self._at_destroy: dict[str, Callable[[], object]] = {}  # before Node's: a refused node is destroyed
        super().__init__(node_name, **kwargs)
        self.active = False
        self.configured = False
        self.configure_s: float | None = None  # how long the last configure took
        self._recording: list[Any] | None = None
        self._made: list[Any] = []

    # ------------------------------------------------------------------ for subclasses
    def start_lifecycle(self, autostart: bool) -> None:
        """At the end of ``__init__``: with ``autostart`` (the node's parameter), configure and
        activate now (a refusal raises, as an unmanaged node's constructor did)."""
        if not autostart:
            self.get_logger().info("waiting to be configured (autostart is false)")
            return
        self._configure()
        self.trigger_configure()  # the state machine follows; the work above is already done
        self.trigger_activate()

    def configure_node(self) -> None:
        raise NotImplementedError

    def close_node(self) -> None:
        """Save and stop the node's threads (idempotent: shutdown may follow cleanup)."""

    def set_active(self, active: bool) -> None:
        self.active = active

    def close(self) -> None:
        """The process is ending (run_node): save and stop, once."""
        if self.configured:
            self.configured = False
            self.close_node()

    def end_with_node(self, name: str, stop: Callable[[], object]) -> None:
        """``stop()`` (bounded) runs first when the node is destroyed; a later call with the same
        ``name`` replaces it (a reconfigure). For threads that may still be in native code (a
        compile, a training step): a process that exits under one aborts."""
        self._at_destroy[name] = stop

    def destroy_node(self) -> None:
        for stop in reversed(list(self._at_destroy.values())):
            stop()
        # rclpy's lifecycle state machine holds the node's handle: destroyed with the node, not
        # left to the garbage collector (until then the node stayed on the DDS graph).
        self._state_machine.destroy_when_not_in_use()
        super().destroy_node()

    def restart_with(self, changes: dict[str, Any], prepare: Callable[[], Callable[[], None]] | None = None
                     ) -> str | None:
        """Deactivate and clean up (the node saves what it holds), take ``changes`` into its
        parameters (``self.params``), configure and activate again as it was: a new map at run time.
        ``prepare()`` runs between cleanup and configure and returns its undo. When the new
        configure fails, the undo runs and the old parameters are configured again; returns why."""
        was_active, old = self.active, self.params
        if self.active:
            self.trigger_deactivate()
        if self.configured:
            self.trigger_cleanup()
        undo = prepare() if prepare is not None else (lambda: None)
        self.params = dataclasses.replace(old, **changes)
        why = None
        try:
            self._configure()
        except MemgsError as err:
            why = str(err)
            undo()
            self.params = old
            self._configure()
        self.trigger_configure()  # the state machine follows; the work above is already done
        if was_active:
            self.trigger_activate()
        return why

    # ------------------------------------------------------------------ entity bookkeeping
    def create_publisher(self, *args: Any, **kwargs: Any) -> Any:
        return self._keep(super().create_publisher(*args, **kwargs))

    def create_subscription(self, *args: Any, **kwargs: Any) -> Any:
        return self._keep(super().create_subscription(*args, **kwargs))

    def create_service(self, *args: Any, **kwargs: Any) -> Any:
        return self._keep(super().create_service(*args, **kwargs))

    def create_timer(self, *args: Any, **kwargs: Any) -> Any:
        return self._keep(super().create_timer(*args, **kwargs))

    def create_client(self, *args: Any, **kwargs: Any) -> Any:
        return self._keep(super().create_client(*args, **kwargs))

    def _keep(self, entity: Any) -> Any:
        recording = getattr(self, "_recording", None)  # Node.__init__ makes its own before ours exist
        if recording is not None:
            recording.append(entity)
        return entity

    def _release(self) -> None:
        for entity in reversed(self._made):
            for destroy in ("destroy_timer", "destroy_subscription", "destroy_publisher", "destroy_service",
                            "destroy_client"):
                try:
                    if getattr(self, destroy)(entity):
                        break
                except (TypeError, AttributeError):
                    continue
        self._made = []

    def _configure(self) -> None:
        if self.configured:
            return
        t0 = time.perf_counter()
        self._recording = []
        try:
            self.configure_node()
        except BaseException:
            self._made, self._recording = self._recording, None
            self._release()
            raise
        self._made, self._recording = self._recording, None
        self.configured = True
        self.configure_s = time.perf_counter() - t0

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except MemgsError as err:
            self.get_logger().error(f"configure failed: {err}")
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f"configured in {self.configure_s:.2f} s")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.set_active(True)
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.set_active(False)
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.close()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.set_active(False)
        self.close()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.set_active(False)
        return TransitionCallbackReturn.SUCCESS
