"""ORB's detection and descriptors by numba kernels (``memgs_ros.core.tracking.orb``) against
OpenCV's own ORB, which is their reference."""
from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from memgs_ros.core.tracking import TrackerConfig, orb
from memgs_ros.core.tracking.features import EDGE_PX, OrbExtractor
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


@pytest.mark.parametrize("n,threshold", [(434, 20), (60, 20), (25, 7), (1, 20)])
def test_detect_level_finds_the_single_level_orbs_keypoints_and_responses(levels: list[np.ndarray], n: int,
                                                                          threshold: int) -> None:
    """Same pixels and bit-equal Harris responses as OpenCV's one-level ORB asked for ``n`` (small
    asks force both of its cuts, by FAST score and by response, ties included)."""
    ref_orb = cv2.ORB_create(nfeatures=n, nlevels=1, edgeThreshold=EDGE_PX, patchSize=31, fastThreshold=threshold)
    fast = cv2.FastFeatureDetector_create(threshold, True)
    cut = 0
    for level in levels:
        ref = ref_orb.detect(level, None)
        pix, resp = orb.detect_level(fast, level, n, EDGE_PX)
        want = {(round(k.pt[0]), round(k.pt[1])): np.float32(k.response) for k in ref}
        got = dict(zip(map(tuple, pix.tolist()), resp.tolist()))
        assert got.keys() == want.keys()
        assert all(np.float32(got[p]) == want[p] for p in want)
        cut += len(fast.detect(level)) > len(ref)
    assert cut > 0  # the asks did cut somewhere


def test_descriptors_are_opencvs_at_opencvs_orientations(levels: list[np.ndarray]) -> None:
    """describe_level's orientation and descriptors against OpenCV's ORB describing the same pixels."""
    ref_orb = cv2.ORB_create(nfeatures=300, nlevels=1, edgeThreshold=EDGE_PX, patchSize=31)
    tests = orb.intensity_tests()
    assert tests is not None
    total = differ = 0
    for level in levels[:8]:
        kps = ref_orb.detect(level, None)
        if not kps:
            continue
        kept, ref = ref_orb.compute(level, kps)
        pix = np.array([k.pt for k in kept]).round().astype(np.int64)
        got = orb.describe_level(level, pix, tests)
        bits = np.unpackbits(got ^ ref, axis=1).sum(axis=1)
        total += len(kept)
        differ += int((bits > 0).sum())
        assert bits.max() <= 2  # cv2.phase against ORB's own atan2: at most a last-bit angle
    assert total > 1000 and differ <= total // 1000


def test_the_intensity_tests_are_read_off_opencv_and_checked() -> None:
    tests = orb.intensity_tests()
    assert tests is not None and tests.shape == (4, 256) and tests.dtype == np.float32
    pairs = {tuple(p) for p in tests.T.tolist()}
    assert len(pairs) == 256  # no test twice
    assert np.abs(tests).max() <= orb.PATCH_RADIUS and np.all(tests == np.round(tests))
    assert orb._check_test_pattern(tests) == 0  # noqa: SLF001
    wrong = tests.copy()
    wrong[0, 5] += 1.0  # one test off by a pixel: the check sees it
    assert orb._check_test_pattern(wrong) > 0  # noqa: SLF001
    # Another seed reads the same tests.
    np.testing.assert_array_equal(orb._derive_test_pattern(seed=7), tests)  # noqa: SLF001


def test_the_orientation_disc_is_symmetric() -> None:
    w = orb.disc_half_widths()
    disc = {(u, v) for v in range(-15, 16) for u in range(-w[abs(v)], w[abs(v)] + 1)}
    assert disc == {(v, u) for u, v in disc}
    assert w[0] == 15 and all(w[i] >= w[i + 1] for i in range(15))


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
    got = orb.select_grid(pts, resp, cfg.n_features, cfg.grid_cell_px, 640, 480)
    np.testing.assert_array_equal(got, want)
    assert len(got) == min(cfg.n_features, m)


def test_without_numba_the_extractor_keeps_opencvs_orb() -> None:
    """MEMGS_DISABLE_NUMBA=1: no kernel is compiled or called, the extractor describes by OpenCV's ORB."""
    code = ("import cv2, numpy as np\n"
            "from memgs_ros.core.tracking import TrackerConfig, orb\n"
            "from memgs_ros.core.tracking.features import OrbExtractor\n"
            "from memgs_ros.io.synthetic import generate_frames, parse_spec\n"
            "assert not orb.compiled_orb_available()\n"
            "ex = OrbExtractor(TrackerConfig(n_features=300))\n"
            "assert ex._tests is None\n"
            "f = next(iter(generate_frames(parse_spec('synthetic:w=320,h=240,n=1'))))\n"
            "feats = ex.extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), f.camera, f.depth_m)\n"
            "assert len(feats) == 300, len(feats)\n"
            "assert not hasattr(orb._describe, 'signatures')\n")
    env = {**os.environ, "MEMGS_DISABLE_NUMBA": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr


def test_the_kernels_and_opencvs_orb_per_level_give_the_same_features_in_the_same_order() -> None:
    """Whichever path describes, the tracker sees the same keypoints in the same order (the grid
    breaks ties by that order), so its results do not depend on whether numba is installed."""
    cfg = TrackerConfig()
    ex = OrbExtractor(cfg)
    described = differ = 0
    for f in generate_frames(parse_spec("synthetic:w=640,h=480,n=3,noise=0.02,holes=0.05")):
        grey = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        a = ex.extract(grey, f.camera, f.depth_m)
        b = ex._extract_levels(grey, ex._pyramid(grey), f.camera, f.depth_m)  # noqa: SLF001
        assert len(a) == len(b) == cfg.n_features
        np.testing.assert_array_equal(a.uv_raw, b.uv_raw)
        np.testing.assert_array_equal(a.octave, b.octave)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        described += len(a)
        differ += int((a.desc != b.desc).any(axis=1).sum())
    assert differ <= described // 1000
