"""The one view preparation (undistort, resize, valid mask) that mapper, sampler and evaluation share."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from memgs_ros.core.geometry.camera import TUM_FR1, PinholeCamera
from memgs_ros.core.geometry.frame import Frame
from memgs_ros.core.geometry.view import (
    DepthUnits,
    Undistorter,
    depth_to_metres,
    depth_to_metres_checked,
    valid_pixel_mask,
    view_preparation,
)
from memgs_ros.errors import ConfigError, DataError

PLAIN = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
# Barrel distortion whose cropped undistortion still leaves a few edge pixels without a full
# bilinear source (14 of 64x48): the mask has something to say.
BARREL = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0, (-0.4, 0.2, 0.01, -0.01, 0.0))


def _coded(cam: PinholeCamera) -> np.ndarray:
    """[H, W] float32 whose value is the pixel's linear index (exact in float32)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    return (v * cam.width + u).astype(np.float32)


def test_no_distortion_full_size_is_identity() -> None:
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    depth = np.random.default_rng(1).random((48, 64)) * 4.0  # float64 in: float32 out
    view = view_preparation(PLAIN)
    out_rgb, out_depth = view(rgb, depth)
    assert view.camera == PLAIN and view.source == PLAIN and view.valid_mask is None
    assert np.array_equal(out_rgb, rgb) and out_depth is not None and out_depth.dtype == np.float32
    assert np.array_equal(out_depth, depth.astype(np.float32))
    assert view(rgb)[1] is None


def test_resize_is_area_for_colour_and_nearest_for_depth() -> None:
    # 2x2 blocks of one colour: an area-averaged half-size image keeps each block's colour
    # exactly; nearest depth takes one of the block's four values, so blocks of one depth too.
    rng = np.random.default_rng(2)
    blocks = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    rgb = np.repeat(np.repeat(blocks, 2, axis=0), 2, axis=1)
    depth = np.repeat(np.repeat(rng.random((24, 32)).astype(np.float32), 2, axis=0), 2, axis=1)
    depth[0, 0] = np.nan  # no blending: a NaN stays within its block's single pixel
    view = view_preparation(PLAIN, 0.5)
    out_rgb, out_depth = view(rgb, depth)
    assert (view.camera.width, view.camera.height) == (32, 24) and view.camera == PLAIN.scaled(0.5)
    assert out_rgb.shape == (24, 32, 3) and out_rgb.dtype == np.uint8 and np.array_equal(out_rgb, blocks)
    assert out_depth is not None and out_depth.shape == (24, 32)
    finite = np.isfinite(out_depth)
    assert np.array_equal(out_depth[finite], depth[::2, ::2][finite])
    assert view.valid_mask is None


