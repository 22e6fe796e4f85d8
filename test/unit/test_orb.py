"""ORB descriptors and the grid selection by numba kernels (``memgs_ros.core.tracking.features.features.orb``) against
OpenCV's ORB and the extractor's numpy selection, their references."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from memgs_ros.core.geometry.view import DepthUnits, depth_to_metres, metres_to_units
from memgs_ros.core.tracking import TrackerConfig
from memgs_ros.core.tracking.features import orb, orb_detect
from memgs_ros.core.tracking.features.features import EDGE_PX, OrbExtractor
from memgs_ros.io.synthetic import generate_frames, parse_spec

pytestmark = pytest.mark.skipif(not orb.compiled_orb_available(),
                                reason="no numba here, or OpenCV's ORB tests could not be read off")


@pytest.fixture(scope="module")
def levels() -> list[np.ndarray]:
    """Pyramid levels of synthetic frames, noisy and clean, 640x480 down to the top level."""
    ex = OrbExtractor(TrackerConfig())
    out = []
    for spec in ("synthetic:w=640,h=480,n=2,noise=0.02", "synthetic:w=640,h=480,n=2,seed=4"):
        for f in generate_frames(parse_spec(spec)):
            out += ex._pyramid(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY))  # noqa: SLF001
    return out


def test_describe_is_opencvs_compute(levels: list[np.ndarray]) -> None:
    """The kernel's descriptors equal OpenCV's for the keypoints (and orientations) its ORB detects."""
    ref_orb = cv2.ORB_create(nfeatures=500, nlevels=1, edgeThreshold=EDGE_PX, patchSize=31)
    tests = orb.intensity_tests()
    assert tests is not None
    total = 0
    for level in levels:
        kps = ref_orb.detect(level, None)
        if not kps:
            continue
        kept, ref = ref_orb.compute(level, kps)
        pix = np.rint([k.pt for k in kept]).astype(np.int64)
        got = orb.describe(orb.smooth(level), pix, np.array([k.angle for k in kept], np.float32), tests)
        np.testing.assert_array_equal(got, ref)
        total += len(kept)
    assert total > 2000


def test_the_intensity_tests_are_read_off_opencv_and_checked() -> None:
    tests = orb.intensity_tests()
    assert tests is not None and tests.shape == (4, 256) and tests.dtype == np.float32
    assert len({tuple(p) for p in tests.T.tolist()}) == 256  # no test twice
    assert np.abs(tests).max() <= orb.PATCH_RADIUS and np.all(tests == np.round(tests))
    assert orb._check_test_pattern(tests, n=20000) == 0  # noqa: SLF001
    wrong = tests.copy()
    wrong[0, 5] += 1.0  # one test off by a pixel: the check sees it
    assert orb._check_test_pattern(wrong) > 0  # noqa: SLF001
    np.testing.assert_array_equal(orb._derive_test_pattern(seed=7), tests)  # noqa: SLF001 - another seed, the same


def test_an_orientation_on_a_half_pixel_rounds_as_opencvs() -> None:
    """A rotated test pixel landing on a half (here -7.5, at 221.41 deg, with float32 cos and sin
    rounded once) goes where OpenCV's goes; numpy's float32 cos, an ulp off, would flip the bit."""
    tests = orb.intensity_tests()
    assert tests is not None
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (200, 200), dtype=np.uint8), (3, 3), 0)
    angle = np.float32(221.4096221923828)
    ref_orb = cv2.ORB_create(nfeatures=1, nlevels=1, edgeThreshold=31, patchSize=31)
    _kept, ref = ref_orb.compute(img, [cv2.KeyPoint(100.0, 100.0, 31.0, float(angle))])
    got = orb.describe(orb.smooth(img), np.array([[100, 100]]), np.array([angle]), tests)
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("seed", range(6))
def test_select_grid_matches_the_numpy_reference(seed: int) -> None:
    """The compiled grid selection keeps what ``OrbExtractor._select_indices`` keeps, ties and both
    ways of meeting the budget included."""
    rng = np.random.default_rng(seed)
    cfg = TrackerConfig(n_features=[300, 1000, 40, 500, 1000, 120][seed], grid_cell_px=[40, 40, 16, 64, 40, 40][seed])
    ex = OrbExtractor(cfg)
    m = [2000, 1900, 900, 700, 1500, 3000][seed]
    pts = (rng.uniform(0, 1, (m, 2)) * [640, 480]).astype(np.float32)
    if seed % 2:  # clusters and repeated responses
        pts[: m // 2] = pts[: m // 2] * 0.2 + 100
        resp = rng.integers(0, 20, m).astype(np.float32)
    else:
        resp = rng.uniform(0, 1e-3, m).astype(np.float32)
    want = ex._select_indices(pts, resp, 640, 480)  # noqa: SLF001
    got = orb_detect.select_grid(pts, resp, cfg.n_features, cfg.grid_cell_px, 640, 480)
    np.testing.assert_array_equal(got, want)
    assert len(got) == min(cfg.n_features, m)


def test_the_kernel_and_opencvs_compute_give_the_same_features_in_the_same_order() -> None:
    """Whichever describes, the tracker sees the same keypoints, in the same order, with the same
    descriptors: its results do not depend on whether numba is installed."""
    cfg = TrackerConfig()
    kernel, opencv = OrbExtractor(cfg), OrbExtractor(cfg)
    opencv._tests = None  # noqa: SLF001
    for f in generate_frames(parse_spec("synthetic:w=640,h=480,n=3,noise=0.02,holes=0.05")):
        grey = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        a, b = kernel.extract(grey, f.camera, f.depth_m), opencv.extract(grey, f.camera, f.depth_m)
        assert len(a) == len(b) == cfg.n_features
        for field in ("uv_raw", "uv", "octave", "desc", "depth_m"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_describe_refuses_keypoints_too_near_the_border() -> None:
    tests = orb.intensity_tests()
    assert tests is not None
    smoothed = orb.smooth(np.zeros((100, 120), np.uint8))
    for x, y in ((18, 50), (60, 18), (101, 50), (60, 81)):
        with pytest.raises(ValueError, match="19 px inside the 120x100 level"):
            orb.describe(smoothed, np.array([[x, y]]), np.zeros(1, np.float32), tests)
    assert orb.describe(smoothed, np.array([[19, 19], [100, 80]]), np.zeros(2, np.float32), tests).shape == (2, 32)
    assert orb.describe(smoothed, np.zeros((0, 2), np.int64), np.zeros(0, np.float32), tests).shape == (0, 32)


@pytest.mark.parametrize("threshold", [20, 7])
def test_detect_level_is_opencvs_single_level_orb(levels: list[np.ndarray], threshold: int) -> None:
    """After OpenCV's FAST, ``detect_level`` keeps what OpenCV's single-level ORB keeps, in its
    order, with its Harris responses and angles to the bit (its order is libstdc++'s
    ``nth_element`` and ``partition``, which the kernel replays)."""
    fast = cv2.FastFeatureDetector_create(threshold, True)
    total = 0
    for n in (1, 60, 400, 5000):
        ref_orb = cv2.ORB_create(nfeatures=n, nlevels=1, edgeThreshold=EDGE_PX, patchSize=31, fastThreshold=threshold)
        for level in levels:
            corners = fast.detect(level)
            xy = np.array([k.pt for k in corners], np.float32).reshape(-1, 2)
            score = np.array([k.response for k in corners], np.float32)
            idx, response, angle = orb_detect.detect_level(level, xy, score, n, EDGE_PX)
            ref = ref_orb.detect(level, None)
            np.testing.assert_array_equal(xy[idx], np.array([k.pt for k in ref], np.float32).reshape(-1, 2))
            np.testing.assert_array_equal(response, np.array([k.response for k in ref], np.float32))
            np.testing.assert_array_equal(angle, np.array([k.angle for k in ref], np.float32))
            total += len(ref)
    assert total > 5000


@pytest.mark.parametrize("threshold", [20, 7, 1])
def test_fast_scores_are_opencvs_responses(levels: list[np.ndarray], threshold: int) -> None:
    """The scores recomputed from FAST's corner positions equal the responses OpenCV's FAST gives
    them, on every level at once, and the extractor uses them only once that is checked here."""
    fast = cv2.FastFeatureDetector_create(threshold, True)
    shapes, flat_parts, offset = [], [], 0
    corners = []
    for level in levels:
        shapes.append((offset, *level.shape))
        flat_parts.append(level.ravel())
        offset += level.size
        corners.append(fast.detect(level))
    starts = np.cumsum([0, *map(len, corners)])
    xy = np.array([k.pt for c in corners for k in c], np.float32)
    ref = np.array([k.response for c in corners for k in c], np.float32)
    got = orb_detect.fast_scores(np.concatenate(flat_parts), np.array(shapes), xy, starts, threshold)
    assert len(ref) > 2000
    np.testing.assert_array_equal(got, ref)
    assert orb_detect.fast_scores_agree()
    assert OrbExtractor(TrackerConfig())._scores_in_kernel  # noqa: SLF001
    # Scored inside the detection, only on the levels where ORB ranks by them: the same keypoints.
    flat = np.concatenate(flat_parts)
    counts = np.full(len(levels), 40, np.int64)  # few enough that most levels need the scores
    args = (starts, counts, EDGE_PX, np.ones(len(levels), np.float32), 200, 16.0, 640, 480)
    given = orb_detect.detect_and_select(flat, np.array(shapes), xy, ref, *args)
    lazy = orb_detect.detect_and_select(flat, np.array(shapes), xy, None, *args, threshold=threshold)
    for a, b in zip(given, lazy):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="threshold"):
        orb_detect.detect_and_select(flat, np.array(shapes), xy, None, *args)


@pytest.mark.parametrize("keys", ["random", "ties", "ascending", "descending", "equal"])
def test_retain_best_keeps_the_n_best_and_their_ties(keys: str) -> None:
    """OpenCV's ``retainBest``: the n largest keys and every key equal to the nth, nothing else
    (the orders the kernel leaves are checked against OpenCV's ORB above)."""
    rng = np.random.default_rng(0)
    m = 3000
    key = {"random": rng.normal(size=m), "ties": rng.integers(0, 9, m), "ascending": np.arange(m),
           "descending": -np.arange(m), "equal": np.zeros(m)}[keys].astype(np.float32)
    for n in (1, 2, 5, 700, 2999, 3000, 4000):
        a = np.arange(m)
        count = orb_detect._retain_best(a, m, key, n)  # noqa: SLF001
        kept = np.sort(a[:count])
        nth = np.sort(key)[::-1][min(n, m) - 1]
        np.testing.assert_array_equal(kept, np.flatnonzero(key >= nth))
        np.testing.assert_array_equal(np.sort(a), np.arange(m))  # a permutation


def test_level_centres_and_keypoint_depths_equal_their_numpy_twins() -> None:
    """The compiled bookkeeping after detection, value for value: where each keypoint lies in the
    pyramid's buffer, and its shifted pixel and depth (NaN for holes, non-finite and out-of-range
    depths, pixels rounded half to even and clipped at the image's edges)."""
    rng = np.random.default_rng(21)
    ex = OrbExtractor(TrackerConfig())
    layout = ex._reused_layout((480, 640))  # noqa: SLF001
    octave = rng.integers(0, len(layout.levels), 3000)
    xy = np.column_stack([rng.uniform(19, layout.widths[octave] - 20), rng.uniform(19, layout.shapes[octave, 1] - 20)])
    xy[:40] = np.floor(xy[:40]) + 0.5  # halves: rounded to even, as numpy's rint
    xy = xy.astype(np.float32)
    np.testing.assert_array_equal(orb.level_centres(xy, octave, layout.offsets, layout.widths),
                                  orb._level_centres_reference(xy, octave, layout.offsets, layout.widths))  # noqa: SLF001
    pts = np.column_stack([rng.uniform(-3.0, 643.0, 3000), rng.uniform(-3.0, 483.0, 3000)]).astype(np.float32)
    pts[:40] = np.floor(pts[:40]) + 0.5
    depth = rng.uniform(0.0, 8.0, (480, 640)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = np.nan
    depth[0, :3] = (np.inf, -1.0, 6.0)
    shift = ex._centre_shift  # noqa: SLF001
    units = np.rint(np.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0) * 5000.0).astype(np.uint16)
    for d in (depth, None, DepthUnits(units, 5000.0), DepthUnits(depth, 1.0)):
        got = orb.keypoint_depths(pts, octave, shift, d, (480, 640), (0.1, 6.0))
        want = orb._keypoint_depths_reference(pts, octave, shift, d, (480, 640), (0.1, 6.0))  # noqa: SLF001
        for a, b in zip(got, want, strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="does not match"):
        orb.keypoint_depths(pts, octave, shift, depth[:, :600], (480, 640), (0.1, 6.0))
    # the camera's units read at the keypoints give the depths of the image converted whole
    np.testing.assert_array_equal(orb.keypoint_depths(pts, octave, shift, DepthUnits(units, 5000.0), (480, 640),
                                                      (0.1, 6.0))[1],
                                  orb.keypoint_depths(pts, octave, shift, depth_to_metres(units, 5000.0), (480, 640),
                                                      (0.1, 6.0))[1])


def test_extracting_from_colour_equals_extracting_from_its_grey() -> None:
    """The tracker's way (the grey written straight into the pyramid's reused buffer) gives the
    features of the grey image, frame after frame: nothing of a frame's features lives in the
    buffer the next frame overwrites."""
    cfg = TrackerConfig()
    ex, ref = OrbExtractor(cfg), OrbExtractor(cfg)
    frames = list(generate_frames(parse_spec("synthetic:w=640,h=480,n=3,noise=0.02,holes=0.05")))
    # the tracker node's depth: the camera's 16-bit units, read at the keypoints
    units = [DepthUnits(metres_to_units(f.depth_m, 5000.0), 5000.0) for f in frames]
    got = [ex.extract_rgb(f.rgb, f.camera, d) for f, d in zip(frames, units, strict=True)]
    for f, d, a in zip(frames, units, got, strict=True):
        b = ref.extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), f.camera, d.metres())
        assert len(a) == cfg.n_features
        for field in ("uv_raw", "uv", "octave", "desc", "depth_m"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_a_short_first_detection_goes_straight_to_the_retry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where FAST finds fewer corners than ``n_features`` at ``fast_threshold``, ORB cannot keep
    enough, so the retry at ``fast_min_threshold`` is certain: the first selection is skipped and
    the features are those of OpenCV's path, which runs both."""
    cfg = TrackerConfig()
    ex, ref = OrbExtractor(cfg), OrbExtractor(cfg)
    ref._tests = None  # noqa: SLF001 - OpenCV's compute: never skips
    calls: list[int] = []
    real = orb_detect.detect_and_select
    monkeypatch.setattr(orb_detect, "detect_and_select", lambda *a, **k: calls.append(a[-1]) or real(*a, **k))
    for f in generate_frames(parse_spec("synthetic:w=640,h=480,n=2,seed=3")):
        grey = cv2.GaussianBlur(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), (9, 9), 3.0)  # little texture left
        calls.clear()
        a, b = ex.extract(grey, f.camera, f.depth_m), ref.extract(grey, f.camera, f.depth_m)
        assert calls == [cfg.fast_min_threshold]  # the first selection skipped, the retry run
        for field in ("uv_raw", "uv", "octave", "desc", "depth_m"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
