"""A calibration in the config instead of camera_info (TUM's bags carry the ROS default one).

Unit tests: the configs carry the published TUM calibrations, the comparison and its warning,
a TUM folder's camera (camera.json, folder name, config) and the error when none gives one.
Node and pipeline tests (ROS): the tracker uses the configured camera for every keyframe it
hands on, and a whole run on a bag with a wrong camera_info maps with the true camera.
"""
from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from memgs_ros.cli import main
from memgs_ros.cli.run import calibration_warning, check_inputs, run_log
from memgs_ros.core.geometry.camera import (
    TUM_CAMERAS,
    TUM_FR1,
    TUM_FR3,
    CameraCalibration,
    PinholeCamera,
    calibration_differences,
)
from memgs_ros.errors import ConfigError, DataError, PipelineError
from memgs_ros.io.synthetic import generate_frames, parse_spec, write_tum_folder
from memgs_ros.io.tum import CAMERA_JSON, TumFolder, write_camera_json
from memgs_ros.orchestration.run_files import (
    ConfiguredCamera,
    RunOptions,
    build_params,
    config_path,
    configured_camera,
    node_params,
)

# What TUM's ROS 1 bags publish as camera_info (reference section 6).
ROS_DEFAULT = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
SMALL = "synthetic:w=64,h=48,n=4,seed=1"


def _params(config: str, overrides: dict | None = None) -> dict[str, dict]:
    return node_params(build_params(RunOptions(source=SMALL, config=config, overrides=overrides or {}),
                                    Path("map.ply")))


def _config_with_camera(tmp_path: Path, camera: PinholeCamera, override: bool = True, base: str = "synthetic") -> Path:
    """``base`` config plus ``camera`` as the tracker's calibration, written to tmp_path."""
    data = yaml.safe_load(config_path(base).read_text())
    tracker = data["/**/tracker"]["ros__parameters"]
    tracker["camera_info_override"] = override
    tracker.update({f"camera.{k}": v for k, v in dataclasses.asdict(CameraCalibration.from_camera(camera)).items()})
    path = tmp_path / "calibrated.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


# ----------------------------------------------------------------------------- configs


@pytest.mark.parametrize("key", ["fr1", "fr2", "fr3"])
def test_tum_configs_carry_the_published_calibration(key: str) -> None:
    """config/tum_frN.yaml and core.camera.TUM_FRN are one calibration (reference section 6)."""
    params = _params(f"tum_{key}")
    got = configured_camera(params)
    assert got.override is True
    assert got.camera == TUM_CAMERAS[key]  # exact: the YAML spells the constants' digits
    # The player gets the same calibration (the camera of a folder that names none).
    assert CameraCalibration.from_params(params["bag_player"]).camera() == TUM_CAMERAS[key]


def test_configs_without_calibration() -> None:
    assert configured_camera(_params("synthetic")) == ConfiguredCamera(None, False)
    off = configured_camera(_params("tum_fr1", {"tracker.camera_info_override": False}))
    assert off == ConfiguredCamera(TUM_FR1, False)


def test_partial_or_bad_calibration_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"camera.cx, camera.cy missing"):
        CameraCalibration(width=640, height=480, fx=500.0, fy=500.0)
    with pytest.raises(ConfigError, match="only some are set"):
        CameraCalibration(fy=500.0)
    with pytest.raises(ConfigError, match=r"tum_fr1.yaml: parameter 'camera.fx' must be a number"):
        _params("tum_fr1", {"tracker.camera.fx": "big"})
    with pytest.raises(ConfigError, match="camera_info_override is true but the tracker has no camera"):
        _params("synthetic", {"tracker.camera_info_override": True})
    with pytest.raises(ConfigError, match="camera_info_override must be true or false"):
        _params("tum_fr1", {"tracker.camera_info_override": "yes please"})


def test_calibration_round_trips_and_rational_polynomial() -> None:
    assert CameraCalibration.from_camera(TUM_FR1).camera() == TUM_FR1
    assert CameraCalibration().camera() is None
    rp = PinholeCamera(640, 480, 500, 500, 320, 240, (0.1, 0.01, 0.0, 0.0, 0.001, 0.2, 0.02, 0.002))
    assert CameraCalibration.from_camera(rp).camera() == rp


