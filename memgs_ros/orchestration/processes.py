"""The graph's nodes as child processes of the runner, and the runner's own rclpy context.

Each node runs in a session of its own and dies with the runner (``NodeProcesses``); a run opens
its context on a DDS domain no other graph uses (``open_context``).
"""
from __future__ import annotations

import importlib
import logging
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import rclpy

from memgs_ros.core.runtime.cpu import PARENT_PID_ENV
from memgs_ros.errors import PipelineError
from memgs_ros.nodes.registry import NODES

logger = logging.getLogger(__name__)

VIEW_NODE = "rerun_bridge"  # started after the graph when RunOptions.rerun is set



class _NodeModules(Mapping[str, ModuleType]):
    """The node modules by name, each imported when first asked for: a runner that starts its
    nodes as processes never loads their code (the mapper's torch cost it ~2.5 s and ~190 MB)."""

    def __getitem__(self, name: str) -> ModuleType:
        return importlib.import_module(NODES[name][0])

    def __iter__(self) -> Iterator[str]:
        return iter(NODES)

    def __len__(self) -> int:
        return len(NODES)


class _NodeFactories(Mapping[str, Callable[..., Any]]):
    """The node classes by name (for a graph in one process), imported when first asked for."""

    def __getitem__(self, name: str) -> Callable[..., Any]:
        return getattr(NODE_MODULES[name], NODES[name][1])

    def __iter__(self) -> Iterator[str]:
        return iter(NODES)

    def __len__(self) -> int:
        return len(NODES)


# The graph, by module: a process runs ``python -m <module>`` (its ``main``); in one process the
# module's Node class is built on a shared executor.
NODE_MODULES: Mapping[str, ModuleType] = _NodeModules()
NODE_FACTORIES: Mapping[str, Callable[..., Any]] = _NodeFactories()
# The Rerun view yields the cores to mapping: on 2 cores its CPU (~3 % of a run's) otherwise
# lengthens the run by as much. It still runs whenever a core idles (acknowledgement waits, I/O).
# Below the mapper, which runs at its own niceness (10, the node's parameter) below the tracker.
NICENESS = {VIEW_NODE: 15}
KILL_WAIT_S = 10.0  # how long the runner waits for a SIGKILLed node to be reaped


class NodeProcesses:
    """The graph's nodes as child processes, logs in ``log_dir``; stopped with SIGINT.

    Each node runs in a session of its own (a terminal's Ctrl-C or hang-up reaches the runner
    alone, which stops the nodes in order) and ends with the runner however the runner ends
    (MEMGS_PARENT_PID: the node arms PR_SET_PDEATHSIG). The kernel sends that signal when the
    forking *thread* exits, so every start happens on the thread that calls ``start`` from
    ``run_pipeline`` and ``_drive`` (the main thread), never on a short-lived one.
    """

    def __init__(self, params_file: Path, namespace: str, env: dict[str, str], log_dir: Path) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.log_dir = log_dir
        self.player_reported = False  # the player announced its end (done or failed): its exit code is known
        self.player_exit_seen: float | None = None  # when the runner first saw the player's process ended
        self.due: dict[str, float] = {}  # node -> monotonic time of a delayed start (start_due)
        self._params_file, self._ns = params_file, namespace
        self._env = dict(env, **{PARENT_PID_ENV: str(os.getpid())})

    def start(self, name: str, extra_ros_args: Sequence[str] = ()) -> None:
        cmd = [sys.executable, "-m", NODES[name][0], "--ros-args", "--params-file", str(self._params_file),
               *extra_ros_args]
        if self._ns:
            cmd += ["-r", f"__ns:={self._ns}"]
        log = open(self.log_dir / f"{name}.log", "wb")  # noqa: SIM115 - owned by the child
        self.procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=self._env,
                                            start_new_session=True)
        if name in NICENESS and hasattr(os, "setpriority"):
            try:
                os.setpriority(os.PRIO_PROCESS, self.procs[name].pid, NICENESS[name])
            except OSError as err:  # the view then competes at normal priority: slower, still right
                logger.warning("could not lower the priority of %s: %s", name, err)

    def kill_and_restart(self, name: str) -> None:
        """SIGKILL a node (no chance to save anything) and start it again."""
        p = self.procs[name]
        p.kill()
        _reap(name, p)
        os.replace(self.log_dir / f"{name}.log", self.log_dir / f"{name}.killed-{int(time.time())}.log")
        self.start(name)

    def start_due(self) -> None:
        """Start the nodes whose delayed start (``due``) has come."""
        now = time.monotonic()
        for name, when in list(self.due.items()):
            if now >= when:
                del self.due[name]
                self.start(name)

    def check(self) -> None:
        for name, p in list(self.procs.items()):
            code = p.poll()
            if code is not None and not (name == "bag_player" and (code == 0 or self.player_reported)):
                tail = (self.log_dir / f"{name}.log").read_text(errors="replace").strip().splitlines()[-15:]
                # Name the signal (SIGKILL: the OOM killer, an operator) rather than a bare -9.
                how = (f"was killed by {signal.Signals(-code).name}" if code < 0 and -code in set(signal.Signals)
                       else f"exited with code {code}")
                raise PipelineError(f"node {name} {how} before the run ended:\n  " + "\n  ".join(tail))

    def stop(self, timeout_s: float = 20.0) -> None:
        """SIGINT to every node (each saves what it holds), SIGKILL to those still running after
        ``timeout_s``, and to all at once on a second Ctrl-C / SIGTERM while waiting."""
        self.due.clear()
        for p in list(self.procs.values()):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        end = time.monotonic() + timeout_s
        try:
            logger.info("stopping the nodes (each saves what it holds; Ctrl-C kills them)")
            for name, p in list(self.procs.items()):
                try:
                    p.wait(timeout=max(0.1, end - time.monotonic()))
                except subprocess.TimeoutExpired:
                    logger.warning("node %s did not stop on SIGINT; killing it", name)
                    p.kill()
                    _reap(name, p)
        except KeyboardInterrupt:
            logger.warning("interrupted again while the nodes stop: killing them")
            self.kill_all()
            raise

    def kill_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
        for name, p in self.procs.items():
            _reap(name, p)


