"""The three QoS profiles the nodes use (reference section 9, DESIGN.md topic contract).

- ``sensor()``: what camera subscribers use (BEST_EFFORT, VOLATILE, depth 5). It also
  receives from RELIABLE publishers, so it works with RealSense (RELIABLE by default)
  and with the bag player.
- ``reliable(depth)``: keyframes, seeds, map deltas, replay acknowledgements, and the bag player's
  sensor topics (a RELIABLE publisher serves both kinds of subscriber; a BEST_EFFORT one
  would starve RELIABLE subscribers).
- ``latched()``: RELIABLE + TRANSIENT_LOCAL, depth 1: the latest map snapshot or "done"
  flag reaches subscribers that join late. Subscribers must use it too to get the
  latched sample.
- ``keyframes(depth)``: RELIABLE + TRANSIENT_LOCAL, keep last ``depth`` (10): the keyframe
  topics (tracker -> sampler -> mapper). A sampler or mapper that restarts (after a crash, from
  its checkpoint) receives the most recent keyframes again instead of losing the ones sent
  while it was down; receivers ignore stamps they already hold. Publishers and subscribers of
  these topics must both use it (a VOLATILE publisher cannot serve a TRANSIENT_LOCAL reader).
"""
from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

__all__ = ["keyframes", "latched", "reliable", "sensor"]


def sensor() -> QoSProfile:
    """qos_profile_sensor_data (BEST_EFFORT, VOLATILE, keep last 5), as a fresh copy."""
    p = qos_profile_sensor_data
    return QoSProfile(history=p.history, depth=p.depth, reliability=p.reliability, durability=p.durability)


def _reliable(depth: int, durability: DurabilityPolicy) -> QoSProfile:
    if depth < 1:
        raise ValueError(f"QoS depth must be >= 1, got {depth}")
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=durability)


def reliable(depth: int = 10) -> QoSProfile:
    """RELIABLE, VOLATILE, keep last ``depth`` (>= 1)."""
    return _reliable(depth, DurabilityPolicy.VOLATILE)


def latched() -> QoSProfile:
    """RELIABLE, TRANSIENT_LOCAL, keep last 1: late joiners get the last sample."""
    return _reliable(1, DurabilityPolicy.TRANSIENT_LOCAL)


def keyframes(depth: int = 10) -> QoSProfile:
    """RELIABLE, TRANSIENT_LOCAL, keep last ``depth``: late or restarted readers get the latest
    ``depth`` keyframes."""
    return _reliable(depth, DurabilityPolicy.TRANSIENT_LOCAL)
