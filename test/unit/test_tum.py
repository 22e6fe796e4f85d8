"""TUM RGB-D folders: round trip through write_tum_folder, association, camera choice, errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from memgs_ros.core.geometry.camera import TUM_FR1, TUM_FR2, PinholeCamera
from memgs_ros.core.geometry.poses import pose_from_tq
from memgs_ros.errors import DataError
from memgs_ros.io.synthetic import SyntheticSpec, generate_frames, write_tum_folder
from memgs_ros.io.tum import TumFolder, associate, parse_stamp_ns, read_trajectory

SPEC = SyntheticSpec(width=64, height=48, n_frames=5, seed=2, hole_fraction=0.05)


@pytest.fixture(scope="module")
def frames():
    return list(generate_frames(SPEC))


def test_write_then_read_gives_same_frames(tmp_path, frames):
    out = tmp_path / "seq"
    assert write_tum_folder(frames, out) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # no temp dir left behind
    src = TumFolder(out)
    assert len(src) == 5 and src.camera == SPEC.camera and src.depth_factor == 5000.0
    got = list(src)
    for a, b in zip(frames, got):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(b.depth_m, a.depth_m, atol=0.5 / 5000 + 1e-6)
        np.testing.assert_array_equal(b.depth_m == 0, a.depth_m == 0)  # holes stay holes
        np.testing.assert_allclose(b.T_wc_gt, a.T_wc_gt, atol=1e-8)
    stamps, poses = src.ground_truth()
    np.testing.assert_array_equal(stamps, [f.stamp_ns for f in frames])
    assert poses.shape == (5, 4, 4)


def test_writer_refuses_overwrite_and_leaves_nothing_on_failure(tmp_path, frames):
    out = tmp_path / "seq"
    write_tum_folder(frames[:2], out)
    with pytest.raises(DataError, match="already exists"):
        write_tum_folder(frames[:2], out)

    def broken():
        yield frames[0]
        raise RuntimeError("source died")

    with pytest.raises(RuntimeError, match="source died"):
        write_tum_folder(broken(), tmp_path / "other")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]


def test_associate_jittered_and_missing_stamps():
    ms = 1_000_000
    rgb = np.arange(6) * 33 * ms
    rng = np.random.default_rng(0)
    depth = rgb + rng.integers(-8, 9, size=6) * ms
    depth = np.delete(depth, 3)  # depth of frame 3 missing
    depth = np.append(depth, 500 * ms)  # a depth image with no partner
    pairs = associate(rgb, depth, 20 * ms)
    assert [i for i, _ in pairs] == [0, 1, 2, 4, 5]
    assert all(abs(int(rgb[i]) - int(depth[j])) <= 8 * ms for i, j in pairs)
    # one-to-one: two colour stamps near one depth stamp -> only the closer gets it
    assert associate(np.array([0, 10 * ms]), np.array([8 * ms]), 20 * ms) == [(1, 0)]
    assert associate(np.array([0]), np.array([21 * ms]), 20 * ms) == []


def test_parse_stamp_is_exact():
    assert parse_stamp_ns("1305031229.528748") == 1305031229_528748000
    assert parse_stamp_ns("12") == 12_000_000_000
    assert parse_stamp_ns("1.5e0") == 1_500_000_000


def _make_folder(root: Path, name: str, n: int = 4, gt_rows: list[str] | None = None, w: int = 640, h: int = 480) -> Path:
    d = root / name
    (d / "rgb").mkdir(parents=True)
    (d / "depth").mkdir()
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth"]
    for k in range(n):
        t = 100.0 + k * 0.04
        cv2.imwrite(str(d / "rgb" / f"{k}.png"), np.full((h, w, 3), 40 * k, np.uint8))
        cv2.imwrite(str(d / "depth" / f"{k}.png"), np.full((h, w), 5000 + 1000 * k, np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{k}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{k}.png")
    (d / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (d / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt_rows is not None:
        (d / "groundtruth.txt").write_text("# gt\n" + "\n".join(gt_rows) + "\n")
    return d


def test_camera_and_depth_factor_from_folder_name_and_gt_interpolation(tmp_path):
    gt = ["100.030000 0 0 0 0 0 0 1", "100.090000 1 2 3 0 0 0.7071067811865476 0.7071067811865476"]
    d1 = _make_folder(tmp_path, "rgbd_dataset_freiburg1_xyz", gt_rows=gt)
    src = TumFolder(d1)
    assert src.camera == TUM_FR1 and src.depth_factor == 5000.0
    frames = list(src)
    assert [f.T_wc_gt is None for f in frames] == [True, False, False, True]  # t=100.00 and 100.12 outside gt
    # t=100.04 is 1/6 of the way, t=100.08 5/6
    np.testing.assert_allclose(frames[1].T_wc_gt[:3, 3], np.array([1, 2, 3]) / 6, atol=1e-9)
    np.testing.assert_allclose(frames[2].T_wc_gt[:3, 3], np.array([1, 2, 3]) * 5 / 6, atol=1e-9)
    assert frames[1].depth_m[0, 0] == pytest.approx(6000 / 5000)
    assert src.gt_coverage == 0.5

    d2 = _make_folder(tmp_path, "rgbd_dataset_freiburg2_xyz", n=1, w=320, h=240)
    src2 = TumFolder(d2)
    assert src2.depth_factor == 5208.0
    assert src2.camera == TUM_FR2.scaled(0.5)  # half-size images: the preset is rescaled
    assert next(iter(src2)).depth_m[0, 0] == pytest.approx(5000 / 5208)

    mine = PinholeCamera(640, 480, 500, 500, 320, 240)
    src3 = TumFolder(d1, camera=mine, depth_factor=1000.0)
    assert src3.camera == mine
    assert next(iter(src3)).depth_m[0, 0] == pytest.approx(5.0)


def test_no_pairs_and_unknown_camera_are_errors(tmp_path):
    d = _make_folder(tmp_path, "plain")
    with pytest.raises(DataError, match="no frames"):
        TumFolder(d, max_dt_s=0.001)
    with pytest.raises(DataError, match="cannot tell the camera"):
        list(TumFolder(d))
    rgb_only = TumFolder(d, camera=TUM_FR1, with_depth=False)
    assert [f.depth_m for f in rgb_only] == [None] * 4


def test_errors_name_file_and_line(tmp_path):
    d = _make_folder(tmp_path, "rgbd_dataset_freiburg1_bad", gt_rows=["100.0 1 2 3 0 0 0 1", "100.1 1 2 x 0 0 0 1"])
    with pytest.raises(DataError, match=r"groundtruth.txt:3: unparsable number"):
        TumFolder(d)
    (d / "groundtruth.txt").write_text("100.0 1 2 3 0 0 1\n")
    with pytest.raises(DataError, match=r"groundtruth.txt:1: expected .* \(8 fields\), got 7"):
        read_trajectory(d / "groundtruth.txt")
    (d / "groundtruth.txt").unlink()
    with open(d / "rgb.txt", "a") as f:
        f.write("notatime rgb/x.png\n")
    with pytest.raises(DataError, match=r"rgb.txt:7: bad timestamp 'notatime'"):
        TumFolder(d)
    (d / "rgb.txt").write_text("100.000000 rgb/missing.png\n")
    (d / "depth.txt").write_text("100.000000 depth/0.png\n")
    src = TumFolder(d)
    assert src.ground_truth()[0].shape == (0,)
    with pytest.raises(DataError, match=r"rgb/missing.png: missing or unreadable image"):
        list(src)
    (d / "depth.txt").unlink()
    with pytest.raises(DataError, match=r"depth.txt: file not found"):
        TumFolder(d)
    with pytest.raises(DataError, match="not a directory"):
        TumFolder(d / "nope")


def test_quaternion_rows_are_checked(tmp_path):
    p = tmp_path / "gt.txt"
    p.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(DataError, match="gt.txt:1: non-finite value or non-unit quaternion"):
        read_trajectory(p)
    p.write_text("2.0 1 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    st, T = read_trajectory(p)
    assert st.tolist() == [1_000_000_000, 2_000_000_000]  # sorted
    np.testing.assert_allclose(T[1], pose_from_tq(np.array([1.0, 0, 0]), np.array([0, 0, 0, 1.0])))


def test_a_bad_image_is_skipped_and_counted_or_refused_with_strict(tmp_path: Path) -> None:
    """One unreadable colour image and one depth image of another size: iteration goes on past
    both and counts them by kind; strict refuses the first, naming the file."""
    import cv2

    from memgs_ros.errors import DataError
    from memgs_ros.io.tum import TumFolder

    folder = tmp_path / "rgbd_dataset_freiburg1_x"
    write_tum_folder(generate_frames(SyntheticSpec(width=32, height=24, n_frames=8, seed=2)), folder)
    rgb = sorted((folder / "rgb").iterdir())
    depth = sorted((folder / "depth").iterdir())
    rgb[2].write_bytes(b"not a png")
    cv2.imwrite(str(depth[5]), np.zeros((10, 10), np.uint16))
    source = TumFolder(folder)
    frames = list(source)
    assert len(frames) == 6 and dict(source.skipped) == {"unreadable_image": 1, "size_mismatch": 1}
    assert [f.stamp_ns for f in frames] == [e.stamp_ns for k, e in enumerate(source.entries) if k not in (2, 5)]
    with pytest.raises(DataError, match="unreadable_image"):
        list(TumFolder(folder, strict=True))
