"""Maps that outlive a flight, end to end (node processes over DDS, generated bags): session 1 saves
a bundle, session 2 continues it in the same world, a third run only localises in it."""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")

from memgs_ros.cli.run import check_map_bundle  # noqa: E402
from memgs_ros.core.map_io.bundle import LATEST, BundleError, check_bundle  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply  # noqa: E402
from memgs_ros.core.metrics.trajectory import align_umeyama, associate  # noqa: E402
from memgs_ros.core.tracking.map_io import read_tracker_map  # noqa: E402
from memgs_ros.errors import ConfigError  # noqa: E402
from memgs_ros.io.bag_writer import write_bag  # noqa: E402
from memgs_ros.io.synthetic import generate_frames, parse_spec  # noqa: E402
from memgs_ros.io.tum import read_trajectory  # noqa: E402
from memgs_ros.orchestration.pipeline import RunOptions, run_pipeline  # noqa: E402
from memgs_ros.orchestration.saved_run import load_saved_run  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SPEC = "synthetic:w=320,h=240,n=60,seed=3"
LATER_NS = 100 * 10**9  # session 2 flies 100 s after session 1: stamps never repeat
FAST = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 60}


@pytest.fixture(scope="module")
def frames() -> list:
    return list(generate_frames(parse_spec(SPEC)))


