"""Place recognition and loop closure: vocabulary, keyframe database, consistency, pose graph, tracker."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from memgs_ros.core.geometry.poses import invert_pose
from memgs_ros.core.tracking import TrackerConfig, make_tracker
from memgs_ros.core.tracking.anchored_path import AnchoredPath, PathChanges
from memgs_ros.core.tracking.backend.bundle_adjustment import apply_left_update
from memgs_ros.core.tracking.features.features import OrbExtractor
from memgs_ros.core.tracking.features.vocabulary import (
    KeyframeDatabase,
    bow_score,
    build_vocabulary,
    default_vocabulary,
)
from memgs_ros.core.tracking.loop_closing.loops import LoopDetector, optimise_pose_graph
from memgs_ros.io.synthetic import (
    generate_frames,
    loop_revisit_frames,
    parse_spec,
    trajectory,
)

LOOP_SPEC = "synthetic:w=160,h=120,n=160,path=loop,noise=0.01,holes=0.05"


@pytest.fixture(scope="module")
def loop_frames() -> list:
    return list(generate_frames(parse_spec(LOOP_SPEC)))


def test_loop_path_travels_round_the_room_and_returns_to_the_start() -> None:
    spec = parse_spec(LOOP_SPEC)
    _, T = trajectory(spec)
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert steps.sum() >= 8.0
    rev = loop_revisit_frames(spec)
    assert len(rev) >= 5 and rev[-1] == spec.n_frames - 1
    # the first revisit frame is the start view again
    np.testing.assert_allclose(T[rev[0], :3, 3], T[0, :3, 3], atol=0.1)
    assert np.degrees(np.arccos(np.clip((np.trace(T[rev[0], :3, :3].T @ T[0, :3, :3]) - 1) / 2, -1, 1))) < 5
    assert parse_spec(spec.to_string()) == spec
    assert "path" not in parse_spec("synthetic:n=3").to_string()  # default spec strings unchanged


def test_vocabulary_scores_identical_images_highest(loop_frames: list) -> None:
    vocab = default_vocabulary()
    assert vocab.n_words >= 1000
    ex = OrbExtractor(TrackerConfig(n_features=300))
    descs = [ex.extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), f.camera, None).desc for f in loop_frames[::20]]
    db = KeyframeDatabase()
    bows = [vocab.transform(d) for d in descs]
    for i, b in enumerate(bows):
        db.add(i, b)
    for i, b in enumerate(bows):
        assert bow_score(b, b) == pytest.approx(1.0)
        hits = db.query(b)
        assert hits[0] == (i, pytest.approx(1.0))
        assert all(s < 0.99 for k, s in hits[1:])
        assert all(k != i for k, _ in db.query(b, exclude=[i]))  # the local map is left out
    db.remove(0)
    assert 0 not in db and all(k != 0 for k, _ in db.query(bows[0]))


def test_compiled_words_equal_the_numpy_descent(loop_frames: list) -> None:
    """The kernel (popcounts) and the reference (+-1 dot products) give every descriptor the same
    word: real ones, random ones and the centres themselves (ties go to the first child in both)."""
    from memgs_ros.core.tracking.kernel_calls import numba_available

    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")
    vocab = default_vocabulary()
    ex = OrbExtractor(TrackerConfig(n_features=300))
    real = np.concatenate([ex.extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY), f.camera, None).desc
                           for f in loop_frames[::40]])
    rng = np.random.default_rng(1)
    centres = np.concatenate(vocab.levels)
    for desc in (real, rng.integers(0, 256, (500, 32), dtype=np.uint8), centres, centres ^ np.uint8(1),
                 np.zeros((0, 32), np.uint8)):
        got, ref = vocab.words(desc), vocab._words_reference(desc)  # noqa: SLF001 - the twin
        assert got.dtype == np.int64 and np.array_equal(got, ref)
    assert len(np.unique(vocab.words(real))) > 50
    small = build_vocabulary([rng.integers(0, 256, (60, 32), dtype=np.uint8) for _ in range(4)], branching=3,
                             depth=2, iterations=3)
    desc = rng.integers(0, 256, (80, 32), dtype=np.uint8)
    assert np.array_equal(small.words(desc), small._words_reference(desc))  # noqa: SLF001


def test_vocabulary_builder_makes_a_usable_tree() -> None:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (50, 32), dtype=np.uint8) for _ in range(6)]
    vocab = build_vocabulary(images, branching=3, depth=2, iterations=3)
    assert vocab.n_words == 9 and vocab.idf.shape == (9,)
    w = vocab.words(images[0])
    assert w.shape == (50,) and w.min() >= 0 and w.max() < 9


def test_consistency_needs_three_consecutive_agreeing_queries() -> None:
    det = LoopDetector(consistency=3)
    g = frozenset({1, 2, 3})
    assert det.update(50, [(2, 0.3, g)]) is None
    assert det.update(51, [(3, 0.3, frozenset({3, 4}))]) is None
    found = det.update(52, [(1, 0.3, frozenset({0, 1}) | g)])
    assert found is not None and found.candidate_id == 1
    det.reset()
    assert det.update(53, [(2, 0.3, g)]) is None
    assert det.update(54, []) is None  # a query without candidates breaks the chain
    assert det.update(55, [(2, 0.3, g)]) is None


def test_pose_graph_closes_a_toy_loop() -> None:
    n = 40
    gt = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        th = 2 * np.pi * k / n
        gt[k, :3, :3] = [[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]]
        gt[k, :3, 3] = [2 * np.cos(th), 2 * np.sin(th), 0.0]
    odo = [gt[0]]
    for k in range(1, n):  # odometry with a systematic bias: drift
        step = invert_pose(gt[k - 1]) @ gt[k]
        odo.append(odo[-1] @ apply_left_update(step, np.array([0.0, 0.0, 0.004, 0.01, 0.0, 0.0])))
    odo = np.stack(odo)
    ei, ej = np.arange(n - 1), np.arange(1, n)
    Z = [invert_pose(odo[i]) @ odo[j] for i, j in zip(ei, ej)]
    ei, ej = np.r_[ei, 0], np.r_[ej, n - 1]
    Z.append(invert_pose(gt[0]) @ gt[n - 1])  # the loop edge
    fixed = np.zeros(n, bool)
    fixed[0] = True
    res = optimise_pose_graph(odo, ei, ej, np.stack(Z), np.ones(len(ei)), fixed)
    err = lambda T: np.linalg.norm(T[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert res.final_cost < 0.01 * res.initial_cost
    assert err(res.T_wc)[-1] < 0.1 * err(odo)[-1]
    assert err(res.T_wc).mean() < 0.5 * err(odo).mean()
    np.testing.assert_allclose(res.T_wc[0], gt[0], atol=1e-9)  # the gauge stays


def _track(frames: list, loop_closure: bool) -> tuple[np.ndarray, object]:
    """Corrected trajectory [N, 4, 4] in the ground-truth frame and the loop stats (inline threads)."""
    cfg = TrackerConfig(n_features=300, ba_threaded=False, loop_closure=loop_closure)
    with make_tracker(cfg, frames[0].camera) as tracker:
        path = AnchoredPath()
        for f in frames:
            res = tracker.track(f)
            path.update(res, tracker.poll_loop_corrections())
        stats = tracker.loop_stats
    _, T = path.poses()
    return frames[0].T_wc_gt @ T, stats


def test_tracker_closes_the_loop_and_corrects_the_revisit_drift(loop_frames: list) -> None:
    rev = loop_revisit_frames(parse_spec(LOOP_SPEC))
    gt = np.stack([f.T_wc_gt for f in loop_frames])
    drift = {}
    for on in (True, False):
        T, stats = _track(loop_frames, on)
        assert len(T) == len(loop_frames)  # no frame lost
        drift[on] = float(np.median(np.linalg.norm(T[rev, :3, 3] - gt[rev, :3, 3], axis=1)))
        if on:
            assert stats.loops_accepted >= 1
            assert stats.global_ba_runs >= 1  # the global BA after the pose graph was committed
            query, matched = stats.last_loop
            assert matched <= 3  # the start keyframes
            assert query - matched >= TrackerConfig().loop_min_keyframe_gap  # never inside the local map
        else:
            assert stats.loops_detected == 0
    assert drift[False] > 0.2  # the sequence makes the uncorrected tracker drift
    assert drift[True] < 0.5 * drift[False]


def test_anchored_path_interpolates_corrections_between_keyframes() -> None:
    path = AnchoredPath()
    for i in range(6):  # keyframe 0 on frames 0-2, keyframe 1 on frames 3-5
        path.add(i, np.eye(4), 0 if i < 3 else 1)
    D0, D1 = np.eye(4), np.eye(4)
    D1[:3, 3] = (0.3, 0.0, 0.0)
    assert path.correct({0: D0, 1: D1}) == {0, 1}
    _, T = path.poses()
    np.testing.assert_allclose(T[:, 0, 3], [0.0, 0.1, 0.2, 0.3, 0.3, 0.3], atol=1e-12)
    path.correct({1: D1})  # keyframe 0 not corrected: its frames stay
    _, T = path.poses()
    np.testing.assert_allclose(T[:, 0, 3], [0.0, 0.1, 0.2, 0.6, 0.6, 0.6], atol=1e-12)


def test_frames_of_a_culled_keyframe_follow_its_heir() -> None:
    path = AnchoredPath()
    for i in range(4):  # keyframe 3 on frames 0-1, keyframe 5 on frames 2-3
        path.add(i, np.eye(4), 3 if i < 2 else 5)
    path.reanchor({3: 5})  # keyframe 3 culled, 5 its heir
    D = np.eye(4)
    D[:3, 3] = (0.0, 0.2, 0.0)
    assert path.correct({3: D}) == set()  # the culled keyframe gets no corrections
    assert path.correct({5: D}) == {5}
    _, T = path.poses()
    np.testing.assert_allclose(T[:, 1, 3], [0.2, 0.2, 0.2, 0.2], atol=1e-12)


def test_path_changes_say_what_a_published_copy_must_change() -> None:
    from memgs_ros.core.tracking.config import TrackingState, TrackResult

    def frame(i: int, ref: int, tracked: bool = True) -> TrackResult:
        return TrackResult(stamp_ns=i, T_wc=np.eye(4) if tracked else None, state=TrackingState.OK, keyframe=None,
                           n_matches=0, n_inliers=0, time_s=0.0, reference_keyframe_id=ref)

    changes = PathChanges(AnchoredPath())
    assert changes.take() is None  # nothing yet
    for i in range(4):
        changes.update(frame(i, 0 if i < 2 else 1), [])
    idx, T = changes.take()
    assert len(idx) == 0 and T.shape == (0, 4, 4)  # frames added, none moved
    assert changes.take() is None
    changes.update(frame(4, 1, tracked=False), [])
    assert changes.take() is None  # a lost frame adds nothing
    D = np.eye(4)
    D[:3, 3] = (0.0, 0.0, 0.5)
    changes.update(frame(5, 1), [{1: D}], heirs={0: 1})  # keyframe 0 culled into 1, then 1 corrected
    idx, T = changes.take()
    assert idx.tolist() == [0, 1, 2, 3, 4]  # every frame follows keyframe 1 now (the new one as it is)
    np.testing.assert_allclose(T[:, 2, 3], [0.5, 0.5, 0.5, 0.5, 0.0])  # the new frame was tracked after it
    assert changes.take() is None


def test_a_second_session_closes_the_loop_onto_the_first_sessions_keyframes(loop_frames: list) -> None:
    """A saved map's keyframes are in the loaded tracker's loop database: session 2 (frames 70-159,
    from session 1's map of frames 0-79) closes the loop onto session 1's start keyframes."""
    cfg = TrackerConfig(n_features=300, ba_threaded=False, loop_closure=True)
    with make_tracker(cfg, loop_frames[0].camera) as first:
        for f in loop_frames[:80]:
            first.track(f)
        first.wait_for_loop_closing()
        saved = first.export_map()
        assert first.loop_stats.loops_accepted == 0  # session 1 never came back
    with make_tracker(cfg, loop_frames[0].camera) as second:
        second.load_map(saved)
        results = [second.track(f) for f in loop_frames[70:]]
        second.wait_for_loop_closing()
        stats = second.loop_stats
    assert second.relocalized_after == 0 and all(r.T_wc is not None for r in results)
    assert stats.loops_accepted >= 1
    query, matched = stats.last_loop
    assert matched <= 3 < saved.n_keyframes <= query  # from a new keyframe onto session 1's start
