"""The runner brings the managed nodes up through their lifecycle (ros/lifecycle.py), as a
lifecycle manager does: each started with ``autostart`` false, then *configure* requested of all
at once (they build in parallel: torch and the device, the session, the kernels' warm-up) and,
once all are inactive, *activate*. A node that refuses a transition ends the run with its name.
Nodes the runner starts later (a delayed start, a restart after a fault) start with
``autostart``: they come back on their own.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from memgs_ros.errors import PipelineError

__all__ = ["AUTOSTART_OFF", "bring_up"]

AUTOSTART_OFF = ("-p", "autostart:=false")  # after --params-file: wins over the file


def _await(futures: Mapping[str, Any], check: Callable[[], None], deadline: float, what: str) -> dict[str, Any]:
    """Each future's result (the executor spinning elsewhere completes them); ``check`` raises when
    a node process died meanwhile."""
    done = threading.Event()
    pending = set(futures)

    def settle(name: str) -> Callable[[Any], None]:
        def cb(_f: Any) -> None:
            pending.discard(name)
            if not pending:
                done.set()
        return cb

    for name, f in futures.items():
        f.add_done_callback(settle(name))
    while not done.wait(0.05):
        check()
        if time.monotonic() > deadline:
            raise PipelineError(f"{', '.join(sorted(pending))} did not answer {what} in time")
    # All done (the callbacks said so); rclpy's Future.result() never waits, it reads what was set.
    return {name: f.result() for name, f in futures.items()}


def bring_up(node: Any, names: Sequence[str], check: Callable[[], None], deadline: float) -> float:
    """Configure, then activate, the managed nodes ``names`` (in ``node``'s namespace) through
    ``<name>/change_state``; returns the seconds from the configure requests to the last active."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    clients = {n: node.create_client(ChangeState, f"{n}/change_state") for n in names}
    try:
        while waiting := [n for n, c in clients.items() if not c.service_is_ready()]:
            check()
            if time.monotonic() > deadline:
                raise PipelineError(f"{', '.join(waiting)} offered no lifecycle service (change_state) in time")
            time.sleep(0.05)
        t0 = time.perf_counter()
        for tid, label in ((Transition.TRANSITION_CONFIGURE, "configure"), (Transition.TRANSITION_ACTIVATE,
                                                                              "activate")):
            futures = {n: c.call_async(ChangeState.Request(transition=Transition(id=tid))) for n, c in clients.items()}
            answers = _await(futures, check, deadline, label)
            refused = sorted(n for n, a in answers.items() if not a.success)
            if refused:
                raise PipelineError(f"{', '.join(refused)} refused to {label} (see logs/<node>.log)")
        return time.perf_counter() - t0
    finally:
        for c in clients.values():
            node.destroy_client(c)