def _reap(name: str, p: subprocess.Popen[Any]) -> None:
    """Wait for a SIGKILLed node, boundedly: a process in uninterruptible I/O (a dead NFS mount)
    does not die at once, and the runner must not hang on it."""
    try:
        p.wait(timeout=KILL_WAIT_S)
    except subprocess.TimeoutExpired:
        logger.error("node %s (pid %d) has not exited %.0f s after SIGKILL; leaving it", name, p.pid, KILL_WAIT_S)


GRAPH_NAMES = frozenset({"tracker", "keyframe_sampler", "mapper", "merger", "bag_player", "memgs_run_observer"})


def open_context(domain_id: int | None, ros_args: list[str], probe_s: float = 1.0,
                 tries: int = 12, namespace: str = "") -> tuple[Any, int]:
    """An rclpy context on ``domain_id``, or on a random domain where no other node is seen.

    Two graphs on one domain hear each other (another run's camera_info reached a tracker):
    a run that picks its own domain first listens for ``probe_s`` that nobody is there. On a
    domain the user named, it listens as long for another memgs graph in the same ``namespace``
    and refuses to mix with it (PipelineError naming the way out); other nodes are welcome.
    """

    candidates = [domain_id] if domain_id is not None else random.sample(range(1, 233), tries)
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    for domain in candidates:
        context = rclpy.Context()
        rclpy.init(args=ros_args, context=context, domain_id=domain)
        probe = rclpy.create_node("memgs_run_domain_probe", context=context)
        time.sleep(probe_s)
        seen = [(n, s) for n, s in probe.get_node_names_and_namespaces() if n != "memgs_run_domain_probe"]
        probe.destroy_node()
        if domain_id is not None:
            ours = sorted({n for n, s in seen if s == ns and n in GRAPH_NAMES})
            if ours:
                rclpy.try_shutdown(context=context)
                raise PipelineError(
                    f"another memgs graph runs on ROS domain {domain} in namespace {ns} (its {', '.join(ours)}): "
                    f"the two would mix their frames and maps; pass --namespace /another or --domain-id N")
            return context, domain
        busy = [n for n, _ in seen]
        if not busy:
            return context, domain
        rclpy.try_shutdown(context=context)
    raise PipelineError(f"no free ROS domain found in {tries} tries; pass one with --domain-id")




SPIN_JOIN_TIMEOUT_S = 10.0  # how long stop_spinning waits for the executor's thread to end


def _spin(executor: Any) -> None:
    """``executor.spin()``, quiet about rclpy's own race at its end: ``Executor.shutdown`` destroys
    its guard condition without waiting for the thread inside ``spin``, which then can raise
    ``AttributeError: 'NoneType' object has no attribute 'handle'`` while building its next wait
    (a ``memgs run`` ending on a failed source printed the traceback). Only then: the spin was
    over anyway; any other error is raised."""
    try:
        executor.spin()
    except AttributeError:
        if getattr(executor, "_guard", None) is not None:  # not shut down: a real error
            raise


def spin_in_background(executor: Any) -> threading.Thread:
    """Spin ``executor`` on a thread of its own; end it with :func:`stop_spinning`."""
    thread = threading.Thread(target=_spin, args=(executor,), name="executor-spin", daemon=True)
    thread.start()
    return thread


def stop_spinning(executor: Any, thread: threading.Thread | None) -> None:
    """Shut ``executor`` down and wait for its spin thread to end.

    rclpy aborts the process ("terminate called without an active exception") when a thread
    still waits in its C++ code as the interpreter finalizes: a bare script that left its daemon
    spin thread running at exit aborted in 29 of 30 tries, joining it in 0 of 30 (and a SIGHUP'd
    ``memgs run`` once in CI).
    """
    executor.shutdown()
    if thread is None:
        return
    thread.join(timeout=SPIN_JOIN_TIMEOUT_S)
    if thread.is_alive():
        logger.warning("the executor's thread did not stop within %.0f s", SPIN_JOIN_TIMEOUT_S)