@pytest.fixture(scope="module")
def bags(frames: list, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Session 1 flies frames 0-39, session 2 frames 25-59 (overlapping 25-39) 100 s later."""
    d = tmp_path_factory.mktemp("sessions")
    write_bag(frames[:40], d / "s1.mcap")
    write_bag([replace(f, stamp_ns=f.stamp_ns + LATER_NS) for f in frames[25:]], d / "s2.mcap")
    return d / "s1.mcap", d / "s2.mcap"


def _run(source: Path, out: Path, domain: int, **kw: object):  # noqa: ANN202
    ns = f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}"
    return run_pipeline(RunOptions(source=str(source), config="synthetic", out_dir=out, namespace=ns, domain_id=domain,
                                   overrides=FAST, timeout_s=600, **kw), progress=False)  # type: ignore[arg-type]


def _ate_one_alignment(frames: list, runs: list[tuple[Path, int]]) -> float:
    """RMSE (m) of every run's poses under one SE(3) alignment to the ground truth."""
    gt_s = np.array([f.stamp_ns for f in frames])
    gt_p = np.stack([f.T_wc_gt[:3, 3] for f in frames])
    est, ref = [], []
    for traj, offset in runs:
        s, T = read_trajectory(traj)
        ia, ib = associate(s - offset, gt_s, 1_000_000)
        est.append(T[ia, :3, 3])
        ref.append(gt_p[ib])
    pe, pg = np.concatenate(est), np.concatenate(ref)
    a = align_umeyama(pe, pg)
    return float(np.sqrt(np.mean(np.sum((a.apply(pe) - pg) ** 2, axis=1))))


def test_a_second_flight_continues_the_map_and_a_third_only_localises(
        frames: list, bags: tuple[Path, Path], tmp_path: Path, ros_domain_id: int) -> None:
    s1_bag, s2_bag = bags
    first = _run(s1_bag, tmp_path / "s1", ros_domain_id)
    assert first.bundle_path and Path(first.bundle_path).parent == tmp_path / "s1" / "maps"
    bundle, manifest = check_bundle(tmp_path / "s1" / "maps")  # "latest"
    assert bundle == Path(first.bundle_path) and manifest.gaussians == first.gaussians == len(load_ply(bundle / "map.ply"))
    assert manifest.keyframes == first.keyframes and manifest.frames == 40
    assert read_tracker_map(bundle / "tracker.npz").n_keyframes == first.keyframes
    shown = load_saved_run(tmp_path / "s1" / "maps")  # memgs view OUT/maps: the latest bundle
    assert len(shown.records) == first.gaussians and len(shown.keyframes[0]) == first.keyframes

    second = _run(s2_bag, tmp_path / "s2", ros_domain_id, map_bundle=tmp_path / "s1" / "maps")
    # Relocalised at once (its first frames are session 1's 25-39), then mapped on in the same world:
    # both sessions' poses agree with the ground truth under one alignment.
    assert second.relocalizing <= 2 and second.poses >= second.frames - 2
    ate = _ate_one_alignment(frames, [(tmp_path / "s1" / "trajectory.txt", 0),
                                      (tmp_path / "s2" / "trajectory.txt", LATER_NS)])
    assert ate < 0.02, ate
    assert second.keyframes >= 1  # frames 40-59 are new ground: keyframes and Gaussians added
    assert second.bundle_path and Path(second.bundle_path).parent == tmp_path / "s2" / "maps"
    assert check_bundle(second.bundle_path)[1].gaussians == second.gaussians > 0
    assert check_bundle(tmp_path / "s1" / "maps")[0] == bundle  # session 1's bundle is untouched

    third = _run(s2_bag, tmp_path / "s3", ros_domain_id, map_bundle=bundle, map_mode="localize")
    assert third.keyframes == 0 and third.gaussians == first.gaussians  # nothing added, nothing trained
    assert third.poses >= third.frames - 2 and third.bundle_path == "" and not (tmp_path / "s3" / "maps").exists()
    assert _ate_one_alignment(frames, [(tmp_path / "s1" / "trajectory.txt", 0),
                                       (tmp_path / "s3" / "trajectory.txt", LATER_NS)]) < 0.02
    assert os.readlink(tmp_path / "s1" / "maps" / LATEST) == bundle.name


def test_a_bundle_is_checked_before_any_node_starts(tmp_path: Path) -> None:
    from memgs_ros.cli.run import check_config
    from memgs_ros.core.geometry.camera import PinholeCamera

    params = check_config("synthetic")
    with pytest.raises(ConfigError, match="needs --map"):
        check_map_bundle(None, "localize", params, PinholeCamera(320, 240, 267.7, 269.6, 159.8, 123.55))
    with pytest.raises(BundleError, match="no such folder"):
        check_map_bundle(tmp_path / "nothing", "mapping", params, PinholeCamera(320, 240, 267.7, 269.6, 159.8, 123.55))


def test_a_tum_folders_bundle_is_checked_in_the_units_the_run_gives_the_tracker(frames: list, tmp_path: Path) -> None:
    """A TUM folder's depth PNGs hold 1/5000 m: the run gives the tracker depth_scale 5000, so its
    bundle is made at 5000 and taken back by ``memgs run --map`` over the same folder, while one
    made at millimetres is refused, before any node starts (the check once used the default 1000)."""
    from memgs_ros.cli.run import check_config, check_inputs
    from memgs_ros.core.map_io.bundle import MAPPER_FILE, PLY_FILE, TRACKER_FILE, Manifest, commit_bundle, new_staging
    from memgs_ros.io.synthetic import write_tum_folder
    from memgs_ros.orchestration.run_files import configured_camera

    folder = tmp_path / "tum"
    write_tum_folder(frames[:3], folder, depth_factor=5000.0)
    configured = configured_camera(check_config("tum_fr1")).camera  # the config's calibration replaces camera_info
    assert configured is not None
    camera = configured.fitted(frames[0].camera.width, frames[0].camera.height)

    def bundle(depth_scale: float) -> Path:
        staging = new_staging(tmp_path / f"maps{depth_scale:g}")
        for f in (PLY_FILE, TRACKER_FILE, MAPPER_FILE):
            (staging / f).write_bytes(f.encode())
        return commit_bundle(staging, Manifest(0, camera.as_dict(), "rgbd", depth_scale, 3, "map_optical",
                                               3, 1, 10, "test", "now"))

    assert check_inputs(str(folder), "tum_fr1", map_bundle=bundle(5000.0)) is not None  # its 16UC1 depth as stored
    with pytest.raises(BundleError, match="depth_scale 1000 units per metre .this source: 5000"):
        check_inputs(str(folder), "tum_fr1", map_bundle=bundle(1000.0))