# ----------------------------------------------------------------------------- comparison


def test_calibration_differences() -> None:
    diffs = calibration_differences(ROS_DEFAULT, TUM_FR1)
    # cx differs by 0.3 %: under the 1 % threshold
    assert [d.split()[0] for d in diffs] == ["fx", "fy", "cy", "distortion"], diffs
    assert diffs[0] == "fx 525.0 vs 517.3 (+1.5 %)"
    assert diffs[-1] == "distortion none vs present"
    assert calibration_differences(TUM_FR1, TUM_FR1) == []
    assert calibration_differences(TUM_FR1.scaled(0.25), TUM_FR1) == []  # compared at the images' size
    near = dataclasses.replace(TUM_FR3, fx=TUM_FR3.fx * 1.009, cy=TUM_FR3.cy * 0.991)
    assert calibration_differences(near, TUM_FR3) == []
    assert calibration_differences(PinholeCamera(64, 64, 50, 50, 32, 32), TUM_FR3) == ["image size 64x64 vs 640x480"]


def test_warning_says_which_camera_the_nodes_use() -> None:
    on = calibration_warning("tum.bag", ROS_DEFAULT, ConfiguredCamera(TUM_FR1, True), "tum_fr1")
    assert on is not None
    assert on.startswith("tum.bag: camera_info (fx 525.0, fy 525.0, cx 319.5, cy 239.5, no distortion (640x480)) "
                         "differs from the calibration in config tum_fr1 (fx 517.3")
    assert on.endswith("the nodes use the config's (camera_info_override)")
    off = calibration_warning("tum.bag", ROS_DEFAULT, ConfiguredCamera(TUM_FR1, False), "tum_fr1")
    assert off is not None and off.endswith("--set tracker.camera_info_override=true uses the config's")
    assert calibration_warning("x", TUM_FR1, ConfiguredCamera(TUM_FR1, True), "tum_fr1") is None
    assert calibration_warning("x", ROS_DEFAULT, ConfiguredCamera(None, False), "synthetic") is None
    with pytest.raises(ConfigError, match="its calibration cannot be used for x: images are 64x64"):
        calibration_warning("x", PinholeCamera(64, 64, 50, 50, 32, 32), ConfiguredCamera(TUM_FR1, True), "tum_fr1")


def _wrong_info_bag(tmp_path: Path, spec: str, ros1: bool = True) -> tuple[Path, PinholeCamera]:
    """A bag of ``spec`` whose camera_info is the ROS default scaled to the images (TUM's bags);
    returns it and the camera the images were made with."""
    from memgs_ros.io.bag_writer import write_bag, write_ros1_tum_bag

    frames = list(generate_frames(parse_spec(spec)))
    true = frames[0].camera
    wrong = ROS_DEFAULT.fitted(true.width, true.height)
    assert calibration_differences(wrong, true), "the bag's camera_info must be clearly wrong"
    out = tmp_path / ("wrong_info.bag" if ros1 else "wrong_info.mcap")
    (write_ros1_tum_bag if ros1 else write_bag)([dataclasses.replace(f, camera=wrong) for f in frames], out)
    return out, true


def test_check_inputs_warns_when_the_bag_disagrees(tmp_path: Path) -> None:
    bag, true = _wrong_info_bag(tmp_path, SMALL)
    config = _config_with_camera(tmp_path, true)
    (warning,) = check_inputs(str(bag), str(config))
    assert warning.startswith(f"{bag}: camera_info (fx 52.5, fy 52.5, cx 31.5, cy 23.5, no distortion (64x48))")
    assert "cy 23.5 vs 24.3" in warning and warning.endswith("(camera_info_override)")
    # the true camera in the bag: nothing to say; a config without calibration: nothing to compare
    assert check_inputs(SMALL, str(config)) == []
    assert check_inputs(str(bag), "synthetic") == []