def test_distorted_pixels_come_from_where_the_camera_model_says() -> None:
    cam = TUM_FR1
    view = view_preparation(cam)
    assert not view.camera.has_distortion and view.camera == Undistorter(cam).camera_undistorted
    assert view.camera.fx > cam.fx  # cropped to the region every output pixel samples
    _, code = view(np.zeros((cam.height, cam.width, 3), np.uint8), _coded(cam))
    assert code is not None
    # Output pixels -> rays of the output camera -> distorted source pixels (OpenCV's model).
    v, u = np.mgrid[0:cam.height:37, 0:cam.width:41]
    rays = np.stack([(u - view.camera.cx) / view.camera.fx, (v - view.camera.cy) / view.camera.fy,
                     np.ones(u.shape)], axis=-1).reshape(-1, 1, 3)
    src, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    got = code[v.ravel(), u.ravel()].astype(int)
    got_uv = np.c_[got % cam.width, got // cam.width]
    assert np.abs(got_uv - src.reshape(-1, 2)).max() <= 0.5 + 1e-6  # nearest neighbour
    assert np.abs(src.reshape(-1, 2) - np.c_[u.ravel(), v.ravel()]).max() > 5.0  # distortion is real


def test_valid_mask_marks_pixels_with_full_source_content() -> None:
    white = np.full((48, 64, 3), 255, np.uint8)
    full = view_preparation(BARREL)
    mask = full.valid_mask
    assert mask is not None and mask.shape == (48, 64) and mask.dtype == bool
    assert 0 < int((~mask).sum()) < 48 * 64 // 50  # a thin border, not nothing, not everything
    rgb, depth = full(white, _coded(BARREL))
    assert (rgb[mask] == 255).all()  # every valid pixel is a blend of source pixels only
    assert depth is not None and np.isfinite(depth[mask]).all()
    # Half size: a pixel is valid when all four full-size pixels it averages are.
    half = view_preparation(BARREL, 0.5)
    assert half.valid_mask is not None and half.valid_mask.shape == (24, 32)
    blocks_valid = mask.reshape(24, 2, 32, 2).all(axis=(1, 3))
    assert np.array_equal(half.valid_mask, blocks_valid)
    assert (half(white)[0][half.valid_mask] == 255).all()
    # A lower threshold keeps pixels with any content; the default is the view's mask.
    assert np.array_equal(valid_pixel_mask(BARREL, 0.5), half.valid_mask)
    loose = valid_pixel_mask(BARREL, 0.5, min_fraction=1e-3)
    assert loose is not None and loose.sum() >= half.valid_mask.sum() and (loose | ~half.valid_mask).all()


def test_one_shared_preparation_per_camera_and_scale() -> None:
    a = view_preparation(BARREL)
    assert view_preparation(BARREL, 1.0) is a and view_preparation(BARREL, resolution_scale=1) is a
    assert view_preparation(dataclasses.replace(BARREL), 1.0) is a  # equal camera, same entry
    b = view_preparation(BARREL, 0.5)
    assert b is not a and b.resolution_scale == 0.5 and b.camera == a.camera.scaled(0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.camera = PLAIN  # type: ignore[misc]


@pytest.mark.parametrize("scale", [0.0, -0.5, float("nan"), float("inf")])
def test_bad_scale_is_a_config_error(scale: float) -> None:
    with pytest.raises(ConfigError, match="resolution_scale must be a positive finite number"):
        view_preparation(PLAIN, scale)


def test_wrong_image_is_a_data_error() -> None:
    view = view_preparation(PLAIN)
    with pytest.raises(DataError, match=r"image must be uint8 \[48, 64, 3\].*got uint8 \[10, 10, 3\]"):
        view(np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(DataError, match="got float32"):
        view(np.zeros((48, 64, 3), np.float32))
    with pytest.raises(DataError, match="depth is 10x48 but the camera is 64x48"):
        view(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 10), np.float32))


FR1 = TUM_FR1


def _images(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3)).astype(np.uint8), (0, 0), 2.0)
    raw = rng.integers(2000, 20000, (480, 640)).astype(np.uint16)
    raw[rng.random((480, 640)) < 0.2] = 0  # no measurement
    return rgb, raw


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_raw_16_bit_depth_prepares_like_its_metres(scale: float) -> None:
    """16-bit depth goes through undistortion and resize as units and becomes metres at the output
    size: the same depths as preparing the metres (0 units -> NaN, a missing measurement)."""
    rgb, raw = _images()
    prep = view_preparation(FR1, scale)
    _, from_raw = prep(rgb, raw, 5000.0)
    _, from_metres = prep(rgb, depth_to_metres(raw, 5000.0))
    assert from_raw.dtype == np.float32 and from_raw.shape == (prep.camera.height, prep.camera.width)
    np.testing.assert_array_equal(from_raw, from_metres)
    assert np.isnan(from_raw).mean() > 0.1


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_device_preparation_matches_opencv(scale: float) -> None:
    """The torch twin (what a GPU runs on the uploaded compact images) against OpenCV on the host:
    depth bit for bit, colour within OpenCV's fixed-point rounding, the same mask."""
    import torch

    from memgs_ros.core.mapping.device_view import device_view

    rgb, raw = _images(1)
    prep = view_preparation(FR1, scale)
    ref_rgb, ref_depth = prep(rgb, raw, 5000.0)
    view = device_view(prep, "cpu")
    assert device_view(prep, "cpu") is view  # one set of tables per preparation and device
    out_rgb, out_depth = view(torch.from_numpy(rgb), torch.from_numpy(raw), 5000.0)
    diff = np.abs(out_rgb.permute(1, 2, 0).numpy().astype(int) - ref_rgb.astype(int))
    assert diff.max() <= 2 and diff.mean() < 0.5, (diff.max(), diff.mean())
    np.testing.assert_array_equal(out_depth.numpy(), np.nan_to_num(ref_depth, nan=0.0))
    np.testing.assert_array_equal(view.valid_mask.numpy(), prep.valid_mask)
    # float metres in, the same metres out
    _, from_metres = view(torch.from_numpy(rgb), torch.from_numpy(depth_to_metres(raw, 5000.0)))
    np.testing.assert_array_equal(from_metres.numpy(), out_depth.numpy())


