"""Fault injection for tests and benchmarks only: not a node parameter, not in any config.

A test sets the environment variable ``MEMGS_TEST_FAULTS`` (``name=value`` pairs, comma-separated)
for the processes it starts; a node reads its own faults once at start. Unset, nothing is injected.

=============================  ==================================================================
fault                          effect
=============================  ==================================================================
merger.drop_every_nth_delta    the merger ignores every n-th delta on arrival (loss on the link),
                               counted as ``fault_dropped_deltas``
=============================  ==================================================================

    MEMGS_TEST_FAULTS=merger.drop_every_nth_delta=5 memgs run ...
"""
from __future__ import annotations

import os
from collections.abc import Mapping

from memgs_ros.errors import ConfigError

__all__ = ["FAULTS", "FAULTS_ENV", "EveryNth", "fault", "faults_env"]

FAULTS_ENV = "MEMGS_TEST_FAULTS"
FAULTS: dict[str, str] = {"merger.drop_every_nth_delta": "the merger ignores every n-th delta on arrival"}


def _parse(text: str) -> dict[str, int]:
    faults = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep or name.strip() not in FAULTS or not value.strip().isdigit():
            raise ConfigError(f"{FAULTS_ENV}: '{item}' is not NAME=N with NAME one of {', '.join(FAULTS)}")
        faults[name.strip()] = int(value)
    return faults


def fault(name: str, environ: Mapping[str, str] = os.environ) -> int:
    """The value of fault ``name`` in ``MEMGS_TEST_FAULTS`` (0: not injected). ConfigError when
    the variable is malformed or names an unknown fault."""
    assert name in FAULTS, name
    return _parse(environ.get(FAULTS_ENV, "")).get(name, 0)


def faults_env(faults: Mapping[str, int]) -> dict[str, str]:
    """The environment entry that injects ``faults`` into the processes a test starts."""
    text = ",".join(f"{name}={int(value)}" for name, value in faults.items())
    _parse(text)  # refuse an unknown fault here, in the test, not in a node's log
    return {FAULTS_ENV: text}


class EveryNth:
    """Called once per event: True for every ``n``-th (never when ``n`` is 0)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._count = 0

    def __call__(self) -> bool:
        self._count += 1
        return self.n > 0 and self._count % self.n == 0