def test_cli_warns_once_on_console_and_in_the_run_log(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("rclpy", reason="the run command imports the pipeline (ROS extra)")
    import memgs_ros.orchestration.pipeline as pipeline

    bag, true = _wrong_info_bag(tmp_path, SMALL)
    config = _config_with_camera(tmp_path, true)
    started: list[RunOptions] = []

    def no_graph(options: RunOptions, progress: bool = True) -> None:
        started.append(options)
        raise PipelineError("stopped by the test before any node")

    monkeypatch.setattr(pipeline, "run_pipeline", no_graph)
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING):
        code = main(["run", "--bag", str(bag), "--config", str(config), "--out", str(out)])
    assert code == 2 and len(started) == 1
    console = [r.getMessage() for r in caplog.records if "differs from the calibration" in r.getMessage()]
    assert len(console) == 1
    log = (out / "logs" / "memgs.log").read_text()
    assert log.count("differs from the calibration") == 1 and console[0] in log


def test_run_log_is_released(tmp_path: Path) -> None:
    with run_log(tmp_path) as path:
        logging.getLogger("memgs_ros.test").warning("inside")
    logging.getLogger("memgs_ros.test").warning("outside")
    text = path.read_text()
    assert "inside" in text and "outside" not in text


# ----------------------------------------------------------------------------- TUM folders


def _folder(tmp_path: Path, name: str, with_json: bool = True) -> Path:
    path = tmp_path / name
    write_tum_folder(generate_frames(parse_spec(SMALL)), path)
    if not with_json:
        (path / CAMERA_JSON).unlink()
    return path


def test_folder_camera_order(tmp_path: Path) -> None:
    """camera.json, then the folder name, then the configured default; all rescaled to the images."""
    spec_camera = parse_spec(SMALL).camera
    mine = PinholeCamera(640, 480, 600.0, 600.0, 320.0, 240.0)
    with_json = _folder(tmp_path, "rgbd_dataset_freiburg1_json")
    src = TumFolder(with_json, default_camera=mine)
    assert (src.camera_origin, src.camera) == (CAMERA_JSON, spec_camera)
    named = _folder(tmp_path, "rgbd_dataset_freiburg1_named", with_json=False)
    src = TumFolder(named, default_camera=mine)
    assert (src.camera_origin, src.camera) == ("folder name", TUM_FR1.scaled(0.1))
    mycopy = _folder(tmp_path, "mycopy", with_json=False)
    src = TumFolder(mycopy, default_camera=mine)
    assert (src.camera_origin, src.camera) == ("default", mine.scaled(0.1))
    assert len(list(src)) == 4
    src = TumFolder(mycopy)
    assert src.camera_origin == ""
    with pytest.raises(DataError, match="mycopy: cannot tell the camera: no camera.json"):
        _ = src.camera
    # camera.json is the documented format: write one and it is used
    write_camera_json(mycopy / CAMERA_JSON, mine, 5000.0)
    assert TumFolder(mycopy).camera == mine.scaled(0.1)