def test_depth_source_index_is_the_opencv_depth_path_as_a_gather() -> None:
    rgb, raw = _images(2)
    prep = view_preparation(FR1, 0.5)
    idx = prep.depth_source_index
    assert idx.shape == (240, 320) and idx.min() >= -1 and idx.max() < 640 * 480
    _, ref = prep(rgb, raw.astype(np.float32))  # floats: 0 stays 0
    gathered = np.where(idx >= 0, raw.reshape(-1)[np.maximum(idx, 0)], 0).astype(np.float32)
    np.testing.assert_array_equal(np.nan_to_num(ref, nan=0.0), gathered)


@pytest.mark.parametrize("scale", [1.0, 1000.0, 5000.0])
def test_depth_to_metres_compiled_equals_the_numpy_reference(scale: float) -> None:
    """Value for value (NaN where invalid), for 16-bit units and float depth with zeros, negative,
    NaN and infinite values, contiguous or strided; what numba is missing runs the reference."""
    from memgs_ros.core.geometry import view as view_module

    rng = np.random.default_rng(5)
    f = rng.uniform(0.2, 9.0, (48, 64)).astype(np.float32)
    f[rng.random(f.shape) < 0.2] = 0.0
    f[0, :4], f[1, :4], f[2, :4], f[3, :4] = np.nan, np.inf, -np.inf, -1.0
    u = rng.integers(0, 65536, (48, 64)).astype(np.uint16)
    u[rng.random(u.shape) < 0.2] = 0
    for raw in (f, u, f[:, ::2], u[::3], f * np.float32(scale)):
        got = depth_to_metres(raw, scale)
        ref = view_module._depth_to_metres_reference(raw, scale)  # noqa: SLF001
        assert got.dtype == np.float32 and got.shape == raw.shape
        np.testing.assert_array_equal(got, ref)
        assert not np.shares_memory(got, raw)


@pytest.mark.parametrize("scale", [1.0, 5000.0])
def test_the_checked_conversion_finds_valid_depth_as_the_frame_does(scale: float) -> None:
    """``depth_to_metres_checked`` says in its one pass what ``Frame.has_valid_depth`` says of the
    converted image: none valid when all are holes, out of range or a single in-range pixel is
    the only one (found wherever it lies, strided input too)."""
    rng = np.random.default_rng(9)
    cam = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    rgb = np.zeros((48, 64, 3), np.uint8)
    for case in range(6):
        m = np.zeros((48, 64), np.float32)
        if case == 1:
            m[:] = 41.0  # beyond the range: no valid depth
        elif case == 2:
            m[rng.integers(0, 48), rng.integers(0, 64)] = 2.5  # one, off the sparse grid as likely as not
        elif case == 3:
            m[:] = np.nan
            m[47, 63] = 0.5
        elif case >= 4:
            m = rng.uniform(0.0, 50.0, (48, 64)).astype(np.float32)
        raw = np.rint(np.nan_to_num(m) * scale).astype(np.uint16) if scale != 1.0 else m
        for r in (raw, raw[:, ::2]) if case == 5 else (raw,):
            got, valid = depth_to_metres_checked(r, scale)
            np.testing.assert_array_equal(got, depth_to_metres(r, scale))
            if r.shape == (48, 64):
                assert valid == Frame(0, rgb, got, cam).has_valid_depth()
                # the camera's image read where needed says the same as its metres
                assert Frame(0, rgb, DepthUnits(r, scale), cam).has_valid_depth() == valid
            assert valid == bool(np.any((got > np.float32(1e-6)) & (got < np.float32(40.0))))
            assert DepthUnits(r, scale).has_valid() == valid


