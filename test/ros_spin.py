"""Waiting on an event in tests that spin nodes in-process: spin the executor until it happens."""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def spin_until(ex: Any, cond: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    """Spin ``ex`` (an rclpy executor) until ``cond()`` holds; False when ``timeout_s`` ran out first."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.02)
        if cond():
            return True
    return False
