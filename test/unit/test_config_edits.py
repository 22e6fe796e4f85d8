"""Typed config changes (orchestration/run_files.ConfigEdit): a ``dataclasses.replace`` on a node's
config group, turned into parameters only in the run's parameter file."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from memgs_ros.core.mapping.config import MappingConfig
from memgs_ros.core.sampling import PatchGridConfig
from memgs_ros.errors import ConfigError
from memgs_ros.evaluation.runs import ABLATION_VARIANTS, run_edits
from memgs_ros.orchestration.run_files import ConfigEdit, RunOptions, build_params, edited_parameters, node_params


def _params(**kw: object) -> dict:
    return node_params(build_params(RunOptions(source="x", config="tum_fr1", **kw), Path("/tmp/m.ply")))  # type: ignore[arg-type]


def test_an_edit_becomes_the_parameters_it_changes_against_the_config() -> None:
    half = ConfigEdit("mapper", "mapping", MappingConfig, lambda c: replace(c, resolution_scale=c.resolution_scale / 2))
    assert _params()["mapper"]["mapping.resolution_scale"] == 0.5  # tum_fr1's own
    assert edited_parameters("tum_fr1", [half]) == {"mapper.mapping.resolution_scale": 0.25}
    assert edited_parameters("tum_fr1", run_edits("rgbd", 0, None)) == {}  # the config already says so
    assert edited_parameters("tum_fr1", ABLATION_VARIANTS["no_patch_grid"]) == {"keyframe_sampler.patch_grid.enabled": False}


def test_edits_apply_in_order_and_a_users_override_wins() -> None:
    p = _params(edits=run_edits("mono", 3, 0.25), overrides={"mapper.mapping.seed": 9})
    assert (p["tracker"]["tracker.mode"], p["keyframe_sampler"]["mode"], p["mapper"]["mode"]) == ("mono",) * 3
    assert p["mapper"]["mapping.resolution_scale"] == 0.25 and p["keyframe_sampler"]["patch_grid.seed"] == 3
    assert p["mapper"]["mapping.seed"] == 9


def test_an_edit_of_a_group_the_node_does_not_have_is_refused() -> None:
    wrong = ConfigEdit("mapper", "patch_grid", PatchGridConfig, lambda c: replace(c, enabled=False))
    with pytest.raises(ConfigError, match="mapper has no config group 'patch_grid'"):
        _params(edits=(wrong,))


def test_an_edit_the_config_refuses_is_refused_before_a_node_starts() -> None:
    bad = ConfigEdit("mapper", "mapping", MappingConfig, lambda c: replace(c, resolution_scale=-1.0))
    with pytest.raises(ConfigError, match="resolution_scale"):
        _params(edits=(bad,))