def test_unknown_folder_camera_fails_before_any_node(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    mycopy = _folder(tmp_path, "mycopy", with_json=False)
    out = tmp_path / "out"
    code = main(["run", "--bag", str(mycopy), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == ("memgs run: error: mycopy: cannot tell the camera: no camera.json, folder name has no "
                   "freiburg1/2/3 and the config (synthetic) gives no calibration; pass --config tum_fr1 "
                   "(tum_fr2, tum_fr3) or write camera.json (see README)")
    assert not out.exists()  # checked before anything was started or written
    code = main(["eval", str(mycopy), "--config", "synthetic", "--out", str(out)])
    assert code == 2 and "mycopy: cannot tell the camera" in capsys.readouterr().err
    # with a config that carries a calibration the folder is accepted: its camera is the config's
    assert check_inputs(str(mycopy), "tum_fr3") == []


def test_evaluation_scores_with_the_camera_the_run_used(tmp_path: Path) -> None:
    from memgs_ros.evaluation.runs import _ground_truth_images

    bag, true = _wrong_info_bag(tmp_path, SMALL, ros1=False)
    wrong = ROS_DEFAULT.fitted(true.width, true.height)
    assert _ground_truth_images(str(bag), 0, 1.0)[2] == wrong
    assert _ground_truth_images(str(bag), 0, 1.0, ConfiguredCamera(true, True))[2] == true
    assert _ground_truth_images(str(bag), 0, 1.0, ConfiguredCamera(true, False))[2] == wrong
    mycopy = _folder(tmp_path, "mycopy", with_json=False)
    got = _ground_truth_images(str(mycopy), 0, 0.5, ConfiguredCamera(TUM_FR3, True))[2]
    assert got == TUM_FR3.fitted(64, 48).scaled(0.5)


# ----------------------------------------------------------------------------- nodes (ROS)


def _spin_until(executor, cond, timeout_s: float = 20.0) -> bool:  # noqa: ANN001
    import time

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
        if cond():
            return True
    return False


@pytest.mark.ros
@pytest.mark.parametrize("override", [True, False])
def test_tracker_hands_on_the_configured_camera(context, override: bool) -> None:  # noqa: ANN001
    """camera_info says the ROS default; with the override the tracker's keyframes carry the
    configured camera (what sampler and mapper use), without it they carry camera_info's."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import CameraInfo, Image

    from memgs_ros.io.image_decoding import decode_camera_info
    from memgs_ros.nodes.tracker.node import TrackerNode
    from memgs_ros.ros import qos
    from memgs_ros.ros.images import camera_to_camera_info, depth_to_image, numpy_to_image

    frames = list(generate_frames(parse_spec("synthetic:w=128,h=96,n=2,seed=2")))
    true = frames[0].camera
    wrong = ROS_DEFAULT.fitted(true.width, true.height)
    # The calibration is given for 640x480: the tracker rescales it to the 128x96 images.
    calib = true.scaled(5.0)
    params = [Parameter("color_topic", value="color/image_raw"), Parameter("depth_topic", value="depth/image_raw"),
              Parameter("camera_info_topic", value="color/camera_info"), Parameter("sync", value="exact"),
              Parameter("camera_info_override", value=override)]
    params += [Parameter(f"camera.{k}", value=v)
               for k, v in dataclasses.asdict(CameraCalibration.from_camera(calib)).items()]
    node = TrackerNode(context=context, parameter_overrides=params)
    feeder = rclpy.create_node("feeder", context=context)
    pc = feeder.create_publisher(Image, "color/image_raw", qos.reliable(10))
    pd = feeder.create_publisher(Image, "depth/image_raw", qos.reliable(10))
    pi = feeder.create_publisher(CameraInfo, "color/camera_info", qos.reliable(10))
    infos: list[CameraInfo] = []
    feeder.create_subscription(CameraInfo, "memgs/keyframe/camera_info", infos.append, qos.keyframes())
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    ex.add_node(feeder)
    try:
        assert _spin_until(ex, lambda: pc.get_subscription_count() and pd.get_subscription_count()
                           and pi.get_subscription_count())
        assert node.wait_until_warm(120)  # a live frame before it is "warming"
        f = frames[0]
        pi.publish(camera_to_camera_info(wrong, f.stamp_ns, "cam"))
        assert _spin_until(ex, lambda: node.cams.camera is not None or node.stats.values["camera_info_differs"], 5.0)
        pc.publish(numpy_to_image(f.rgb, "rgb8", f.stamp_ns, "cam"))
        pd.publish(depth_to_image(f.depth_m, "32FC1", f.stamp_ns, "cam"))
        assert _spin_until(ex, lambda: len(infos) >= 1), "no keyframe from the first frame"
        got = decode_camera_info(infos[0])
        if override:
            assert got.width == true.width and np.allclose(
                [got.fx, got.fy, got.cx, got.cy], [true.fx, true.fy, true.cx, true.cy], rtol=1e-9)
            assert node.stats.values["camera_info_differs"] == 1
        else:
            assert got == wrong
            assert node.stats.values["camera_info_differs"] == 0
    finally:
        node.close()
        ex.shutdown()
        node.destroy_node()
        feeder.destroy_node()


@pytest.mark.ros
def test_tracker_override_without_calibration_is_refused(context) -> None:  # noqa: ANN001
    from rclpy.parameter import Parameter

    from memgs_ros.nodes.tracker.node import TrackerNode

    with pytest.raises(ConfigError, match="camera_info_override is true but no calibration is set"):
        TrackerNode(context=context, parameter_overrides=[Parameter("camera_info_override", value=True)])
    with pytest.raises(ConfigError, match=r"camera.width, camera.height, camera.cx, camera.cy missing"):
        TrackerNode(context=context, parameter_overrides=[Parameter("camera.fx", value=500.0),
                                                          Parameter("camera.fy", value=500.0)])


@pytest.mark.ros
def test_player_gives_an_unnamed_folder_the_configured_camera(context, tmp_path: Path) -> None:  # noqa: ANN001
    from rclpy.parameter import Parameter

    from memgs_ros.nodes.bag_player.node import BagPlayer

    mycopy = _folder(tmp_path, "mycopy", with_json=False)
    with pytest.raises(DataError, match="mycopy: cannot tell the camera"):
        BagPlayer(context=context, parameter_overrides=[Parameter("source", value=str(mycopy))])
    params = [Parameter("source", value=str(mycopy))]
    params += [Parameter(f"camera.{k}", value=v)
               for k, v in dataclasses.asdict(CameraCalibration.from_camera(TUM_FR3)).items()]
    player = BagPlayer(context=context, parameter_overrides=params)
    try:
        assert player.feed.source.camera == TUM_FR3.fitted(64, 48)  # type: ignore[attr-defined]
    finally:
        player.destroy_node()


# ----------------------------------------------------------------------------- the whole graph


@pytest.mark.ros
@pytest.mark.slow
def test_run_on_a_bag_with_wrong_camera_info_maps_with_the_true_camera(tmp_path: Path, ros_domain_id: int) -> None:
    """TUM's situation in small: a ROS 1 bag whose camera_info is the ROS default while the images
    were made with another camera. With the true calibration in the config the keyframes the mapper
    trained on carry the true camera, and the trajectory matches ground truth."""
    from memgs_ros.core.mapping import checkpoint
    from memgs_ros.core.metrics.trajectory import ate
    from memgs_ros.io.tum import read_trajectory
    from memgs_ros.orchestration.pipeline import run_pipeline

    spec = "synthetic:w=320,h=240,n=30,seed=3"  # the test_pipeline sequence: its path tracks to ~1 cm
    bag, true = _wrong_info_bag(tmp_path, spec)
    config = _config_with_camera(tmp_path, true.scaled(2.0))  # given at 640x480, rescaled by the nodes
    fast = {"mapper.iterations_per_frame": 2, "mapper.final_iterations": 30}
    s = run_pipeline(RunOptions(source=str(bag), config=str(config), out_dir=tmp_path / "run",
                                namespace=f"/memgs_calib_{os.getpid()}_{os.urandom(3).hex()}",
                                domain_id=ros_domain_id, overrides=fast, timeout_s=600), progress=False)
    assert s.frames == 30 and s.poses == 30 and s.keyframes >= 2
    ckpt = checkpoint.load(tmp_path / "run" / "mapper_checkpoint.npz")
    assert ckpt.keyframes
    expected = true.scaled(0.5)  # the synthetic config maps at half resolution
    for kf in ckpt.keyframes:
        assert (kf.camera.width, kf.camera.height) == (expected.width, expected.height)
        np.testing.assert_allclose([kf.camera.fx, kf.camera.fy, kf.camera.cx, kf.camera.cy],
                                   [expected.fx, expected.fy, expected.cx, expected.cy], rtol=1e-6)
    frames = list(generate_frames(parse_spec(spec)))
    est_stamps, est_poses = read_trajectory(Path(s.trajectory_path))
    err = ate(est_stamps, est_poses, np.array([f.stamp_ns for f in frames]), np.stack([f.T_wc_gt for f in frames]))
    assert err.n_matched == 30 and err.rmse_m < 0.02, err.rmse_m
    tracker_log = (tmp_path / "run" / "logs" / "tracker.log").read_text()
    assert "differs from the configured calibration" in tracker_log
