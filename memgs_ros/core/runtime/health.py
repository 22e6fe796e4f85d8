"""A node's health from its stats: OK, WARN (degraded) or ERROR, judged on the current window.

Every node publishes its counters and gauges once a second (``ros/diagnostics.NodeStats``); the
level is decided from what changed since the previous publication, not from everything that ever
happened (a problem an hour ago does not keep a node in WARN). ``/diagnostics`` carries it, as
``diagnostic_aggregator`` and rqt read it, and the runner reads the same messages.

Rules (the first that holds):

- tracker: ERROR while the tracking state is LOST (no pose goes out); WARN while RECENTLY_LOST
  (poses coasted on the velocity model) or when frames were skipped in the window (stale, busy,
  unpaired: the camera outran the tracker or depth is missing);
- mapper: ERROR when its session's worker stopped (``alive`` fell to 0) or a command failed in the
  window (``problem.command_failed``), WARN when it is behind (``insert_queue`` beyond
  ``MAPPER_BEHIND_KEYFRAMES`` keyframes);
- every node: WARN when a problem was counted in the window; else OK.
"""
from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["Health", "Level", "assess"]

MAPPER_BEHIND_KEYFRAMES = 5  # keyframes waiting in the mapper's insert queue


class Level(enum.IntEnum):
    """diagnostic_msgs/DiagnosticStatus levels."""

    OK = 0
    WARN = 1
    ERROR = 2


@dataclass(frozen=True)
class Health:
    level: Level
    message: str


def _grew(now: Mapping[str, object], before: Mapping[str, object] | None, prefix: str) -> list[str]:
    """Keys under ``prefix`` whose count rose since ``before`` (all present ones when there is none)."""
    out = []
    for key, value in now.items():
        if not key.startswith(prefix) or not isinstance(value, (int, float)):
            continue
        old = (before or {}).get(key, 0)
        if value > (old if isinstance(old, (int, float)) else 0):
            out.append(key[len(prefix):])
    return sorted(out)


def assess(node: str, now: Mapping[str, object], before: Mapping[str, object] | None) -> Health:
    """The health of ``node`` (its stats name: tracker, mapper, ...) from its stats ``now`` and those
    of the previous window (``before``; None at the first publication)."""
    problems = _grew(now, before, "problem.")
    if node == "tracker":
        state = str(now.get("tracking_state", ""))
        if state == "LOST":
            return Health(Level.ERROR, "tracking lost: no pose until relocalisation")
        if state == "RECENTLY_LOST":
            return Health(Level.WARN, "tracking weak: poses coasted on the motion model")
        skipped = _grew(now, before, "skipped.")
        if skipped:
            return Health(Level.WARN, f"frames skipped ({', '.join(skipped)})")
    if node == "mapper":
        if now.get("alive") == 0 and (before or {}).get("alive") == 1:
            return Health(Level.ERROR, "mapping stopped: the session's worker is gone")
        if "command_failed" in problems:
            return Health(Level.ERROR, "a mapping command failed")
        pending = now.get("insert_queue", 0)
        if isinstance(pending, (int, float)) and pending > MAPPER_BEHIND_KEYFRAMES:
            return Health(Level.WARN, f"mapper behind: {int(pending)} keyframes wait for insertion")
    if problems:
        return Health(Level.WARN, f"problems: {', '.join(problems)}")
    if node == "tracker" and now.get("tracking_state") == "NOT_INITIALIZED":
        return Health(Level.OK, "waiting for a first frame with depth")
    return Health(Level.OK, "ok")
