"""Parameters from config dataclasses: the specs they declare, and check_values judging given values
without a node, in the words a node uses when it refuses the same values at start."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pytest
from rclpy.parameter import Parameter

from memgs_ros.core.geometry.camera import CameraCalibration
from memgs_ros.errors import ConfigError
from memgs_ros.nodes.bag_player.node import BagPlayer
from memgs_ros.nodes.keyframe_sampler.node import KeyframeSamplerNode
from memgs_ros.nodes.merger.node import MergerNode
from memgs_ros.nodes.params import DEFAULT_TOPICS, KeyframeSamplerParams, MapperParams, MergerParams, RecorderParams
from memgs_ros.ros.config_params import check_values, config_specs, parameter_names, unknown_parameters
from memgs_ros.ros.params import ParamSpec


@dataclass(frozen=True)
class _Example:
    """A config with every kind of field.

    long_one: a description too long for the field's line,
        continued here
    """

    count: int = 3  # how many
    gain: float = -0.5  # any sign
    flag: bool = False  # on or off
    kind: str = "a"  # which kind
    names: tuple[str, ...] = ("x", "y")  # a string array
    long_one: float = 1.0
    weights: tuple[float, float] = (1.0, 2.0)  # not a parameter: only string tuples are

    RANGES: ClassVar[dict[str, tuple[float, float]]] = {"count": (1, 10)}
    CHOICES: ClassVar[dict[str, tuple[str, ...]]] = {"kind": ("a", "b")}

    def __post_init__(self) -> None:
        if self.flag and self.count < 5:
            raise ValueError("flag needs count >= 5")


def test_specs_carry_names_defaults_descriptions_ranges_and_choices() -> None:
    specs = {s.name: s for s in config_specs(_Example, "ex")}
    assert list(specs) == ["ex.count", "ex.gain", "ex.flag", "ex.kind", "ex.names", "ex.long_one"]
    assert specs["ex.count"] == ParamSpec("ex.count", 3, "how many", (1, 10))
    assert specs["ex.gain"].range == (-1e12, 1e12)  # no RANGES entry: any sign, as the default has
    assert specs["ex.long_one"].range == (0, 1e12) and specs["ex.flag"].range is None
    assert specs["ex.long_one"].description == "a description too long for the field's line, continued here"
    assert specs["ex.kind"].choices == ("a", "b")
    assert specs["ex.names"].default == ("x", "y") and specs["ex.names"].range is None
    assert config_specs(_Example, "ex", ranges={"count": (0, 3)})[0].range == (0, 3)  # ranges= overrides RANGES
    assert config_specs(_Example, "", defaults={"kind": "b"})[3] == ParamSpec("kind", "b", "which kind",
                                                                              choices=("a", "b"))
    assert parameter_names([("ex", _Example), ("", RecorderParams)]) >= {"ex.names", "topics", "use_sim_time"}


def test_good_values_pass() -> None:
    given = {"ex.count": 7, "ex.gain": -2.0, "ex.flag": True, "ex.kind": "b", "ex.names": ["p", "q"],
             "other.thing": "not this config's: left to unknown_parameters"}
    assert check_values(_Example, "ex", given) == []
    assert check_values(RecorderParams, "", {"topics": list(DEFAULT_TOPICS[:2]), "path": "/tmp/a.mcap"}) == []


def test_wrong_types_are_named_with_the_type_wanted() -> None:
    lines = check_values(MergerParams, "", {"render_width": "320", "max_buffered_deltas": True, "render_fx": 2,
                                            "world_frame": 3})
    assert lines == [
        "parameter 'max_buffered_deltas' must be of type int, got True",  # bool is no int to rclpy
        "parameter 'world_frame' must be of type str, got 3",
        "parameter 'render_width' must be of type int, got '320'",
        "parameter 'render_fx' must be of type float (write floats with a decimal point, e.g. 2.0), got 2",
    ]
    assert check_values(MergerParams, "", {"render_fx": 2}, int_as_float=True) == []


def test_out_of_range_and_nan_are_refused() -> None:
    assert check_values(MergerParams, "", {"render_width": 0, "save_period_s": 2e6}) == [
        "parameter 'save_period_s' = 2000000.0 is outside [0.0, 1000000.0]",
        "parameter 'render_width' = 0 is outside [1, 8192]",
    ]
    assert check_values(MergerParams, "", {"render_fx": math.nan}) == [
        "parameter 'render_fx' = nan is outside [0.001, 1000000.0]"]
    # a number without a RANGES entry keeps the sign of its default (mapping.* and the like)
    assert check_values(_Example, "ex", {"ex.long_one": -1.0}) == [
        "parameter 'ex.long_one' = -1.0 is outside [0, 1000000000000.0]"]


def test_a_bad_choice_lists_the_allowed_values() -> None:
    assert check_values(MapperParams, "", {"mode": "stereo"}, node="mapper") == [
        "mapper: parameter 'mode' = 'stereo' is not one of ['rgbd', 'mono']"]


def test_the_pacing_is_one_value_and_its_old_parameters_name_the_new_ones() -> None:
    assert check_values(MapperParams, "", {"pacing": "fast"}, node="mapper") == [
        "mapper: parameter 'pacing' = 'fast' is not one of ['live', 'lockstep']"]
    assert MapperParams(pacing="lockstep").replay.acknowledged and not MapperParams().replay.acknowledged
    declared = parameter_names([("", MapperParams)])
    assert unknown_parameters("mapper", ["lockstep_iterations", "lockstep", "lockstep_windw"], declared) == [
        "mapper has no parameter 'lockstep': it is called 'pacing' now",
        "mapper has no parameter 'lockstep_iterations': it is called 'iterations_per_frame' now",
        "mapper has no parameter 'lockstep_windw' (did you mean ack_window?)"]


def test_the_configs_own_validation_judges_the_whole_group() -> None:
    assert check_values(CameraCalibration, "camera", {"camera.fx": 500.0, "camera.k1": -0.2}) == [
        "parameters 'camera.*': camera calibration: camera.width, camera.height, camera.fy, camera.cx, camera.cy "
        "missing or 0"]
    assert check_values(_Example, "ex", {"ex.flag": True}) == [
        "parameters 'ex.*' are inconsistent: flag needs count >= 5"]
    assert check_values(_Example, "ex", {"ex.flag": True}, defaults={"count": 5}) == []
    # a value refused on its own is not also passed to the config (no second, confusing line)
    assert check_values(_Example, "ex", {"ex.flag": True, "ex.count": 0}) == [
        "parameter 'ex.count' = 0 is outside [1, 10]"]


def test_string_arrays() -> None:
    assert check_values(RecorderParams, "", {"topics": ("memgs/pose",)}) == []
    assert check_values(RecorderParams, "", {"topics": "memgs/pose"}) == [
        "parameter 'topics' must be of type string array, got 'memgs/pose'"]
    assert check_values(RecorderParams, "", {"topics": ["memgs/pose", 3]}) == [
        "parameter 'topics' must be of type string array, got ['memgs/pose', 3]"]


def _refusal(factory, overrides: dict[str, object]) -> str:  # noqa: ANN001 - a node class or factory
    with pytest.raises(ConfigError) as info:
        factory(parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()]).destroy_node()
    return str(info.value)


@pytest.mark.parametrize("cls, prefix, overrides", [
    (MergerParams, "", {"render_width": 0}),  # rclpy's own range check refuses it first
    (MergerParams, "", {"render_fx": math.nan}),
    (MergerParams, "", {"render_fx": 2}),  # rclpy: an int for a float parameter
    (MergerParams, "", {"max_buffered_deltas": True}),
    (KeyframeSamplerParams, "", {"mode": "stereo"}),
    (CameraCalibration, "camera", {"camera.fx": 500.0}),  # the config's __post_init__
])
def test_check_values_says_what_the_node_says_at_start(context, cls: type, prefix: str,  # noqa: ANN001
                                                      overrides: dict[str, object]) -> None:
    factories = {MergerParams: MergerNode, KeyframeSamplerParams: KeyframeSamplerNode,
                 CameraCalibration: lambda **kw: BagPlayer(frames=[], **kw)}
    at_start = _refusal(lambda **kw: factories[cls](context=context, **kw), overrides)
    (before,) = check_values(cls, prefix, overrides)
    if " must be of type " in before:  # the node adds rclpy's own words after a colon
        assert at_start.startswith(before.split(", got ")[0] + ": "), (before, at_start)
    else:
        assert before == at_start


def test_every_number_of_every_config_has_a_range_a_user_can_reason_about() -> None:
    """No parameter falls back to the catch-all [0, 1e12]: each numeric field of a node's configs
    has a range of its own (a typo such as resolution_scale=50 for 0.5 is then refused)."""
    import dataclasses
    import importlib

    from memgs_ros.nodes.registry import NODES

    missing = []
    for node, (module_name, _) in NODES.items():
        module = importlib.import_module(module_name)
        for prefix, cls in module.CONFIGS:
            ranges = getattr(cls, "RANGES", {})
            for f in dataclasses.fields(cls):
                numeric = isinstance(f.default, (int, float)) and not isinstance(f.default, bool)
                if numeric and f.name not in ranges:
                    missing.append(f"{node}: {prefix + '.' if prefix else ''}{f.name}")
    assert missing == [], missing


def test_parameters_are_checked_without_rclpy() -> None:
    """The runner checks a config before any node starts, from the parameter tables alone: with
    rclpy unimportable the check still runs and still refuses an out-of-range value."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['rclpy'] = None\n"
        "from memgs_ros.errors import ConfigError\n"
        "from memgs_ros.orchestration.run_files import check_parameters\n"
        "check_parameters({'mapper': {'mapping.resolution_scale': 0.5}, 'tracker': {'depth_scale': 5000.0}})\n"
        "try:\n"
        "    check_parameters({'mapper': {'mapping.resolution_scale': 50.0}})\n"
        "except ConfigError as err:\n"
        "    print(err)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "resolution_scale" in out.stdout and "50" in out.stdout, out.stdout


