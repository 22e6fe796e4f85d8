"""docs/parameters.md is the nodes' parameter tables, current, complete and as the nodes declare them."""
from __future__ import annotations

from pathlib import Path

import pytest

from memgs_ros.nodes.registry import node_name
from memgs_ros.orchestration import param_reference as ref
from memgs_ros.ros.config_params import ROS_PARAMETERS, module_parameter_names, module_specs

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / ref.DEFAULT_PATH


def test_the_reference_file_is_current() -> None:
    assert DOC.is_file(), f"{ref.DEFAULT_PATH} is missing: run {ref.REGENERATE}"
    assert DOC.read_text(encoding="utf-8") == ref.render_markdown(), (
        f"{ref.DEFAULT_PATH} is stale (a node's parameters changed): run {ref.REGENERATE}")


def test_every_declared_parameter_is_listed_once_under_its_node() -> None:
    """The names are those config_params.module_parameter_names gives (what the CLI checks overrides
    against, and what test_node_bad_input shows the running nodes declare)."""
    text = ref.render_markdown()
    sections = {s.split("\n", 1)[0]: s for s in text.split("\n## ")[1:]}
    modules = ref.node_modules()
    assert [node_name(m.__name__) for m in modules] == list(sections)
    for module in modules:
        node = node_name(module.__name__)
        rows = ref.parameter_rows(module)
        names = [r.name for r in rows]
        assert len(names) == len(set(names)), f"{node}: a parameter listed twice"
        assert set(names) == module_parameter_names(module) - ROS_PARAMETERS, node
        for row in rows:
            assert row.node == node and row.type and row.default and row.description, row
            assert sections[node].count(f"\n| `{row.name}` |") == 1, f"{node}.{row.name} not in its table"


def test_ranges_and_choices_are_those_the_nodes_enforce() -> None:
    rows = {(r.node, r.name): r for m in ref.node_modules() for r in ref.parameter_rows(m)}
    assert rows["tracker", "sync"].range == "one of `approximate`, `exact`"
    assert rows["tracker", "sync"].description == "colour/depth pairing"
    assert rows["mapper", "insert_queue"].range == "[1, 1000]"  # MapperParams.RANGES
    assert rows["mapper", "mode"].range == "one of `rgbd`, `mono`"  # MapperParams.CHOICES
    assert rows["mapper", "mode"].description == "camera mode: rgbd, or mono (keyframes carry no depth)"
    assert rows["tracker", "camera.k1"].range == "[-1000000, 1000000]"  # CameraCalibration.RANGES: either sign
    assert rows["tracker", "camera.fx"].range == "[0, 1000000]"  # CameraCalibration.RANGES
    assert rows["mapper", "mapping.max_gaussians"].range == "[0, 1000000000]"  # MappingConfig.RANGES
    assert rows["tracker", "camera_info_override"].range == ""  # bool: no range
    assert rows["merger", "render_fx"].default == "`258.65`" and rows["mapper", "iterations_per_frame"].default == "`10`"
    assert rows["recorder", "topics"].type == "string array"


def test_rows_equal_what_running_nodes_declare(context, tmp_path: Path) -> None:  # noqa: ANN001
    """The stand-in node records what a real rclpy node gets: same names, defaults, descriptions,
    ranges. (The mapper is left out: it takes ~20 s to start on a CPU; its groups go through the
    same declare_config, with the RANGES on its classes.)"""
    from rclpy.parameter import Parameter

    from memgs_ros.nodes.bag_player import node as bag_player
    from memgs_ros.nodes.keyframe_sampler import node as keyframe_sampler
    from memgs_ros.nodes.merger import node as merger
    from memgs_ros.nodes.recorder import node as recorder
    from memgs_ros.nodes.tracker import node as tracker

    cases = ((tracker, tracker.TrackerNode, []), (merger, merger.MergerNode, []),
             (keyframe_sampler, keyframe_sampler.KeyframeSamplerNode, []),
             (bag_player, lambda **kw: bag_player.BagPlayer(frames=[], **kw), []),
             (recorder, recorder.RecorderNode, [Parameter("path", value=str(tmp_path / "run.mcap"))]))
    for module, factory, overrides in cases:
        node = factory(context=context, parameter_overrides=overrides)
        try:
            declared = {name: (p.value, node.describe_parameter(name))
                        for name, p in node._parameters.items() if name not in ROS_PARAMETERS}
            if overrides:  # the row shows the default, not this test's value
                declared.update({p.name: (next(s.default for s in module_specs(module) if s.name == p.name),
                                          declared[p.name][1]) for p in overrides})
        finally:
            node.destroy_node()
        real = sorted(ref.rows_from_declarations(module, declared), key=lambda r: r.name)
        assert real == sorted(ref.parameter_rows(module), key=lambda r: r.name), module.__name__


def test_check_exits_1_on_a_stale_file_and_names_the_command(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    stale = tmp_path / "parameters.md"
    stale.write_text("# old\n", encoding="utf-8")
    assert ref.main(["--check", str(stale)]) == 1
    assert f"--write {stale}" in capsys.readouterr().err
    assert ref.main(["--write", str(stale)]) == 0
    assert ref.main(["--check", str(stale)]) == 0
    assert stale.read_text(encoding="utf-8") == ref.render_markdown()
