"""The runner's spin thread ends quietly on rclpy's own shutdown race, and only on it."""
from __future__ import annotations

import pytest

from memgs_ros.orchestration.processes import _spin


class _Executor:
    def __init__(self, guard: object | None) -> None:
        self._guard = guard

    def spin(self) -> None:
        raise AttributeError("'NoneType' object has no attribute 'handle'")


def test_the_guard_destroyed_by_shutdown_ends_the_spin_quietly() -> None:
    _spin(_Executor(None))  # shut down: rclpy set its guard condition to None under the wait


def test_any_other_attribute_error_is_raised() -> None:
    with pytest.raises(AttributeError):
        _spin(_Executor(object()))  # not shut down: a real error