def test_the_tracker_reads_a_replay_in_the_units_its_player_writes(tmp_path: Path) -> None:
    """The tracker alone reads a camera's 16-bit units (depth_scale; the player declares none and
    sampler and mapper get REP-118's): ``memgs run`` sets it to what the player writes, a TUM
    folder's PNG units as stored (its camera.json's, or TUM's 5000) or millimetres for depth read as
    metres; a user's own ``--set`` still wins."""
    from memgs_ros.core.geometry.camera import PinholeCamera
    from memgs_ros.io.tum import write_camera_json
    from memgs_ros.orchestration.run_files import RunOptions, build_params, check_parameters, node_params

    def params(source: str, **kw: object) -> dict[str, dict]:
        return node_params(build_params(RunOptions(source, config="tum_fr1", **kw), tmp_path / "m.ply"))

    synth = params("synthetic:w=32,h=24,n=2")
    assert synth["tracker"]["depth_scale"] == 1000.0 and synth["bag_player"]["depth_encoding"] == "16UC1"
    assert not {"depth_scale"} & (set(synth["bag_player"]) | set(synth["keyframe_sampler"]) | set(synth["mapper"]))
    check_parameters(synth)
    folder = tmp_path / "rgbd_dataset_freiburg1_x"
    folder.mkdir()
    (folder / "rgb.txt").write_text("")
    assert params(str(folder))["tracker"]["depth_scale"] == 5000.0  # TUM's own, by the folder's name
    own = tmp_path / "my_room"
    own.mkdir()
    (own / "rgb.txt").write_text("")
    write_camera_json(own / "camera.json", PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0), 1000.0)
    assert params(str(own))["tracker"]["depth_scale"] == 1000.0
    assert params(str(own), overrides={"tracker.depth_scale": 4000.0})["tracker"]["depth_scale"] == 4000.0