def test_depth_units_read_where_needed_as_the_whole_image_converts() -> None:
    """``DepthUnits``: its metres are the converted image's, for 16-bit units and float depth,
    contiguous, strided (a message with padded rows) or read-only (a view on a message); bad raw
    images and scales are refused, as is a depth of another size than the frame's camera."""
    rng = np.random.default_rng(12)
    u = rng.integers(0, 40000, (48, 64)).astype(np.uint16)
    u[rng.random(u.shape) < 0.2] = 0
    f = rng.uniform(-1.0, 9.0, (48, 64)).astype(np.float32)
    f[rng.random(f.shape) < 0.1] = np.nan
    ro = u.copy()
    ro.flags.writeable = False
    for raw, scale in ((u, 5000.0), (f, 1.0), (f, 2.5), (u[:, ::2], 1000.0), (f[:, ::2], 1.0), (ro, 5000.0)):
        got = DepthUnits(raw, scale).metres()
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, depth_to_metres(np.array(raw), scale))
    for bad in (np.zeros((4, 4), np.int32), np.zeros((4, 4, 1), np.uint16)):
        with pytest.raises(DataError, match="raw depth"):
            DepthUnits(bad, 1000.0)
    for scale in (0.0, -1.0, float("nan")):
        with pytest.raises(DataError, match="depth scale"):
            DepthUnits(u, scale)
    cam = PinholeCamera(64, 48, 50.0, 50.0, 32.0, 24.0)
    with pytest.raises(DataError, match="match the camera"):
        Frame(0, np.zeros((48, 64, 3), np.uint8), DepthUnits(u[:40], 5000.0), cam)
    frame = Frame(0, np.zeros((48, 64, 3), np.uint8), DepthUnits(u, 5000.0), cam)
    np.testing.assert_array_equal(frame.depth_metres(), depth_to_metres(u, 5000.0))
    converted = Frame(0, frame.rgb, frame.depth_metres(), cam)
    np.testing.assert_array_equal(frame.valid_depth_mask(), converted.valid_depth_mask())


@pytest.mark.parametrize("scale", [1000.0, 5000.0, 0.37])
def test_metres_to_units_compiled_equals_the_numpy_reference(scale: float) -> None:
    """The 16-bit encoder (replays publish every depth frame through it) value for value: halves
    rounded to even, zeros, negative, NaN, infinite and out-of-range depths as 0, strided input."""
    from memgs_ros.core.geometry import view as view_module

    rng = np.random.default_rng(6)
    f = rng.uniform(0.0, 70000.0 / scale, (48, 64)).astype(np.float32)
    f[0, :5] = np.nan, np.inf, -np.inf, -1.0, 0.0
    f[1, :4] = np.float32(0.5 / scale), np.float32(1.5 / scale), np.float32(65535 / scale), np.float32(65536 / scale)
    for raw in (f, f[:, ::2], f[::3], f.astype(np.float64)):
        got = view_module.metres_to_units(raw, scale)
        ref = view_module._metres_to_units_reference(raw, scale)  # noqa: SLF001
        assert got.dtype == np.uint16 and got.shape == raw.shape
        np.testing.assert_array_equal(got, ref)
    assert (ref[0, :5] == 0).all() and (ref > 0).mean() > 0.8
