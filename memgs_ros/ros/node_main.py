"""One ``main()`` for every node, and for the nodes composed in one process: init, spin, clean
shutdown on Ctrl-C or SIGTERM.

A node may define ``close()`` (save the map, stop threads); it runs before
``destroy_node()`` whether the node ends normally, by signal, or by error. A
``MemgsError`` at start (a refused parameter, say) is one fatal log line and exit 2. A node whose
work ends (the bag player) hands ``until`` its completion future: the spin ends with it, and its
result gives the exit status (true: 0, false: 1).
"""
from __future__ import annotations

import os
import signal
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

from memgs_ros.core.runtime.cpu import PARENT_PID_ENV, die_with_parent, lower_priority
from memgs_ros.core.runtime.warm import settle_heap
from memgs_ros.errors import MemgsError
from memgs_ros.ros.config_params import check_declared


def started_by_runner() -> bool:
    """For a node that ``memgs run`` started (it sets MEMGS_PARENT_PID): arm SIGTERM for when the
    runner ends, however it ends (SIGKILL too), so no node outlives it; SIGTERM takes the same
    clean path as Ctrl-C (the merger saves its map). False: the runner is already gone, exit."""
    parent = os.environ.get(PARENT_PID_ENV, "")
    return not parent.isdigit() or die_with_parent(int(parent), signal.SIGTERM)


Until = Callable[[Sequence[Any]], Future]  # the nodes -> the future whose completion ends the spin


def run_node(factory: Callable[[], Node], name: str, args: Sequence[str] | None = None,
             until: Until | None = None) -> int:
    """Create the node with ``factory`` after rclpy.init and spin it until shutdown (or ``until``:
    module docstring). A background node (mapper, sampler, merger) alone in its process yields the
    cores to the tracker: every thread it has, and every one started later, runs at its ``niceness``."""
    return run_nodes([factory], name, args, lower_process=True, until=until)


def run_nodes(factories: Sequence[Callable[[], Node]], name: str, args: Sequence[str] | None = None,
              lower_process: bool = False, until: Until | None = None) -> int:
    """Create the nodes (in order) after rclpy.init and spin them on one single-threaded executor
    until shutdown, or until the future ``until(nodes)`` completes (its result: exit 0 when true, 1
    when false; a stop by signal before it completes is exit 0); each node's ``close()`` runs
    before ``destroy_node()``, in reverse order. ``lower_process``: apply the (one) node's
    ``niceness`` to the whole process. Nodes sharing a process (composed) lower their own
    background threads instead."""
    if not started_by_runner():
        return 0
    # rclpy's own handlers (SignalHandlerOptions.ALL) turn SIGINT and SIGTERM into a context
    # shutdown that wakes the executor, which then ends the spin, so close still runs.
    # (A Python handler that shuts the context down could land while the executor builds its
    # wait set, which then fails with RCLError instead of ending cleanly.)
    rclpy.init(args=list(args) if args is not None else None, signal_handler_options=SignalHandlerOptions.ALL)
    # One thread runs every callback: none of the nodes' callbacks waits (their work runs on their
    # own workers), and rclpy's multi-threaded executor took ~30 ms to pick up a message.
    executor = SingleThreadedExecutor()
    nodes: list[Node] = []
    code = 0
    try:
        try:
            for factory in factories:
                nodes.append(factory())
        except Exception:
            if rclpy.ok():
                raise
            return code  # Ctrl-C / SIGTERM arrived while the nodes were still being built
        for node in nodes:
            check_declared(node)  # a misspelt parameter would otherwise run silently on its default
        niceness = int(getattr(nodes[0], "niceness", 0) or 0) if nodes else 0  # a node's own parameter
        if lower_process and niceness:
            lower_priority(niceness)
        for node in nodes:
            executor.add_node(node)
        settle_heap()  # started: no full garbage-collector pass over the imports mid-run
        try:
            code = _spin(executor, None if until is None else until(nodes))
        except Exception:
            if rclpy.ok():
                raise
            # The signal handler shut the context down while the executor was between waits
            # (building its wait set fails with RCLError then): the same clean stop.
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except MemgsError as err:
        rclpy.logging.get_logger(name).fatal(str(err))
        code = 2
    finally:
        for node in reversed(nodes):
            hook = getattr(node, "close", None)
            if hook is not None:
                try:
                    hook()
                except Exception as err:  # noqa: BLE001 - shutdown must finish; say what failed
                    rclpy.logging.get_logger(node.get_name()).error(f"shutdown hook failed: {err}")
                    code = code or 1
        executor.shutdown()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _spin(executor: SingleThreadedExecutor, done: Future | None) -> int:
    """Spin until shutdown (exit 0) or until ``done`` completes (0 when its result is true, else 1)."""
    if done is None:
        executor.spin()
        return 0
    executor.spin_until_future_complete(done)
    # rclpy's result() never waits (it takes no timeout): read only once the future is done;
    # not done means a signal ended the spin, a clean stop.
    return 0 if not done.done() or done.result() else 1
