"""Fault injection is test-only: an environment variable read by the nodes, never a parameter."""
from __future__ import annotations

import pytest

from memgs_ros.errors import ConfigError
from memgs_ros.testing.faults import FAULTS_ENV, EveryNth, fault, faults_env


def test_faults_come_from_the_environment_only() -> None:
    env = faults_env({"merger.drop_every_nth_delta": 3})
    assert env == {FAULTS_ENV: "merger.drop_every_nth_delta=3"}
    assert fault("merger.drop_every_nth_delta", env) == 3
    assert fault("merger.drop_every_nth_delta", {}) == 0  # unset: nothing injected
    with pytest.raises(ConfigError, match=r"MEMGS_TEST_FAULTS: 'merger.drop_every=2' is not NAME=N"):
        fault("merger.drop_every_nth_delta", {FAULTS_ENV: "merger.drop_every=2"})
    with pytest.raises(ConfigError, match="is not NAME=N"):
        faults_env({"mapper.crash": 1})


def test_every_nth() -> None:
    drop = EveryNth(3)
    assert [drop() for _ in range(7)] == [False, False, True, False, False, True, False]
    never = EveryNth(0)
    assert not any(never() for _ in range(5))


def test_no_node_declares_a_fault_parameter() -> None:
    from memgs_ros.nodes.params import NODE_CONFIGS
    from memgs_ros.ros.config_params import config_specs

    names = [spec.name for configs in NODE_CONFIGS.values() for prefix, cls in configs
             for spec in config_specs(cls, prefix)]
    assert names and not [n for n in names if "fault" in n]
